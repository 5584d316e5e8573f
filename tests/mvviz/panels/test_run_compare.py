"""The Pipeline panel's "Compare with the saved config" (mvviz/panels/run_compare.py) on
the tiny synthesized scene: the saved config (B) uses a Kalman q 1000 times the run's
(A); the comparison lists the filter's figures as different and the triangulation's as
equal, its moment buttons jump there, B's skeletons are drawn; and in headless chromium
the table is on screen (a screenshot is kept)."""

from __future__ import annotations

import dataclasses
import shutil
import time

import numpy as np
import pytest

from mvviz.app import ViewerApp
from mvviz.panels.run_compare import figures_table, moment_label
from mvviz.state import ViewerState
from pipeline.config import save_config
from pipeline.data.scene import load_scene
from pipeline.diagnose.compare_runs import Difference
from tests.mvviz.conftest import free_port, keep_screenshot, open_tab, open_viewer, settle

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")


@pytest.fixture(scope="module")
def compare_app(viewer_scene, frame_store, tmp_path_factory):
    scene, results, model = viewer_scene
    root = tmp_path_factory.mktemp("compare") / "scene"
    shutil.copytree(scene.root, root, ignore=shutil.ignore_patterns(".mvviz"))
    scene = load_scene(root)
    cfg_b = dataclasses.replace(
        results.config, kalman=dataclasses.replace(results.config.kalman, q=1e5)
    )
    save_config(cfg_b, root / "mvviz_config.json")
    state = ViewerState.create(scene, results, model)
    app = ViewerApp(state, host="127.0.0.1", port=free_port(), frames=frame_store)
    assert app.wait_idle(30)
    yield app
    app.stop()


@pytest.mark.slow
def test_compare_with_the_saved_config(compare_app):
    app = compare_app
    section = app.pipeline_panel.compare
    section.compare()
    assert section.wait_idle(300)
    cmp = section.comparison
    assert cmp is not None, section.gui.status.content
    assert cmp.config_changes == [("kalman.q", app.state.results.config.kalman.q, 1e5)]
    rows = {name: (a, b) for name, a, b in cmp.rows}
    assert rows["raw MPJPE mm"][0] == rows["raw MPJPE mm"][1]  # q is not triangulation's
    assert rows["kalman accel error mm"][1] > rows["kalman accel error mm"][0]
    table = section.gui.table.content
    assert "| kalman accel error mm |" in table and "| raw MPJPE mm |" not in table
    assert "other figures equal" in table and "kalman.q" in section.gui.status.content
    # The buttons: the largest differences, each jumping to its frame and track.
    assert section.shown and len(section.gui.moments) == len(section.shown)
    d = section.shown[0]
    assert section.gui.moments[0].label == moment_label(d)
    section.jump(0)
    assert app.wait_idle(30)
    assert app.state.frame == d.peak_frame
    if d.track_a >= 0:
        assert app.state.selection.track == d.track_a
    # B's skeletons are drawn at that frame, from B's filtered joints.
    bones = section._b_nodes["bones"]
    assert section._b_nodes["root"].visible and bones.visible
    b = section.run_b.track_filtered[:, d.peak_frame]
    assert np.isfinite(b).any() and len(bones.points) > 0
    assert np.allclose(np.nanmax(bones.points.reshape(-1, 3), 0),
                       np.nanmax(b.reshape(-1, 3), 0) / 1000, atol=1e-4)  # fmt: skip
    # Cached the second time.
    section.compare()
    assert section.wait_idle(60) and "(cached;" in section.gui.status.content


def test_the_table_text():
    from pipeline.config import PipelineConfig
    from pipeline.diagnose.compare_runs import RunComparison

    cmp = RunComparison(
        PipelineConfig(), PipelineConfig(), [("a", 1.0, 1.0), ("b", 2.0, 3.5), ("c", 4.0, np.nan)],
        [], np.zeros((0, 0)), [],
    )  # fmt: skip
    text = figures_table(cmp)
    assert "| b | 2 | 3.5 | 1.5 |" in text.replace("\u2002", "")
    assert "| c | 4 | – | – |" in text.replace("\u2002", "")
    assert "_1 other figures equal._" in text
    assert moment_label(Difference("only in B", -1, 4, 3, 9, 3, np.nan, np.nan)) == (
        "f 3–9 · B track 4 · only in B"
    )


@pytest.mark.slow
def test_the_compare_table_in_the_browser(browser, compare_app, tmp_path):
    app, section = compare_app, compare_app.pipeline_panel.compare
    if section.comparison is None:
        section.compare()
        assert section.wait_idle(300)
    page = open_viewer(browser, app.url)
    try:
        open_tab(page, "Pipeline")
        folder = page.get_by_text("Compare runs (A/B)").first
        folder.scroll_into_view_if_needed()
        inside = page.get_by_role("button", name="Compare with the saved config")
        for _ in range(3):  # open the folder (a click before the page settled is lost)
            if inside.count() and inside.first.is_visible():
                break
            folder.click()
            settle(page, 1.0)
        text = page.locator("body").inner_text()
        assert "kalman accel error mm" in text and "other figures equal" in text
        label = moment_label(section.shown[0])
        button = page.get_by_role("button", name=label)
        assert button.count() == 1
        button.scroll_into_view_if_needed()
        button.click()  # as a user does: the viewer goes there
        deadline = time.monotonic() + 20
        while app.state.frame != section.shown[0].peak_frame and time.monotonic() < deadline:
            time.sleep(0.05)
        assert app.state.frame == section.shown[0].peak_frame
        assert app.wait_idle(30) and section._b_nodes["root"].visible
        notices = page.locator("button.mantine-Notification-closeButton")
        for i in range(notices.count()):
            notices.nth(i).click()
        settle(page, 2.0)
        shot = tmp_path / "compare_runs.png"
        page.screenshot(path=str(shot))
        keep_screenshot(shot, "compare_runs.png")
        print("screenshot:", shot)
    finally:
        page.close()
