"""The "Filter A/B" panel: B re-filters the sequence, scores it, plots it, applies it.

Unit tests drive a viewer without a browser (GUI values set from Python, as a click
would); one browser test checks that the plot image in the page follows B and saves
docs/screenshots/filter_ab.png.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time

import cv2
import numpy as np
import pytest

from mvviz.analysis.filter_runs import results_run, run_filter, with_filter
from mvviz.analysis.trace_plot import PLAYHEAD_HEIGHT, PLOT_HEIGHT, PLOT_WIDTH
from mvviz.app import ViewerApp
from mvviz.cli.run import resolve_config
from mvviz.panels.filter_panel import (
    B_DASHES,
    B_ROOT,
    PLACEMENTS,
    dashed_segments,
    metrics_table,
    score,
)
from mvviz.scene.geometry import bone_segments
from mvviz.state import ViewerState
from pipeline.config import load_config
from pipeline.evaluation.evaluate import evaluate
from pipeline.stages.kalman import KalmanParams, kalman_filter
from tests.mvviz.conftest import free_port, keep_screenshot, open_tab, settle, wait_rendered
from tools.chromium import pinned_dpr_url

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")


@pytest.fixture
def app(viewer_scene, tmp_path):
    """A viewer (no browser) of the tiny scene, its root moved to a temporary directory
    so that "Apply B" writes mvviz_config.json there."""
    scene, results, _ = viewer_scene
    scene = dataclasses.replace(scene, root=tmp_path)
    app = ViewerApp(ViewerState.create(scene, results, None), port=free_port())
    assert app.wait_idle(30) and app.filter_panel.wait_idle(30)
    yield app
    app.stop()


def idle(app: ViewerApp) -> None:
    for _ in range(2):  # a render may request panel work and the panel a redraw
        assert app.wait_idle(30)
        assert app.filter_panel.wait_idle(30)


def expected_forward(track_raw: np.ndarray, params: KalmanParams) -> np.ndarray:
    fr = kalman_filter(np.moveaxis(track_raw, 1, 0), dataclasses.replace(params, smoother=True))
    return np.moveaxis(fr.forward, 0, 1)


def test_filter_a_reproduces_the_run(viewer_scene):
    _, results, _ = viewer_scene
    a, again = (
        results_run(results),
        run_filter(results.track_raw, results.config.kalman, skip=results.track_contradicted),
    )
    np.testing.assert_array_equal(a.forward, again.forward)
    np.testing.assert_array_equal(a.smoothed, again.smoothed)
    np.testing.assert_array_equal(a.mahalanobis, again.mahalanobis)
    assert a.shown is results.track_filtered
    # a gated run: A's rejections follow from its Mahalanobis distances
    gated = run_filter(results.track_raw, dataclasses.replace(results.config.kalman, gate=2.0))
    assert gated.rejected.any()
    again = results_run(with_filter(results, gated))
    np.testing.assert_array_equal(again.rejected, gated.rejected)


@pytest.mark.slow
def test_changing_b_q_refilters_the_sequence(app):
    fp, results = app.filter_panel, app.state.results
    a = results.config.kalman
    assert fp.run_b.params == a and fp.run_b is fp.run_a  # B starts as a copy of A
    fp.gui.q.value = 3.0
    idle(app)
    b = dataclasses.replace(a, q=3.0)
    assert fp.run_b.params == b
    np.testing.assert_array_equal(fp.run_b.forward, expected_forward(results.track_raw, b))
    finite = np.isfinite(fp.run_b.forward) & np.isfinite(results.track_forward)
    assert finite.sum() > 100
    assert np.abs(fp.run_b.forward - results.track_forward)[finite].max() > 1.0
    # the results (filter A) are untouched, B is drawn beside them
    assert app.state.results is results
    assert fp.gui.show_b.value  # turned on by the first edit
    node = fp._nodes[f"{B_ROOT}/0/bones"]
    assert node.visible and len(node.points) > 3
    # over A (no shift), dashed: B_DASHES dashes per bone
    assert fp._nodes[B_ROOT].visible and np.allclose(fp._nodes[B_ROOT].position, 0.0)
    f = app.state.frame
    bones = bone_segments(fp.run_b.forward[0, f] / 1000, app.state.data.joint_set.bones)
    assert len(node.points) == B_DASHES * len(bones)
    np.testing.assert_allclose(node.points[0, 0], bones[0, 0], atol=1e-5)
    np.testing.assert_allclose(
        fp._nodes[f"{B_ROOT}/0/joints"].points,
        fp.run_b.forward[0, f][np.isfinite(fp.run_b.forward[0, f]).all(1)] / 1000,
        rtol=1e-5,
    )
    assert fp._worker.errors == []
    print(
        f"\nB re-filter {fp.timings['filter_ms']:.1f} ms, plot {fp.timings['plot_ms']:.1f} ms, "
        f"metrics {fp.timings['metrics_ms']:.1f} ms, whole update {fp.timings['work_ms']:.1f} ms"
    )


@pytest.mark.slow
def test_rapid_edits_collapse_to_the_last(app):
    fp = app.filter_panel
    for q in np.linspace(1.0, 60.0, 25):
        fp.gui.q.value = float(q)
    idle(app)
    assert fp.run_b.params.q == pytest.approx(60.0)
    fp.scale_q("×2")  # what the "B q scale" buttons do
    idle(app)
    assert fp.run_b.params.q == pytest.approx(120.0)


@pytest.mark.slow
def test_metrics_of_a_and_b(app):
    fp = app.filter_panel
    scene, results = app.state.scene, app.state.results
    ev = evaluate(scene, results)
    for name, row in (("raw", "raw"), ("A", "kalman")):  # A is the forward filter here
        for k in ("mpjpe", "pck", "accel", "jitter"):
            assert fp.metrics[name][k] == pytest.approx(ev.stages[row][k]), (name, k)
    fp.gui.q.value = 0.5  # a stiff filter: smooth, lagging
    idle(app)
    a, b = fp.metrics["A"], fp.metrics["B"]
    assert b["jitter"] < 0.7 * a["jitter"], (a["jitter"], b["jitter"])
    assert b["mpjpe"] != a["mpjpe"]
    md = fp.gui.metrics.content
    assert "MPJPE" in md and "PCK@160" in md and f"{b['jitter']:.2f}" in md
    # the smoother is scored when B asks for it
    fp.gui.smoother.value = True
    idle(app)
    rts = run_filter(results.track_raw, fp.run_b.params, skip=results.track_contradicted).smoothed
    np.testing.assert_array_equal(fp.run_b.shown, rts)


def test_scores_without_ground_truth(viewer_scene):
    _, results, _ = viewer_scene
    raw = score(results.track_raw, results.track_raw, results.joint_set, None)
    a = score(results.track_forward, results.track_raw, results.joint_set, None)
    assert set(a) == {"jitter"} and 0 < a["jitter"] < raw["jitter"]
    md = metrics_table({"raw": raw, "A": a})
    assert "jitter" in md and "MPJPE" not in md and "no ground truth" in md


@pytest.mark.slow
def test_invalid_b_is_reported_not_run(app):
    fp = app.filter_panel
    before = fp.run_b
    fp.gui.r.value = 0.0
    idle(app)
    assert fp.run_b is before
    assert "not valid" in fp.gui.status.content
    fp.gui.r.value = 100.0
    idle(app)
    assert fp.run_b.params.r == 100.0 and "not valid" not in fp.gui.status.content


@pytest.mark.slow
def test_apply_b_saves_the_config_and_swaps_the_results(app):
    fp = app.filter_panel
    root = app.state.scene.root
    fp.gui.q.value = 25.0
    fp.gui.smoother.value = True
    fp.gui.gate_on.value = True
    fp.gui.gate.value = 8.0
    idle(app)
    b = fp.run_b.params
    assert (b.q, b.smoother, b.gate) == (25.0, True, 8.0)
    path = fp.apply_b()
    idle(app)
    assert path == root / "mvviz_config.json"
    saved = json.loads(path.read_text())["kalman"]
    assert saved == dataclasses.asdict(b)
    assert load_config(path).kalman == b
    args = argparse.Namespace(scene=root, config=None, set=[])
    assert resolve_config(args).kalman == b  # what `mvviz run` / `python app.py` will use
    res = app.state.results
    assert res.config.kalman == b
    np.testing.assert_array_equal(res.track_smoothed, fp.run_b.smoothed)
    np.testing.assert_array_equal(app.state.data.filtered, res.track_smoothed)
    assert fp.run_a.params == b and "applied" in fp.gui.status.content
    assert "gate 8" in fp.gui.a_info.content
    # B's skeletons were rebuilt for the new results; B = the new A, so not drawn
    assert f"{B_ROOT}/0/bones" in fp._nodes and not fp._nodes[B_ROOT].visible
    # Apply keeps the other sections of an existing config file
    text = json.loads(path.read_text())
    text["triangulation"]["min_views"] = 3
    path.write_text(json.dumps(text))
    fp.gui.q.value = 40.0
    idle(app)
    assert fp._nodes[B_ROOT].visible and fp._nodes[f"{B_ROOT}/0/bones"].visible
    fp.apply_b()
    cfg = load_config(path)
    assert cfg.kalman.q == 40.0 and cfg.triangulation.min_views == 3
    assert fp._worker.errors == [] and app.render_errors == []


@pytest.mark.slow
def test_reset_b_to_a(app):
    fp = app.filter_panel
    fp.gui.model.value = "random_walk"
    fp.gui.q.value = 400.0
    idle(app)
    assert fp.run_b.params.model == "random_walk" and not fp.gui.control_gain.disabled
    assert fp.b_differs and fp._nodes[B_ROOT].visible
    fp.reset_b()
    idle(app)
    assert fp.run_b.params == fp.run_a.params
    assert fp.gui.control_gain.disabled
    # B = A: nothing of B drawn, though "Show B skeletons" stays on
    assert fp.gui.show_b.value and not fp.b_differs
    assert not fp._nodes[B_ROOT].visible and "B = A" in fp.gui.status.content


@pytest.mark.slow
def test_b_overlay_only_when_b_differs_and_its_strip_lands_on_nobody(app):
    """B starts as A: not drawn even with "Show B" on; an edit draws it over A (dashed);
    "strip" shifts it past the x range of every person of the run."""
    fp = app.filter_panel
    fp.gui.show_b.value = True
    idle(app)
    assert not fp._nodes[B_ROOT].visible
    fp.gui.q.value = float(fp.run_a.params.q) * 4
    idle(app)
    assert fp._nodes[B_ROOT].visible
    fp.gui.placement.value = PLACEMENTS[1]
    idle(app)
    dx = fp._nodes[B_ROOT].position
    raw_x = app.state.results.track_raw[..., 0] / 1000
    lo, hi = np.nanmin(raw_x), np.nanmax(raw_x)
    assert dx[1] == dx[2] == 0.0 and dx[0] == pytest.approx(hi - lo + 1.0)
    f = app.state.frame
    for k in range(app.state.data.num_tracks):
        b_x = fp._nodes[f"{B_ROOT}/{k}/joints"].points[:, 0] + dx[0]
        assert b_x.min() > hi + 0.5  # beyond everyone, at every frame
    assert fp.gui.placement.value == PLACEMENTS[1] and f == app.state.frame
    seg = dashed_segments(np.array([[[0.0, 0, 0], [7.0, 0, 0]]]), 4)
    np.testing.assert_allclose(seg[:, :, 0], [[0, 1], [2, 3], [4, 5], [6, 7]])


@pytest.mark.slow
def test_panel_plot_follows_selection_and_frame(app):
    fp = app.filter_panel
    app.jump_to(frame=5, track=0, joint=3)
    idle(app)
    first = fp.plot_image.copy()
    assert first.shape == (PLOT_HEIGHT, PLOT_WIDTH, 3)
    app.jump_to(joint=9)
    idle(app)
    other = fp.plot_image.copy()
    assert np.abs(other.astype(int) - first).mean() > 1.0
    strip5 = fp.playhead_image.copy()
    t0 = time.perf_counter()
    app.set_frame(12)
    idle(app)
    assert fp._marker_frame == 12
    # a frame change moves the playhead under the plot; the plot itself is not re-sent
    assert np.array_equal(fp.plot_image, other)
    assert fp.playhead_image.shape == (PLAYHEAD_HEIGHT, PLOT_WIDTH, 3)
    cols5 = np.flatnonzero((strip5[2:27] < 128).all(-1).any(0))
    cols12 = np.flatnonzero((fp.playhead_image[2:27] < 128).all(-1).any(0))
    x5, x12 = fp._plot.frame_x(5), fp._plot.frame_x(12)
    assert abs(cols5.mean() - x5) < 1.5 and abs(cols12.mean() - x12) < 1.5
    assert x12 - x5 > 10  # 7 frames apart on an axis ~ 500 px wide
    print(f"\nframe change incl. playhead: {(time.perf_counter() - t0) * 1e3:.0f} ms")


def plot_element(page):
    """The plot <img> of the panel (the only image of the plot's pixel size)."""
    imgs = page.locator("img")
    for i in range(imgs.count()):
        size = imgs.nth(i).evaluate("e => [e.naturalWidth, e.naturalHeight]")
        if size == [PLOT_WIDTH, PLOT_HEIGHT]:
            return imgs.nth(i)
    return None


def element_image(locator) -> np.ndarray:
    png = locator.screenshot()
    return cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)


