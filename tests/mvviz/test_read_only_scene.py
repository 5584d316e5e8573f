"""A scene folder that cannot be written still opens in the viewer: its results and
decoded videos go to the user's cache (pipeline.core.files.scene_cache_dir), which the
log says once, and nothing in the scene changes.

The viewer runs in a process of its own (as ``mvviz view`` does) on a copy of the tiny
scene made read-only with chmod. Root writes through chmod, so as root that process runs
without the capabilities that let it (``setpriv`` drops CAP_DAC_OVERRIDE and
CAP_DAC_READ_SEARCH from what it executes); the process checks that it really cannot
write the folder, so the test cannot pass on a folder that is writable after all.
"""

from __future__ import annotations

import json
import os
import shutil
import stat
import subprocess
import sys
from pathlib import Path

import pytest

from pipeline.core.files import CACHE_ENV
from tests.conftest import REPO

pytestmark = pytest.mark.slow

VIEW = r"""
import argparse, json, sys
from mvviz.cli.view import add_view_options, start
from pipeline.core.files import cannot_write
from pipeline.results.store import default_results_path

parser = argparse.ArgumentParser()
add_view_options(parser)
app = start(parser.parse_args([sys.argv[1], "--port", "0"]), progress=False)
try:
    decoded = app.frames.wait(120)
    idle = app.wait_idle(60)
    print(json.dumps({
        "cannot_write": cannot_write(sys.argv[1]),
        "results": str(default_results_path(app.state.scene)),
        "export_dir": str(app.writes.export_dir),
        "decoded": decoded, "idle": idle, "render_errors": app.render_errors,
    }))
finally:
    app.stop()
"""


def _unprivileged() -> list[str]:
    """The command prefix that runs a program without root's power over file modes."""
    if os.geteuid() != 0:
        return []
    if shutil.which("setpriv") is None:
        pytest.skip("as root, a read-only folder needs setpriv (util-linux) to drop root's "
                    "CAP_DAC_OVERRIDE; it is absent")  # fmt: skip
    return ["setpriv", "--bounding-set", "-dac_override,-dac_read_search"]


def _snapshot(root: Path) -> dict[str, tuple[int, int]]:
    return {str(p.relative_to(root)): (p.stat().st_size, p.stat().st_mtime_ns)
            for p in sorted(root.rglob("*"))}  # fmt: skip


def _set_writable(root: Path, writable: bool) -> None:
    bits = stat.S_IWUSR | stat.S_IWGRP | stat.S_IWOTH
    for p in [root, *root.rglob("*")]:
        mode = p.stat().st_mode
        p.chmod(mode | stat.S_IWUSR if writable else mode & ~bits)


def _view(scene: Path, cache: Path) -> tuple[dict, str, str]:
    done = subprocess.run(
        [*_unprivileged(), sys.executable, "-c", VIEW, str(scene)],
        cwd=REPO, capture_output=True, text=True, timeout=600,
        env={**os.environ, "PYTHONPATH": str(REPO), CACHE_ENV: str(cache)},
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    (figures,) = [line for line in done.stdout.splitlines() if line.startswith("{")]
    return json.loads(figures), done.stdout, done.stderr


def test_a_read_only_scene_opens_with_its_caches_elsewhere(viewer_scene, tmp_path):
    scene = tmp_path / "scene"
    shutil.copytree(viewer_scene[0].root, scene, ignore=shutil.ignore_patterns(".mvviz"))
    cache = tmp_path / "user_cache"
    before = _snapshot(scene)
    _set_writable(scene, False)
    try:
        first, out1, err1 = _view(scene, cache)
        second, out2, err2 = _view(scene, cache)
    finally:
        _set_writable(scene, True)  # for pytest's cleanup
    assert first["cannot_write"], "the folder was writable after all: nothing was tested"
    for run in (first, second):
        assert run["decoded"] and run["idle"] and not run["render_errors"], run
        assert Path(run["results"]).is_relative_to(cache / "scenes")
        assert Path(run["export_dir"]).is_relative_to(cache / "scenes")
    assert "computed results" in out1 and "cached results" in out2  # the second start is warm
    for err in (err1, err2):  # said once per start
        said = [line for line in err.splitlines() if "cannot be written" in line]
        assert len(said) == 1 and str(cache) in said[0], err[-2000:]
    assert Path(first["results"]).is_file()
    assert list((Path(first["results"]).parent / "frames").glob("*.npz"))  # decoded videos
    assert _snapshot(scene) == before  # nothing written, moved or touched in the scene
