"""The association's kernels as first written, kept as references: the tests hold the
product's kernels to them (same numbers, same clusters) and bench/bench_scale.py swaps
them in to time what each faster kernel saves. None of them runs in the product.

- :func:`ray_distances_reference`: (n, m, J, 3) arrays, what
  :func:`pipeline.association.affinity.ray_distances` computes by matrix products.
- :func:`dense_frame_distances`: every pair's distance, what the association did before
  its screen (:func:`pipeline.association.affinity.screened_distances`).
- :func:`average_linkage_reference`: a Python loop over merges, what
  :func:`pipeline.association.affinity.average_linkage` does with SciPy in O(n^2).
- :func:`screen_distances_unblocked` / :func:`pair_ray_distances_unchunked`: the screen
  and the pair kernel before :mod:`pipeline.association.pairs` cut them into blocks.
- :func:`fused_pairwise_distances`: the compiled pass one pair at a time with a branch
  per joint, before :func:`pipeline.association.fused.fused_screened_distances`
  vectorised its rows (the same numbers to the bit).

Units: mm.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from pipeline.association.affinity import _dot, _outer_dot, ray_distances
from pipeline.association.associate import _mirrored_distances
from pipeline.association.fused import _screen_row, prepare_frame
from pipeline.association.pairs import PARALLEL_SIN2, shared_joints
from pipeline.association.params import AssociationParams


def ray_distances_reference(
    origins: np.ndarray,
    dirs: np.ndarray,
    weights: np.ndarray,
    params: AssociationParams,
    *,
    other: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
) -> np.ndarray:
    """:func:`pipeline.association.affinity.ray_distances` (which :func:`associate_frame` uses)
    as first written, over (n, m, J, 3) arrays: the reference its tests and
    bench/bench_scale.py compare with.

    (n, m) confidence-weighted mean of clipped ray-to-ray distances, mm.

    Between the n detections ``(origins, dirs, weights)`` and the m of ``other`` (the
    same n when None; the diagonal is then NaN). NaN where two detections share fewer
    than ``min_shared_joints`` joints.
    """
    o2, d2, w2 = (origins, dirs, weights) if other is None else other
    # Closest points of lines a + s da and b + t db; distance |(b - a) . (da x db)| / |da x db|.
    cross = np.cross(dirs[:, None], d2[None, :])  # (n, m, J, 3)
    norm = np.linalg.norm(cross, axis=-1)
    base = o2[None, :] - origins[:, None]  # (n, m, 3)
    with np.errstate(invalid="ignore", divide="ignore"):
        d = np.abs(np.einsum("abc,abjc->abj", base, cross)) / norm
        # Both closest points must lie in front of their cameras, else the rays diverge.
        dd = np.einsum("ajc,bjc->abj", dirs, d2)
        w0 = np.einsum("abc,ajc->abj", base, dirs)
        w1 = np.einsum("abc,bjc->abj", base, d2)
        denom = 1 - dd**2
        s = (w0 - dd * w1) / denom
        t = (dd * w0 - w1) / denom
    behind = (s <= 0) | (t <= 0)
    clip = params.joint_clip_mm
    d = np.where(behind | ~np.isfinite(d), clip, np.minimum(d, clip))
    w = weights[:, None, :] * w2[None, :, :]
    w = np.where(np.isfinite(norm) & (norm > 1e-6), w, 0.0)
    shared = (w > 0).sum(-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = (w * d).sum(-1) / w.sum(-1)
    mean[shared < params.min_shared_joints] = np.nan
    if other is None:
        mean[np.arange(len(origins)), np.arange(len(origins))] = np.nan
    return mean


def dense_frame_distances(
    origins: np.ndarray,
    dirs: np.ndarray,
    weights: np.ndarray,
    views: np.ndarray,
    flip: np.ndarray | None,
    params: AssociationParams,
) -> tuple[np.ndarray, np.ndarray]:
    """(n, n) ray distances as labelled and with one of the pair mirrored (NaN where not
    scored, and for pairs of one view), every pair by :func:`ray_distances`: what
    :func:`associate_frame` did before the screen
    (:func:`pipeline.association.affinity.screened_distances`), kept for bench_scale."""
    dist = ray_distances(origins, dirs, weights, params)
    mirrored = np.full_like(dist, np.nan)
    if flip is not None:
        mirrored = _mirrored_distances(origins, dirs, weights, views, flip, params)
    dist[views[:, None] == views[None, :]] = np.nan  # as the screened ones: no same-view pair
    return dist, mirrored


def average_linkage_reference(
    affinity: np.ndarray, views: np.ndarray, threshold: float, *, condensed=None
) -> np.ndarray:
    """Agglomerative clustering with average linkage and same-view cannot-links, as first
    written (a Python loop over merges): the reference of the tests and bench_scale.

    Returns (n,) cluster labels. Merges the pair of clusters with the highest mean
    cross affinity while it is >= threshold; pairs with an unknown affinity (NaN)
    count as 0 in the mean, so a detection must agree with most of a cluster.
    ``condensed`` is not read (the reference makes its own means).
    """
    n = len(views)
    A = np.nan_to_num(affinity, nan=0.0)
    sums = A.copy()  # sum of affinities between clusters i and j
    counts = np.ones((n, n))
    view_sets = np.zeros((n, int(views.max()) + 1), bool)
    view_sets[np.arange(n), views] = True
    alive = np.ones(n, bool)
    label = np.arange(n)
    while True:
        mean = sums / counts
        conflict = (view_sets.astype(int) @ view_sets.T.astype(int)) > 0
        mean[conflict | ~alive[:, None] | ~alive[None, :]] = -np.inf
        np.fill_diagonal(mean, -np.inf)
        i, j = np.unravel_index(np.argmax(mean), mean.shape)
        if mean[i, j] < threshold:
            break
        # Merge j into i.
        label[label == j] = i
        sums[i, :] += sums[j, :]
        sums[:, i] += sums[:, j]
        counts[i, :] += counts[j, :]
        counts[:, i] += counts[:, j]
        view_sets[i] |= view_sets[j]
        alive[j] = False
    return label


def screen_distances_unblocked(
    origins: np.ndarray, dirs: np.ndarray, weights: np.ndarray, groups: list[np.ndarray],
    clip: float,
) -> np.ndarray:  # fmt: skip
    """(n, n) a cheap stand-in for :func:`ray_distances`: the same clipped, weighted mean,
    over each body part's mean ray (``groups``) instead of every joint, and without the
    behind-the-camera test (which only raises a distance). Float32, NaN where two
    detections share no part. Each part is 3 matrix products of depth 3 on (n, n): the
    screen before :func:`pipeline.association.pairs.screen_distances` (the same numbers by row
    blocks), kept for its test and bench/bench_scale.py's ratio."""
    o = (origins - origins.mean(0)).astype(np.float32)  # centred: float32 keeps 0.01 mm
    ray = np.stack([(np.nan_to_num(dirs[:, g]) * weights[:, g, None]).sum(1) for g in groups])
    norm = np.linalg.norm(ray, axis=-1)  # (K, n)
    u = (ray / np.maximum(norm, 1e-12)[..., None]).astype(np.float32)  # (K, n, 3) part rays
    w = np.where(norm > 1e-9, np.stack([weights[:, g].sum(1) for g in groups]), 0.0)
    w = w.astype(np.float32)
    m = np.cross(u, o)  # line moments
    cos, um = _outer_dot(u, u), _outer_dot(u, m)  # (K, n, n)
    with np.errstate(invalid="ignore", divide="ignore"):
        d = np.abs(um + np.swapaxes(um, 1, 2)) / np.sqrt(np.maximum(1.0 - cos * cos, 0.0))
    pw = w[:, :, None] * w[:, None, :]
    num = (pw * np.fmin(d, clip)).sum(0)  # fmin: a NaN (parallel rays) is the clip
    with np.errstate(invalid="ignore", divide="ignore"):
        return num / pw.sum(0)


