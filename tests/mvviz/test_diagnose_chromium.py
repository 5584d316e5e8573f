"""The Diagnose tab and the bodies on the camera image, as a person sees them: the
viewer in headless chromium (software WebGL). The Diagnose tab is run by clicking its
button on the Shelf scene with camera "1" recording 4 frames late: the page shows the
offset, the plots and the field. The camera panel with the layer "Fitted bodies on the
camera image" on shows the bodies in their tracks' colours and each one's residual.
Screenshots are printed (and kept under docs/screenshots with MVVIZ_UPDATE_SCREENSHOTS=1)."""

from __future__ import annotations

import re
import time

import cv2
import numpy as np
import pytest

from mvviz.app import ViewerApp
from mvviz.scene.images import mesh_residuals
from mvviz.state import ViewerState
from pipeline.body.model import load_body_model
from pipeline.config import PipelineConfig
from pipeline.data.scene import load_scene
from pipeline.diagnose.perturb import delay_camera
from pipeline.run.pipeline import run_pipeline
from tests.mvviz.conftest import (
    REPO,
    free_port,
    keep_screenshot,
    open_tab,
    open_viewer,
    settle,
    wait_rendered,
)

pytestmark = [pytest.mark.slow, pytest.mark.filterwarnings("ignore::DeprecationWarning")]
DELAY, LATE = 4, "1"


def _png(locator) -> np.ndarray:
    bgr = cv2.imdecode(np.frombuffer(locator.screenshot(), np.uint8), cv2.IMREAD_COLOR)
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def test_the_diagnose_tab_shows_a_late_camera(browser, tmp_path):
    model = load_body_model()
    scene = delay_camera(load_scene(REPO / "sample_data" / "shelf_synth"), LATE, DELAY)
    results = run_pipeline(scene, PipelineConfig(fit_smpl=False), model, progress=False)
    app = ViewerApp(ViewerState.create(scene, results, model), port=free_port())
    try:
        assert app.wait_idle(60)
        page = open_viewer(browser, app.url)
        try:
            open_tab(page, "Diagnose")
            page.get_by_role("button", name="Run diagnose").click()
            page.wait_for_function(
                "() => document.body.textContent.includes('Diagnosed in')", timeout=300_000
            )
            assert app.diagnose_panel.wait(120)  # its plots drawn after the status text
            settle(page, 2.0)
            found = app.diagnose_panel.findings.diagnosis.sync[LATE]
            text = page.locator("body").inner_text()
            m = re.search(rf"\b{LATE}\s*\|?\s*([+-][0-9.]+) late", text)
            assert m, text[:2000]
            assert abs(float(m.group(1)) - DELAY) < 0.15
            assert float(m.group(1)) == pytest.approx(found.offset_frames, abs=0.005)
            assert "--set sync.offsets=" in text
            # judged in sync, the late camera is not a calibration suspect: out of sync
            c = app.diagnose_panel.findings.diagnosis.calibration[LATE]
            assert c.out_of_sync and not c.suspect, c.to_dict()
            assert f"Camera {LATE} is out of sync, not miscalibrated" in text
            assert "suspect" not in text
            # the plots and the field are on the page, drawn (not blank)
            # (the page decodes them after their messages: polled, with a deadline)
            deadline = time.monotonic() + 30
            while True:
                imgs = [page.locator("img").nth(i) for i in range(page.locator("img").count())]
                shown = [im for im in imgs if (b := im.bounding_box()) and b["x"] > 1000
                         and b["height"] > 100]  # fmt: skip
                if (len(shown) >= 2 and all(_png(im).std() > 20 for im in shown[:2])) or (
                    time.monotonic() > deadline
                ):
                    break
                settle(page, 0.5)
            assert len(shown) >= 2, [im.bounding_box() for im in imgs]
            for im in shown[:2]:
                img = _png(im)
                assert img.std() > 20
            page.get_by_text("sync (frames)").scroll_into_view_if_needed()
            settle(page, 0.5)
            path = tmp_path / "diagnose_tab.png"
            page.screenshot(path=str(path))
            keep_screenshot(path, "diagnose_tab.png")
            # a click on "worst frame" goes there and shows that camera
            series = app.diagnose_panel.findings.series(LATE)
            worst = int(np.nanargmax(series))
            page.get_by_role("button", name="worst frame").scroll_into_view_if_needed()
            page.get_by_role("button", name="worst frame").click()
            page.wait_for_function(
                "t => document.body.textContent.includes(t)", arg=f"frame {worst} / ",
                timeout=30_000,
            )  # fmt: skip
            assert app.state.frame == worst and app.state.scene.rig.names[app.state.camera] == LATE
            settle(page, 1.0)
            plots = tmp_path / "diagnose_tab_plots.png"
            page.screenshot(path=str(plots))
            print(f"\nscreenshots: {path} {plots}")
        finally:
            page.close()
    finally:
        app.stop()


def test_the_camera_panel_shows_the_fitted_bodies(browser, running_app, tmp_path):
    app = running_app
    toggles = app.layers_panel.gui.toggles
    assert not toggles["bodies_on_images"].value  # off by default
    page = open_viewer(browser, app.url)
    try:
        frame, view = 8, 0
        app.jump_to(frame=frame, view=view)
        wait_rendered(app, page)
        imgs = [page.locator("img").nth(i) for i in range(page.locator("img").count())]
        boxes = [(im, b) for im in imgs if (b := im.bounding_box()) and b["x"] < 450]
        panel_img = max(boxes, key=lambda ib: ib[1]["width"] * ib[1]["height"])[0]
        before = _png(panel_img)
        toggles["bodies_on_images"].value = True
        wait_rendered(app, page)
        after = _png(panel_img)
        assert before.shape == after.shape
        changed = np.abs(after.astype(int) - before.astype(int)).max(-1) > 20
        assert changed.mean() > 0.01  # the bodies are drawn
        # pixels of each body: the picture blended toward its track's colour
        bodies = app.camera_panel.gui.image.image  # what the server sent
        data = app.state.data
        shown = mesh_residuals(data, view, frame)
        text = page.locator("body").inner_text()
        for k, px in shown.items():
            assert f"track {k} {px:.1f} px" in text
        assert shown and bodies.shape[1] == 400
        path = tmp_path / "camera_bodies.png"
        page.screenshot(path=str(path))
        box = panel_img.bounding_box()
        cv2.imwrite(
            str(tmp_path / "camera_bodies_panel.png"), cv2.cvtColor(after, cv2.COLOR_RGB2BGR)
        )
        keep_screenshot(path, "camera_bodies_on_image.png")
        print(f"\nscreenshots: {path} {tmp_path / 'camera_bodies_panel.png'} box {box}")
    finally:
        toggles["bodies_on_images"].value = False
        page.close()
