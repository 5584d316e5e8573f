"""Stage 3, triangulation: each associated person's 2D joints in several views -> 3D joints.

A confidence-weighted linear (DLT) triangulation per joint, with outlier-view rejection:
while a joint's worst view reprojects too far, one view is dropped and the joint
re-solved, as long as enough views remain.

Why these choices:

* The DLT is solved in undistorted *normalised* image coordinates with ``[R | t]``
  matrices: lens distortion is removed once up front (iterative, per camera), after
  which the problem is linear, and ``[R | t]`` has entries of order one.
* The homogeneous DLT ``A X = 0`` is solved inhomogeneously (``X = (x, y, z, 1)``) through
  the 3 x 3 normal equations, in closed form (adjugate / determinant), for all joints at
  once. Unlike the unit-norm SVD solution, this does not depend on where the world origin
  is or on its units, and it is many times faster than a batched SVD or ``eigh``. The
  normal matrix is linear in ``(w^2, w^2 x, w^2 y, w^2 (x^2 + y^2))`` with constant
  per-view coefficients, so one small matrix product builds it for every joint
  (:func:`_normal_basis`); the 2V x 4 system itself is never formed.
* The DLT residual of a view is its image error times depth / focal length, so far
  cameras would count more than near ones. :func:`triangulate_people` therefore solves
  twice: the second time with each view's rows rescaled by focal / depth (depths from the
  first solution), which makes every residual a pixel error. On the Shelf rig this brings
  the mean error under 2 px noise from 6% above to within 1% of the maximum-likelihood
  (bundle-adjusted) point.
* Which view to drop: each candidate (the joint without one of its views) is solved and
  the one with the smallest mean squared reprojection error over its remaining views wins.
  Simply dropping the view with the largest residual is wrong surprisingly often, because
  a view with high leverage drags the solution towards its outlier and the *other* views
  show the large residuals: on synthetic Shelf data with one outlier (40-200 px) among
  5 / 4 / 3 views, the largest residual is the outlier in 93% / 81% / 58% of joints, the
  best candidate in 98% / 95% / 87%, and the overall MPJPE drops from 14.1 to 7.7 mm.
  Candidates are only solved for joints over the threshold, so this costs little.

Units: world millimetres, image pixels. Shapes use P people, V views (cameras, in rig
order), J joints, N a flat batch.
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass

import numpy as np

from pipeline.data.cameras import CameraRig, max_valid_radius2

__all__ = ["Triangulation", "triangulate_dlt", "triangulate_people"]

# A 3 x 3 normal matrix whose determinant is this small relative to its scale has (nearly)
# parallel rays: the depth is undetermined, so the point is NaN rather than a huge number.
_MIN_RELATIVE_DET = 1e-14

# Matrix products are split into blocks of this many columns. OpenBLAS multi-threads a
# product once m * n * k exceeds 4 * 65536; for these thin products threads gain nothing
# and, when the cores are busy, make the product 5-20x slower.
_GEMM_COLUMNS = 1024


@dataclass(frozen=True, eq=False)
class Triangulation:
    """3D joints of the people of one frame (or of any batch of people).

    Attributes:
        points: (P, J, 3) world mm; NaN where fewer than ``min_views`` views were usable
            (never invented).
        reprojection_error: (P, J, V) pixels, between each observed (distorted) 2D joint and
            the projection of ``points`` with the camera's distortion; reported for dropped
            views too. NaN where the view has no usable observation or the point is NaN;
            +inf where the point lies behind that camera (or past the radius where its
            lens distortion folds back).
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


