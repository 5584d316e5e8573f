"""Tests of ``mvviz calibrate`` (mvviz/cli/calibrate.py), called through ``mvviz.cli.main``."""

from __future__ import annotations

from mvviz.cli import main
from pipeline.data.cameras import load_cameras
from pipeline.importers.calibration import write_caliscope_calibration
from tests.pipeline.calibrate_synth import SPEC, board_poses, default_rig, write_session


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
