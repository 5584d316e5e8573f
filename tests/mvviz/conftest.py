"""Viewer fixtures: a tiny synthesized scene with its results, a running viewer on a free
port, and a headless chromium page on it (skipped when /usr/bin/chromium is absent)."""

from __future__ import annotations

import dataclasses
import os
import shutil
import socket
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from mvviz.app import ViewerApp
from mvviz.scene.images import FrameStore
from mvviz.state import ViewerState
from pipeline.body.model import load_body_model
from pipeline.config import PipelineConfig
from pipeline.data.scene import load_scene
from pipeline.importers.calibration import read_voxelpose_calibration
from pipeline.run.pipeline import run_or_load, run_pipeline
from pipeline.synth.scene_gen import SynthConfig, write_synth_scene
from tools.chromium import CHROMIUM, close_webgl_notice, launch_chromium, pinned_dpr_url

REPO = Path(__file__).resolve().parents[2]
CAMPUS = REPO / "sample_data" / "rigs" / "campus_voxelpose.json"
VIEWPORT = {"width": 1400, "height": 860}
NUM_FRAMES = 20


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def synth_campus_scene(root: Path, num_frames: int):
    """(scene, results, model): 2 people on the 3-camera campus rig, with videos."""
    model = load_body_model()
    write_synth_scene(
        root,
        read_voxelpose_calibration(CAMPUS),
        model,
        SynthConfig(num_people=2, num_frames=num_frames, seed=3),
        progress=False,
    )
    scene = load_scene(root)
    results, _ = run_or_load(scene, PipelineConfig(), model, progress=False)
    return scene, results, model


@pytest.fixture(scope="session")
def viewer_scene(tmp_path_factory):
    """(scene, results, model): 2 people, 20 frames on the 3-camera campus rig, videos."""
    return synth_campus_scene(tmp_path_factory.mktemp("viewer") / "scene", NUM_FRAMES)


@pytest.fixture
def viewer_state(viewer_scene) -> ViewerState:
    scene, results, model = viewer_scene
    return ViewerState.create(scene, results, model)


@pytest.fixture(scope="session")
def blind_camera_scene(viewer_scene):
    """The tiny scene with every detection of camera 0 removed, and its fresh results."""
    scene, _, model = viewer_scene
    keep = scene.detections.view != 0
    blind = dataclasses.replace(scene, detections=scene.detections.take(keep))
    return blind, run_pipeline(blind, PipelineConfig(), model, progress=False), model


@pytest.fixture(scope="session")
def frame_store(viewer_scene) -> FrameStore:
    scene, _, _ = viewer_scene
    store = FrameStore(scene, cache_dir=scene.root / ".mvviz" / "frames").start()
    assert store.wait(120), "decoding the tiny scene's videos took too long"
    return store


@pytest.fixture(scope="session")
def running_app(viewer_scene, frame_store):
    """A viewer serving the tiny scene on a free port (default layers)."""
    scene, results, model = viewer_scene
    state = ViewerState.create(scene, results, model)
    app = ViewerApp(state, host="127.0.0.1", port=free_port(), frames=frame_store)
    assert app.wait_idle(30)
    yield app
    app.stop()


@pytest.fixture(scope="session")
def browser():
    if not CHROMIUM.exists():
        pytest.skip(f"{CHROMIUM} is absent (apt-get install chromium) - browser tests skipped")
    sync_api = pytest.importorskip("playwright.sync_api")
    with sync_api.sync_playwright() as pw:
        b = launch_chromium(pw)
        yield b
        b.close()


def open_viewer(browser, url: str, *, adaptive_dpr: bool = False):
    """A page showing the viewer, its canvas up and the software-WebGL notice closed.

    Its device-pixel ratio is pinned to 1 (:func:`tools.chromium.pinned_dpr_url`) unless
    ``adaptive_dpr``: viser's adaptive ratio makes a picture depend on how slowly the
    page drew before it (pictures of the same frame differed by thinner, paler rays
    at ratio 0.75, not by what was shown)."""
    page = browser.new_page(viewport=VIEWPORT)
    page.goto(url if adaptive_dpr else pinned_dpr_url(url))
    page.wait_for_selector("canvas", timeout=60_000)
    close_webgl_notice(page)
    settle(page)
    return page


