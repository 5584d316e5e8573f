"""Bad input of each command beyond the scene corpus (test_errors.py): synth's rigs,
export's and export-rrd's choices, detect's videos and crops, diagnose's outputs,
train-prior's data, batch's settings and cluster address, convert's calibrations and
protocol truth. Every case: exit code 2, one line ``mvviz CMD: error: ...`` naming the
file or option and what was expected, no traceback, nothing written."""

from __future__ import annotations

import re
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from mvviz.cli import main
from tests.conftest import CAMPUS_CALIB
from tests.pipeline.malformed import write_tiny_scene

PROGRESS = re.compile(r"^[^:]+: \d+/\d+ \S+ in [\d.]+ s$")


@dataclass(frozen=True)
class BadInput:
    """``argv`` with ``{scene}`` / ``{tmp}`` filled in; ``needles`` must all be in the
    error line; ``out`` (under ``{tmp}``) must not exist afterwards."""

    name: str
    argv: tuple[str, ...]
    needles: tuple[str, ...]
    out: str = "out"
    setup: str = ""


def _setup(kind: str, tmp: Path) -> None:
    if kind == "bad_json":
        (tmp / "rig.json").write_text("{")
    elif kind == "no_cameras":
        (tmp / "rig.json").write_text('{"a": 1}')
    elif kind == "not_a_video":
        (tmp / "videos").mkdir()
        (tmp / "videos" / "0.mp4").write_text("not a video")
    elif kind == "no_videos":
        (tmp / "videos").mkdir()
    elif kind == "empty_root":
        (tmp / "empty").mkdir()
    elif kind == "short_poses":
        np.savez(tmp / "poses.npz", poses=np.zeros((5, 10)))
    elif kind == "object_poses":
        np.savez(tmp / "poses.npz", poses=np.array([{}], dtype=object))
    elif kind == "truth_without_joints":
        np.savez(tmp / "gt.npz", frame=np.zeros(2, int), person_id=np.zeros(2, int))


CASES = [
    BadInput("synth rig file missing", ("synth", "{tmp}/out", "--rig", "{tmp}/none.json",
             "--people", "1", "--frames", "3"), ("none.json", "not found")),
    BadInput("synth rig not JSON", ("synth", "{tmp}/out", "--rig", "{tmp}/rig.json",
             "--people", "1", "--frames", "3"), ("rig.json", "not valid JSON"), setup="bad_json"),
    BadInput("synth rig without cameras", ("synth", "{tmp}/out", "--rig", "{tmp}/rig.json",
             "--people", "1", "--frames", "3"), ("rig.json", "'cameras'"), setup="no_cameras"),
    BadInput("synth dome spec", ("synth", "{tmp}/out", "--rig", "dome:x", "--people", "1",
             "--frames", "3"), ("dome:x", "'--rig'", "dome:N")),
    BadInput("export track not a number", ("export", "{scene}", "--format", "trc", "--track",
             "abc", "-o", "{tmp}/out"), ("--track", "'all' or a track id")),
    BadInput("export format", ("export", "{scene}", "--format", "xyz", "-o", "{tmp}/out"),
             ("--format", "invalid choice")),
    BadInput("detect videos missing", ("detect", "{scene}", "--videos", "{tmp}/none",
             "--overwrite"), ("--videos", "neither a file nor a directory")),
    BadInput("detect not a video", ("detect", "{scene}", "--videos", "{tmp}/videos",
             "--overwrite"), ("0.mp4", "cannot decode"), setup="not_a_video"),
    BadInput("detect no videos", ("detect", "{scene}", "--videos", "{tmp}/videos",
             "--overwrite"), ("no video files",), setup="no_videos"),
    BadInput("detect crop spec", ("detect", "{scene}", "--videos", "{tmp}/videos",
             "--overwrite", "--video-crop", "cam0=1,2"), ("--video-crop", "LEFT,TOP,RIGHT,BOTTOM"),
             setup="no_videos"),
    BadInput("detect every 0", ("detect", "{scene}", "--videos", "{tmp}/videos", "--overwrite",
             "--every", "0"), ("--every", ">= 1"), setup="no_videos"),
    BadInput("diagnose scene missing", ("diagnose", "{tmp}/none"), ("scene.json", "not found")),
    BadInput("train-prior data missing", ("train-prior", "--data", "{tmp}/none.npz", "--out",
             "{tmp}/out"), ("none.npz", "'poses'")),
    BadInput("train-prior poses too short", ("train-prior", "--data", "{tmp}/poses.npz",
             "--out", "{tmp}/out"), ("poses.npz", "(N, 72)"), setup="short_poses"),
    BadInput("train-prior object array", ("train-prior", "--data", "{tmp}/poses.npz", "--out",
             "{tmp}/out"), ("poses.npz", "'poses'", "numeric"), setup="object_poses"),
    BadInput("batch bad --set", ("batch", "{scene}", "--set", "kalman.q=abc", "--out",
             "{tmp}/out"), ("--set", "'kalman.q'", "finite number")),
    BadInput("batch bad sweep value", ("batch", "{scene}", "--sweep", "kalman.q=1,abc",
             "--out", "{tmp}/out"), ("--sweep", "kalman.q")),
    BadInput("batch config missing", ("batch", "{scene}", "--config", "{tmp}/none.json",
             "--out", "{tmp}/out"), ("none.json", "not found")),
    BadInput("batch address unparsed", ("batch", "{scene}", "--address", "foo", "--out",
             "{tmp}/out"), ("'--address'", "HOST:PORT")),
    BadInput("batch address nobody answers", ("batch", "{scene}", "--address", "127.0.0.1:1",
             "--out", "{tmp}/out"), ("'--address'", "no Ray head answers")),
    BadInput("batch empty root", ("batch", "--root", "{tmp}/empty", "--out", "{tmp}/out"),
             ("no scenes",), setup="empty_root"),
    BadInput("convert calibration missing", ("convert", "--from", "voxelpose", "{tmp}/none.json",
             "-o", "{tmp}/out"), ("none.json",)),
    BadInput("convert protocol truth", ("convert", "--from", "voxelpose", str(CAMPUS_CALIB),
             "--protocol-gt", "{tmp}/gt.npz", "-o", "{tmp}/out"), ("gt.npz", "'joints3d'"),
             setup="truth_without_joints"),
    BadInput("eval --gt without --protocol", ("eval", "{scene}", "--gt", "{tmp}/gt.npz",
             "--no-sync"), ("gt.npz", "--protocol"), setup="truth_without_joints"),
]  # fmt: skip


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> Path:
    return write_tiny_scene(tmp_path_factory.mktemp("tiny") / "scene")


