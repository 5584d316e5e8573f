"""SIGKILL of the real command-line processes at random points, repeated: ``mvviz run``
(results file) and ``mvviz convert --overwrite`` (scene directory). Afterwards the old or
the new output is in place and complete, and the next run of the same command leaves no
temporary file behind. Complements tests/pipeline/test_kill.py, which kills looping
writer scripts many times; these are fewer kills (each start pays Python's imports)."""

from __future__ import annotations

import os
import random
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from pipeline.data.scene import load_scene
from pipeline.results.store import load_results
from tests.conftest import REPO
from tests.pipeline.layout_data import layout_detections, write_openpose_tree

DEMO = REPO / "sample_data" / "pose2sim_demo"
SHELF = REPO / "sample_data" / "rigs" / "shelf_voxelpose.json"
KILLS = 3


def _kill_at_random(cmd: list[str], lo: float, hi: float, seed: int) -> int:
    """Start ``cmd``, SIGKILL it after a random delay in [lo, hi] s; its return code."""
    proc = subprocess.Popen(
        cmd, cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        env={**os.environ, "PYTHONPATH": str(REPO)},
    )  # fmt: skip
    time.sleep(random.Random(seed).uniform(lo, hi))
    proc.send_signal(signal.SIGKILL)
    return proc.wait()


def _leftovers(directory: Path) -> list[str]:
    return sorted(p.name for p in directory.iterdir() if p.name.startswith("."))


def test_killed_mvviz_run_leaves_old_or_new_results(tmp_path):
    scene = tmp_path / "demo"
    shutil.copytree(DEMO, scene, ignore=shutil.ignore_patterns(".mvviz"))
    out = tmp_path / "out" / "results.npz"
    out.parent.mkdir()
    cmd = [sys.executable, "-m", "mvviz.cli", "run", str(scene), "--out", str(out),
           "--set", "fit_smpl=false"]  # fmt: skip
    for i in range(KILLS):
        _kill_at_random(cmd, 2.0, 9.0, seed=i)
        if out.exists():  # a complete file, never a torn one
            assert load_results(out).num_frames == 100
    done = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert load_results(out).num_frames == 100
    assert _leftovers(out.parent) == []  # the dead writers' temporaries are gone


@pytest.fixture(scope="module")
def openpose_dir(tmp_path_factory):
    from pipeline.data.joint_sets import BODY25B

    root = tmp_path_factory.mktemp("op") / "op"
    write_openpose_tree(root, layout_detections(BODY25B, frames=slice(0, 250, 2)), list("01234"))
    return root


def test_killed_mvviz_convert_overwrite_leaves_a_complete_scene(tmp_path, openpose_dir):
    out = tmp_path / "scene"
    cmd = [sys.executable, "-m", "mvviz.cli", "convert", "--from", "voxelpose", str(SHELF),
           "--detections-from", "openpose", "--detections", str(openpose_dir),
           "-o", str(out), "--overwrite"]  # fmt: skip
    assert subprocess.run(cmd, cwd=REPO, capture_output=True, timeout=300).returncode == 0
    for i in range(KILLS):
        _kill_at_random(cmd, 2.0, 7.0, seed=10 + i)
        scene = load_scene(out)  # completes or rolls back an interrupted replacement
        assert scene.joint_set.name == "body25b" and len(scene.detections) > 0
    assert subprocess.run(cmd, cwd=REPO, capture_output=True, timeout=300).returncode == 0
    load_scene(out)
    assert _leftovers(tmp_path) == []
