"""The documentation as a reader meets it: the site builds with strict checks (broken
links, missing pages and anchors fail), and the commands and code the README, the
tutorial and the API page show are run, so none of them can rot."""

from __future__ import annotations

import os
import re
import shlex
import shutil
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import pytest

from tests.conftest import SHARED_DATA

REPO = Path(__file__).resolve().parents[1]
CALISCOPE = SHARED_DATA / "caliscope_charuco"


def code_blocks(path: Path, language: str) -> list[str]:
    """The fenced ``language`` blocks of a Markdown file, in order."""
    pattern = re.compile(rf"^```{language}\n(.*?)^```", re.S | re.M)
    return pattern.findall(path.read_text())


def commands(block: str) -> list[str]:
    """A shell block's commands: continuation lines joined, comments dropped."""
    joined = re.sub(r"\\\n\s*", " ", block)
    out = []
    for line in joined.splitlines():
        line = re.sub(r"\s+#.*$", "", line).strip()
        if line and not line.startswith("#"):
            out.append(line)
    return out


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def mvviz_command(words: list[str]) -> list[str]:
    """``mvviz ...`` as installed, else through the interpreter running the tests."""
    exe = shutil.which("mvviz")
    return [exe, *words[1:]] if exe else [sys.executable, "-m", "mvviz.cli", *words[1:]]


def serve_and_fetch(argv: list[str], cwd: Path) -> None:
    """Start ``python app.py ...`` on a free port, wait for its URL, fetch the page, stop."""
    port = free_port()
    proc = subprocess.Popen(
        [sys.executable, str(REPO / "app.py"), *argv, "--port", str(port)],
        cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )  # fmt: skip
    try:
        deadline = time.monotonic() + 600
        lines = []
        for line in proc.stdout:
            lines.append(line)
            if "ready in" in line or time.monotonic() > deadline:
                break
        assert any("ready in" in x for x in lines), "".join(lines[-20:])
        url = re.search(r"(http://\S+)", [x for x in lines if "ready in" in x][0]).group(1)
        with urllib.request.urlopen(url, timeout=30) as answer:
            assert answer.status == 200
    finally:
        proc.terminate()
        proc.wait(30)


def run_shell_command(line: str, cwd: Path, env: dict[str, str]) -> None:
    words = shlex.split(os.path.expandvars(line) if "$" in line else line)
    if words[:2] == ["python", "app.py"]:
        serve_and_fetch(words[2:], cwd)
        return
    assert words[0] == "mvviz", f"not a command the docs test knows how to run: {line}"
    done = subprocess.run(
        mvviz_command(words), cwd=cwd, env=env, capture_output=True, text=True, timeout=1200
    )
    assert done.returncode == 0, f"{line}\n{done.stdout[-2000:]}\n{done.stderr[-2000:]}"


def test_the_site_builds_with_strict_checks(tmp_path):
    """``mkdocs build --strict``: a broken link or anchor, a page missing from the
    navigation or a docstring mkdocstrings cannot read fails the build."""
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1", "PYTHONPATH": str(REPO)}
    done = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(tmp_path / "site")],
        cwd=REPO, capture_output=True, text=True, timeout=900, env=env,
    )  # fmt: skip
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    cli = (tmp_path / "site" / "reference" / "cli" / "index.html").read_text()
    for command in ("mvviz calibrate", "mvviz export", "python app.py"):
        assert command in cli  # the options page is generated from the parsers
    assert "--floor-frame" in cli and "--allow-writes" in cli
    api = (tmp_path / "site" / "api" / "index.html").read_text()
    assert "load_scene" in api and "SCENE/.mvviz/export" in api  # from the docstrings