@pytest.mark.parametrize("case", CASES, ids=[c.name for c in CASES])
def test_bad_input_is_one_line_exit_2_and_writes_nothing(case, tiny, tmp_path, capsys):
    scene = tmp_path / "scene"
    shutil.copytree(tiny, scene)
    before = sorted(p.relative_to(scene) for p in scene.rglob("*"))
    _setup(case.setup, tmp_path)
    argv = [a.format(scene=scene, tmp=tmp_path) for a in case.argv]
    capsys.readouterr()
    try:
        code = main(argv)
    except SystemExit as exc:  # argparse's usage errors
        code = exc.code
    text = capsys.readouterr().err
    assert "Traceback" not in text, text
    # leave out progress lines of the stages a command ran before refusing
    # ("associate+triangulate: 4/4 frame in 0.0 s") and argparse's usage lines
    err = [line for line in text.strip().splitlines()
           if line.strip() and not PROGRESS.match(line)
           and not line.startswith(("usage:", " "))]  # fmt: skip
    assert code == 2, err
    assert len(err) == 1 and "Traceback" not in err[0], err
    assert err[0].startswith(f"mvviz {case.argv[0]}: error: "), err[0]
    for needle in case.needles:
        assert needle in err[0], (needle, err[0])
    assert not (tmp_path / case.out).exists()
    assert sorted(p.relative_to(scene) for p in scene.rglob("*")) == before


@pytest.mark.slow
def test_a_full_disk_is_one_line_and_the_old_results_stay(tiny, tmp_path):
    """A write that runs out of room (here a file-size limit, RLIMIT_FSIZE) is exit 2, one
    line naming the file, and the previous results are left as they were."""
    import resource
    import subprocess
    import sys

    scene = tmp_path / "scene"
    shutil.copytree(tiny, scene)
    assert main(["run", str(scene)]) == 0
    results = scene / ".mvviz" / "results.npz"
    old = results.read_bytes()
    assert len(old) > 4000

    def limit() -> None:
        resource.setrlimit(resource.RLIMIT_FSIZE, (4000, 4000))

    proc = subprocess.run(
        [sys.executable, "-m", "mvviz.cli", "run", str(scene), "--force"],
        capture_output=True, text=True, preexec_fn=limit, timeout=300,
    )  # fmt: skip
    lines = [ln for ln in proc.stderr.strip().splitlines() if not PROGRESS.match(ln)]
    assert proc.returncode == 2, proc.stderr
    assert len(lines) == 1 and "File too large" in lines[0] and "results.npz" in lines[0], lines
    assert results.read_bytes() == old
    assert not [p for p in results.parent.iterdir() if p.name.endswith(".tmp")]
