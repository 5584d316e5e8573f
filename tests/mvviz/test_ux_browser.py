"""The review workflow as a user sees it in headless chromium (software WebGL): the
failures list (entries merging several frames, their whole text shown, a jump showing a
camera that sees the person), filter B's overlay drawn only while B differs from A, and
the camera panel's camera highlighted in the 3D view. Screenshots are saved under the
test's tmp_path (and looked at when these tests were written)."""

from __future__ import annotations

import time

import numpy as np
import pytest

from mvviz.app import ViewerApp
from mvviz.panels.filter_panel import B_ROOT
from mvviz.scene.geometry import SELECTED_CAMERA
from mvviz.state import ViewerState
from tests.mvviz.conftest import (
    free_port,
    open_tab,
    open_viewer,
    wait_drawn,
    wait_rendered,
    wait_until,
)


@pytest.fixture
def own_app(viewer_scene, frame_store):
    """A viewer of the tiny scene for one test: the session's ``running_app`` carries what
    earlier tests left (``test_browser_plot_follows_filter_b`` ends with "Show B" off, so
    B's overlay is never drawn there; other pages; the selection; the 3D camera)."""
    scene, results, model = viewer_scene
    app = ViewerApp(
        ViewerState.create(scene, results, model), host="127.0.0.1", port=free_port(),
        frames=frame_store,
    )  # fmt: skip
    assert app.wait_idle(30)
    yield app
    app.stop()


pytestmark = [pytest.mark.slow, pytest.mark.filterwarnings("ignore::DeprecationWarning")]


def idle(app) -> None:
    for _ in range(2):  # a render may request panel work and a panel a redraw
        assert app.wait_idle(30)
        assert app.filter_panel.wait_idle(30) and app.failure_panel.wait_idle(30)


