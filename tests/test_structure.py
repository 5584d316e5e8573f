"""The package structure, checked: which part of the code may import which.

``pipeline`` is the processing and never imports the viewer. Its folders stand in one
order (:data:`PIPELINE_ORDER`): a folder imports only from itself and the folders before
it, and only ``__init__.py`` and ``config.py`` sit at its top. In ``mvviz`` the command
line is the top, the app builds the panels, the panels are built against the panel
contract (never the app), and scene drawing, analysis and export sit below the panels.
No module of either package takes part in an import circle. Every import counts,
including those inside functions and under ``TYPE_CHECKING``.
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


# pipeline's folders, lowest first: each may import only from itself and those before it
# (``config`` is the module pipeline/config.py: the settings of the stages below it)
PIPELINE_ORDER = (
    "core",  # files, progress, schema, units, rotations: no pipeline imports
    "data",  # scene, cameras, joint sets, reference tracks
    "importers",  # other tools' files -> scenes
    "calibrate",  # cameras calibrated from footage of a board
    "body",  # the body model, its kinematics, keypoints, limits, measures
    "stages",  # restore, triangulate, track, kalman, retime
    "association",  # cross-view association (uses triangulation for left/right flips)
    "fit",  # SMPL fit, the VAE prior model and its correction
    "mocap",  # motion-capture clips fitted with the body model
    "synth",  # synthetic scenes
    "config",  # every stage's settings
    "results",  # the results' arrays, file format and cache key
    "run",  # the one place that composes the stages
    "evaluation",  # metrics and the evaluation of results
    "prior",  # training the pose prior, its data sources
    "detect",  # the 2D detector on videos
    "exports",  # results -> other tools' files
    "diagnose",  # sync, calibration and floor checks
    "batch",  # many scenes and sweeps on Ray
)
TOP_LEVEL = {"__init__.py", "config.py"}


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


def _folder_rank(module: str) -> int | None:
    """Rank in :data:`PIPELINE_ORDER` of a ``pipeline`` module's folder (-1: the package)."""
    parts = module.split(".")
    if len(parts) < 2:
        return -1
    name = parts[1]
    return PIPELINE_ORDER.index(name) if name in PIPELINE_ORDER else None


def test_pipeline_top_level_holds_only_init_and_config():
    top = {p.name for p in (ROOT / "pipeline").glob("*.py")}
    assert top == TOP_LEVEL, f"modules outside a folder: {sorted(top - TOP_LEVEL)}"
    folders = {p.name for p in (ROOT / "pipeline").iterdir() if (p / "__init__.py").is_file()}
    assert folders == set(PIPELINE_ORDER) - {"config"}, sorted(folders ^ set(PIPELINE_ORDER))


def test_pipeline_folders_import_in_order():
    bad = []
    for f in sources("pipeline"):
        rank = _folder_rank(module_name(f))
        for name in sorted(imported_modules(f)):
            other = _folder_rank(name) if _under(name, "pipeline") else None
            if other is not None and other > rank:
                bad.append(f"{f.relative_to(ROOT)} imports {name}")
    assert not bad, "\n".join(bad)


def test_pipeline_folders_say_what_they_hold():
    """Each folder's ``__init__.py`` opens with a docstring naming what lives there."""
    thin = [
        str(init.relative_to(ROOT))
        for init in sorted((ROOT / "pipeline").glob("*/__init__.py"))
        if len(ast.get_docstring(ast.parse(init.read_text())) or "") < 80
    ]
    assert not thin, thin


def import_graph(packages: tuple[str, ...] = ("pipeline", "mvviz")) -> dict[str, set[str]]:
    """Module -> the project modules it imports (a name resolved to its longest module)."""
    files = {module_name(f): f for p in packages for f in sources(p)}

    def resolve(name: str) -> str | None:
        parts = name.split(".")
        for k in range(len(parts), 0, -1):
            if ".".join(parts[:k]) in files:
                return ".".join(parts[:k])
        return None

    return {
        m: {r for n in imported_modules(f) if (r := resolve(n)) is not None and r != m}
        for m, f in files.items()
    }


def import_circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    circles = []
    for root in sorted(graph):
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            v, children = work[-1]
            w = next(children, None)
            if w is not None:
                if w not in index:
                    index[w] = low[w] = len(index)
                    stack.append(w)
                    on_stack.add(w)
                    work.append((w, iter(sorted(graph[w]))))
                elif w in on_stack:
                    low[v] = min(low[v], index[w])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[v])
            if low[v] == index[v]:
                component = []
                while True:
                    w = stack.pop()
                    on_stack.discard(w)
                    component.append(w)
                    if w == v:
                        break
                if len(component) > 1:
                    circles.append(sorted(component))
    return circles


def test_no_import_circles():
    circles = import_circles(import_graph())
    assert not circles, "\n".join(" <-> ".join(c) for c in circles)


def test_circle_finder_finds_circles():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a", "e"}, "e": {"d"}, "f": set()}
    assert sorted(import_circles(graph)) == [["a", "b", "c"], ["d", "e"]]
    assert import_circles({"a": {"b"}, "b": set()}) == []
