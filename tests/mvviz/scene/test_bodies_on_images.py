"""Fitted bodies on the camera image (mvviz.scene.images): the silhouettes are where the
fitted meshes project, agree with every face filled, the residual shown is the one
computed independently, and the layer is off by default and costs nothing then."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest

from mvviz.scene.geometry import LayerToggles, prepare
from mvviz.scene.images import (
    BODY_ALPHA,
    BODY_PALE,
    blank_frame,
    bodies_text,
    body_labels,
    body_outlines,
    draw_overlay,
    image_overlay,
    mesh_residuals,
    posed_vertices,
)

FRAME = 8


def _exact_silhouettes(data, view, frame):
    """(h, w) bool: every face of every fitted body filled, full resolution."""
    cam, b = data.scene.rig[view], data.fit_bodies
    out = np.zeros((cam.height, cam.width), np.uint8)
    for i in np.flatnonzero(b.present[:, frame]):
        px = cam.project(posed_vertices(b, i, frame) * 1000.0)
        tri = px[b.faces]
        for t in tri[np.isfinite(tri).all((1, 2))]:
            cv2.fillConvexPoly(out, np.round(t * 8).astype(np.int32), 1, cv2.LINE_8, 3)
    return out > 0


@pytest.mark.slow
def test_silhouettes_agree_with_every_face_filled(viewer_state):
    data = viewer_state.data
    assert data.fit_bodies is not None
    for view in range(len(data.scene.rig)):
        cam = data.scene.rig[view]
        bo = body_outlines(data, view, FRAME)
        assert len(bo.tracks) == data.fit_bodies.present[:, FRAME].sum()
        mine = body_labels(bo, (cam.height, cam.width), 1.0) > 0
        exact = _exact_silhouettes(data, view, FRAME)
        iou = (mine & exact).sum() / (mine | exact).sum()
        assert exact.sum() > 500 and iou > 0.93, (view, iou)


def test_posed_bodies_are_the_fitted_meshes(viewer_state):
    """Skinned as the browser does (no pose blend shapes), the vertices stay within a
    few cm of the body model's own mesh of the fit."""
    data = viewer_state.data
    fit = data.results.smpl_vae or data.results.smpl
    b = data.fit_bodies
    for i, k in enumerate(b.ids):
        if not fit.present[k, FRAME]:
            continue
        mine = posed_vertices(b, i, FRAME) * 1000.0
        model = fit.vertices(k, FRAME)
        d = np.linalg.norm(mine - model, axis=-1)
        assert np.median(d) < 10.0 and d.max() < 60.0, (k, np.median(d), d.max())


def test_the_residual_shown_is_the_one_computed_here(viewer_state):
    data = viewer_state.data
    res, fit = data.results, data.results.smpl_vae or data.results.smpl
    view = 1
    shown = mesh_residuals(data, view, FRAME)
    assert shown
    rows = data.rows_per_frame[FRAME]
    rows = rows[data.scene.detections.view[rows] == view]
    for k, px in shown.items():
        (row,) = rows[data.det_track[rows] == k]  # the track's detection in that camera
        kp = res.det_joints2d[row]
        uv = cv2.projectPoints(
            fit.keypoints[k, FRAME], cv2.Rodrigues(data.scene.rig[view].R)[0],
            data.scene.rig[view].t, data.scene.rig[view].K, data.scene.rig[view].dist,
        )[0][:, 0]  # fmt: skip
        err = np.linalg.norm(uv - kp[:, :2], axis=-1)
        ok = np.isfinite(err) & (kp[:, 2] >= data.min_confidence)
        assert px == pytest.approx(np.median(err[ok]), abs=1e-6)
        assert 0 < px < 25  # a clean synthetic scene: the fit sits on the 2D
    text = bodies_text(body_outlines(data, view, FRAME))
    for k, px in shown.items():
        assert f"track {k} {px:.1f} px" in text


def test_the_layer_draws_translucent_bodies_under_the_skeletons(viewer_state):
    data, view = viewer_state.data, 0
    cam = data.scene.rig[view]
    w = 400
    h = round(cam.height * w / cam.width)
    base = blank_frame(w, h)
    off = LayerToggles(detections2d=False, filtered=False, gt=False)
    assert LayerToggles().bodies_on_images is False  # off by default
    assert image_overlay(data, view, FRAME, off).bodies is None
    on = dataclasses.replace(off, bodies_on_images=True)
    ov = image_overlay(data, view, FRAME, on)
    assert ov.bodies is body_outlines(data, view, FRAME)  # cached per frame
    plain, drawn = draw_overlay(base, image_overlay(data, view, FRAME, off)), draw_overlay(base, ov)
    changed = (plain != drawn).any(-1)
    assert changed.mean() > 0.01
    # inside the nearest body, away from its outline: the base blended with its colour
    near = ov.bodies.tracks[-1]
    color = ov.bodies.colors[-1].astype(float)
    fill = color + (255 - color) * BODY_PALE  # the track colour, paled
    expect = (48 * (1 - BODY_ALPHA) + fill * BODY_ALPHA).astype(np.uint8)
    hits = (np.abs(drawn.astype(int) - expect).max(-1) <= 1).sum()
    assert hits > 100, near


def test_no_fits_no_bodies(viewer_scene):
    scene, results, _ = viewer_scene
    bare = prepare(scene, dataclasses.replace(results, smpl=None, smpl_vae=None), None)
    assert bare.fit_bodies is None and body_outlines(bare, 0, FRAME) is None
    assert mesh_residuals(bare, 0, FRAME) == {} and bodies_text(None) == ""