def _gemm(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a @ b`` for 2D arrays, in single-threaded column blocks (see ``_GEMM_COLUMNS``)."""
    n = b.shape[1]
    if n <= _GEMM_COLUMNS:
        return a @ b
    out = np.empty((a.shape[0], n))
    for s in range(0, n, _GEMM_COLUMNS):
        np.matmul(a, b[:, s : s + _GEMM_COLUMNS], out=out[:, s : s + _GEMM_COLUMNS])
    return out


# Entries of the symmetric 4 x 4 normal matrix that the solve needs:
# M00 M01 M02 M11 M12 M22 (the 3 x 3 block) and M03 M13 M23 (minus the right-hand side).
_NORMAL_ROWS = np.array([0, 0, 0, 1, 1, 2, 0, 1, 2])
_NORMAL_COLS = np.array([0, 1, 2, 1, 2, 2, 3, 3, 3])


def _normal_basis(proj: np.ndarray) -> np.ndarray:
    """(V, 3, 4) projection matrices -> (9, 4 V) coefficients of the normal equations.

    View v contributes the rows ``w (x P2 - P0)`` and ``w (y P2 - P1)`` (``Pk`` the rows of
    its matrix) to the DLT system ``A X = 0``; their share of ``A^T A`` is

        w^2 (P0^T P0 + P1^T P1) - w^2 x (P0^T P2 + P2^T P0)
            - w^2 y (P1^T P2 + P2^T P1) + w^2 (x^2 + y^2) P2^T P2,

    four constant 4 x 4 matrices per view. Column ``k V + v`` holds the 9 needed entries
    of the k-th matrix of view v, so that ``basis @ c`` with ``c[k V + v]`` the k-th
    coefficient of view v sums every view's share.
    """
    P0, P1, P2 = proj[:, 0], proj[:, 1], proj[:, 2]  # (V, 4) each

    def sym(a: np.ndarray, b: np.ndarray) -> np.ndarray:  # a b^T + b a^T, per view
        return a[:, :, None] * b[:, None, :] + b[:, :, None] * a[:, None, :]

    terms = np.stack(
        [0.5 * (sym(P0, P0) + sym(P1, P1)), -sym(P0, P2), -sym(P1, P2), 0.5 * sym(P2, P2)],
        axis=1,
    )  # (V, 4 terms, 4, 4)
    return terms[:, :, _NORMAL_ROWS, _NORMAL_COLS].transpose(2, 1, 0).reshape(9, -1)


def _solve_normal(basis: np.ndarray, x: np.ndarray, y: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Weighted DLT of a batch, view-major.

    Args:
        basis: (9, 4 V) from :func:`_normal_basis`.
        x, y: (V, N) image coordinates matching the projection matrices; must be finite
            (any value) where ``w == 0``.
        w: (V, N) row weights, 0 = view unused.
    Returns:
        (3, N) points; NaN where the rays are (nearly) parallel or fewer than two.
    """
    V, N = w.shape
    c = np.empty((4, V, N))
    w2 = np.multiply(w, w, out=c[0])
    wx = np.multiply(w2, x, out=c[1])
    wy = np.multiply(w2, y, out=c[2])
    np.add(wx * x, wy * y, out=c[3])
    a, b, c_, d, e, f, r0, r1, r2 = _gemm(basis, c.reshape(4 * V, N))  # (9, N) -> rows
    # Adjugate of the symmetric [[a b c] [b d e] [c e f]]; Cramer's rule is accurate for a
    # 3 x 3 system as well conditioned as ours and needs no per-matrix LAPACK call. The
    # right-hand side is -(r0, r1, r2), hence the sign of the determinant below.
    A00, A01, A02 = d * f - e * e, c_ * e - b * f, b * e - c_ * d
    A11, A12, A22 = a * f - c_ * c_, b * c_ - a * e, a * d - b * b
    det = a * A00 + b * A01 + c_ * A02
    scale = (a + d + f) * (1.0 / 3.0)
    regular = np.abs(det) > _MIN_RELATIVE_DET * scale * scale * scale
    neg_inv_det = np.divide(-1.0, det, out=np.full(N, np.nan), where=regular)
    out = np.empty((3, N))
    np.multiply(A00 * r0 + A01 * r1 + A02 * r2, neg_inv_det, out=out[0])
    np.multiply(A01 * r0 + A11 * r1 + A12 * r2, neg_inv_det, out=out[1])
    np.multiply(A02 * r0 + A12 * r1 + A22 * r2, neg_inv_det, out=out[2])
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
            f"weights: expected (..., {V}) to go with points {points.shape}, got {weights.shape}"
        )
    # View-major (V, N) arrays, as the solver wants them.
    xy = np.broadcast_to(points, batch + (V, 2)).reshape(-1, V, 2).transpose(2, 1, 0)
    w = np.broadcast_to(weights, batch + (V,)).reshape(-1, V).T
    usable = (w > 0) & np.isfinite(xy).all(0)  # NaN weights compare False
    x, y = np.where(usable, xy[0], 0.0), np.where(usable, xy[1], 0.0)
    X = _solve_normal(_normal_basis(proj), x, y, np.where(usable, w, 0.0))
    X[:, usable.sum(0) < 2] = np.nan
    return X.T.reshape(batch + (3,))