@pytest.mark.slow
def test_browser_plot_follows_filter_b(browser, running_app, tmp_path):
    """Change B from Python: the plot image in the page changes; B's skeletons show."""
    app, fp = running_app, running_app.filter_panel
    others = set(app.server.get_clients())
    page = browser.new_page(viewport={"width": 1500, "height": 1400})
    try:
        page.goto(pinned_dpr_url(app.url))  # compared pictures: a fixed pixel ratio
        page.wait_for_selector("canvas", timeout=60_000)
        deadline = time.monotonic() + 10
        while not set(app.server.get_clients()) - others and time.monotonic() < deadline:
            time.sleep(0.05)
        mine = [c for i, c in app.server.get_clients().items() if i not in others]
        close = page.locator("button.mantine-Notification-closeButton")
        try:
            close.first.wait_for(timeout=5_000)
            close.first.click()
        except Exception:
            pass
        app.jump_to(frame=10, track=0, joint="right_wrist")
        idle(app)
        wait_rendered(app, page)
        open_tab(page, "Filter A/B")
        plot = None
        deadline = time.monotonic() + 30
        while plot is None and time.monotonic() < deadline:
            plot = plot_element(page)
            settle(page, 0.3)
        assert plot is not None, "no plot image of the expected size in the page"
        plot.scroll_into_view_if_needed()
        settle(page, 1.0)
        before = element_image(plot)
        box = plot.bounding_box()
        assert box["width"] > 200 and box["height"] > 250

        a = fp.run_a.params
        fp.gui.q.value = float(a.q) / 50  # a stiff, smoothed B: clearly not A
        fp.gui.smoother.value = True
        idle(app)
        wait_rendered(app, page)
        diff = 0.0
        deadline = time.monotonic() + 20
        while diff < 0.5 and time.monotonic() < deadline:
            settle(page, 0.5)
            after = element_image(plot)
            diff = float(np.abs(after.astype(int) - before).mean())
        assert diff >= 0.5, f"the plot in the page did not change ({diff:.2f})"
        assert fp.gui.show_b.value and fp.metrics["B"]["jitter"] < fp.metrics["A"]["jitter"]
        # this page's camera on track 0, B dashed over A
        pts = app.state.data.filtered[0, app.state.frame]
        target = np.nanmean(pts, axis=0) / 1000 + np.array([0.0, 0.0, -0.1])
        for client in mine:
            client.camera.position = target + np.array([0.0, -2.4, 0.8])
            client.camera.look_at = target
        # the whole folder in view, from its title down to the plot
        title = page.get_by_text("Filter A/B", exact=True).last  # the folder, not the tab
        title.evaluate("e => e.scrollIntoView({block: 'start'})")
        if plot.bounding_box()["y"] + plot.bounding_box()["height"] > 1400:
            plot.scroll_into_view_if_needed()
        settle(page, 2.5)
        shot = tmp_path / "filter_ab.png"
        page.screenshot(path=str(shot))
        keep_screenshot(shot, "filter_ab.png")
    finally:
        page.close()
        fp.reset_b()
        fp.gui.show_b.value = False
        idle(app)
