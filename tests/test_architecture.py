"""The package boundaries of docs/architecture.md, checked on every import in src/vinetwin: a new
dependency between packages is a decision made in that document, not an accident."""

from __future__ import annotations

import ast
from pathlib import Path

from tests.conftest import ROOT

SRC = ROOT / "src" / "vinetwin"
PACKAGES = ("twin", "capture", "registration", "render", "reconstruct", "servo", "sim", "web")

#: package -> packages it may import (core: the top-level modules).
ALLOWED: dict[str, set[str]] = {
    "core": {"core"},
    "twin": {"core", "twin"},
    "capture": {"core", "capture"},
    "registration": {"core", "registration"},
    "render": {"core", "twin", "render"},
    "reconstruct": {"core", "twin", "capture", "registration", "render", "reconstruct"},
    "servo": {"core", "twin", "capture", "registration", "render", "servo"},
    "sim": {"core", "twin", "capture", "registration", "render", "reconstruct", "servo", "sim"},
    "web": {"core", "twin", "capture", "registration", "render", "reconstruct", "servo", "sim",
            "web"},
    "cli": {"core", "twin", "capture", "registration", "render", "reconstruct", "servo", "sim",
            "web"},
}  # fmt: skip
#: single modules allowed across a boundary (none: every arrow follows the table)
EXCEPTIONS: set[tuple[str, str]] = set()


def _package(module: str) -> str:
    parts = module.split(".")
    if len(parts) > 1 and parts[1] in PACKAGES:
        return parts[1]
    return "cli" if parts[1:2] == ["cli"] else "core"


def _imports() -> list[tuple[str, str]]:
    out = []
    for path in sorted(SRC.rglob("*.py")):
        rel = path.relative_to(SRC.parent).with_suffix("")
        module = ".".join(p for p in rel.parts if p != "__init__")
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                names = [node.module]
            elif isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            else:
                continue
            out += [(module, n) for n in names if n == "vinetwin" or n.startswith("vinetwin.")]
    return out


def test_packages_import_only_what_the_architecture_allows() -> None:
    imports = _imports()
    assert len(imports) > 100
    wrong = [
        f"{src} imports {dst}"
        for src, dst in imports
        if dst != "vinetwin"
        and _package(dst) not in ALLOWED[_package(src)]
        and (src, dst) not in EXCEPTIONS
    ]
    assert not wrong, "\n".join(wrong)


def test_the_exceptions_are_used_and_acyclic() -> None:
    imports = set(_imports())
    for src, dst in EXCEPTIONS:
        assert (src, dst) in imports, f"stale exception: {src} -> {dst}"
        assert not any(s == dst and d.startswith(src.rsplit(".", 1)[0]) for s, d in imports)


def test_no_import_circle_between_modules() -> None:
    """Every import, module-level or inside a function, points one way: no module reaches
    itself again through the modules it imports."""
    modules = {src for src, _ in _imports()}
    graph: dict[str, set[str]] = {}
    for src, dst in _imports():
        if dst in modules and dst != src:
            graph.setdefault(src, set()).add(dst)
    state: dict[str, int] = {}
    path: list[str] = []

    def visit(m: str) -> None:
        state[m] = 1
        path.append(m)
        for n in sorted(graph.get(m, ())):
            if state.get(n) == 1:
                raise AssertionError("import circle: " + " -> ".join([*path[path.index(n) :], n]))
            if n not in state:
                visit(n)
        path.pop()
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m)


def test_servo_and_reconstruct_do_not_import_each_other() -> None:
    crossing = [
        (s, d) for s, d in _imports() if {_package(s), _package(d)} == {"servo", "reconstruct"}
    ]
    assert not crossing, crossing


def test_the_architecture_document_lists_every_package() -> None:
    doc = (ROOT / "docs" / "architecture.md").read_text()
    for name in (*PACKAGES, "executor", "jobstore", "files", "mesh", "odometry"):
        assert name in doc
    assert Path(SRC / "executor.py").exists()


def test_the_variant_list_of_the_configs_is_the_core_one() -> None:
    """Core modules name the variants in `cloud.ICP_VARIANTS`; the configs' `Variant` type (the
    command line's choices) must be the same list, in the same order."""
    from vinetwin.cloud import ICP_VARIANTS
    from vinetwin.servo.config import VARIANTS
    from vinetwin.sim.config import ALL_VARIANTS

    assert VARIANTS == ALL_VARIANTS == ICP_VARIANTS
