"""Stage 3, triangulation: each associated person's 2D joints in several views -> 3D joints.

A confidence-weighted linear (DLT) triangulation per joint, with outlier-view rejection:
a view whose reprojection error is too large is dropped and the joint re-solved, as long
as enough views remain.

Why these choices:

* The DLT is solved in undistorted *normalised* image coordinates with ``[R | t]``
  matrices: lens distortion is removed once up front (an iterative, per-camera step),
  after which the problem is linear, and ``[R | t]`` has entries of order one, so the
  normal equations are as well conditioned as the view geometry allows.
* The homogeneous DLT ``A X = 0`` is solved inhomogeneously (``X = (x, y, z, 1)``) through
  the 3 x 3 normal equations, in closed form (adjugate / determinant), for all joints at
  once. Unlike the unit-norm SVD solution, this does not depend on where the world origin
  is or on the world's units, and it is many times faster than a batched SVD or ``eigh``.
  The normal matrix is never formed from the 2V x 4 system: it is linear in
  ``(w^2, w^2 x, w^2 y, w^2 (x^2 + y^2))`` with per-view constant coefficient matrices,
  so one small matrix product builds it for every joint (see :func:`_normal_basis`).
* Rejection drops only the single worst view of a joint per round and then re-solves,
  because one gross outlier drags the first solution and inflates the errors of the
  good views too; the worst view is the one to distrust, the others are re-judged after.

Units: world millimetres, image pixels. Shapes use P people, V views (cameras, in rig
order), J joints, N a flat batch.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.cameras import CameraRig, distort_and_project

__all__ = ["Triangulation", "triangulate_dlt", "triangulate_people"]

# A 3 x 3 normal matrix whose determinant is this small relative to its scale has (nearly)
# parallel rays: the depth is undetermined, so the point is NaN rather than a huge number.
_MIN_RELATIVE_DET = 1e-14


@dataclass(frozen=True, eq=False)
class Triangulation:
    """3D joints of the people of one frame (or of any batch of people).

    Attributes:
        points: (P, J, 3) world mm; NaN where fewer than ``min_views`` views were usable
            (never invented).
        reprojection_error: (P, J, V) pixels, between each observed (distorted) 2D joint and
            the projection of ``points`` with the camera's distortion; reported for dropped
            views too. NaN where the view has no usable observation or the point is NaN;
            +inf where the point lies behind that camera.
        used: (P, J, V) bool, the views that ``points`` was solved from (all False where
            ``points`` is NaN).
        num_views: (P, J) int, ``used.sum(-1)``.
    """

    points: np.ndarray
    reprojection_error: np.ndarray
    used: np.ndarray
    num_views: np.ndarray

    @property
    def num_people(self) -> int:
        return self.points.shape[0]


# --------------------------------------------------------------------------- linear solve


def _normal_basis(proj: np.ndarray) -> np.ndarray:
    """(V, 3, 4) projection matrices -> (4 V, 9) coefficients of the normal equations.

    View v contributes the rows ``w (x P2 - P0)`` and ``w (y P2 - P1)`` (``Pk`` the rows of
    its matrix) to the DLT system ``A X = 0``; their share of ``A^T A`` is

        w^2 (P0^T P0 + P1^T P1) - w^2 x (P0^T P2 + P2^T P0)
            - w^2 y (P1^T P2 + P2^T P1) + w^2 (x^2 + y^2) P2^T P2,

    four constant 4 x 4 matrices per view. Row ``4 v + k`` holds the 9 entries we need
    (the upper 3 x 3 triangle and the first three of the last column) of the k-th of them.
    """
    P0, P1, P2 = proj[:, 0], proj[:, 1], proj[:, 2]  # (V, 4) each

    def outer_sym(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        return a[:, :, None] * b[:, None, :] + b[:, :, None] * a[:, None, :]

    mats = np.stack(
        [
            0.5 * (outer_sym(P0, P0) + outer_sym(P1, P1)),
            -outer_sym(P0, P2),
            -outer_sym(P1, P2),
            0.5 * outer_sym(P2, P2),
        ],
        axis=1,
    )  # (V, 4, 4, 4): view, term, row, column
    rows, cols = _NORMAL_ENTRIES
    return mats[:, :, rows, cols].reshape(-1, 9)


# Entries of the symmetric 4 x 4 normal matrix kept: M00 M01 M02 M11 M12 M22 M03 M13 M23.
_NORMAL_ENTRIES = (np.array([0, 0, 0, 1, 1, 2, 0, 1, 2]), np.array([0, 1, 2, 1, 2, 2, 3, 3, 3]))


def _solve_normal(basis: np.ndarray, xy: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Weighted DLT of a flat batch.

    Args:
        basis: (4 V, 9) from :func:`_normal_basis`.
        xy: (N, V, 2) image coordinates matching the projection matrices; must be finite
            (anything) where ``w == 0``.
        w: (N, V) row weights, 0 = view unused.
    Returns:
        (N, 3) points; NaN or inf where the system is singular (the caller masks those).
    """
    x, y = xy[..., 0], xy[..., 1]
    w2 = w * w
    coeff = np.stack([w2, w2 * x, w2 * y, w2 * (x * x + y * y)], axis=-1)  # (N, V, 4)
    m = coeff.reshape(len(w), -1) @ basis  # (N, 9), one GEMM for the whole batch
    a, b, c, d, e, f = m[:, 0], m[:, 1], m[:, 2], m[:, 3], m[:, 4], m[:, 5]
    r0, r1, r2 = -m[:, 6], -m[:, 7], -m[:, 8]  # right-hand side -M[:3, 3]
    # Adjugate of the symmetric [[a b c] [b d e] [c e f]]; Cramer's rule is accurate for
    # a 3 x 3 system as well conditioned as ours and needs no per-matrix LAPACK call.
    A00, A01, A02 = d * f - e * e, c * e - b * f, b * e - c * d
    A11, A12, A22 = a * f - c * c, b * c - a * e, a * d - b * b
    det = a * A00 + b * A01 + c * A02
    scale = (a + d + f) / 3.0
    with np.errstate(divide="ignore", invalid="ignore"):
        inv_det = np.where(np.abs(det) > _MIN_RELATIVE_DET * scale**3, 1.0 / det, np.nan)
    out = np.empty((len(w), 3))
    out[:, 0] = (A00 * r0 + A01 * r1 + A02 * r2) * inv_det
    out[:, 1] = (A01 * r0 + A11 * r1 + A12 * r2) * inv_det
    out[:, 2] = (A02 * r0 + A12 * r1 + A22 * r2) * inv_det
    return out


