"""The calibration view (mvviz/calibration_view.py): ``mvviz view OUT`` on a ``mvviz
calibrate`` output, on synthetic footage calibrated by the test; drawn in headless
chromium (skipped without /usr/bin/chromium)."""

from __future__ import annotations

import numpy as np
import pytest

from mvviz.calibration_view import CalibrationApp, draw_view, load_calibration_folder
from mvviz.cli import build_parser
from mvviz.cli.view import is_calibration_folder, start
from pipeline.calibrate.calibrate import calibrate_cameras, write_calibration
from pipeline.data.calibration_views import load_calibration_views
from tests.mvviz.conftest import canvas_image, free_port, keep_screenshot, open_viewer, wait_until
from tests.pipeline.calibrate_synth import BOARD, board_poses, default_rig, write_session

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")


@pytest.fixture(scope="module")
def calibration_folder(tmp_path_factory):
    """A calibration of the three synthetic cameras (one never sees the board, so it is
    not calibrated: the view names it)."""
    root = tmp_path_factory.mktemp("calview")
    rig = default_rig()
    folders = write_session(root / "footage", rig, board_poses(16, seed=7),
                            blank={"right": set(range(16))})  # fmt: skip
    cal = calibrate_cameras(folders, BOARD, intrinsics=rig)
    write_calibration(cal, root / "out")
    return root / "out"


def colour_pixels(image: np.ndarray, rgb, tol: int = 40) -> int:
    return int((np.abs(image.astype(int) - rgb).max(-1) < tol).sum())


def test_a_view_drawn_with_detected_and_reprojected_corners(calibration_folder):
    views, _ = load_calibration_folder(calibration_folder)
    k = int(np.nanargmax(views.view_rms()))
    c, f = int(views.view_camera[k]), int(views.view_frame[k])
    image, line = draw_view(views, c, f)
    assert image.shape[1] == 456 and image.shape[2] == 3
    assert colour_pixels(image, (60, 220, 60)) > 50  # green rings: detected
    assert colour_pixels(image, (255, 40, 40)) > 50  # red crosses: reprojected
    assert f"frame {f}" in line and "RMS" in line and "zoomed" in line
    whole, line = draw_view(views, c, f, zoom=False)
    assert "zoomed" not in line
    # a frame the camera does not see the board in: said, not drawn
    unseen = sorted(set(range(20)) - set(views.view_frame[views.view_camera == c].tolist()))[0]
    _, line = draw_view(views, c, unseen)
    assert "no board" in line


def test_mvviz_view_opens_a_calibration_folder(calibration_folder, tmp_path):
    assert is_calibration_folder(calibration_folder)
    assert not is_calibration_folder(tmp_path)
    args = build_parser(["view"]).parse_args(
        ["view", str(calibration_folder), "--port", str(free_port())]
    )
    app = start(args, progress=False)
    try:
        assert isinstance(app, CalibrationApp)
        view = app.view
        saved = load_calibration_views(calibration_folder / "calibration.npz")
        assert "right" in view.table.content and "never sees the board" in view.table.content
        assert [c.calibrated for c in saved.cameras] == [True, True, False]
        assert "never sees the board" in saved.cameras[2].problem
        view.select(camera=1, frame=5)
        assert view.frame_slider.value == 5 and view.camera_choice.value == "front"
        assert "frame 5" in view.view_line.content
        view._step("next ▶")
        assert view.frame > 5
        # the frame slider moved by hand selects that frame
        view.frame_slider.value = 9
        wait_until(lambda: view.frame == 9, what="the slider's frame")
    finally:
        app.stop()


def test_calibration_view_in_chromium(browser, calibration_folder, tmp_path):
    import viser

    server = viser.ViserServer(host="127.0.0.1", port=free_port(), verbose=False)
    app = CalibrationApp(calibration_folder, server)
    try:
        page = open_viewer(browser, app.url)
        canvas = canvas_image(page)
        assert canvas.std() > 10, f"the 3D view looks blank (std {canvas.std():.1f})"
        # the cameras' colours (blue, orange frusta) and the boards are drawn
        assert colour_pixels(canvas, (31, 119, 180)) > 100
        assert colour_pixels(canvas, (255, 127, 14)) > 100
        page.get_by_role("button", name="worst view").click()
        rms = app.view.views.view_rms()
        k = int(np.nanargmax(rms))
        want = (int(app.view.views.view_camera[k]), int(app.view.views.view_frame[k]))
        wait_until(lambda: (app.view.camera, app.view.frame) == want, what="the worst view")
        page.wait_for_timeout(1500)
        path = tmp_path / "calibration_view_synthetic.png"
        page.screenshot(path=str(path))
        keep_screenshot(path, "calibration_view_synthetic.png")
        # the panel shows the view's picture and the chart
        assert page.get_by_text("reprojection error per view, px").count() == 1
        assert page.get_by_text(f"frame {want[1]}:").count() >= 1
        page.close()
    finally:
        app.stop()
