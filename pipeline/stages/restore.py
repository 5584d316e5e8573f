"""Stage 1, 2D restoration: monocular SMPL predictions (or monocular 3D joints, e.g.
BlazePose's world landmarks) -> 2D joints by their weak-perspective camera, depth dropped.

Weak-perspective convention (SPIN's): with joints ``(X, Y, Z)`` in metres in the
regressor's camera frame (x right, y down), the crop-normalised image coordinates are
``u_n = s * (X + tx)``, ``v_n = s * (Y + ty)`` in [-1, 1] over the crop, i.e. the 2x4
camera matrix ``[[s, 0, 0, s*tx], [0, s, 0, s*ty]]`` applied to ``(X, Y, Z, 1)``; the
crop ``bbox = (x0, y0, x1, y1)`` maps them to image pixels.
"""

from __future__ import annotations

import numpy as np
import torch

from pipeline.core.torch_threads import torch_threads

RESTORE_THREADS = 1
"""torch intra-op threads of :func:`restore_joints_2d` (restored after). Its ops are
small (a few thousand rows of 24 joints): one thread is as fast, and two beside a busy
core spin instead of working (0.02 vs 0.14-0.70 CPU s per sample-sized scene, measured
at a load of 8 on 2 cores, e.g. two ``mvviz batch`` workers). A fixed count also keeps
the numbers the same in every process whatever its torch setting."""


def weak_perspective_matrix(cam_weak: np.ndarray) -> np.ndarray:
    """(N, 3) (s, tx, ty) -> (N, 2, 4) camera matrices acting on homogeneous joints."""
    s, tx, ty = np.moveaxis(np.asarray(cam_weak, float), -1, 0)
    z = np.zeros_like(s)
    return np.stack([np.stack([s, z, z, s * tx], -1), np.stack([z, s, z, s * ty], -1)], -2)


def crop_to_pixels(uv_norm: np.ndarray, bbox: np.ndarray) -> np.ndarray:
    """(N, J, 2) crop-normalised [-1, 1] coordinates, (N, 4) bbox -> (N, J, 2) pixels."""
    bbox = np.asarray(bbox, float)
    centre = 0.5 * (bbox[:, None, :2] + bbox[:, None, 2:])
    half = 0.5 * (bbox[:, None, 2:] - bbox[:, None, :2])
    return centre + uv_norm * half


def pixels_to_crop(pixels: np.ndarray, bbox: np.ndarray) -> np.ndarray:
    """Inverse of :func:`crop_to_pixels`."""
    bbox = np.asarray(bbox, float)
    centre = 0.5 * (bbox[:, None, :2] + bbox[:, None, 2:])
    half = 0.5 * (bbox[:, None, 2:] - bbox[:, None, :2])
    return (pixels - centre) / half


def weak_perspective_project(
    joints_m: np.ndarray, cam_weak: np.ndarray, bbox: np.ndarray
) -> np.ndarray:
    """Project regressor-frame joints to image pixels.

    Args:
        joints_m: (N, J, 3) joints in metres, regressor camera frame.
        cam_weak: (N, 3) s, tx, ty.  bbox: (N, 4) x0, y0, x1, y1 pixels.
    Returns:
        (N, J, 2) pixels (the depth Z is dropped).
    """
    joints_m = np.asarray(joints_m, float)
    homo = np.concatenate([joints_m, np.ones(joints_m.shape[:-1] + (1,))], -1)
    uv_norm = np.einsum("nab,njb->nja", weak_perspective_matrix(cam_weak), homo)
    return crop_to_pixels(uv_norm, bbox)


def fit_weak_perspective(
    joints_m: np.ndarray, pixels: np.ndarray, bbox: np.ndarray, weights: np.ndarray | None = None
) -> np.ndarray:
    """Least-squares (s, tx, ty) so that ``joints_m`` project onto ``pixels``.

    Args:
        joints_m: (N, J, 3); pixels: (N, J, 2); bbox: (N, 4); weights: (N, J) or None.
    Returns:
        (N, 3) cam_weak. Linear in (s, s*tx, s*ty): closed form for all rows at once
        (the weighted centroids give the offsets, the centred sums the scale); rows with
        fewer than two distinct usable joints by least squares one at a time.
    """
    target = pixels_to_crop(np.asarray(pixels, float), bbox)  # (N, J, 2)
    joints_m = np.asarray(joints_m, float)
    n, j = target.shape[:2]
    w = np.ones((n, j)) if weights is None else np.asarray(weights, float)
    ok = (w > 0) & np.isfinite(target).all(-1) & np.isfinite(joints_m).all(-1)
    w = np.where(ok, w, 0.0)
    xy = np.where(ok[..., None], joints_m[..., :2], 0.0)
    uv = np.where(ok[..., None], target, 0.0)
    total = w.sum(1)
    with np.errstate(divide="ignore", invalid="ignore"):
        xy_mean = np.einsum("nj,njc->nc", w, xy) / total[:, None]
        uv_mean = np.einsum("nj,njc->nc", w, uv) / total[:, None]
        dxy = np.where(ok[..., None], xy - xy_mean[:, None], 0.0)
        spread = np.einsum("nj,njc->n", w, dxy * dxy)
        s = np.einsum("nj,njc->n", w, dxy * (uv - uv_mean[:, None])) / spread
        offset = uv_mean - s[:, None] * xy_mean  # (s * tx, s * ty)
        out = np.column_stack([s, offset / s[:, None]])
    bad = ~((total > 0) & (spread > 1e-12 * np.maximum(total, 1e-300)) & np.isfinite(out).all(1))
    for i in np.flatnonzero(bad):
        out[i] = _fit_weak_perspective_row(joints_m[i], target[i], w[i], ok[i])
    return out