def triangulate_dlt(proj: np.ndarray, points: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Batched, weighted linear (DLT) triangulation.

    Args:
        proj: (V, 3, 4) projection matrices. Best: ``[R | t]`` with ``points`` in undistorted
            normalised coordinates (pixels with ``K [R | t]`` work too).
        points: (..., V, 2) image coordinates of each point in each view; NaN = unseen.
        weights: (..., V) non-negative; each view's two DLT rows are scaled by its weight;
            0 = unused.
    Returns:
        (..., 3) points in the world frame of ``proj``; NaN where fewer than 2 views have a
        weight > 0 and finite coordinates, or the rays are parallel.
    """
    proj = np.asarray(proj, float)
    points = np.asarray(points, float)
    weights = np.asarray(weights, float)
    if proj.ndim != 3 or proj.shape[1:] != (3, 4):
        raise ValueError(f"proj: expected (num_views, 3, 4), got {proj.shape}")
    V = proj.shape[0]
    if points.ndim < 2 or points.shape[-2:] != (V, 2):
        raise ValueError(f"points: expected (..., {V}, 2) for {V} views, got {points.shape}")
    try:
        batch = np.broadcast_shapes(points.shape[:-2], weights.shape[:-1])
    except ValueError:
        batch = None
    if weights.ndim < 1 or weights.shape[-1] != V or batch is None:
        raise ValueError(
            f"weights: expected (..., {V}) matching points {points.shape}, got {weights.shape}"
        )
    points = np.broadcast_to(points, batch + (V, 2)).reshape(-1, V, 2)
    weights = np.broadcast_to(weights, batch + (V,)).reshape(-1, V)
    usable = (weights > 0) & np.isfinite(points).all(-1)
    w = np.where(usable, weights, 0.0)
    xy = np.where(usable[..., None], points, 0.0)
    out = _solve_normal(_normal_basis(proj), xy, w)
    out[usable.sum(-1) < 2] = np.nan
    return out.reshape(batch + (3,))


# --------------------------------------------------------------------------- rig stage


@dataclass(frozen=True, eq=False)
class _RigArrays:
    """A rig's cameras as stacked arrays, shaped for broadcasting over (N, V)."""

    basis: np.ndarray  # (4 V, 9) normal-equation coefficients of [R | t]
    axis: np.ndarray  # (3, V): X @ axis + t[:, 2] = depth of X in every camera
    focal: np.ndarray  # (V,) mean focal length, px
    R_stack: np.ndarray  # (3, 3 V): X @ R_stack = all camera coordinates at once
    t: np.ndarray  # (V, 3)
    K: np.ndarray  # (3, 3, V): K[i, j] is a (V,) row that broadcasts over (N, V)
    dist: np.ndarray  # (5, V)
    distorted: bool  # any camera with non-zero distortion


def _rig_arrays(rig: CameraRig) -> _RigArrays:
    R = np.stack([c.R for c in rig])
    t = np.stack([c.t for c in rig])
    return _RigArrays(
        basis=_normal_basis(np.concatenate([R, t[:, :, None]], axis=2)),
        axis=R[:, 2].T.copy(),
        focal=np.array([0.5 * (c.K[0, 0] + c.K[1, 1]) for c in rig]),
        R_stack=R.transpose(2, 0, 1).reshape(3, -1),
        t=t,
        K=np.stack([c.K for c in rig], axis=-1),
        dist=np.stack([c.dist for c in rig], axis=-1),
        distorted=any(np.any(c.dist != 0) for c in rig),
    )


def _normalise(rig: CameraRig, arrays: _RigArrays, pixels: np.ndarray) -> np.ndarray:
    """(N, V, 2) distorted pixels -> (N, V, 2) undistorted normalised coordinates."""
    if not arrays.distorted:
        # No distortion: the map is exactly K^-1, done for all views at once (cv2's
        # per-call overhead would dominate at a few hundred joints per frame).
        K = arrays.K
        y = (pixels[..., 1] - K[1, 2]) / K[1, 1]
        x = (pixels[..., 0] - K[0, 2] - K[0, 1] * y) / K[0, 0]
        return np.stack([x, y], axis=-1)
    out = np.empty(pixels.shape)
    for v, cam in enumerate(rig):
        out[:, v] = cam.undistort_to_normalised(pixels[:, v])
    return out


def _reprojection_error(arrays: _RigArrays, X: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """(N, 3) world mm and (N, V, 2) observed pixels -> (N, V) pixel distances.

    NaN where the observation or the point is NaN; +inf where the point is behind a camera.
    """
    V = arrays.t.shape[0]
    X_cam = (X @ arrays.R_stack).reshape(len(X), V, 3) + arrays.t
    # The same projection model as Camera.project, with every camera's K and dist
    # broadcast over the views axis.
    uv = distort_and_project(X_cam, arrays.K, arrays.dist)
    err = np.hypot(uv[..., 0] - pixels[..., 0], uv[..., 1] - pixels[..., 1])
    behind = (X_cam[..., 2] <= 1e-9) & np.isfinite(pixels[..., 0]) & np.isfinite(X[:, None, 0])
    err[behind] = np.inf
    return err


def _pixel_scale(arrays: _RigArrays, X: np.ndarray) -> np.ndarray:
    """(N, 3) world mm -> (N, V) focal / depth of each point in each camera.

    |depth| because the algebraic residual of a point behind a camera has that magnitude
    too; floored at 1 mm so that a point at a camera centre cannot divide by zero.
    """
    depth = X @ arrays.axis + arrays.t[:, 2]
    return arrays.focal / np.maximum(np.abs(depth), 1.0)


def triangulate_people(
    rig: CameraRig,
    keypoints: np.ndarray,
    *,
    min_confidence: float = 0.1,
    outlier_threshold_px: float = 25.0,
    min_views: int = 2,
) -> Triangulation:
    """Triangulate every joint of every person, dropping outlier views.

    Args:
        rig: the V cameras, in the order of the views axis.
        keypoints: (P, V, J, 3) distorted pixels (u, v) and confidence per person, view and
            joint. Observations with NaN or confidence < ``min_confidence`` are missing.
        min_confidence: below this a 2D joint is not used.
        outlier_threshold_px: a joint whose worst used view reprojects further than this is
            re-solved without that view, while more than ``min_views`` views remain.
        min_views: a joint needs this many used views (>= 2), else its point is NaN. With
            exactly ``min_views`` views no view is dropped: a 2-view joint with one bad view
            keeps both, and its large ``reprojection_error`` is what tells.
    Returns:
        :class:`Triangulation`. The DLT weights are the confidences, rescaled per view by
        focal / depth so that they weigh pixel errors alike in every camera.
    """
    keypoints = np.asarray(keypoints, float)
    V = len(rig)
    if keypoints.ndim != 4 or keypoints.shape[1] != V or keypoints.shape[3] != 3:
        raise ValueError(
            f"keypoints: expected (num_people, {V} views, num_joints, 3) as (u, v, confidence),"
            f" got {keypoints.shape}"
        )
    if min_views < 2:
        raise ValueError(f"min_views must be >= 2 (a point needs two rays), got {min_views}")
    P, _, J, _ = keypoints.shape
    N = P * J

    # 1. Flatten to (N, V, ...) joints x views; missing = NaN or low confidence.
    kp = keypoints.transpose(0, 2, 1, 3).reshape(N, V, 3)
    pixels, conf = kp[..., :2], kp[..., 2]
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(pixels).all(-1) & (conf >= min_confidence)  # NaN conf -> False
    pixels = np.where(valid[..., None], pixels, np.nan)
    w = np.where(valid, conf, 0.0)
    used = valid.copy()

    points = np.full((N, 3), np.nan)
    err = np.full((N, V), np.nan)
    solvable = np.flatnonzero(valid.sum(-1) >= min_views)
    if len(solvable):
        arrays = _rig_arrays(rig)
        # 2. Undistort once; unused entries become 0 so that they add exact zeros.
        xy = _normalise(rig, arrays, pixels[solvable])
        xy[~valid[solvable]] = 0.0
        # 3. A first solve with the confidences as weights gives each joint's depth in every
        #    camera. The DLT residual of a view is its image error times depth / focal, so
        #    far cameras would count more; rescaling each view's rows by focal / depth makes
        #    every residual a pixel error (this brings the linear solution to within ~1% of
        #    the maximum-likelihood one; without it, ~6% larger mean error on the Shelf rig).
        conf_s = w[solvable]
        X = _solve_normal(arrays.basis, xy, conf_s)
        # 4. Solve with every usable view, then reject: each round drops the worst view of
        #    each joint that is over the threshold and can spare a view, and re-solves only
        #    those joints. At most V - min_views rounds.
        idx, pos = solvable, np.arange(len(solvable))  # joint ids; their rows in xy
        sub_xy, sub_w = xy, conf_s
        for _ in range(V - min_views + 1):
            X = _solve_normal(arrays.basis, sub_xy, sub_w * _pixel_scale(arrays, X))
            points[idx] = X
            err[idx] = _reprojection_error(arrays, X, pixels[idx])
            sub_used = used[idx]
            e = np.where(sub_used, err[idx], -1.0)
            e[np.isnan(e)] = np.inf  # a used view without a projection is the worst one
            worst = e.argmax(-1)
            drop = (
                (e[np.arange(len(idx)), worst] > outlier_threshold_px)
                & (sub_used.sum(-1) > min_views)
                & np.isfinite(X[:, 0])  # singular geometry: dropping views cannot help
            )
            if not drop.any():
                break
            idx, pos, X = idx[drop], pos[drop], X[drop]
            used[idx, worst[drop]] = False
            sub_xy, sub_w = xy[pos], conf_s[pos] * used[idx]

    # 5. Points with too few views (or singular geometry) are NaN, never invented.
    num_views = used.sum(-1)
    bad = (num_views < min_views) | ~np.isfinite(points).all(-1)
    points[bad] = np.nan
    err[bad] = np.nan
    used[bad] = False
    num_views[bad] = 0
    return Triangulation(
        points=points.reshape(P, J, 3),
        reprojection_error=err.reshape(P, J, V),
        used=used.reshape(P, J, V),
        num_views=num_views.reshape(P, J),
    )
