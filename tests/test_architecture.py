"""The package boundaries of docs/architecture.md, checked on every import in src/vinetwin: a new
dependency between packages is a decision made in that document, not an accident."""

from __future__ import annotations

import ast
from pathlib import Path

from tests.conftest import ROOT

SRC = ROOT / "src" / "vinetwin"
PACKAGES = ("twin", "scan", "plan", "capture", "registration", "render", "reconstruct", "servo", "sim",
            "web")  # fmt: skip

#: package -> packages it may import (core: the top-level modules).
ALLOWED: dict[str, set[str]] = {
    "core": {"core"},
    "twin": {"core", "twin"},
    "scan": {"core", "twin", "scan"},
    "plan": {"core", "twin", "plan"},
    "capture": {"core", "capture"},
    "registration": {"core", "registration"},
    "render": {"core", "twin", "render"},
    "reconstruct": {"core", "twin", "capture", "registration", "render", "reconstruct"},
    "servo": {"core", "twin", "capture", "registration", "render", "servo"},
    "sim": {"core", "twin", "plan", "capture", "registration", "render", "reconstruct", "servo",
            "sim"},
    "web": {"core", "twin", "plan", "capture", "registration", "render", "reconstruct",
            "servo", "sim", "web"},
    "cli": {"core", "twin", "scan", "plan", "capture", "registration", "render",
            "reconstruct", "servo", "sim", "web", "cli"},
}  # fmt: skip
#: single modules allowed across a boundary (none: every arrow follows the table)
EXCEPTIONS: set[tuple[str, str]] = set()


def _package(module: str) -> str:
    parts = module.split(".")
    if len(parts) > 1 and parts[1] in PACKAGES:
        return parts[1]
    return "cli" if parts[1:2] == ["cli"] else "core"


def imports_of(source: str, module: str, package: bool = False) -> list[tuple[str, str]]:
    """Every vinetwin module `module` (a package's `__init__` when `package`) imports, at any
    depth of the code: `import vinetwin.a.b`, `from vinetwin.a import b` (vinetwin.a), `from
    vinetwin import a` (vinetwin.a: the name may be a subpackage) and relative imports."""
    out = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:  # relative: from the module's package upwards
                parts = module.split(".")[: len(module.split(".")) - node.level + int(package)]
                base = ".".join([*parts, *([base] if base else [])])
            # the module, and each name as a submodule (it may be one: `from vinetwin import sim`)
            names = [base, *(f"{base}.{a.name}" for a in node.names if a.name != "*")]
        else:
            continue
        out += [(module, n) for n in names if n == "vinetwin" or n.startswith("vinetwin.")]
    return out


def _imports() -> list[tuple[str, str]]:
    out = []
    for path in sorted(SRC.rglob("*.py")):
        rel = path.relative_to(SRC.parent).with_suffix("")
        module = ".".join(p for p in rel.parts if p != "__init__")
        out += imports_of(path.read_text(), module, package=path.name == "__init__.py")
    return out


def _crossings(imports: list[tuple[str, str]]) -> list[str]:
    return [
        f"{src} imports {dst}"
        for src, dst in imports
        if dst != "vinetwin"
        and _package(dst) not in ALLOWED[_package(src)]
        and (src, dst) not in EXCEPTIONS
    ]


def test_packages_import_only_what_the_architecture_allows() -> None:
    imports = _imports()
    assert len(imports) > 100
    wrong = _crossings(imports)
    assert not wrong, "\n".join(wrong)


def test_every_form_of_import_is_seen_across_a_layer() -> None:
    """The check sees an upward import whichever way it is written, at module level or inside
    a function; a plain `from vinetwin import errors` (core) is allowed."""
    for code in (
        "from vinetwin import sim",
        "from vinetwin import errors, sim",
        "import vinetwin.sim.session",
        "from vinetwin.sim.session import SimSpec",
        "def f():\n    from vinetwin import web\n",
        "from ..sim import session",
        "from .. import servo",
    ):
        found = _crossings(imports_of(code, "vinetwin.render.reference"))
        assert found, code
    assert not _crossings(imports_of("from vinetwin import errors, _lazy", "vinetwin.render.x"))
    assert ("vinetwin.render", "vinetwin.render.backends") in imports_of(
        "from . import backends", "vinetwin.render", package=True
    )


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
