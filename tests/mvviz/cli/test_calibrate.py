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
        "calibration.npz",
        "calibration_report.html",
        "cameras.json",
    ]
    assert load_cameras(out / "cameras.json").names == ["left", "front"]
    page = (out / "calibration_report.html").read_text()
    assert page.count("<svg") == 2 and "BA RMS" in page


def test_checkerboard_end_to_end(tmp_path, capsys):
    """A plain checkerboard (7 x 6 squares of 50 mm: 6 x 5 inner corners, every corner or
    none) rendered into the three synthetic cameras, the portrait one rolled 90 deg;
    calibrated from scratch: intrinsics and relative poses recovered. One view of "left"
    sees the board nearly edge-on, its corners found 1-3 px off: left out of the
    intrinsics (kept, it made left's focal 1.5 % short and the poses 1.3 deg off)."""
    import numpy as np

    from pipeline.calibrate.board import parse_board
    from tests.pipeline.calibrate_synth import checkerboard_image

    spec = "checkerboard:7x6:0.05"
    board = parse_board(spec)
    rig = default_rig()
    folders = write_session(tmp_path / "footage", rig, board_poses(30, seed=11),
                            image=checkerboard_image(board))  # fmt: skip
    out = tmp_path / "out"
    code = main(["calibrate", *map(str, folders), "--board", spec, "-o", str(out)])
    printed = capsys.readouterr().out
    assert code == 0, printed
    got = load_cameras(out / "cameras.json")
    assert got.names == rig.names
    for cam, true in zip(got, rig, strict=True):
        np.testing.assert_allclose(cam.K[[0, 1], [0, 1]], true.K[[0, 1], [0, 1]], rtol=0.02)
    for i, j in ((0, 1), (0, 2), (1, 2)):
        R, R0 = got[j].R @ got[i].R.T, rig[j].R @ rig[i].R.T
        t, t0 = got[j].t - R @ got[i].t, rig[j].t - R0 @ rig[i].t
        angle = np.degrees(np.arccos(np.clip((np.trace(R @ R0.T) - 1) / 2, -1, 1)))
        assert angle < 1.0 and np.linalg.norm(t - t0) < 0.03 * np.linalg.norm(t0), (i, j)
    saved = np.load(out / "calibration.npz")
    assert len(saved["corner_id"]) % board.num_corners == 0  # whole boards only


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
    # now a scene: mvviz view opens the scene viewer, with the calibration in a tab
    from mvviz.cli import build_parser
    from mvviz.cli.view import is_calibration_folder, start, stop
    from tests.mvviz.conftest import free_port

    assert not is_calibration_folder(out)
    app = start(build_parser(["view"]).parse_args(["view", str(out), "--port",
                                                   str(free_port())]), progress=False)  # fmt: skip
    try:
        panel = app.calibration_panel
        assert panel is not None and panel.embedded and not panel.group.visible
        panel.show_boards.value = True
        assert panel.group.visible
        panel.select(camera=1, frame=96)
        assert "**cam_1**, frame 96" in panel.view_line.content
        assert panel.image.image.shape[1] == 320
    finally:
        stop(app)
