"""The per-joint ray distance of a list of detection pairs, in blocks that stay in cache.

:func:`pair_ray_distances` computes what ``pair_ray_distances_unchunked``
(bench/reference_association.py) does (the float32 Plucker form of
:func:`pipeline.association.affinity.ray_distances` on the pairs a screen kept), laid out
for the memory hierarchy rather than for the fewest NumPy calls: the per-detection
arrays are (coordinates, detections, joints), so gathering a block of pairs takes whole
rows of J values (a gather across the last axis, as before, costs 5-8 times as much),
and the pairs go through in blocks of :data:`BLOCK_PAIRS` whose ~30 float32 temporaries
fit in a core's L2 cache (a dome's 26,000 pairs x 17 joints made every temporary 1.7 MB,
and each of the ~90 whole-array operations ran at memory speed). Units: mm.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from pipeline.association.params import AssociationParams

BLOCK_PAIRS = 2048
"""At most this many pairs per block (2048 x 17 joints x 4 bytes = 140 KB a temporary;
the pairs are split into equal blocks)."""

PARALLEL_SIN2 = 1e-6
"""Rays closer to parallel than this (sin^2 of their angle; 0.06 degrees) say nothing: in
float32 a cosine near 1 is known to about 1e-7."""


def _detection_arrays(origins: np.ndarray, dirs: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """(8, n, J) float32 per detection and joint: the unit ray (3), its moment d x o (3),
    d . o and the weight (0 where the ray is missing). Origins are centred on their mean
    (a moment's rounding stays ~1e-3 mm)."""
    o = (origins - (origins.mean(0) if len(origins) else 0.0)).astype(np.float32)
    o = o.T[:, :, None]  # (3, n, 1)
    ok = np.isfinite(dirs).all(-1)
    out = np.empty((8,) + ok.shape, np.float32)
    out[0:3] = np.where(ok[..., None], dirs, 0.0).transpose(2, 0, 1)
    d = out[0:3]
    for k, (i, j) in enumerate(((1, 2), (2, 0), (0, 1))):
        out[3 + k] = d[i] * o[j] - d[j] * o[i]
    out[6] = d[0] * o[0] + d[1] * o[1] + d[2] * o[2]
    out[7] = np.where(ok, weights, 0.0)
    return out


def pair_ray_distances(
    origins: np.ndarray,
    dirs: np.ndarray,
    weights: np.ndarray,
    ia: np.ndarray,
    ib: np.ndarray,
    params: AssociationParams,
    *,
    flip: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray | None]:
    """(P,) ray distances of the pairs ``(ia[k], ib[k])``, mm, and (P,) the same with
    ``ib``'s detection left/right mirrored (``flip``; None without it): the numbers of
    ``pair_ray_distances_unchunked``, bench/reference_association.py (float32, NaN where a
    pair shares fewer than ``min_shared_joints`` joints)."""
    straight = _detection_arrays(origins, dirs, weights)
    mirror = None if flip is None else straight[:, :, np.asarray(flip)]
    o = (origins - (origins.mean(0) if len(origins) else 0.0)).astype(np.float32)
    out = [np.empty(len(ia))] + ([] if flip is None else [np.empty(len(ia))])
    size = -(-len(ia) // max(-(-len(ia) // BLOCK_PAIRS), 1))  # equal blocks
    for lo in range(0, len(ia), size):
        a, b = ia[lo : lo + size], ib[lo : lo + size]
        A = np.take(straight, a, axis=1)  # (8, p, J)
        oa, ob = o[a].T[:, :, None], o[b].T[:, :, None]  # (3, p, 1)
        w0 = A[0] * ob[0]
        w0 += A[1] * ob[1]
        w0 += A[2] * ob[2]
        w0 -= A[6]  # (ob - oa) . da
        one_centre = (origins[a] == origins[b]).all(1)[:, None]
        for k, arrays in enumerate((straight,) if mirror is None else (straight, mirror)):
            out[k][lo : lo + len(a)] = _block(A, np.take(arrays, b, axis=1), oa, w0,
                                              one_centre, params)  # fmt: skip
    return out[0], (out[1] if flip is not None else None)


def _block(
    A: np.ndarray, B: np.ndarray, oa: np.ndarray, w0: np.ndarray, one_centre: np.ndarray,
    params: AssociationParams,
) -> np.ndarray:  # fmt: skip
    """(p,) mean clipped ray distance of a block of pairs: A, B (8, p, J) from
    :func:`_detection_arrays`; oa (3, p, 1) the first detection's centred origin; w0
    (p, J) ``(ob - oa) . da``; one_centre (p, 1) both seen from one camera centre."""
    dd = A[0] * B[0]
    dd += A[1] * B[1]
    dd += A[2] * B[2]
    num = A[0] * B[3]  # |da . m_b + db . m_a| = |(b - a) . (da x db)|
    for c in (1, 2):
        num += A[c] * B[3 + c]
    for c in range(3):
        num += A[3 + c] * B[c]
    np.abs(num, out=num)
    w1 = B[6] - B[0] * oa[0]  # (ob - oa) . db
    w1 -= B[1] * oa[1]
    w1 -= B[2] * oa[2]
    sin2 = 1.0 - dd * dd
    parallel = sin2 <= PARALLEL_SIN2
    np.maximum(sin2, PARALLEL_SIN2, out=sin2)
    np.sqrt(sin2, out=sin2)
    clip = np.float32(params.joint_clip_mm)
    d = np.fmin(np.divide(num, sin2, out=num), clip)
    # the closest points' parameters s, t (times sin^2 > 0) must both be > 0
    behind = (w0 - dd * w1 <= 0) | (dd * w0 - w1 <= 0) | one_centre
    d = np.where(behind, clip, d)
    w = np.where(parallel, np.float32(0.0), A[7] * B[7])
    # sums over the joints as einsums: a sum or count over a short last axis is 2-4x slower
    total = np.einsum("pj->p", w)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.einsum("pj,pj->p", w, d) / total
    if w.shape[1] < 256:  # a uint8 count
        shared = np.einsum("pj->p", (w > 0).view(np.uint8))
    else:
        shared = np.count_nonzero(w, axis=1)
    mean[shared < params.min_shared_joints] = np.nan
    return mean


SCREEN_BLOCK = 16384
"""Pairs per row block of :func:`screen_distances` (x 4 parts x 4 bytes = 260 KB a
temporary: 35 rows on a 31-camera dome with 20 people)."""


def screen_distances(
    origins: np.ndarray, dirs: np.ndarray, weights: np.ndarray, groups: list[np.ndarray],
    clip: float,
) -> np.ndarray:  # fmt: skip
    """(n, n) ``screen_distances_unblocked`` of bench/reference_association.py (the clipped,
    weighted mean ray distance over each body part's mean ray, float32, NaN where two
    detections share no part) by blocks of rows (:data:`SCREEN_BLOCK`) against the columns
    from the block on (the upper triangle; the lower is its mirror), each term
    ``da . m_b + db . m_a`` computed as such rather than as an (n, n) array plus its
    transpose (a transposed read of a 3 MB array runs at memory speed)."""
    n = len(origins)
    o = (origins - origins.mean(0)).astype(np.float32)  # centred: float32 keeps 0.01 mm
    part = np.zeros((len(groups), dirs.shape[1]))  # (K, J) which joints make each part
    for k, g in enumerate(groups):
        part[k, g] = 1.0
    wd = np.where(np.isfinite(dirs), dirs, 0.0) * weights[..., None]
    ray = np.einsum("kj,njc->knc", part, wd)
    norm = np.linalg.norm(ray, axis=-1)  # (K, n)
    u = (ray / np.maximum(norm, 1e-12)[..., None]).astype(np.float32)  # (K, n, 3) part rays
    w = np.where(norm > 1e-9, np.einsum("kj,nj->kn", part, weights), 0.0)
    w = w.astype(np.float32)
    U = np.ascontiguousarray(u.transpose(2, 0, 1))  # (3, K, n)
    M = np.ascontiguousarray(np.cross(u, o).transpose(2, 0, 1))  # line moments
    out = np.empty((n, n), np.float32)
    rows = max(16, SCREEN_BLOCK // max(n, 1))
    for lo in range(0, n, rows):
        hi = min(lo + rows, n)
        ua, ma = U[:, :, lo:hi, None], M[:, :, lo:hi, None]  # (3, K, r, 1)
        ub, mb = U[:, :, None, lo:], M[:, :, None, lo:]  # (3, K, 1, c)
        cos = ua[0] * ub[0]
        num = ua[0] * mb[0]
        num += ub[0] * ma[0]
        for c in (1, 2):
            cos += ua[c] * ub[c]
            num += ua[c] * mb[c]
            num += ub[c] * ma[c]
        np.abs(num, out=num)
        sin = np.maximum(1.0 - cos * cos, 0.0, out=cos)
        np.sqrt(sin, out=sin)
        with np.errstate(invalid="ignore", divide="ignore"):
            d = np.fmin(np.divide(num, sin, out=num), clip)  # NaN (parallel): the clip
        pw = w[:, lo:hi, None] * w[:, None, lo:]
        d *= pw
        with np.errstate(invalid="ignore", divide="ignore"):
            block = d.sum(0) / pw.sum(0)
        out[lo:hi, hi:] = block[:, hi - lo :]
        out[hi:, lo:hi] = block[:, hi - lo :].T
        square = np.triu(block[:, : hi - lo])  # symmetric to the bit, as the one before
        out[lo:hi, lo:hi] = square + np.triu(square, 1).T
    return out


def shared_joints(seen: np.ndarray) -> np.ndarray:
    """(n, J) bool -> (n, n) how many joints each pair of detections both see: popcounts
    of the AND of bit masks (one machine word per detection up to 64 joints)."""
    n, J = seen.shape
    if J > 64:
        s = seen.astype(np.float32)
        return np.rint(s @ s.T).astype(np.int64)
    bits = np.left_shift(np.uint64(1), np.arange(J, dtype=np.uint64))
    mask = np.bitwise_or.reduce(np.where(seen, bits, np.uint64(0)), axis=1)
    return np.bitwise_count(mask[:, None] & mask[None, :]).astype(np.int64)