# --------------------------------------------------------------------------- rig stage


@dataclass(frozen=True, eq=False)
class _RigArrays:
    """A rig's cameras as stacked arrays, shaped to broadcast over view-major (V, N)."""

    basis: np.ndarray  # (9, 4 V) normal-equation coefficients of the [R | t] matrices
    R_all: np.ndarray  # (3 V, 3): rows x, y, z of every camera, so R_all @ X -> (3, V, N)
    t_all: np.ndarray  # (3 V, 1) the matching translations
    K: np.ndarray  # (3, 3, V, 1): K[i, j] is a (V, 1) column
    dist: np.ndarray  # (5, V, 1)
    distorted: bool  # any camera with non-zero distortion
    fold_r2: np.ndarray  # (V, 1) squared normalised radius where the distortion folds back
    focal: np.ndarray  # (V, 1) mean focal length, px


# Rigs are frozen, so their stacked arrays are built once per rig object (~150 us, as
# much as the rest of an outlier-free frame); weak keys let a rig no longer used go.
_RIG_ARRAYS: weakref.WeakKeyDictionary[CameraRig, _RigArrays] = weakref.WeakKeyDictionary()


def _rig_arrays(rig: CameraRig) -> _RigArrays:
    arrays = _RIG_ARRAYS.get(rig)
    if arrays is None:
        arrays = _RIG_ARRAYS[rig] = _stack_rig(rig)
    return arrays


def _stack_rig(rig: CameraRig) -> _RigArrays:
    R = np.stack([c.R for c in rig])  # (V, 3, 3)
    t = np.stack([c.t for c in rig])  # (V, 3)
    K = np.stack([c.K for c in rig], axis=-1)[..., None]
    return _RigArrays(
        basis=_normal_basis(np.concatenate([R, t[:, :, None]], axis=2)),
        R_all=R.transpose(1, 0, 2).reshape(-1, 3),
        t_all=t.T.reshape(-1, 1),
        K=K,
        dist=np.stack([c.dist for c in rig], axis=-1)[..., None],
        distorted=any(np.any(c.dist != 0) for c in rig),
        fold_r2=np.array([[max_valid_radius2(c.dist)] for c in rig]),
        focal=0.5 * (K[0, 0] + K[1, 1]),
    )


