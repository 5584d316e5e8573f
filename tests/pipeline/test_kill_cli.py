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

pytestmark = pytest.mark.slow

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


# The viewer re-running the pipeline on changed settings and saving them (the Pipeline
# panel's "Save into run config": the config at once, the results when the re-run lands),
# CYCLES times (0: for ever); each threshold printed once both are written.
VIEWER_RERUN = r"""
import dataclasses, itertools, sys
from mvviz.app import ViewerApp
from mvviz.state import ViewerState
from pipeline.body.model import load_body_model
from pipeline.config import PipelineConfig
from pipeline.data.scene import load_scene
from pipeline.run.pipeline import run_or_load

scene, cycles = load_scene(sys.argv[1]), int(sys.argv[2])
model = load_body_model()
results, _ = run_or_load(scene, PipelineConfig(fit_smpl=False), model, progress=False)
app = ViewerApp(ViewerState.create(scene, results, model), port=0)
panel = app.pipeline_panel
print("ready", flush=True)
for i in itertools.count(1):
    base = panel.base.config
    px = 10.0 + (i % 7) * 5.0
    panel.set_config(dataclasses.replace(
        base, triangulation=dataclasses.replace(base.triangulation, outlier_threshold_px=px)))
    panel.save()
    assert panel.wait_idle(300)
    print("saved", px, flush=True)
    if i == cycles:
        break
app.stop()
"""
RERUN_PX = {10.0 + k * 5.0 for k in range(7)}


def _viewer_rerun(scene: Path, cycles: int = 0) -> subprocess.Popen:
    proc = subprocess.Popen(
        [sys.executable, "-c", VIEWER_RERUN, str(scene), str(cycles)], cwd=REPO, text=True,
        stdout=subprocess.PIPE, stderr=subprocess.PIPE,
        env={**os.environ, "PYTHONPATH": str(REPO)},
    )  # fmt: skip
    for line in proc.stdout:  # viser's banner first
        if line.strip() == "ready":
            return proc
    proc.kill()
    raise AssertionError(f"the viewer did not start: {proc.stderr.read()[-2000:]}")


def test_killed_viewer_rerun_leaves_old_or_new_results(tmp_path):
    """SIGKILL of a viewer re-running and saving, at random points of a save cycle (the
    first cycle of each start times it): the results at the default path and the saved
    config are whole, the results are the first run's or a saved re-run's, and the next
    save leaves no temporary behind."""
    from pipeline.config import CONFIG_FILE, PipelineConfig, load_config
    from pipeline.results.store import default_results_path

    scene_dir = tmp_path / "demo"
    shutil.copytree(DEMO, scene_dir, ignore=shutil.ignore_patterns(".mvviz"))
    results_path = default_results_path(load_scene(scene_dir))
    first_px = PipelineConfig().triangulation.outlier_threshold_px
    rng = random.Random(7)
    for _ in range(KILLS):
        proc = _viewer_rerun(scene_dir)
        t0 = time.monotonic()
        assert "saved" in proc.stdout.readline()  # one whole cycle: its length
        time.sleep(rng.uniform(0.0, 1.5 * (time.monotonic() - t0)))
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        res = load_results(results_path)  # whole, never torn
        assert res.config.triangulation.outlier_threshold_px in RERUN_PX | {first_px}
        load_config(scene_dir / CONFIG_FILE)  # whole JSON
    proc = _viewer_rerun(scene_dir, cycles=1)  # the next run: one cycle, then it stops
    out, err = proc.communicate(timeout=300)
    assert proc.returncode == 0 and "saved" in out, err[-2000:]
    load_scene(scene_dir)
    assert _leftovers(results_path.parent) == [], "a dead writer's temporary outlived a save"
    assert [p for p in _leftovers(scene_dir) if p != ".mvviz"] == []
