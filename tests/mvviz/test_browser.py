"""The viewer in a real browser: headless Debian chromium (software WebGL) via playwright.

Assertions are numbers on canvas screenshots: the scene is drawn (not blank), and the
timeline, a layer toggle and an in-page button click each change what is drawn.
Screenshots go to a temporary directory and the final ones to docs/screenshots/.
Skipped when /usr/bin/chromium is absent.
"""

from __future__ import annotations

import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from tests.mvviz.conftest import (
    REPO,
    canvas_image,
    keep_screenshot,
    open_viewer,
    settle,
    wait_drawn,
    wait_rendered,
)

DOCS = REPO / "docs" / "screenshots"

pytestmark = [pytest.mark.slow, pytest.mark.filterwarnings("ignore::DeprecationWarning")]


@pytest.fixture(scope="module")
def shots(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("screenshots")


def save(page, shots: Path, name: str, *, docs: bool = False) -> np.ndarray:
    path = shots / f"{name}.png"
    page.screenshot(path=str(path))
    if docs:
        keep_screenshot(path, f"{name}.png")
    return canvas_image(page)


def diff(a: np.ndarray, b: np.ndarray) -> float:
    """Mean absolute difference, grey levels per channel."""
    return float(np.abs(a.astype(np.int16) - b.astype(np.int16)).mean())


def distinct_colours(img: np.ndarray) -> int:
    q = (img // 8).reshape(-1, 3).astype(np.int32)
    return int(np.unique(q[:, 0] * 1024 + q[:, 1] * 32 + q[:, 2]).size)


def test_canvas_is_not_blank(page, running_app, shots):
    running_app.set_frame(0)
    wait_rendered(running_app, page)
    img = save(page, shots, "viewer_tiny_frame0", docs=True)
    assert img.shape[0] > 400 and img.shape[1] > 600
    assert img.std() > 15, f"canvas looks blank (std {img.std():.1f})"
    assert distinct_colours(img) > 150
    # track colours are on screen: saturated pixels (skeletons, rays, video)
    sat = img.max(-1).astype(int) - img.min(-1)
    assert (sat > 80).sum() > 2000


def test_timeline_changes_the_canvas(page, running_app, shots):
    app = running_app
    assert not app.state.playing  # left by no earlier test: the frame is the one set
    app.set_frame(0)
    a = wait_drawn(app, page)
    cv2.imwrite(str(shots / "viewer_tiny_frame0_visit.png"), cv2.cvtColor(a, cv2.COLOR_RGB2BGR))
    app.set_frame(15)
    b = wait_drawn(app, page)
    save(page, shots, "viewer_tiny_frame15")
    assert app.state.frame == 15
    assert diff(a, b) > 0.3, f"frame change barely changed the canvas ({diff(a, b):.3f})"
    # and back: the same frame is the same picture once the page has drawn it all
    app.set_frame(0)
    c = wait_drawn(app, page)
    cv2.imwrite(str(shots / "viewer_tiny_frame0_again.png"), cv2.cvtColor(c, cv2.COLOR_RGB2BGR))
    # With viser's adaptive pixel ratio this failed whenever earlier tests had made the
    # page draw slowly (ratio 0.75: thinner, paler rays; 3.594 vs 4.925): the page
    # fixture pins the ratio (open_viewer), so a revisit is the same picture.
    print(f"\nframe 0 revisited: {diff(a, c):.3f} (0 -> 15: {diff(a, b):.3f})")
    assert diff(a, c) < 0.1 * diff(a, b), f"frame 0 revisited differs ({diff(a, c):.3f})"


def test_layer_toggle_changes_the_canvas(page, running_app, shots):
    # a toggle leaves the frame label as it was: wait_drawn, not the label, says drawn
    running_app.set_frame(8)
    a = wait_drawn(running_app, page)
    toggle = running_app.layers_panel.gui.toggles["grid"]
    toggle.value = False
    wait_drawn(running_app, page)
    b = save(page, shots, "viewer_tiny_no_grid")
    toggle.value = True
    wait_drawn(running_app, page)
    assert diff(a, b) > 0.3
    # a skeleton layer, too
    filt = running_app.layers_panel.gui.toggles["filtered"]
    filt.value = False
    c = wait_drawn(running_app, page)
    filt.value = True
    wait_drawn(running_app, page)
    assert diff(a, c) > 0.05


def test_in_page_step_button_moves_the_timeline(page, running_app):
    running_app.set_frame(4)
    wait_rendered(running_app, page, 1.0)
    page.get_by_role("button", name="+1 ▶").click()
    deadline = time.monotonic() + 10
    while running_app.state.frame != 5 and time.monotonic() < deadline:
        time.sleep(0.05)
    assert running_app.state.frame == 5


def test_two_clients_and_a_disconnect(browser, running_app, page, shots):
    second = open_viewer(browser, running_app.url)
    try:
        assert len(running_app.server.get_clients()) >= 2
        running_app.set_frame(12)
        wait_rendered(running_app, second)
        img = canvas_image(second)
        assert img.std() > 15
    finally:
        second.close()
    deadline = time.monotonic() + 10
    while len(running_app.server.get_clients()) > 1 and time.monotonic() < deadline:
        time.sleep(0.1)
    # the server keeps serving the remaining client
    running_app.set_frame(3)
    wait_rendered(running_app, page)
    assert running_app.state.frame == 3 and canvas_image(page).std() > 15


def test_bytes_and_time_per_frame_change(browser, running_app, shots):
    """Scrub with a client connected; report server time and websocket bytes per frame."""
    received: list[int] = []
    pg = browser.new_page()

    def on_ws(ws):
        ws.on("framereceived", lambda payload: received.append(len(payload)))

    pg.on("websocket", on_ws)
    pg.goto(running_app.url)
    pg.wait_for_selector("canvas", timeout=60_000)
    settle(pg, 3)
    running_app.frame_times_ms.clear()
    received.clear()
    n = 15
    for f in range(n):
        running_app.set_frame(f)
        assert running_app.wait_idle(10)
    settle(pg, 1)
    pg.close()
    stats = running_app.frame_time_stats()
    per_frame = sum(received) / n
    print(
        f"\nframe change: server median {stats['median_ms']:.1f} ms, "
        f"p95 {stats['p95_ms']:.1f} ms; {per_frame / 1024:.1f} kB/frame over the websocket"
    )
    assert stats["median_ms"] < 500  # liveness here; the speed target is bench_viewer's
    assert 0 < per_frame < 400_000


def test_meshes_and_side_by_side_screenshot(page, running_app, shots):
    """A README screenshot with the GT meshes and the filtered skeletons shifted 1 m."""
    lay = running_app.layers_panel.gui.toggles
    lay["meshes"].value = True
    lay["offset_filtered"].value = True
    running_app.set_frame(10)
    wait_rendered(running_app, page, 3)
    img = save(page, shots, "viewer_tiny_meshes_offset", docs=True)
    lay["offset_filtered"].value = False
    lay["meshes"].value = False
    wait_rendered(running_app, page)
    assert img.std() > 15
    cv2.imwrite(str(shots / "canvas_last.png"), cv2.cvtColor(img, cv2.COLOR_RGB2BGR))


def project_to_canvas(app, client, point_m: np.ndarray) -> tuple[float, float]:
    """Where a world point (metres) appears in the client's canvas, in CSS pixels: the
    server knows each client's camera (OpenCV convention: +z forward, +y down)."""
    import viser.transforms as vtf

    cam = client.camera
    R = vtf.SO3(cam.wxyz).as_matrix()
    p = R.T @ (np.asarray(point_m) - cam.position)
    h, w = cam.image_height, cam.image_width
    f = 0.5 * h / np.tan(cam.fov / 2)
    return w / 2 + f * p[0] / p[2], h / 2 + f * p[1] / p[2]


def test_clicking_a_joint_selects_it(page, running_app):
    """Click the filtered skeleton's joint in the canvas: the selection follows."""
    app = running_app
    app.jump_to(frame=10, track=0, joint="nose")
    wait_rendered(app, page)
    data, f = app.state.data, 10
    client = next(iter(app.server.get_clients().values()))
    box = page.locator("canvas").first.bounding_box()
    names = data.joint_set.names
    target = None
    for k in range(data.num_tracks):
        for j in (names.index("left_hip"), names.index("right_knee")):
            p = data.filtered[k, f, j] / 1000
            if not np.isfinite(p).all() or (k, j) == (0, names.index("nose")):
                continue
            x, y = project_to_canvas(app, client, p)
            if 20 < x < box["width"] - 20 and 20 < y < box["height"] - 20:
                target = (k, j, x, y)
                break
        if target:
            break
    assert target is not None, "no joint of the tiny scene is on screen"
    k, j, x, y = target
    page.mouse.click(box["x"] + x, box["y"] + y)
    deadline = time.monotonic() + 10
    sel = app.state.selection
    while (sel.track, sel.joint) != (k, j) and time.monotonic() < deadline:
        time.sleep(0.05)
        sel = app.state.selection
    assert (sel.track, sel.joint) == (k, j)