def sees(app, failure, view: int) -> bool:
    """Camera ``view`` sees the failure's person: it detected the track's person at that
    frame or, where the track has no person there, its nearest pose projects into it."""
    res, scene = app.state.results, app.state.scene
    q = np.flatnonzero((res.person_frame == failure.frame) & (res.person_track == failure.track))
    if len(q):
        return bool(res.person_members[q[0], view] >= 0)
    present = np.flatnonzero(np.isfinite(res.track_filtered[failure.track]).all((1, 2)))
    near = present[np.argmin(np.abs(present - failure.frame))]
    cam = scene.rig[view]
    uv = cam.project(res.track_filtered[failure.track, near])
    inside = (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
    return bool(inside.mean() > 0.5)


def test_failures_list_shows_spans_whole_texts_and_jumps_to_a_seeing_camera(
    browser, running_app, tmp_path
):
    app, panel = running_app, running_app.failure_panel
    page = open_viewer(browser, app.url)
    before = panel.criterion
    try:
        open_tab(page, "Failures")
        spans, jumps = [], []
        for criterion in ("reprojection", "association", "kalman", "mpjpe", "id"):
            panel.set_criterion(criterion)
            idle(app)
            failures = list(panel.failures)
            if not failures:
                continue
            last = page.get_by_role(
                "button", name=f"{len(failures)}. {failures[-1].head}", exact=True
            )
            wait_until(lambda last=last: last.count() == 1, what=f"{criterion}'s last entry")
            for i, f in enumerate(failures):
                button = page.get_by_role("button", name=f"{i + 1}. {f.head}", exact=True)
                assert button.count() == 1, (criterion, i, f.head)
                # the entry's whole text under its button: shown, not cut, not overflowing
                rest = f.text[len(f.span) :].lstrip(" ·")
                details = page.get_by_text(rest, exact=True)
                assert details.count() >= 1, (criterion, f.text)
                el = details.first
                assert "…" not in el.inner_text()
                assert el.evaluate("e => e.scrollWidth <= e.clientWidth + 1"), f.text
                if f.first != f.last:
                    spans.append(f)
                    assert f"{f.first}–{f.last}" in f.head  # the span is on the button
                if f.track is not None and f.view is None:
                    jumps.append((criterion, i, f))
        assert spans, "no entry merges consecutive frames"
        assert jumps, "no entry to jump to a person from"
        page.screenshot(path=str(tmp_path / "failures_list.png"))
        # a jump from the page: the timeline moves and the camera panel sees the person
        criterion, i, f = jumps[0]
        panel.set_criterion(criterion)
        idle(app)
        app.set_frame(0 if f.frame else 1)
        idle(app)
        button = page.get_by_role("button", name=f"{i + 1}. {f.head}", exact=True)
        button.scroll_into_view_if_needed()
        button.click()
        wait_until(lambda: app.state.frame == f.frame, what="the jump")
        idle(app)
        view = app.state.scene.rig.names.index(app.camera_panel.gui.camera.value)
        assert sees(app, f, view), (f.text, app.camera_panel.gui.camera.value)
        wait_rendered(app, page)
        page.screenshot(path=str(tmp_path / "failures_jump.png"))
    finally:
        panel.set_criterion(before)
        idle(app)
        page.close()


def test_filter_b_overlay_only_while_b_differs(browser, own_app, tmp_path):
    app, fp = own_app, own_app.filter_panel
    page = open_viewer(browser, app.url)
    q0 = float(fp.gui.q.value)
    try:
        # the tab first: every picture below is taken with the same panels shown
        open_tab(page, "Filter A/B")
        app.jump_to(frame=10, track=0)
        idle(app)
        assert not fp._nodes[B_ROOT].visible  # B = A: nothing drawn
        a_only = wait_drawn(app, page).astype(int)
        page.screenshot(path=str(tmp_path / "b_equals_a.png"))
        fp.gui.q.value = q0 / 50  # a stiff B: clearly not A
        idle(app)
        assert fp._nodes[B_ROOT].visible and fp.gui.show_b.value
        with_b = wait_drawn(app, page).astype(int)
        page.screenshot(path=str(tmp_path / "b_differs.png"))
        changed = float(np.abs(with_b - a_only).max(-1).__gt__(40).mean())
        assert changed > 1e-3, f"B's skeletons did not show in the page ({changed:.5f})"
        # "Reset B to A" from the page removes them
        page.get_by_role("button", name="Reset B to A").click()
        wait_until(lambda: float(fp.gui.q.value) == q0, what="the reset")
        idle(app)
        assert not fp._nodes[B_ROOT].visible
        reset = wait_drawn(app, page).astype(int)
        page.screenshot(path=str(tmp_path / "b_reset.png"))
        left = float(np.abs(reset - a_only).max(-1).__gt__(40).mean())
        print(f"\nfilter B: pixels changed by B {changed:.5f}, left after the reset {left:.5f}")
        assert left < changed / 10, f"B's skeletons stayed after the reset ({left} vs {changed})"
    finally:
        fp.gui.q.value = q0
        idle(app)
        page.close()


def yellow_mask(img: np.ndarray) -> np.ndarray:
    """Pixels of the selected camera's yellow (SELECTED_CAMERA, (235, 190, 0), drawn lit
    and antialiased: ~(230, 210, 100) on screen); the tracks' orange has less green."""
    r, g, b = (img[..., c].astype(int) for c in range(3))
    assert SELECTED_CAMERA[0] > 180 and SELECTED_CAMERA[1] > 150 and SELECTED_CAMERA[2] < 130
    return (r > 180) & (g > 170) & (b < 150) & (r - b > 80)


def test_selected_camera_is_highlighted_in_the_page(browser, own_app, tmp_path):
    app = own_app
    before = set(app.server.get_clients())
    page = open_viewer(browser, app.url)
    try:
        wait_until(lambda: set(app.server.get_clients()) - before, what="the page's client")
        (client,) = (c for i, c in app.server.get_clients().items() if i not in before)
        centre = app.state.scene.rig.centers.mean(0) / 1000  # metres
        above = centre + np.array([0.0, -4.0, 30.0])  # the whole rig in view

        def camera_above() -> bool:
            # a fresh page reports its own camera once it is up, which can undo a camera
            # set before that: set it until the page reports it back
            if np.linalg.norm(np.asarray(client.camera.position) - above) < 0.05:
                return True
            client.camera.position, client.camera.look_at = above, centre
            time.sleep(0.2)
            return False

        wait_until(camera_above, seconds=20, what="the page's camera above the rig")
        masks = []
        for v in (0, 1):
            app.jump_to(view=v)
            idle(app)
            img = wait_drawn(app, page)
            page.screenshot(path=str(tmp_path / f"camera_{v}.png"))
            masks.append(yellow_mask(img))
        # each camera's frustum is yellow while it is the camera panel's, not otherwise
        only0, only1 = masks[0] & ~masks[1], masks[1] & ~masks[0]
        assert only0.sum() > 30, f"camera 0 is not highlighted ({only0.sum()} px)"
        assert only1.sum() > 30, f"camera 1 is not highlighted ({only1.sum()} px)"
        c0, c1 = (np.argwhere(m).mean(0) for m in (only0, only1))  # (row, col) centroids
        apart = np.linalg.norm(c0 - c1)
        print(f"\nhighlight: {only0.sum()} / {only1.sum()} px, centroids {apart:.0f} px apart")
        assert apart > 20, "the highlight did not move to the other camera"
    finally:
        app.jump_to(view=0)
        idle(app)
        page.close()
