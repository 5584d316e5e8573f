"""SIGKILL of ``mvviz export``, ``mvviz batch`` and ``mvviz detect`` at random points,
repeated, over a complete earlier output: afterwards the earlier (or a new) output is in
place and whole, and the next complete run leaves no temporary behind. The kill points
are spread over one complete run of the same command, timed first. Companion of
tests/pipeline/test_kill_cli.py (``mvviz run``, ``mvviz convert``, the viewer's re-run).
"""

from __future__ import annotations

import json
import os
import random
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from pipeline.data.scene import load_scene
from pipeline.results.store import load_results
from tests.conftest import REPO

pytestmark = pytest.mark.slow

DEMO = REPO / "sample_data" / "pose2sim_demo"
KILLS = 3
ENV = {**os.environ, "PYTHONPATH": str(REPO)}


def _descendants(pid: int) -> list[int]:
    """Every live descendant of ``pid`` (from /proc)."""
    kids: dict[int, list[int]] = {}
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                stat = Path(f"/proc/{entry}/stat").read_text()
                ppid = int(stat.rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                continue
            kids.setdefault(ppid, []).append(int(entry))
    out, todo = [], [pid]
    while todo:
        for k in kids.get(todo.pop(), []):
            out.append(k)
            todo.append(k)
    return out


def _run(cmd: list[str]) -> float:
    """Run ``cmd`` to the end; its wall time."""
    t0 = time.monotonic()
    done = subprocess.run(cmd, cwd=REPO, env=ENV, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    return time.monotonic() - t0


def _kill_at(cmd: list[str], delay: float) -> None:
    """Start ``cmd``, SIGKILL it after ``delay`` s with every process it started (Ray's),
    each by its id."""
    proc = subprocess.Popen(
        cmd, cwd=REPO, env=ENV, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        start_new_session=True,
    )  # fmt: skip
    seen: set[int] = set()
    stop = threading.Event()

    def watch() -> None:  # its children come and go: note each one seen
        while not stop.is_set():
            seen.update(_descendants(proc.pid))
            stop.wait(0.1)

    watcher = threading.Thread(target=watch, daemon=True)
    watcher.start()
    time.sleep(delay)
    seen.update(_descendants(proc.pid))
    stop.set()
    watcher.join()
    for pid in [proc.pid, *seen]:
        try:
            os.kill(pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
    proc.wait(timeout=30)


def _kills(cmd: list[str], seconds: float, seed: int, check) -> None:
    """``KILLS`` kills of ``cmd`` spread over ``seconds``, ``check()`` after each."""
    rng = random.Random(seed)
    for _ in range(KILLS):
        _kill_at(cmd, rng.uniform(0.2, 1.0) * seconds)
        check()


def _temporaries(*folders: Path) -> list[str]:
    """Dot files and folders the writers leave while writing (their temporaries)."""
    return sorted(
        str(p) for d in folders if d.is_dir() for p in d.iterdir()
        if p.name.startswith(".") and p.name != ".mvviz"
    )  # fmt: skip


@pytest.fixture
def demo(tmp_path) -> Path:
    scene = tmp_path / "demo"
    shutil.copytree(DEMO, scene, ignore=shutil.ignore_patterns(".mvviz"))
    return scene


def test_killed_mvviz_export_leaves_the_old_or_new_file(demo, tmp_path):
    from pipeline.exports.markers import read_c3d_points

    _run([sys.executable, "-m", "mvviz.cli", "run", str(demo), "--set", "fit_smpl=false"])
    out = tmp_path / "out" / "run.c3d"
    cmd = [sys.executable, "-m", "mvviz.cli", "export", str(demo), "--format", "c3d",
           "-o", str(out), "--set", "fit_smpl=false"]  # fmt: skip
    seconds = _run(cmd)
    frames = read_c3d_points(out)[1].shape

    def whole() -> None:
        assert read_c3d_points(out)[1].shape == frames  # never torn, never gone

    _kills(cmd, seconds, 1, whole)
    _run(cmd)
    whole()
    assert _temporaries(out.parent) == []


def test_killed_mvviz_batch_leaves_whole_results_and_report(demo, tmp_path):
    report = tmp_path / "report"
    cmd = [sys.executable, "-m", "mvviz.cli", "batch", str(demo), "--set", "fit_smpl=false",
           "--force", "--num-cpus", "2", "--report", str(report)]  # fmt: skip
    seconds = _run(cmd)
    results = demo / ".mvviz" / "results.npz"

    def whole() -> None:
        assert load_results(results).num_frames == 100
        json.loads((report / "batch_report.json").read_text())

    whole()
    _kills(cmd, seconds, 2, whole)
    _run(cmd)
    whole()
    assert _temporaries(report, results.parent) == []


def test_killed_mvviz_detect_keeps_the_scene_whole_and_resumes(tmp_path):
    pytest.importorskip("ai_edge_litert")
    scene = tmp_path / "scene"
    scene.mkdir()
    shutil.copy(DEMO / "cameras.json", scene)
    cmd = [sys.executable, "-m", "mvviz.cli", "detect", str(scene), "--videos",
           str(DEMO / "videos"), "--max-frames", "8", "--no-progress", "--overwrite"]  # fmt: skip
    seconds = _run(cmd)
    first = load_scene(scene)

    def whole() -> None:
        s = load_scene(scene)  # the scene and its detections read whole
        assert s.num_frames == first.num_frames and len(s.detections) > 0

    _kills(cmd, seconds, 3, whole)
    _run(cmd)
    whole()
    assert _temporaries(scene, scene / ".mvviz", scene / ".mvviz" / "detect") == []