def _normalise(
    rig: CameraRig, arrays: _RigArrays, u: np.ndarray, v: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(V, N) distorted pixels u, v -> (V, N) undistorted normalised x, y."""
    if not arrays.distorted:
        # No distortion: the map is exactly K^-1, done for all views at once (cv2's
        # per-call overhead would dominate at a few hundred joints per frame).
        K = arrays.K
        y = (v - K[1, 2]) / K[1, 1]
        return (u - K[0, 2] - K[0, 1] * y) / K[0, 0], y
    x, y = np.empty(u.shape), np.empty(u.shape)
    for i, cam in enumerate(rig):
        x[i], y[i] = cam.undistort_to_normalised(np.stack([u[i], v[i]], axis=-1)).T
    return x, y


def _depth(arrays: _RigArrays, X: np.ndarray) -> np.ndarray:
    """(3, N) world mm -> (3, V, N) camera coordinates, mm."""
    V = len(arrays.focal)
    return (_gemm(arrays.R_all, X) + arrays.t_all).reshape(3, V, -1)


def _pixel_scale(arrays: _RigArrays, X: np.ndarray) -> np.ndarray:
    """(3, N) world mm -> (V, N) focal / depth of each point in each camera.

    |depth|, because the DLT residual of a point behind a camera has that magnitude too;
    floored at 1 mm so that a point at a camera centre cannot divide by zero.
    """
    z = _depth(arrays, X)[2]
    return arrays.focal / np.maximum(np.abs(z), 1.0)


def _reprojection_error(
    arrays: _RigArrays, X: np.ndarray, u: np.ndarray, v: np.ndarray
) -> np.ndarray:
    """(3, N) world mm and (V, N) observed pixels -> (V, N) pixel distances.

    The projection is :func:`pipeline.data.cameras.distort_and_project` (Camera.project)
    vectorised over the cameras, whose K and dist broadcast as (V, 1) columns; a test
    keeps the two equal. NaN where the observation or the point is NaN; +inf where the
    point is behind the camera or past the radius where its distortion folds back.
    """
    X_cam = _depth(arrays, X)
    z = X_cam[2]
    inv_z = np.divide(1.0, z, out=np.full(z.shape, np.nan), where=z > 1e-9)
    x, y = X_cam[0] * inv_z, X_cam[1] * inv_z
    invalid = z <= 1e-9
    if arrays.distorted:
        k1, k2, p1, p2, k3 = arrays.dist
        r2 = x * x + y * y
        invalid |= r2 > arrays.fold_r2
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        x, y = (
            x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x),
            y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y,
        )
    K = arrays.K
    du = K[0, 0] * x + K[0, 1] * y + (K[0, 2] - u)
    dv = K[1, 1] * y + (K[1, 2] - v)
    err = np.sqrt(du * du + dv * dv)
    err[invalid & (u == u)] = np.inf  # u == u: observed
    return err


def _candidate_solves(
    arrays: _RigArrays, obs: np.ndarray, used: np.ndarray, num_used: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each joint re-solved without each one of its used views; the best candidate wins.

    Args:
        obs: (5, V, n) x, y (normalised), u, v (pixels) and row weights (0 where unused)
            of n joints.
        used: (V, n) bool; num_used: (n,) its column sums.
    Returns:
        (3, n) points, (V, n) reprojection errors and (n,) dropped view of the candidate
        with the smallest mean squared reprojection error over its remaining views; the
        dropped view is -1 where no candidate could be solved.
    """
    _, V, n = obs.shape
    keep = ~np.eye(V, dtype=bool)  # (view, candidate): candidate c is without view c
    tiled = np.concatenate([obs] * V, axis=2)  # (5, V, V * n), column c * n + joint
    x, y, u, v, w = tiled
    w *= np.repeat(keep, n, axis=1)
    X = _solve_normal(arrays.basis, x, y, w)
    err = _reprojection_error(arrays, X, u, v).reshape(V, V, n)
    sq = np.where(used[:, None] & keep[:, :, None], err * err, 0.0)
    score = sq.sum(0) / (num_used - 1)  # (candidate, n)
    # Dropping an unused view is no candidate; NaN: the candidate is singular.
    score = np.where(used & (score == score), score, np.inf)
    best = score.argmin(0)
    cols = np.arange(n)
    dropped = np.where(score[best, cols] < np.inf, best, -1)
    chosen = best * n + cols
    return X[:, chosen], err.reshape(V, V * n)[:, chosen], dropped


def _drop_outlier_views(
    arrays: _RigArrays,
    obs: np.ndarray,
    used: np.ndarray,
    num_used: np.ndarray,
    points: np.ndarray,
    err: np.ndarray,
    *,
    outlier_threshold_px: float,
    min_views: int,
) -> None:
    """Rejection rounds of :func:`triangulate_people`, updating ``used`` (V, N),
    ``points`` (3, N) and ``err`` (V, N) in place.

    Each round drops, for every joint whose worst used view reprojects further than
    ``outlier_threshold_px`` and that has more than ``min_views`` used views, the view
    whose removal fits the others best; so at most V - min_views rounds. NaN points
    (singular) compare False and stay out. ``obs`` (5, V, N) is x, y, u, v, weight.
    """
    V = used.shape[0]
    sub, X, e, sub_used, sub_num = np.arange(used.shape[1]), points, err, used, num_used
    for _ in range(V - min_views):
        over = (np.where(sub_used, e, -1.0).max(0) > outlier_threshold_px) & (sub_num > min_views)
        if not over.any():
            break
        sub, sub_used, sub_num, X = sub[over], sub_used[:, over], sub_num[over], X[:, over]
        sub_obs = obs[:, :, sub]
        sub_obs[4] *= sub_used * _pixel_scale(arrays, X)
        X, e, dropped = _candidate_solves(arrays, sub_obs, sub_used, sub_num)
        solved = dropped >= 0  # else keep the joint as it was, with all its views
        if not solved.all():
            sub, sub_used, X, e = sub[solved], sub_used[:, solved], X[:, solved], e[:, solved]
            sub_num, dropped = sub_num[solved], dropped[solved]
        sub_used[dropped, np.arange(len(sub))] = False
        sub_num = sub_num - 1
        used[:, sub] = sub_used
        points[:, sub], err[:, sub] = X, e


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
        outlier_threshold_px: while a joint's worst used view reprojects further than this
            and it has more than ``min_views`` used views, one view is dropped (the one whose
            removal fits the others best) and the joint re-solved.
        min_views: a joint needs this many used views (>= 2), else its point is NaN. A joint
            at ``min_views`` views keeps them all: with 2 views and one bad view, both stay
            and the large ``reprojection_error`` is what tells (which one is wrong is
            undecidable from two views).
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

    # 1. View-major (V, N) arrays, N = P * J joints; missing = NaN or low confidence.
    u, v, conf = keypoints.transpose(3, 1, 0, 2).reshape(3, V, N)
    # NaN confidence compares False; a zero weight would be "used" without any effect.
    used = np.isfinite(u) & np.isfinite(v) & (conf >= min_confidence) & (conf > 0)
    points = np.full((3, N), np.nan)
    err = np.full((V, N), np.nan)
    num_used = used.sum(0)
    if (num_used >= min_views).any():
        # Every joint is solved, also those with too few views: they come out NaN or are
        # masked in step 5, which is cheaper than selecting the others.
        arrays = _rig_arrays(rig)
        # obs: x, y (normalised), u, v (pixels), weight. Missing: x = y = w = 0 (so that they
        # add exact zeros), u = v = NaN (no reprojection error).
        obs = np.empty((5, V, N))
        np.copyto(obs[2:4], np.where(used, [u, v], np.nan))
        # 2. Undistort once.
        x, y = _normalise(rig, arrays, obs[2], obs[3])
        np.copyto(obs[0:2], np.where(used, [x, y], 0.0))
        np.copyto(obs[4], np.where(used, conf, 0.0))
        x, y, u, v, w = obs
        # 3. Solve with the confidences, then again with the rows in pixel units.
        X = _solve_normal(arrays.basis, x, y, w)
        points = _solve_normal(arrays.basis, x, y, w * _pixel_scale(arrays, X))
        err = _reprojection_error(arrays, points, u, v)
        # 4. Rejection rounds over the joints still over the threshold.
        _drop_outlier_views(
            arrays, obs, used, num_used, points, err,
            outlier_threshold_px=outlier_threshold_px, min_views=min_views,
        )  # fmt: skip

    # 5. Points with too few views (or singular geometry) are NaN, never invented.
    num_views = used.sum(0)
    bad = (num_views < min_views) | ~np.isfinite(points).all(0)
    points[:, bad], err[:, bad] = np.nan, np.nan
    used[:, bad], num_views[bad] = False, 0
    return Triangulation(
        points=points.T.reshape(P, J, 3),
        reprojection_error=err.T.reshape(P, J, V),
        used=used.T.reshape(P, J, V),
        num_views=num_views.reshape(P, J),
    )
