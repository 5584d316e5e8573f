"""2D restoration: the weak-perspective camera, and restoring joints from SMPL predictions."""

from __future__ import annotations

import numpy as np
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.body.model import load_body_model
from pipeline.stages.restore import (
    _fit_weak_perspective_row,
    crop_to_pixels,
    fit_weak_perspective,
    pixels_to_crop,
    restore_joints_2d,
    weak_perspective_matrix,
    weak_perspective_project,
)


@settings(max_examples=50, deadline=None)
@given(
    s=st.floats(0.3, 3.0),
    tx=st.floats(-0.5, 0.5),
    ty=st.floats(-0.5, 0.5),
    x0=st.floats(0, 500),
    size=st.floats(50, 600),
)
def test_fit_recovers_the_camera(s, tx, ty, x0, size):
    rng = np.random.default_rng(0)
    joints = rng.normal(0, 0.4, (1, 24, 3))
    bbox = np.array([[x0, x0 / 2, x0 + size, x0 / 2 + size]])
    cam = np.array([[s, tx, ty]])
    px = weak_perspective_project(joints, cam, bbox)
    np.testing.assert_allclose(fit_weak_perspective(joints, px, bbox), cam, atol=1e-8)
    np.testing.assert_allclose(pixels_to_crop(crop_to_pixels(px, bbox), bbox), px, atol=1e-9)


def test_the_closed_form_fit_is_least_squares_row_by_row():
    """All rows at once equal np.linalg.lstsq one row at a time, with weights, missing
    joints, and rows with one joint or none (those take the row-by-row path)."""
    rng = np.random.default_rng(3)
    n, j = 200, 24
    joints = rng.normal(0, 0.4, (n, j, 3))
    cam = np.column_stack([rng.uniform(0.5, 2, n), rng.uniform(-0.3, 0.3, (n, 2))])
    bbox = np.column_stack([rng.uniform(0, 400, (n, 2)), np.zeros((n, 2))])
    bbox[:, 2:] = bbox[:, :2] + rng.uniform(100, 500, (n, 1))
    px = weak_perspective_project(joints, cam, bbox) + rng.normal(0, 3, (n, j, 2))
    w = rng.uniform(0, 1, (n, j)) * (rng.uniform(size=(n, j)) > 0.2)
    px[rng.uniform(size=(n, j)) < 0.05] = np.nan
    w[0] = 0
    w[1, 1:] = 0
    w[1, 0] = 1
    got = fit_weak_perspective(joints, px, bbox, w)
    target = pixels_to_crop(px, bbox)
    ok = (w > 0) & np.isfinite(target).all(-1)
    rows = [_fit_weak_perspective_row(joints[i], target[i], w[i], ok[i]) for i in range(n)]
    want = np.stack(rows)
    np.testing.assert_allclose(got[2:], want[2:], rtol=1e-9, atol=1e-12)
    np.testing.assert_array_equal(got[:2], want[:2])  # the degenerate rows: the same path
    assert np.isfinite(got[2:]).all() and np.isnan(got[0, 1:]).all()


def test_matrix_form_drops_depth():
    M = weak_perspective_matrix(np.array([[2.0, 0.1, -0.2]]))[0]
    np.testing.assert_allclose(M, [[2, 0, 0, 0.2], [0, 2, 0, -0.4]])
    a = weak_perspective_project(
        np.array([[[0.1, 0.2, 5.0]]]), np.array([[2.0, 0.1, -0.2]]), np.array([[0, 0, 100, 100]])
    )
    b = weak_perspective_project(
        np.array([[[0.1, 0.2, -9.0]]]), np.array([[2.0, 0.1, -0.2]]), np.array([[0, 0, 100, 100]])
    )
    np.testing.assert_allclose(a, b)
    np.testing.assert_allclose(a[0, 0], [50 + 50 * 0.4, 50 + 50 * 0.0])


def test_restore_uses_the_joints_only_path_and_skips_missing_rows():
    model = load_body_model()
    rng = np.random.default_rng(1)
    pose = rng.normal(0, 0.2, (3, 72))
    pose[1] = np.nan  # no prediction for this row
    betas = rng.normal(0, 1, (3, 10))
    cam = np.array([[1.2, 0.0, 0.1]] * 3)
    bbox = np.array([[100.0, 50.0, 400.0, 350.0]] * 3)
    out = restore_joints_2d(pose, betas, cam, bbox, model, score=np.array([0.7, 0.9, 2.0]))
    assert np.isnan(out[1, :, :2]).all() and (out[1, :, 2] == 0).all()
    assert (out[0, :, 2] == 0.7).all() and (out[2, :, 2] == 1.0).all()  # clipped to [0, 1]
    with torch.no_grad():
        j = model.joints(
            torch.tensor(pose[[0]], dtype=torch.float32),
            torch.tensor(betas[[0]], dtype=torch.float32),
        )
    expect = weak_perspective_project(j.double().numpy(), cam[:1], bbox[:1])
    np.testing.assert_allclose(out[0, :, :2], expect[0], atol=1e-3)
