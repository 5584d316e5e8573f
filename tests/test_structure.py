"""The package structure, checked: which part of the code may import which.

``pipeline`` is the processing and never imports the viewer; in ``mvviz`` the command
line is the top, the app builds the panels, the panels are built against the panel
contract (never the app), and scene drawing, analysis and export sit below the panels.
Every import counts, including those inside functions and under ``TYPE_CHECKING``.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

# package prefix -> prefixes it must never import
FORBIDDEN = {
    "pipeline": ("mvviz",),
    "mvviz.scene": ("mvviz.app", "mvviz.cli", "mvviz.panels", "mvviz.analysis", "mvviz.export"),
    "mvviz.analysis": ("mvviz.app", "mvviz.cli", "mvviz.panels", "mvviz.export"),
    "mvviz.export": ("mvviz.app", "mvviz.cli", "mvviz.panels"),
    "mvviz.panels": ("mvviz.app", "mvviz.cli"),
    "mvviz.state": ("mvviz.app", "mvviz.cli", "mvviz.panels"),
    "mvviz.workers": ("mvviz.app", "mvviz.cli", "mvviz.panels", "mvviz.scene"),
    "mvviz.safe_paths": ("mvviz.app", "mvviz.cli", "mvviz.panels", "mvviz.scene", "pipeline"),
}


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def imported_modules(path: Path) -> set[str]:
    """Absolute names of every module ``path`` imports (relative imports resolved)."""
    tree = ast.parse(path.read_text(), filename=str(path))
    me = module_name(path).split(".")
    package = me if path.name == "__init__.py" else me[:-1]
    names: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package[: len(package) - node.level + 1]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            names.add(mod)
            names.update(f"{mod}.{a.name}" for a in node.names)  # "from mvviz import app"
    return names


def sources(package: str) -> list[Path]:
    base = ROOT / package.replace(".", "/")
    return sorted(base.rglob("*.py")) if base.is_dir() else [base.with_suffix(".py")]


def _under(name: str, prefix: str) -> bool:
    return name == prefix or name.startswith(prefix + ".")


@pytest.mark.parametrize("package", sorted(FORBIDDEN))
def test_import_direction(package):
    files = sources(package)
    assert files and all(f.is_file() for f in files), f"{package}: no sources found"
    bad = [
        f"{f.relative_to(ROOT)} imports {name}"
        for f in files
        for name in sorted(imported_modules(f))
        if any(_under(name, p) for p in FORBIDDEN[package])
    ]
    assert not bad, "\n".join(bad)


def test_checker_sees_forbidden_imports(tmp_path, monkeypatch):
    """The checker itself: a function-level and a TYPE_CHECKING import are both seen."""
    pkg = tmp_path / "mvviz" / "panels"
    pkg.mkdir(parents=True)
    (pkg / "x.py").write_text(
        "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from mvviz.app import A\n"
        "def f():\n    from ..cli import run\n"
    )
    monkeypatch.setattr(__import__(__name__, fromlist=["ROOT"]), "ROOT", tmp_path)
    assert {"mvviz.app", "mvviz.cli"} <= imported_modules(pkg / "x.py")
