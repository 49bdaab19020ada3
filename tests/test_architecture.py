"""The package boundaries of docs/architecture.md, checked on every import in src/vinetwin: a new
dependency between packages is a decision made in that document, not an accident."""

from __future__ import annotations

import ast
from pathlib import Path

from tests.conftest import ROOT

SRC = ROOT / "src" / "vinetwin"
PACKAGES = ("twin", "render", "reconstruct", "servo", "web")

#: package -> packages it may import (core: the top-level modules).
ALLOWED: dict[str, set[str]] = {
    "core": {"core"},
    "twin": {"core", "twin"},
    "render": {"core", "twin", "render"},
    "reconstruct": {"core", "twin", "render", "reconstruct"},
    "servo": {"core", "twin", "render", "servo"},
    "web": {"core", "twin", "render", "servo", "web"},
    "cli": {"core", "twin", "render", "reconstruct", "servo", "web"},
}
#: single modules allowed across a boundary (kept acyclic: neither side imports the other back)
EXCEPTIONS: set[tuple[str, str]] = {
    ("vinetwin.reconstruct.odometry", "vinetwin.servo.icp"),  # frame-to-frame ICP
    ("vinetwin.servo.sources", "vinetwin.reconstruct.capture"),  # capture-folder playback
    ("vinetwin.servo.sim", "vinetwin.reconstruct.capture"),  # recording simulated frames
    ("vinetwin.servo.runner", "vinetwin.reconstruct.capture"),  # servo --record
}


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


def test_the_architecture_document_lists_every_package() -> None:
    doc = (ROOT / "docs" / "architecture.md").read_text()
    for name in (*PACKAGES, "executor", "capture", "odometry"):
        assert name in doc
    assert Path(SRC / "executor.py").exists()