def test_readme_commands_run(tmp_path):
    """Every command of the README's shell blocks (the set-up's pip and pytest are what
    CI itself runs), from a folder holding the repository's sample data."""
    (tmp_path / "sample_data").symlink_to(REPO / "sample_data")
    env = dict(os.environ)
    ran = 0
    for block in code_blocks(REPO / "README.md", "bash"):
        for line in commands(block):
            first = line.split("&&")[-1].strip()
            if line.startswith("pip install") and first in ("python app.py", "pytest -q"):
                if first == "python app.py":
                    serve_and_fetch([], tmp_path)
                    ran += 1
                continue
            if line.startswith("mkdocs"):
                continue  # the site: the test above
            run_shell_command(line, tmp_path, env)
            ran += 1
    assert ran >= 5
    assert (tmp_path / "shelf.trc").stat().st_size > 0 and (tmp_path / "shelf.rrd").is_file()


def test_api_page_examples_run(tmp_path):
    """The Python API page's examples, in order, in one fresh interpreter."""
    code = "\n\n".join(code_blocks(REPO / "docs" / "api.md", "python"))
    script = tmp_path / "api_examples.py"
    script.write_text(code)
    done = subprocess.run(
        [sys.executable, str(script)], cwd=REPO, capture_output=True, text=True, timeout=1200,
        env={**os.environ, "PYTHONPATH": str(REPO)},
    )  # fmt: skip
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    assert "tracks over 250 frames" in done.stdout and "True" in done.stdout


@pytest.mark.skipif(not CALISCOPE.is_dir(), reason="../shared/data/caliscope_charuco is absent")
def test_tutorial_commands_run(tmp_path):
    """The tutorial on the real four-webcam session, every command as printed (detection
    on every 10th frame, to stay quick): calibrate, detect, run, diagnose, view, export."""
    pytest.importorskip("ai_edge_litert")
    env = {**os.environ, "DATA": str(CALISCOPE)}
    os.environ.setdefault("DATA", str(CALISCOPE))
    ran = []
    for block in code_blocks(REPO / "docs" / "tutorial.md", "bash"):
        for line in commands(block):
            if line.startswith("DATA="):
                continue  # the reader's own path; the test's is in the environment
            if line.startswith("mvviz detect"):
                line += " --every 10"
            run_shell_command(line.replace("$DATA", str(CALISCOPE)), tmp_path, env)
            ran.append(line.split()[1] if line.startswith("mvviz") else "view")
    assert ran == ["calibrate", "detect", "run", "diagnose", "view", "export", "export"]
    capture = tmp_path / "capture"
    for name in ("cameras.json", "Calib.toml", "calibration_report.html", "detections.npz",
                 "person.trc", "person.glb"):  # fmt: skip
        assert (capture / name).stat().st_size > 0, name


NARRATION = [
    re.compile(r"\bstops? [0-9]+\b", re.I),
    re.compile(r"\bissue #?[0-9]+\b", re.I),
    re.compile(r"\bthis session\b|\bthe previous session\b", re.I),
]


WORK_DATE = re.compile(r"\b20[0-9]{2}-[01][0-9]-[0-3][0-9]\b")
"""A date in the product's text: the benchmarks' pages carry the date of their run, tests
may hold dates as data; anywhere else a date is the history of the work."""


def test_the_product_does_not_narrate_its_making():
    """README, docs, docstrings, comments, tests and benchmarks say what the product does,
    never how it was made (work steps, issue numbers)."""
    files = subprocess.run(
        ["git", "ls-files", "*.py", "*.md", "*.toml", "*.yml", "*.html"],
        cwd=REPO, capture_output=True, text=True, check=True,
    ).stdout.split()  # fmt: skip
    found = []
    for name in files:
        path = REPO / name
        if not path.is_file() or name == "tests/test_docs.py":
            continue
        dated = not name.startswith(("tests/", "docs/benchmarks/"))  # test inputs; run dates
        for n, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
            if any(p.search(line) for p in NARRATION) or (dated and WORK_DATE.search(line)):
                found.append(f"{name}:{n}: {line.strip()[:100]}")
    assert not found, "\n".join(found[:30])
