"""Code size: no module over MAX_MODULE_LINES lines and no function over MAX_FUNCTION_LINES
lines in ``pipeline/`` and ``mvviz/``, unless the line of its ``def`` (or the line above
it, or of its first decorator) carries ``# long: <reason>``. Lines count as the file has
them (docstrings and comments included); a function's lines run from its ``def`` (or first
decorator) to its last line.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

from tests.conftest import REPO

MAX_MODULE_LINES = 800
MAX_FUNCTION_LINES = 80
PACKAGES = ("pipeline", "mvviz")
LONG = re.compile(r"#\s*long:\s*\S")


def size_problems(
    path: Path, *, max_module: int = MAX_MODULE_LINES, max_function: int = MAX_FUNCTION_LINES
) -> list[str]:
    """``"path: N lines"`` / ``"path:line name: N lines"`` for what is too long and unexcused."""
    text = path.read_text(encoding="utf-8")
    lines = text.splitlines()
    out = []
    if len(lines) > max_module and not (lines and LONG.search(lines[0])):
        out.append(f"{path}: {len(lines)} lines (module; > {max_module})")
    for node in ast.walk(ast.parse(text, filename=str(path))):
        if not isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
            continue
        first = min([node.lineno] + [d.lineno for d in node.decorator_list])
        n = node.end_lineno - first + 1
        marks = {first - 1, first, node.lineno}  # 1-based: the line above, decorator, def
        if n > max_function and not any(
            1 <= i <= len(lines) and LONG.search(lines[i - 1]) for i in marks
        ):
            out.append(f"{path}:{node.lineno} {node.name}: {n} lines (> {max_function})")
    return out


def test_the_checker_finds_long_code(tmp_path):
    body = "\n".join(f"    x{i} = {i}" for i in range(6))
    (tmp_path / "a.py").write_text(
        f"def short():\n    return 1\n\n\ndef too_long():\n{body}\n\n\n"
        f"def excused():  # long: a flat table\n{body}\n\n\n"
        f"# long: generated\n@staticmethod\ndef excused_above():\n{body}\n"
    )
    found = size_problems(tmp_path / "a.py", max_module=10, max_function=5)
    assert len(found) == 2, found
    assert "a.py: " in found[0] and "module" in found[0]
    assert "too_long: 7 lines" in found[1]
    assert size_problems(tmp_path / "a.py", max_module=100, max_function=7) == []


@pytest.mark.parametrize("package", PACKAGES)
def test_no_long_modules_or_functions(package):
    files = sorted((REPO / package).rglob("*.py"))
    found = [p.replace(f"{REPO}/", "") for f in files for p in size_problems(f)]
    assert not found, "too long (split it, or say why beside its def: '# long: <reason>'):\n" + (
        "\n".join(found)
    )