def _fit_weak_perspective_row(
    joints_m: np.ndarray, target: np.ndarray, w: np.ndarray, ok: np.ndarray
) -> np.ndarray:
    """One row of :func:`fit_weak_perspective` by ``np.linalg.lstsq``: (J, 3) joints,
    (J, 2) crop-normalised targets, (J,) weights, (J,) usable joints -> (3,)."""
    X, Y = joints_m[ok, 0], joints_m[ok, 1]
    one, zero = np.ones(ok.sum()), np.zeros(ok.sum())
    A = np.concatenate([np.stack([X, one, zero], -1), np.stack([Y, zero, one], -1)])
    b = np.concatenate([target[ok, 0], target[ok, 1]])
    sw = np.sqrt(np.concatenate([w[ok], w[ok]]))
    with np.errstate(divide="ignore", invalid="ignore"):
        s, a, c = np.linalg.lstsq(A * sw[:, None], b * sw, rcond=None)[0]
        return np.array([s, a / s, c / s])


def restore_joints_2d(
    smpl_pose: np.ndarray,
    smpl_betas: np.ndarray,
    cam_weak: np.ndarray,
    bbox: np.ndarray,
    model,
    *,
    score: np.ndarray | None = None,
    batch: int = 4096,
) -> np.ndarray:
    """2D SMPL-24 joints of monocular SMPL predictions.

    Joints come from the joints-only kinematics path (rest joints regressed from the
    shaped template, posed by forward kinematics), projected by the weak-perspective
    camera; their depth is dropped.

    Args:
        smpl_pose: (N, 72); smpl_betas: (N, 10); cam_weak: (N, 3); bbox: (N, 4).
            Rows with NaN pose are "no prediction".
        model: a :class:`pipeline.body.model.BodyModel`.
        score: (N,) confidence given to every joint of a row (default 1).
    Returns:
        (N, 24, 3) x px, y px, confidence; NaN x, y and confidence 0 where no prediction.
    """
    n = smpl_pose.shape[0]
    out = np.full((n, 24, 3), np.nan)
    out[..., 2] = 0.0
    valid = np.isfinite(smpl_pose).all(1) & np.isfinite(cam_weak).all(1)
    rows = np.flatnonzero(valid)
    with torch_threads(RESTORE_THREADS):
        _restore_rows(smpl_pose, smpl_betas, cam_weak, bbox, model, score, rows, batch, out)
    return out


def _restore_rows(smpl_pose, smpl_betas, cam_weak, bbox, model, score, rows, batch, out) -> None:
    for s in range(0, rows.size, batch):
        r = rows[s : s + batch]
        with torch.no_grad():
            joints = (
                model.joints(
                    torch.as_tensor(smpl_pose[r], dtype=torch.float32),
                    torch.as_tensor(smpl_betas[r], dtype=torch.float32),
                )
                .double()
                .numpy()
            )
        out[r, :, :2] = weak_perspective_project(joints, cam_weak[r], bbox[r])
        out[r, :, 2] = 1.0 if score is None else np.clip(score[r], 0, 1)[:, None]


def restore_mono_joints_2d(
    mono_joints3d: np.ndarray,
    cam_weak: np.ndarray,
    bbox: np.ndarray,
    *,
    score: np.ndarray | None = None,
) -> np.ndarray:
    """2D SMPL-24 joints of monocular 3D joint predictions: the same weak-perspective
    projection as :func:`restore_joints_2d`, on joints given directly.

    Args:
        mono_joints3d: (N, 24, 3) metres, camera axes; NaN for joints not predicted.
        cam_weak: (N, 3); bbox: (N, 4). Rows with NaN cam_weak are "no prediction".
        score: (N,) confidence given to every predicted joint of a row (default 1).
    Returns:
        (N, 24, 3) x px, y px, confidence; NaN x, y and confidence 0 where no prediction.
    """
    joints = np.asarray(mono_joints3d, float)
    n = joints.shape[0]
    out = np.full((n, joints.shape[1], 3), np.nan)
    out[..., 2] = 0.0
    rows = np.flatnonzero(np.isfinite(cam_weak).all(1))
    if rows.size:
        out[rows, :, :2] = weak_perspective_project(joints[rows], cam_weak[rows], bbox[rows])
        have = np.isfinite(out[rows, :, :2]).all(-1)
        conf = np.ones(rows.size) if score is None else np.clip(score[rows], 0, 1)
        out[rows, :, 2] = np.where(have, conf[:, None], 0.0)
    return out
