"""The screen and the per-joint ray distance of one frame's pairs in one compiled pass.

:func:`fused_screened_distances` gives the numbers of
:func:`pipeline.association.affinity.screened_distances` (the NumPy screen of
:func:`pipeline.association.pairs.screen_distances`, then
:func:`pipeline.association.pairs.pair_ray_distances` on the pairs it keeps) in float64, one row of
pairs (a, b > a) at a time: the screen's four part rays against every b at once, then the pair's
joints straight and mirrored for the b's
it keeps, with no temporary array larger than a row.
The NumPy kernels are ~90 whole-array operations on blocks of pairs; at 16 cameras x 10
people every one of them costs more in NumPy's per-call overhead and memory traffic than
its arithmetic (bench/bench_scale.py times both). Each row's loops run over b with no
branch and contiguous reads, so the compiler vectorises them (AVX-512: 8 pairs a square
root); one pair at a time with a branch per joint (the pass before, kept in
bench/reference_association.py)
was scalar and ~2.5x slower at 31 cameras x 20 people, and gives the same numbers to the
bit (each lane sums its joints in the same order). Numba compiles it once per machine
(cached beside this module) and loads it where a frame has
``pipeline.association.affinity.COMPILED_MIN_DETECTIONS`` detections; the NumPy path stays the
reference and tests/pipeline/test_ray_fused.py holds the two together.

Units: mm.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from pipeline.association.pairs import PARALLEL_SIN2


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _prepare(origins, dirs, weights, part_of, K):
    """The pass's inputs in one loop (NumPy's where / einsum / cross on these small arrays
    cost ~0.7 ms a frame at 16 x 10 in call overhead): (n, 4, J) each detection's rays'
    x, y, z and weights, 0 where a ray is missing (one contiguous row per detection: the
    kernel gathers the rows of the pairs it keeps); (n, 3) origins centred on their mean;
    and each detection's body-part mean rays as the screen sees them, (K, 3, n) unit rays
    and their moments ``u x o``, (K, n) weights (the part's summed joint weights, 0 where
    its rays cancel)."""
    n, J = weights.shape
    centre = np.zeros(3)
    for i in range(n):
        for c in range(3):
            centre[c] += origins[i, c] / n
    o = np.empty((n, 3))
    joints = np.zeros((n, 4, J))
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
                joints[i, 0, j], joints[i, 1, j], joints[i, 2, j] = x, y, z
                joints[i, 3, j] = weights[i, j]
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
    return joints, o, U, M, W


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _screen_row(U, M, W, a, clip, num, den):
    """The screen of detection a against every b > a: the clipped, weighted mean distance
    of their part rays in ``num[b - a - 1] / den[b - a - 1]`` (den 0: no part shared;
    parallel part rays count the clip). U, M (K, 3, n) part rays and moments, W (K, n).
    The loop over b runs on slices from a + 1 and selects instead of branching: indices
    that start at 0 are known not to wrap around, so the compiler vectorises it (indexed
    from ``a + 1`` it stayed scalar)."""
    lo = a + 1
    num[: U.shape[2] - lo] = 0.0
    den[: U.shape[2] - lo] = 0.0
    for k in range(U.shape[0]):
        ux, uy, uz = U[k, 0, a], U[k, 1, a], U[k, 2, a]
        mx, my, mz = M[k, 0, a], M[k, 1, a], M[k, 2, a]
        wa = W[k, a]
        Ux, Uy, Uz, Wb = U[k, 0, lo:], U[k, 1, lo:], U[k, 2, lo:], W[k, lo:]
        Mx, My, Mz = M[k, 0, lo:], M[k, 1, lo:], M[k, 2, lo:]
        for i in range(len(Wb)):
            cos = ux * Ux[i] + uy * Uy[i] + uz * Uz[i]
            mom = (ux * Mx[i] + uy * My[i] + uz * Mz[i]
                   + Ux[i] * mx + Uy[i] * my + Uz[i] * mz)  # fmt: skip
            sin2 = 1.0 - cos * cos
            d = abs(mom) / math.sqrt(sin2 if sin2 > 0.0 else 0.0)
            d = d if d < clip else clip  # NaN or inf (parallel): the clip
            pw = wa * Wb[i]
            num[i] += pw * d
            den[i] += pw


@numba.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _add_joint(ax, ay, az, wa, C, jb, base, one_centre, clip, m, num, den, count):
    """Add to pair k < m's ``num``, ``den``, ``count`` the term of a's joint ray (ax, ay,
    az), weight wa, with b's joint ``jb`` (C (4 J, >= m): the pairs' columns of rays'
    x, y, z and weights, unit or zero); base (3, >= m) ``o_b - o_a``, one_centre (>= m,)
    both seen from one centre. Selects where :func:`_pair_mean` branches (no weight,
    parallel rays), so the loop over pairs vectorises; adding 0.0 leaves a sum's bits as
    skipping the term does. Inlined (Numba's IR): as a call, passing its six arrays cost
    ~0.5 ms a frame at 31 x 20 (~16,000 calls)."""
    J = C.shape[0] // 4
    Cx, Cy, Cz, Cw = C[jb], C[J + jb], C[2 * J + jb], C[3 * J + jb]
    Bx, By, Bz = base[0], base[1], base[2]
    for k in range(m):
        bx, by, bz = Bx[k], By[k], Bz[k]
        cx, cy, cz = Cx[k], Cy[k], Cz[k]
        wj = wa * Cw[k]
        dd = ax * cx + ay * cy + az * cz
        sin2 = 1.0 - dd * dd
        # |(ob - oa) . (da x db)| / |da x db|
        tri = bx * (ay * cz - az * cy) + by * (az * cx - ax * cz) + bz * (ax * cy - ay * cx)
        dist = abs(tri) / math.sqrt(sin2)
        dist = dist if dist < clip else clip
        w0 = bx * ax + by * ay + bz * az  # (ob - oa) . da
        w1 = bx * cx + by * cy + bz * cz  # (ob - oa) . db
        # the closest points' parameters (times sin^2 > 0) must both be > 0
        behind = one_centre[k] | (w0 - dd * w1 <= 0.0) | (dd * w0 - w1 <= 0.0)
        dist = clip if behind else dist
        counts = (not wj <= 0.0) & (not sin2 <= PARALLEL_SIN2)
        num[k] += wj * dist if counts else 0.0
        den[k] += wj if counts else 0.0
        count[k] += 1.0 if counts else 0.0


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _kernel_row(joints, o, a, keep, m, flip, has_flip, clip, cols, base, one_centre, sums):
    """The per-joint means of detection a against the m detections ``keep[:m]``, straight
    and (``has_flip``) with b mirrored: a's joint j against b's joint j, then ``flip[j]``.
    Into ``sums`` (6, >= m): numerator, weight and count of the straight means, then of
    the mirrored. The kept rows of ``joints`` (n, 4, J) are first copied into ``cols``
    (4 J, >= m), one column per pair, so the joint loop reads each pair's values
    contiguously across pairs: the compiler vectorises it over pairs, and each pair's
    terms add up in joint order, as one pair at a time (:func:`_pair_mean`) does.
    base (3, >= m) and one_centre (>= m,) are scratch."""
    J = joints.shape[2]
    rows = joints.reshape(joints.shape[0], 4 * J)
    for k in range(m):  # one contiguous row per pair (from joint-major arrays, ~20 % slower)
        row, col = rows[keep[k]], cols[:, k]
        for cj in range(4 * J):
            col[cj] = row[cj]
    ox, oy, oz = o[a, 0], o[a, 1], o[a, 2]
    for k in range(m):
        b = keep[k]
        base[0, k] = o[b, 0] - ox
        base[1, k] = o[b, 1] - oy
        base[2, k] = o[b, 2] - oz
        one_centre[k] = o[b, 0] == ox and o[b, 1] == oy and o[b, 2] == oz
    sums[:, :m] = 0.0
    for j in range(J):
        ax, ay, az, wa = joints[a, 0, j], joints[a, 1, j], joints[a, 2, j], joints[a, 3, j]
        if wa <= 0.0:
            continue  # a does not see joint j: no term with any b (weights are finite)
        _add_joint(ax, ay, az, wa, cols, j, base, one_centre, clip, m, sums[0], sums[1], sums[2])
        if has_flip:
            jb = flip[j]
            _add_joint(
                ax, ay, az, wa, cols, jb, base, one_centre, clip, m, sums[3], sums[4], sums[5]
            )


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _fused(U, M, PW, joints, o, views, flip, has_flip, prune, clip, min_shared):
    """Every pair a < b of different views: the screen, then, where it is below
    ``prune``, the straight (and with ``has_flip`` the mirrored) per-joint mean; else the
    screen's own distance where the pair shares ``min_shared`` joints (counted here, a
    row at a time over a's joints: the (n, n) popcount table of
    :func:`pipeline.association.pairs.shared_joints` cost ~1 ms a frame at 31 x 20, its
    temporaries as much as its arithmetic). Both (n, n), symmetric:
    the rows fill the upper triangle, copied to the lower by blocks at the end (writing
    both in the loop wrote a column per row, a cache line per element)."""
    n, J = joints.shape[0], joints.shape[2]
    dist = np.empty((n, n))
    mirrored = np.empty((n, n))
    num, den = np.empty(n), np.empty(n)
    keep = np.empty(n, np.int64)
    cols, base = np.empty((4 * J, n)), np.empty((3, n))
    one_centre = np.empty(n, np.bool_)
    sums = np.empty((6, n))
    seen = np.zeros((J, n), np.int32)  # joint-major: a row of b's for each of a's joints
    for i in range(n):
        for j in range(J):
            seen[j, i] = joints[i, 3, j] > 0.0  # a ray with a weight
    shared = np.empty(n, np.int32)
    for a in range(n):
        lo = a + 1
        _screen_row(U, M, PW, a, clip, num, den)
        shared[: n - lo] = 0
        for j in range(J):
            if joints[a, 3, j] > 0.0:
                seen_b = seen[j, lo:]
                for i in range(n - lo):  # (an array expression here allocates, 4x slower)
                    shared[i] += seen_b[i]
        va, vb = views[a], views[lo:]
        drow, mrow = dist[a, lo:], mirrored[a, lo:]
        for i in range(n - lo):  # the screen's distance where it prunes; selects: vectorised
            s = num[i] / den[i] if den[i] > 0.0 else np.nan
            pruned = vb[i] != va and shared[i] >= min_shared and not s < prune
            drow[i] = s if pruned else np.nan
            mrow[i] = np.nan
            num[i] = s
        m = 0
        for i in range(n - lo):  # the pairs the screen keeps, without a branch
            keep[m] = lo + i
            m += (vb[i] != va) & (num[i] < prune)
        _kernel_row(joints, o, a, keep, m, flip, has_flip, clip, cols, base, one_centre, sums)
        for k in range(m):
            i = keep[k] - lo
            drow[i] = sums[0, k] / sums[1, k] if sums[2, k] >= min_shared else np.nan
            if has_flip:
                mrow[i] = sums[3, k] / sums[4, k] if sums[5, k] >= min_shared else np.nan
    step = 32
    for r0 in range(0, n, step):
        for c0 in range(r0, n, step):
            for r in range(r0, min(r0 + step, n)):
                dist[r, r] = mirrored[r, r] = np.nan
                for c in range(max(c0, r + 1), min(c0 + step, n)):
                    dist[c, r] = dist[r, c]
                    mirrored[c, r] = mirrored[r, c]
    return dist, mirrored


def prepare_frame(
    origins: np.ndarray,
    dirs: np.ndarray,
    weights: np.ndarray,
    views: np.ndarray,
    flip: np.ndarray | None,
    groups: list[np.ndarray],
) -> tuple[np.ndarray, ...]:
    """One frame's arrays as the compiled passes read them: (joints, o, U, M, PW) of
    :func:`_prepare`, the (J,) joint permutation of a mirror (identity without ``flip``)
    and the (n,) int64 views. ``dirs`` must hold at least one detection."""
    J = dirs.shape[1]
    part_of = np.zeros(J, np.int64)  # the part of each joint (the groups cover them all)
    for k, g in enumerate(groups):
        part_of[g] = k
    joints, o, U, M, PW = _prepare(
        np.ascontiguousarray(origins, dtype=np.float64),
        np.ascontiguousarray(dirs, dtype=np.float64),
        np.ascontiguousarray(weights, dtype=np.float64), part_of, len(groups),
    )  # fmt: skip
    perm = np.arange(J) if flip is None else np.asarray(flip, dtype=np.int64)
    return joints, o, U, M, PW, perm, np.ascontiguousarray(views, dtype=np.int64)


def fused_screened_distances(
    origins: np.ndarray,
    dirs: np.ndarray,
    weights: np.ndarray,
    views: np.ndarray,
    flip: np.ndarray | None,
    groups: list[np.ndarray],
    params,
) -> tuple[np.ndarray, np.ndarray]:
    """(n, n) straight and mirrored ray distances (mm) of
    :func:`pipeline.association.affinity.screened_distances`, given its part ``groups``."""
    if dirs.shape[0] == 0:
        return np.zeros((0, 0)), np.zeros((0, 0))
    joints, o, U, M, PW, perm, views = prepare_frame(origins, dirs, weights, views, flip, groups)
    scalars = float(params.prune_mm), float(params.joint_clip_mm), int(params.min_shared_joints)
    return _fused(U, M, PW, joints, o, views, perm, flip is not None, *scalars)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def frame_affinity(dist, mirrored, views, max_distance_mm):
    """One frame's pair scores from its (n, n) symmetric straight and mirrored ray
    distances (mm) and (n,) views, in one pass over the upper triangle: the better of the
    two (``np.fmin``: a NaN loses), the affinity ``1 - best / max_distance_mm``, and the
    condensed distances :func:`linkage_distances` makes of that affinity. Returns (best,
    affinity, condensed). The same numbers to the bit as ``np.fmin``, ``np.divide(best,
    -m) + 1`` and :func:`linkage_distances`, whose four whole-array passes (and the
    linkage's read of the affinity) cost ~0.6 ms a frame at 31 x 20."""
    n = dist.shape[0]
    best = np.empty((n, n))
    affinity = np.empty((n, n))
    out = np.empty(n * (n - 1) // 2)
    apart = 4.0 * n * n + 10.0
    negm = -max_distance_mm
    k = 0
    for a in range(n):  # the diagonal and the upper triangle, row by row
        for b in range(a, n):
            d, m = dist[a, b], mirrored[a, b]
            x = m if d != d else (d if m != m or d <= m else m)  # np.fmin
            best[a, b] = x
            affinity[a, b] = x / negm + 1.0
        arow, vb = affinity[a, a + 1 :], views[a + 1 :]
        for i in range(n - a - 1):
            y = arow[i]
            one = 1.0 if y != y else 1.0 - y
            out[k + i] = 0.5 * (apart + apart) if vb[i] == views[a] else 0.5 * (one + one)
        k += n - a - 1
    step = 32  # the lower triangle by blocks (a column per row costs a cache line a value)
    for r0 in range(0, n, step):
        for c0 in range(r0, n, step):
            for r in range(r0, min(r0 + step, n)):
                for c in range(max(c0, r + 1), min(c0 + step, n)):
                    best[c, r] = best[r, c]
                    affinity[c, r] = affinity[r, c]
    return best, affinity, out


@numba.njit(cache=True, nogil=True, error_model="numpy")
def linkage_distances(affinity, views):
    """(n (n - 1) / 2,) the condensed distances
    :func:`pipeline.association.affinity.average_linkage` clusters, from (n, n) affinities and (n,)
    views, in one pass over the upper triangle: ``1 - affinity`` (1 where unknown), a same-view pair
    at ``4 n^2 + 10``, symmetrised as
    ``0.5 * (d + d.T)``. NumPy's where, mask, transpose and squareform made five (n, n)
    passes (0.6 ms a frame at 31 x 20, this 0.4); this gives their numbers to the bit."""
    n = affinity.shape[0]
    out = np.empty(n * (n - 1) // 2)
    apart = 4.0 * n * n + 10.0
    k = 0
    for a in range(n):
        for b in range(a + 1, n):
            ab, ba = affinity[a, b], affinity[b, a]
            d = 0.5 * ((1.0 if ab != ab else 1.0 - ab) + (1.0 if ba != ba else 1.0 - ba))
            out[k] = 0.5 * (apart + apart) if views[a] == views[b] else d
            k += 1
    return out


@numba.njit(cache=True, nogil=True, error_model="numpy")
def best_move(gain, col, seen, views, size, dist, has_ray, max_mm, min_views):
    """:func:`pipeline.association.refine._best_move` in two passes over (n, C), no
    temporaries: the refinement's ~15 NumPy calls a move cost ~0.15 ms each at 31 x 20.
    The same move: NumPy's argmax takes the first maximum in row-major order, and so does
    this (a strict ``>`` row after row, column after column)."""
    n, C = gain.shape
    geometric = dist.shape[0] > 0
    solid = np.zeros(C, np.int64)
    if geometric:
        for i in range(n):
            solid[col[i]] += has_ray[i]
    row_best = np.full(n, -np.inf)
    row_arg = np.zeros(n, np.int64)
    stranded = np.zeros(C, np.int64)
    for i in range(n):
        own, v = gain[i, col[i]], views[i]
        for c in range(C):
            ok = seen[c, v] == 0 and gain[i, c] > 0.0
            if ok and geometric:
                ok = solid[c] < 2 or dist[c, i] <= max_mm or not has_ray[i]
            if ok and gain[i, c] - own > row_best[i]:
                row_best[i], row_arg[i] = gain[i, c] - own, c
        stranded[col[i]] += not row_best[i] > 1e-9
    best, bi, bc = -np.inf, 0, 0
    for i in range(n):
        homeless = not row_best[i] > 1e-9
        left = size[col[i]] - 1
        keeps = left >= min_views or left == 0 or stranded[col[i]] - homeless == 0
        if keeps and row_best[i] > best:
            best, bi, bc = row_best[i], i, row_arg[i]
    return bi, bc, best
