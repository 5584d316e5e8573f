"""The screen and the per-joint ray distance of one frame's pairs in one compiled pass.

:func:`fused_screened_distances` gives the numbers of
:func:`pipeline.ray_affinity.screened_distances` (the NumPy screen of
:func:`pipeline.ray_pairs.screen_distances`, then :func:`pipeline.ray_pairs.pair_ray_distances`
on the pairs it keeps) in float64, one pair at a time: the screen's four part rays, and
only when they pass, the pair's joints straight and mirrored, with no temporary array.
The NumPy kernels are ~90 whole-array operations on blocks of pairs; at 16 cameras x 10
people every one of them costs more in NumPy's per-call overhead and memory traffic than
its arithmetic (bench/bench_scale.py times both). Numba compiles it once per machine
(cached beside this module) and loads it where a frame has
``pipeline.ray_affinity.COMPILED_MIN_DETECTIONS`` detections; the NumPy path stays the
reference and tests/pipeline/test_ray_fused.py holds the two together.

Units: mm.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from pipeline.ray_pairs import PARALLEL_SIN2


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _prepare(origins, dirs, weights, part_of, K):
    """The pass's inputs in one loop (NumPy's where / einsum / cross on these small arrays
    cost ~0.7 ms a frame at 16 x 10 in call overhead): (n, J, 3) rays and (n, J) weights,
    0 where a ray is missing; (n, 3) origins centred on their mean; and each detection's
    body-part mean rays as the screen sees them, (K, 3, n) unit rays and their moments
    ``u x o``, (K, n) weights (the part's summed joint weights, 0 where its rays cancel)."""
    n, J = weights.shape
    centre = np.zeros(3)
    for i in range(n):
        for c in range(3):
            centre[c] += origins[i, c] / n
    o = np.empty((n, 3))
    d = np.zeros((n, J, 3))
    w = np.zeros((n, J))
    U = np.zeros((K, 3, n))
    M = np.zeros((K, 3, n))
    W = np.zeros((K, n))
    for i in range(n):
        for c in range(3):
            o[i, c] = origins[i, c] - centre[c]
        for j in range(J):
            k = part_of[j]
            W[k, i] += weights[i, j]
            x, y, z = dirs[i, j, 0], dirs[i, j, 1], dirs[i, j, 2]
            if math.isfinite(x) and math.isfinite(y) and math.isfinite(z):
                d[i, j, 0], d[i, j, 1], d[i, j, 2] = x, y, z
                w[i, j] = weights[i, j]
                U[k, 0, i] += x * weights[i, j]
                U[k, 1, i] += y * weights[i, j]
                U[k, 2, i] += z * weights[i, j]
        for k in range(K):
            norm = math.sqrt(U[k, 0, i] ** 2 + U[k, 1, i] ** 2 + U[k, 2, i] ** 2)
            if norm <= 1e-9:
                W[k, i] = 0.0
            scale = 1.0 / max(norm, 1e-12)
            ux, uy, uz = U[k, 0, i] * scale, U[k, 1, i] * scale, U[k, 2, i] * scale
            U[k, 0, i], U[k, 1, i], U[k, 2, i] = ux, uy, uz
            M[k, 0, i] = uy * o[i, 2] - uz * o[i, 1]
            M[k, 1, i] = uz * o[i, 0] - ux * o[i, 2]
            M[k, 2, i] = ux * o[i, 1] - uy * o[i, 0]
    return d, w, o, U, M, W


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _screen_row(U, M, W, a, clip, num, den):
    """The screen of detection a against every b > a: the clipped, weighted mean distance
    of their part rays in ``num / den`` (den 0: no part shared; parallel part rays count
    the clip). U, M (K, 3, n) part rays and moments, W (K, n): a loop over b, contiguous
    in b (scalar code: the compiler does not vectorise it, checked in its assembly)."""
    n = U.shape[2]
    num[a + 1 :] = 0.0
    den[a + 1 :] = 0.0
    for k in range(U.shape[0]):
        ux, uy, uz = U[k, 0, a], U[k, 1, a], U[k, 2, a]
        mx, my, mz = M[k, 0, a], M[k, 1, a], M[k, 2, a]
        wa = W[k, a]
        for b in range(a + 1, n):
            cos = ux * U[k, 0, b] + uy * U[k, 1, b] + uz * U[k, 2, b]
            mom = (ux * M[k, 0, b] + uy * M[k, 1, b] + uz * M[k, 2, b]
                   + U[k, 0, b] * mx + U[k, 1, b] * my + U[k, 2, b] * mz)  # fmt: skip
            d = abs(mom) / math.sqrt(max(1.0 - cos * cos, 0.0))
            d = d if d < clip else clip  # NaN or inf (parallel): the clip
            pw = wa * W[k, b]
            num[b] += pw * d
            den[b] += pw


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _pair_mean(d, o, w, a, b, perm, clip, min_shared):
    """The per-joint kernel of :func:`pipeline.ray_pairs._block` for one pair: joint j of
    a against joint ``perm[j]`` of b (a mirror, or the identity). NaN where fewer than
    ``min_shared`` joints both see."""
    one_centre = o[a, 0] == o[b, 0] and o[a, 1] == o[b, 1] and o[a, 2] == o[b, 2]
    bx = o[b, 0] - o[a, 0]
    by = o[b, 1] - o[a, 1]
    bz = o[b, 2] - o[a, 2]
    num = 0.0
    den = 0.0
    shared = 0
    for j in range(d.shape[1]):
        jb = perm[j]
        wj = w[a, j] * w[b, jb]
        if wj <= 0.0:
            continue
        ax, ay, az = d[a, j, 0], d[a, j, 1], d[a, j, 2]
        cx, cy, cz = d[b, jb, 0], d[b, jb, 1], d[b, jb, 2]
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


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _fused(U, M, PW, d, o, w, views, flip, has_flip, shared, prune, clip, min_shared):
    """Every pair a < b of different views: the screen, then, where it is below
    ``prune``, the straight (and with ``has_flip`` the mirrored) per-joint mean; else the
    screen's own distance where the pair shares enough joints. Both (n, n), symmetric."""
    n = d.shape[0]
    dist = np.full((n, n), np.nan)
    mirrored = np.full((n, n), np.nan)
    ident = np.arange(d.shape[1])
    num = np.empty(n)
    den = np.empty(n)
    for a in range(n):
        _screen_row(U, M, PW, a, clip, num, den)
        for b in range(a + 1, n):
            if views[a] == views[b]:
                continue
            s = num[b] / den[b] if den[b] > 0.0 else np.nan
            if s < prune:
                v = _pair_mean(d, o, w, a, b, ident, clip, min_shared)
                dist[a, b] = dist[b, a] = v
                if has_flip:
                    v = _pair_mean(d, o, w, a, b, flip, clip, min_shared)
                    mirrored[a, b] = mirrored[b, a] = v
            elif shared[a, b]:
                dist[a, b] = dist[b, a] = s
    return dist, mirrored


def fused_screened_distances(
    origins: np.ndarray,
    dirs: np.ndarray,
    weights: np.ndarray,
    views: np.ndarray,
    flip: np.ndarray | None,
    groups: list[np.ndarray],
    shared: np.ndarray,
    params,
) -> tuple[np.ndarray, np.ndarray]:
    """(n, n) straight and mirrored ray distances (mm) of
    :func:`pipeline.ray_affinity.screened_distances`, given its part ``groups`` and the
    (n, n) bool ``shared`` (the pair sees ``min_shared_joints`` joints)."""
    n, J = dirs.shape[:2]
    if n == 0:
        return np.zeros((0, 0)), np.zeros((0, 0))
    part_of = np.zeros(J, np.int64)  # the part of each joint (the groups cover them all)
    for k, g in enumerate(groups):
        part_of[g] = k
    d, w, o, U, M, PW = _prepare(
        np.ascontiguousarray(origins, dtype=np.float64),
        np.ascontiguousarray(dirs, dtype=np.float64),
        np.ascontiguousarray(weights, dtype=np.float64), part_of, len(groups),
    )  # fmt: skip
    perm = np.arange(J) if flip is None else np.asarray(flip, dtype=np.int64)
    return _fused(
        U, M, PW, d, o, w, np.ascontiguousarray(views, dtype=np.int64), perm,
        flip is not None, np.ascontiguousarray(shared), float(params.prune_mm),
        float(params.joint_clip_mm), int(params.min_shared_joints),
    )  # fmt: skip