def pair_ray_distances_unchunked(
    origins: np.ndarray,
    dirs: np.ndarray,
    weights: np.ndarray,
    ia: np.ndarray,
    ib: np.ndarray,
    params: AssociationParams,
    *,
    flip: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray | None]:
    """(P,) :func:`ray_distances` of the pairs ``(ia[k], ib[k])`` only, and (P,) the same
    with ``ib``'s detection left/right mirrored (``flip``; None without it), mm: the pair
    kernel before :func:`pipeline.association.pairs.pair_ray_distances` (which gives the same
    numbers in cache-sized blocks), kept for its test and bench/bench_scale.py's ratio.

    The Plucker form of :func:`ray_distances` in float32 over (3, J, P) arrays, pairs
    last: a dot product is 3 whole-array products and the mean over joints adds J rows
    (an einsum over a length-3 axis or a sum over a length-J one is 3-5 times slower).
    Origins are centred on their mean so a moment's rounding stays ~1e-3 mm; the signs
    of the closest points' parameters decide the behind-the-camera clip, so the distance
    is the only division.
    """
    o = (origins - (origins.mean(0) if len(origins) else 0.0)).astype(np.float32)
    ok = np.isfinite(dirs).all(-1)
    D = np.where(ok[..., None], dirs, 0.0).astype(np.float32).transpose(2, 1, 0)  # (3, J, n)
    W = np.where(ok, weights, 0.0).astype(np.float32).T  # (J, n)
    oc = o.T[:, None, :]  # (3, 1, n)
    M = np.stack([D[1] * oc[2] - D[2] * oc[1], D[2] * oc[0] - D[0] * oc[2],
                  D[0] * oc[1] - D[1] * oc[0]])  # (3, J, n) moments d x o  # fmt: skip
    own = _dot(D, oc)  # (J, n) d . o
    take = lambda x, rows: np.take(x, rows, axis=-1)  # noqa: E731
    A, MA, Wa, oa, ob = take(D, ia), take(M, ia), take(W, ia), take(oc, ia), take(oc, ib)
    w0 = _dot(A, ob) - take(own, ia)  # (ob - oa) . da
    centre_id = np.unique(origins, axis=0, return_inverse=True)[1].ravel()
    one_centre = centre_id[ia] == centre_id[ib]
    clip = np.float32(params.joint_clip_mm)
    out = []
    for perm in (None,) if flip is None else (None, np.asarray(flip)):
        Dv, Mv, Wv, ov = (D, M, W, own) if perm is None else (
            D[:, perm], M[:, perm], W[perm], own[perm])  # fmt: skip
        B, MB = take(Dv, ib), take(Mv, ib)
        dd = _dot(A, B)
        num = np.abs(_dot(A, MB) + _dot(MA, B))
        w1 = take(ov, ib) - _dot(B, oa)  # (ob - oa) . db
        sin2 = 1.0 - dd * dd
        d = np.fmin(num / np.sqrt(np.maximum(sin2, PARALLEL_SIN2)), clip)
        behind = (w0 - dd * w1 <= 0) | (dd * w0 - w1 <= 0)
        behind[:, one_centre] = True
        d[behind] = clip
        w = Wa * take(Wv, ib)
        w[sin2 <= PARALLEL_SIN2] = 0.0
        with np.errstate(invalid="ignore", divide="ignore"):
            mean = (w * d).sum(0) / w.sum(0)
        mean[np.count_nonzero(w, axis=0) < params.min_shared_joints] = np.nan
        out.append(mean.astype(float))
    return out[0], (out[1] if flip is not None else None)


