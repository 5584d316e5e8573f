"""Issue 13's points as a user sees them in headless chromium (software WebGL): the
failures list (entries merging several frames, their whole text shown, a jump showing a
camera that sees the person), filter B's overlay drawn only while B differs from A, and
the camera panel's camera highlighted in the 3D view. Screenshots are saved under the
test's tmp_path (and looked at when these tests were written)."""

from __future__ import annotations

import time

import numpy as np

from tests.mvviz.conftest import open_tab, open_viewer, wait_rendered


def idle(app) -> None:
    for _ in range(2):  # a render may request panel work and a panel a redraw
        assert app.wait_idle(30)
        assert app.filter_panel.wait_idle(30) and app.failure_panel.wait_idle(30)


def wait_until(predicate, seconds: float = 10.0, what: str = "") -> None:
    deadline = time.monotonic() + seconds
    while not predicate():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.05)


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