@pytest.fixture(scope="session")
def page(browser, running_app):
    p = open_viewer(browser, running_app.url)
    yield p
    p.close()


def open_tab(page, name: str) -> None:
    """Show the right-hand panel's tab ``name`` ("Layers", "Failures", ...)."""
    page.get_by_role("tab", name=name).click()
    settle(page, 0.3)


def wait_until(predicate, seconds: float = 10.0, what: str = "") -> None:
    """Poll ``predicate`` until it holds: a deadline on a shared machine, not a fixed
    sleep (the thread or page it waits for may not be scheduled for a while)."""
    deadline = time.monotonic() + seconds
    while not predicate():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.05)


def settle(page, seconds: float = 2.0) -> None:
    """Give the client time to apply messages and software-render a few frames."""
    page.wait_for_timeout(int(seconds * 1000))


def canvas_image(page) -> np.ndarray:
    """(h, w, 3) RGB screenshot of the 3D canvas."""
    png = page.locator("canvas").first.screenshot()
    bgr = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def wait_rendered(app: ViewerApp, page, seconds: float = 1.5) -> None:
    """Wait for the server to draw the current state and the page to show it: the frame
    label arrives in the same atomic message batch as the scene updates."""
    assert app.wait_idle(30)
    n = app.state.data.num_frames
    text = f"frame {app.state.frame} / {n - 1} "
    # textContent: the label may sit in a tab that is not shown (innerText skips those)
    page.wait_for_function("t => document.body.textContent.includes(t)", arg=text, timeout=30_000)
    time.sleep(0.1)
    settle(page, seconds)


def wait_drawn(
    app: ViewerApp, page, timeout_s: float = 60.0, interval_s: float = 0.4
) -> np.ndarray:
    """The (h, w, 3) canvas once the page shows everything sent for the app's state.

    A label and a fixed settle are not a drawn state: filter B's overlay and the failure
    marks are sent by panel workers outside the render's batch, and a frustum's video
    is a JPEG that viser's client decodes into a texture after applying its message
    (asynchronously). So: the render and panel workers idle, every page answered a round
    trip queued behind what was sent (:class:`~mvviz.workers.PageAcks`), then canvas
    screenshots ``interval_s`` apart until two in a row are the same picture.
    """
    from mvviz.workers import PageAcks

    for _ in range(2):  # a render may start panel work and a panel a redraw
        assert app.wait_idle(30), "the viewer's render did not finish"
        for panel in (app.filter_panel, app.failure_panel):
            assert panel.wait_idle(30), f"{type(panel).__name__} did not finish"
    wait_rendered(app, page, 0.0)  # this page has the frame's batch (its label)
    acks = PageAcks(app.server, timeout_s=30.0)
    try:
        assert acks.wait() >= 1, "no page answered after the viewer's last messages"
    finally:
        acks.stop()
    deadline = time.monotonic() + timeout_s
    prev = canvas_image(page)
    while True:
        page.wait_for_timeout(int(interval_s * 1000))
        img = canvas_image(page)
        change = float(np.abs(img.astype(np.int16) - prev).mean())
        if change < 0.01:  # grey levels per channel: the same picture
            return img
        assert time.monotonic() < deadline, f"the canvas kept changing ({change:.3f})"
        prev = img


def keep_screenshot(path: Path, name: str) -> None:
    """Copy a test's screenshot to docs/screenshots/ (the README's pictures) when
    MVVIZ_UPDATE_SCREENSHOTS=1; a normal test run never changes the work tree."""
    if os.environ.get("MVVIZ_UPDATE_SCREENSHOTS") == "1":
        docs = REPO / "docs" / "screenshots"
        docs.mkdir(parents=True, exist_ok=True)
        shutil.copy(path, docs / name)