@numba.njit(cache=False, nogil=True, error_model="numpy")
def _pair_mean(joints, o, a, b, perm, clip, min_shared):
    """The per-joint kernel of :func:`pipeline.association.pairs._block` for one pair, with a
    branch per joint: joint j of a against joint ``perm[j]`` of b (a mirror, or the
    identity). NaN where fewer than ``min_shared`` joints both see. The pass before
    :func:`_kernel_row`, which must give its numbers to the bit."""
    one_centre = o[a, 0] == o[b, 0] and o[a, 1] == o[b, 1] and o[a, 2] == o[b, 2]
    bx = o[b, 0] - o[a, 0]
    by = o[b, 1] - o[a, 1]
    bz = o[b, 2] - o[a, 2]
    num = 0.0
    den = 0.0
    shared = 0
    for j in range(joints.shape[2]):
        jb = perm[j]
        wj = joints[a, 3, j] * joints[b, 3, jb]
        if wj <= 0.0:
            continue
        ax, ay, az = joints[a, 0, j], joints[a, 1, j], joints[a, 2, j]
        cx, cy, cz = joints[b, 0, jb], joints[b, 1, jb], joints[b, 2, jb]
        dd = ax * cx + ay * cy + az * cz
        sin2 = 1.0 - dd * dd
        if sin2 <= PARALLEL_SIN2:
            continue  # parallel rays say nothing
        # |(ob - oa) . (da x db)| / |da x db|
        tri = bx * (ay * cz - az * cy) + by * (az * cx - ax * cz) + bz * (ax * cy - ay * cx)
        dist = min(abs(tri) / math.sqrt(sin2), clip)
        w0 = bx * ax + by * ay + bz * az  # (ob - oa) . da
        w1 = bx * cx + by * cy + bz * cz  # (ob - oa) . db
        # the closest points' parameters (times sin^2 > 0) must both be > 0
        if one_centre or w0 - dd * w1 <= 0.0 or dd * w0 - w1 <= 0.0:
            dist = clip
        num += wj * dist
        den += wj
        shared += 1
    if shared < min_shared:
        return np.nan
    return num / den


