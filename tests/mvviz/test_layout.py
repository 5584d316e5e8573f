"""The viewer's layout: one tab per panel, the camera panel's camera highlighted in 3D,
a legend for the camera panel's lines; in process and in headless chromium."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from mvviz.analysis.timeline_strip import CRITERION_RGB
from mvviz.panels.view_panels import CAMERA_LEGEND
from mvviz.scene.geometry import SELECTED_CAMERA
from mvviz.scene.layers import FRUSTUM_COLOR
from tests.mvviz.conftest import open_tab, open_viewer, settle, wait_rendered

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")

TABS = ("Layers", "Selection", "Pipeline", "Filter A/B", "Failures", "Export", "Diagnose")


def test_selected_camera_is_highlighted(running_app):
    app = running_app
    names = app.state.scene.rig.names
    try:
        for v in (1, 0):
            app.jump_to(view=v)
            assert app.wait_idle(10)
            assert app.layers.highlighted == names[v]
            for u, name in enumerate(names):
                frustum = app.layers.nodes[f"/world/cameras/{name}/frustum"]
                label = app.layers.nodes[f"/world/cameras/{name}/label"]
                want = tuple(SELECTED_CAMERA) if u == v else FRUSTUM_COLOR
                assert tuple(int(c) for c in frustum.color) == want
                assert frustum.thickness == (4.0 if u == v else 1.5)
                assert label.text == (f"▶ {name}" if u == v else name)
    finally:
        app.jump_to(view=0)
        assert app.wait_idle(10)
    assert "grey" in app.camera_panel.gui.legend.content
    assert app.camera_panel.gui.legend.content == CAMERA_LEGEND


@pytest.mark.slow
def test_panels_are_tabs_in_the_page(browser, running_app, tmp_path):
    """Each tab shows its own panel and hides the others'; screenshots of two tabs."""
    app = running_app
    page = open_viewer(browser, app.url)
    try:
        tabs = page.get_by_role("tab")
        names = [tabs.nth(i).inner_text().strip() for i in range(tabs.count())]
        assert names == ["Camera", *TABS]  # the camera panel's own tab, then the main panel
        app.set_frame(5)
        wait_rendered(app, page)
        # the Layers tab is open first, the timeline above it; Failures' criterion hidden
        assert page.get_by_role("button", name="+1 ▶").is_visible()
        assert not page.get_by_text("Look at it", exact=True).is_visible()
        page.screenshot(path=str(tmp_path / "tab_first.png"))
        open_tab(page, "Failures")
        assert page.get_by_text("Look at it", exact=True).is_visible()
        # the timeline stays visible whatever tab is open
        assert page.get_by_role("button", name="+1 ▶").is_visible()
        open_tab(page, "Layers")
        assert page.get_by_text("Mesh style", exact=True).is_visible()
        assert page.get_by_text("Ground-truth skeletons", exact=True).is_visible()
        settle(page, 1.0)
        page.screenshot(path=str(tmp_path / "tab_layers.png"))
        # the camera panel's legend, beside its image
        assert page.get_by_text("reprojected", exact=False).first.is_visible()
        print(f"\nscreenshots: {tmp_path}")
    finally:
        page.close()
    assert np.isfinite(app.state.frame)


@pytest.mark.slow
def test_timeline_shows_the_failure_marks(browser, running_app, tmp_path):
    """The strip under the frame slider, as wide as the panel, carries a mark per
    failure in its criterion's colour; "failure ▶" goes to the next one."""
    app = running_app
    assert app.failure_panel.wait_idle(120)
    timeline = app.timeline
    assert timeline.failures and timeline.criteria == app.failure_panel.criteria
    assert len(timeline.failures) == sum(app.failure_panel.counts.values())
    page = open_viewer(browser, app.url)
    try:
        app.set_frame(0)
        wait_rendered(app, page)
        imgs = [page.locator("img").nth(i) for i in range(page.locator("img").count())]
        boxes = [(im, im.bounding_box()) for im in imgs]
        strips = [(im, b) for im, b in boxes if b and b["x"] > 1000 and 20 < b["height"] < 120]
        assert strips, boxes
        strip, box = max(strips, key=lambda ib: ib[1]["height"])
        assert box["width"] > 280  # as wide as the panel, not the slider's 150 px
        png = strip.screenshot()
        bgr = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
        img = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
        shown = {c for c in timeline.criteria if any(f.criterion == c for f in timeline.failures)}
        for c in shown:  # each criterion with failures has pixels of its colour
            near = np.abs(img.astype(int) - CRITERION_RGB[c]).max(-1) <= 40
            assert near.sum() > 4, c
        after = min(f.first for f in timeline.failures if f.first > 0)
        page.get_by_role("button", name="failure ▶").click()
        text = f"frame {after} / "
        page.wait_for_function(
            "t => document.body.textContent.includes(t)", arg=text, timeout=30_000
        )
        assert app.state.frame == after
        page.screenshot(path=str(tmp_path / "timeline.png"))
        print(f"\nscreenshot: {tmp_path / 'timeline.png'}")
    finally:
        page.close()
