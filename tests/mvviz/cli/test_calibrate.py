"""Tests of ``mvviz calibrate`` (mvviz/cli/calibrate.py), called through ``mvviz.cli.main``."""

from __future__ import annotations

import pytest

from mvviz.cli import main
from pipeline.data.cameras import load_cameras
from pipeline.importers.calibration import write_caliscope_calibration
from tests.conftest import SHARED_DATA
from tests.pipeline.calibrate_synth import SPEC, board_poses, default_rig, write_session


@pytest.mark.slow
def test_calibrate_writes_both_files_and_prints_each_camera(tmp_path, capsys):
    rig = default_rig().subset([0, 1])
    folders = write_session(tmp_path / "footage", rig, board_poses(24, seed=2))
    intr = write_caliscope_calibration(rig, tmp_path / "camera_array.toml")
    out = tmp_path / "out"
    code = main(["calibrate", *map(str, folders), "--board", SPEC, "-o", str(out),
                 "--intrinsics", str(intr), "--floor-frame", "0"])  # fmt: skip
    printed = capsys.readouterr().out
    assert code == 0, printed
    assert "left" in printed and "front" in printed and "BA RMS" in printed
    assert sorted(p.name for p in out.iterdir()) == [
        "Calib.toml",
        "calibration_report.html",
        "cameras.json",
    ]
    assert load_cameras(out / "cameras.json").names == ["left", "front"]
    page = (out / "calibration_report.html").read_text()
    assert page.count("<svg") == 2 and "BA RMS" in page


def test_bad_inputs_are_one_line_and_write_nothing(tmp_path, capsys):
    video = tmp_path / "cam.mp4"
    video.write_bytes(b"not a video")
    out = tmp_path / "out"
    for board in ("charuco:4x5:0.054", SPEC):
        code = main(["calibrate", str(video), "--board", board, "-o", str(out)])
        err = capsys.readouterr().err
        errors = [line for line in err.splitlines() if "error" in line]
        assert code == 2 and len(errors) == 1 and errors[0].startswith("mvviz calibrate: error:")
    assert not out.exists()


CALISCOPE = SHARED_DATA / "caliscope_charuco"


@pytest.mark.slow
@pytest.mark.skipif(not CALISCOPE.is_dir(), reason="../shared/data/caliscope_charuco is absent")
def test_calibrate_detect_run_on_the_real_session(tmp_path):
    """The real four-webcam session end to end: its board calibrates the cameras, the
    calibration folder takes the same videos' detections (every 10th frame), and the run
    follows the one person who holds the board, reprojecting within a few pixels."""
    import numpy as np

    from pipeline.results.store import load_results

    videos = CALISCOPE / "extrinsic"
    out = tmp_path / "calibration"
    assert main(["calibrate", *[str(videos / f"cam_{k}.mp4") for k in range(4)],
                 "--board", str(CALISCOPE / "charuco.toml"),
                 "--sync", str(videos / "timestamps.csv"), "-o", str(out)]) == 0  # fmt: skip
    pytest.importorskip("ai_edge_litert")
    assert main(["detect", str(out), "--videos", str(videos), "--every", "10"]) == 0
    assert main(["run", str(out)]) == 0
    results = load_results(out / ".mvviz" / "results.npz")
    lengths = np.isfinite(results.track_raw).all(-1).any(-1).sum(1)
    assert int((lengths >= 5).sum()) == 1  # one person, followed by one track
    used = results.person_used & np.isfinite(results.person_reproj)
    assert float(np.median(results.person_reproj[used])) < 15.0
