"""SIGKILL at random points of the project's writers, repeated: afterwards the old or the
new output is in place and complete, and no temporary file outlives the next run
(pipeline/core/files.py). Small data, a few repetitions: about half a minute."""

from __future__ import annotations

import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from pipeline.core.files import load_npz, recover, save_npz_atomic
from pipeline.data.scene import load_scene
from tests.conftest import REPO

# A writer that loops forever: "results" rewrites one npz file (what mvviz run does),
# "scene" writes scenes A and B over each other (mvviz convert --overwrite), "fresh"
# writes new scene directories (mvviz convert); each write is stamped with its number.
WRITER = r"""
import sys, numpy as np
from pathlib import Path
from pipeline.core.files import save_npz_atomic
from pipeline.importers.calibration import read_voxelpose_calibration
from pipeline.data.joint_sets import COCO17
from pipeline.data.scene import Detections, write_scene

kind, out = sys.argv[1], Path(sys.argv[2])
rig = read_voxelpose_calibration("sample_data/rigs/campus_voxelpose.json")
big = np.random.default_rng(0).normal(size=(200_000,))
print("ready", flush=True)
i = 0
while True:
    i += 1
    if kind == "results":
        save_npz_atomic(out, stamp=np.array(i), data=big + i)
        continue
    n = 300
    kp = np.concatenate([np.full((n, 17, 2), 100.0), np.full((n, 17, 1), 0.5)], 2)
    det = Detections(frame=np.arange(n) % 50, view=np.arange(n) % 3, keypoints=kp)
    target = out if kind == "scene" else out / f"s{i % 3}"
    write_scene(target, name=f"v{i}", fps=25, num_frames=50, joint_set=COCO17, rig=rig,
                detections=det, overwrite=True)
"""


def _kill_at_random(kind: str, out: Path, rng: random.Random) -> None:
    proc = subprocess.Popen(
        [sys.executable, "-c", WRITER, kind, str(out)],
        cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    assert proc.stdout.readline().strip() == "ready", proc.stderr.read()
    time.sleep(rng.uniform(0.05, 0.6))
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()


def _leftovers(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if p.name.startswith("."))


@pytest.mark.slow
def test_killed_results_writer_leaves_a_whole_file_and_no_temp_for_long(tmp_path):
    rng = random.Random(0)
    out = tmp_path / ".mvviz" / "results.npz"
    for _ in range(4):
        _kill_at_random("results", out, rng)
        if out.exists():  # the file in place is always whole: the old one or a new one
            a = load_npz(out)  # (on a busy machine the writer may be killed before it wrote)
            old = int(a["stamp"]) == -1 and a["data"].shape == (3,)
            assert old or (int(a["stamp"]) >= 1 and a["data"].shape == (200_000,))
        save_npz_atomic(out, stamp=np.array(-1), data=np.zeros(3))  # the next run
        assert _leftovers(out.parent) == []
        assert int(load_npz(out)["stamp"]) == -1


@pytest.mark.slow
def test_killed_overwrite_keeps_the_old_or_the_new_scene_whole(tmp_path):
    rng = random.Random(1)
    out = tmp_path / "scene"
    for _ in range(5):
        _kill_at_random("scene", out, rng)
        if not out.exists() and not _leftovers(tmp_path):
            continue  # killed before the first scene was complete: nothing to keep
        scene = load_scene(out)  # completes an interrupted replacement first
        assert scene.name.startswith("v") and len(scene.detections) == 300
        assert _leftovers(tmp_path) == []


@pytest.mark.slow
def test_killed_convert_leaves_no_hidden_folders_after_the_next_run(tmp_path):
    rng = random.Random(2)
    for _ in range(3):
        _kill_at_random("fresh", tmp_path, rng)
        for i in range(3):
            target = tmp_path / f"s{i}"
            recover(target)  # what the next write or load of that target does first
            if target.exists():
                assert len(load_scene(target).detections) == 300
        assert _leftovers(tmp_path) == []


def _dead_pid() -> int:
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def _dir(path: Path, text: str) -> Path:
    path.mkdir()
    (path / "scene.json").write_text(text)
    return path


def test_recover_completes_or_rolls_back_each_interrupted_state(tmp_path):
    pid = _dead_pid()
    target = tmp_path / "s"
    # killed between the two renames: the complete new one is put in place
    _dir(tmp_path / f".s.old-{pid}", "old")
    _dir(tmp_path / f".s.new-{pid}", "new")
    recover(target)
    assert (target / "scene.json").read_text() == "new" and _leftovers(tmp_path) == []
    # killed before the old one moved away: the old one stays
    _dir(tmp_path / f".s.new-{pid}", "newer")
    recover(target)
    assert (target / "scene.json").read_text() == "new" and _leftovers(tmp_path) == []
    # only the old one left (the new one lost): roll back
    (target / "scene.json").rename(tmp_path / "x")
    target.rmdir()
    _dir(tmp_path / f".s.old-{pid}", "old")
    recover(target)
    assert (target / "scene.json").read_text() == "old" and _leftovers(tmp_path) == []
    # temporaries: a dead writer's go, a live one's (ours) stays
    _dir(tmp_path / f".s.{pid}.abc123.tmp", "half")
    (tmp_path / f".s.{os.getpid()}.def456.tmp").write_text("busy")
    recover(target)
    assert _leftovers(tmp_path) == [f".s.{os.getpid()}.def456.tmp"]
