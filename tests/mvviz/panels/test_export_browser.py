"""The exported GLB in three.js: viser's ``add_glb`` hands it to three.js's GLTFLoader
in headless chromium, which skins the bodies and plays the animation
(``THREE.AnimationMixer``). Checked on screenshots: both tracks' colours are drawn, where
the fitted bodies stand, and the picture changes as the animation plays."""

from __future__ import annotations

import time

import numpy as np
import pytest
import viser
import viser.transforms as vtf

from pipeline.core.palette import track_rgb
from pipeline.exports import export_results
from pipeline.importers.bvh import Y_UP_TO_WORLD
from tests.mvviz.conftest import (
    canvas_image,
    close_webgl_notice,
    free_port,
    keep_screenshot,
    settle,
)

pytestmark = pytest.mark.slow


def _colour_fraction(img: np.ndarray, rgb, tol: float = 60.0) -> float:
    """Share of pixels near a track's colour (lit and shaded: a generous tolerance on
    the colour's direction, not its brightness)."""
    px = img.reshape(-1, 3).astype(float)
    c = np.asarray(rgb, float)
    scale = (px @ c) / (c @ c)
    near = np.linalg.norm(px - scale[:, None] * c, axis=1) < tol * 0.5
    return float((near & (scale > 0.25)).mean())


def test_glb_plays_in_three_js(viewer_scene, browser, tmp_path):
    scene, results, _ = viewer_scene
    [f] = export_results(results, "glb", tmp_path / "run.glb", fps=scene.fps)
    fit = results.smpl_vae
    center = np.nanmean(fit.joints[:, :, 0], axis=(0, 1)) / 1000.0  # world m
    server = viser.ViserServer(host="127.0.0.1", port=free_port(), verbose=False)
    try:
        server.scene.set_up_direction("+z")
        # glTF is y up: world = (z, x, y) of a glTF point
        wxyz = vtf.SO3.from_matrix(Y_UP_TO_WORLD).wxyz
        server.scene.add_grid("/floor", width=10, height=10, position=(*center[:2], 0.0))
        server.scene.add_glb("/export", f.path.read_bytes(), wxyz=tuple(wxyz))
        server.initial_camera.position = tuple(center + np.array([4.0, -4.0, 2.5]))
        server.initial_camera.look_at = tuple(center)
        server.initial_camera.up = (0.0, 0.0, 1.0)
        page = browser.new_page(viewport={"width": 900, "height": 700})
        try:
            page.goto(f"http://127.0.0.1:{server.get_port()}")
            page.wait_for_selector("canvas", timeout=60_000)
            close_webgl_notice(page)
            # the GLB is fetched, parsed and its shaders compiled in software: poll, with
            # a deadline, until every track's body is drawn, then until the picture moves
            tracks = range(results.num_tracks)
            deadline = time.monotonic() + 90
            while True:
                settle(page, 1.0)
                a = canvas_image(page)
                drawn = [_colour_fraction(a, track_rgb(k)) > 0.002 for k in tracks]
                if all(drawn) or time.monotonic() > deadline:
                    break
            deadline = time.monotonic() + 20
            while True:
                page.wait_for_timeout(250)
                b = canvas_image(page)
                if _changed(a, b) or time.monotonic() > deadline:
                    break
            png = tmp_path / "glb_three.png"
            page.locator("canvas").first.screenshot(path=str(png))
            keep_screenshot(png, "export_glb_three.png")
        finally:
            page.close()
    finally:
        server.stop()
    for k in range(results.num_tracks):
        assert _colour_fraction(a, track_rgb(k)) > 0.002, f"track {k}'s body is not drawn"
    assert _changed(a, b), "the animation does not play"


def _changed(a: np.ndarray, b: np.ndarray) -> bool:
    return bool(np.abs(a.astype(int) - b.astype(int)).sum(-1).astype(bool).mean() > 1e-4)