@numba.njit(cache=False, nogil=True, error_model="numpy")
def _fused_pairwise(U, M, PW, joints, o, views, flip, has_flip, shared, prune, clip, min_shared):
    """:func:`_fused` one pair at a time (the pass before it, scalar code: the reference
    tests/pipeline/test_ray_fused.py holds it to, bit for bit)."""
    n = joints.shape[0]
    dist = np.full((n, n), np.nan)
    mirrored = np.full((n, n), np.nan)
    ident = np.arange(joints.shape[2])
    num = np.empty(n)
    den = np.empty(n)
    for a in range(n):
        _screen_row(U, M, PW, a, clip, num, den)
        for b in range(a + 1, n):
            if views[a] == views[b]:
                continue
            i = b - a - 1
            s = num[i] / den[i] if den[i] > 0.0 else np.nan
            if s < prune:
                v = _pair_mean(joints, o, a, b, ident, clip, min_shared)
                dist[a, b] = dist[b, a] = v
                if has_flip:
                    v = _pair_mean(joints, o, a, b, flip, clip, min_shared)
                    mirrored[a, b] = mirrored[b, a] = v
            elif shared[a, b]:
                dist[a, b] = dist[b, a] = s
    return dist, mirrored


def fused_pairwise_distances(
    origins: np.ndarray,
    dirs: np.ndarray,
    weights: np.ndarray,
    views: np.ndarray,
    flip: np.ndarray | None,
    groups: list[np.ndarray],
    params: AssociationParams,
) -> tuple[np.ndarray, np.ndarray]:
    """(n, n) straight and mirrored ray distances (mm) of
    :func:`pipeline.association.fused.fused_screened_distances` by the pass one pair at a
    time (:func:`_fused_pairwise`); the pairs' shared joints from
    :func:`pipeline.association.pairs.shared_joints`."""
    if dirs.shape[0] == 0:
        return np.zeros((0, 0)), np.zeros((0, 0))
    joints, o, U, M, PW, perm, views = prepare_frame(origins, dirs, weights, views, flip, groups)
    shared = shared_joints(joints[:, 3] > 0.0) >= params.min_shared_joints
    return _fused_pairwise(
        U, M, PW, joints, o, views, perm, flip is not None, shared,
        float(params.prune_mm), float(params.joint_clip_mm), int(params.min_shared_joints),
    )  # fmt: skip
