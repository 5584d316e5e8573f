"""The per-frame association's heavy kernels, at the scale of a dome (16-31 views,
10-20 people: 100-600 detections a frame).

- :func:`ray_distances`: the confidence-weighted mean ray-to-ray distance of every pair
  of detections, as J matrix products of depth 3 instead of (n, n, J, 3) arrays.
- :func:`average_linkage`: agglomerative clustering with average linkage and
  same-view cannot-links, by SciPy's O(n^2) hierarchical clustering instead of a
  Python loop that rebuilds an (n, n) view-conflict matrix per merge (O(n^3 V)).

Both give what the association computed before (``ray_distances_reference`` /
``average_linkage_reference`` of bench/reference_association.py, which the tests and
``bench/bench_scale.py`` compare with). Units: mm.
"""

from __future__ import annotations

import functools
from typing import TYPE_CHECKING

import numpy as np

from pipeline.association.pairs import (
    pair_ray_distances,
    screen_distances,
    shared_joints,
)

if TYPE_CHECKING:
    from pipeline.association.params import AssociationParams
    from pipeline.data.cameras import CameraRig

__all__ = [
    "average_linkage",
    "camera_centres",
    "frame_affinity",
    "linkage_distances_reference",
    "pair_ray_distances",
    "pinhole_rays",
    "part_groups",
    "ray_distances",
    "screen_distances",
    "screened_distances",
]


def ray_distances(
    origins: np.ndarray,
    dirs: np.ndarray,
    weights: np.ndarray,
    params: AssociationParams,
    *,
    other: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
) -> np.ndarray:
    """(n, m) confidence-weighted mean of clipped ray-to-ray distances, mm.

    Between the n detections ``(origins, dirs, weights)`` and the m of ``other`` (the
    same n when None; the diagonal is then NaN). NaN where two detections share fewer
    than ``min_shared_joints`` joints. A joint's distance is clipped at
    ``joint_clip_mm``, and is the clip where the closest points of the two rays lie
    behind a camera (the rays diverge).

    Every term is a product over the 3 coordinates, so each joint's (n, m) block is a
    3-deep matrix product instead of an (n, m, J, 3) array (10-30 times less memory
    traffic than ``ray_distances_reference``, which gives the same numbers): with
    unit directions ``da``, ``db`` through camera centres ``a``, ``b`` and the lines'
    moments ``m = d x o`` (Plucker coordinates),
    ``(b - a) . (da x db) = da . m_b + db . m_a`` and ``|da x db|^2 = 1 - (da . db)^2``.
    """
    o2, d2, w2 = (origins, dirs, weights) if other is None else other
    A = np.nan_to_num(np.swapaxes(dirs, 0, 1))  # (J, n, 3); a missing joint has weight 0
    B = np.nan_to_num(np.swapaxes(d2, 0, 1))  # (J, m, 3)
    MA, MB = np.cross(A, origins[None]), np.cross(B, o2[None])  # line moments d x o
    Bt, MBt = np.swapaxes(B, 1, 2), np.swapaxes(MB, 1, 2)
    dd = A @ Bt  # (J, n, m) cosines
    num = np.abs(A @ MBt + MA @ Bt)  # |(b - a) . (da x db)|
    # base = b - a: w0 = base . da, w1 = base . db
    w0 = A @ o2.T - np.einsum("jnc,nc->jn", A, origins)[..., None]
    w1 = np.einsum("jmc,mc->jm", B, o2)[:, None, :] - np.einsum("nc,jmc->jnm", origins, B)
    sin2 = 1.0 - dd * dd
    with np.errstate(invalid="ignore", divide="ignore"):
        d = num / np.sqrt(sin2)
        s = (w0 - dd * w1) / sin2
        t = (dd * w0 - w1) / sin2
    clip = params.joint_clip_mm
    # two rays from one camera centre meet there, behind both closest points: the clip
    one_centre = (origins[:, None] == o2[None]).all(-1)
    d = np.where((s <= 0) | (t <= 0) | ~np.isfinite(d) | one_centre, clip, np.minimum(d, clip))
    wa = np.where(np.isfinite(dirs).all(-1), weights, 0.0).T  # (J, n)
    wb = np.where(np.isfinite(d2).all(-1), w2, 0.0).T  # (J, m)
    w = wa[:, :, None] * wb[:, None, :]
    w[sin2 <= 1e-12] = 0.0  # parallel rays (|da x db| <= 1e-6) say nothing
    shared = (w > 0).sum(0)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = (w * d).sum(0) / w.sum(0)
    mean[shared < params.min_shared_joints] = np.nan
    if other is None:
        mean[np.arange(len(origins)), np.arange(len(origins))] = np.nan
    return mean


def frame_affinity(
    dist: np.ndarray, mirrored: np.ndarray, views: np.ndarray, max_distance_mm: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """One frame's (n, n) better of its straight and mirrored distances (a NaN loses),
    its affinity ``1 - best / max_distance_mm``, and :func:`average_linkage`'s condensed
    distances of it, or None where that function is to make them itself. Frames of
    ``COMPILED_MIN_DETECTIONS`` detections get all three from one compiled pass
    (:func:`pipeline.association.fused.frame_affinity`, the same numbers to the bit)."""
    if len(views) >= COMPILED_MIN_DETECTIONS:
        from pipeline.association.fused import frame_affinity as compiled  # numba

        return compiled(
            np.ascontiguousarray(dist, dtype=np.float64),
            np.ascontiguousarray(mirrored, dtype=np.float64),
            np.ascontiguousarray(views, dtype=np.int64), float(max_distance_mm),
        )  # fmt: skip
    best = np.fmin(dist, mirrored)
    affinity = np.divide(best, -max_distance_mm)  # 1 - best / max_distance_mm, to the
    affinity += 1.0  # bit, without a temporary (x / -m = -(x / m); 1 + -y = 1 - y)
    return best, affinity, None


@functools.cache
def _scipy_linkage() -> tuple:
    """(nn_chain, cluster_dist): what ``scipy.cluster.hierarchy.linkage`` / ``fcluster``
    call after validating their input, or (None, None) on a SciPy without them (the
    public functions then). Imported on the first clustering: scipy.cluster and
    scipy.spatial cost ~0.2 s of imports to every process that imports the stages (the
    batch's driver, which only plans)."""
    try:
        from scipy.cluster._hierarchy import cluster_dist, nn_chain
    except ImportError:
        return None, None
    return nn_chain, cluster_dist


def average_linkage(
    affinity: np.ndarray,
    views: np.ndarray,
    threshold: float,
    *,
    condensed: np.ndarray | None = None,
) -> np.ndarray:
    """Agglomerative clustering with average linkage and same-view cannot-links.

    Merges the pair of clusters with the highest mean cross affinity while it is
    ``>= threshold``; an unknown affinity (NaN) counts as 0 in the mean, and two clusters
    holding detections of one view never merge.

    Done as UPGMA on the distance ``1 - affinity`` with a same-view pair at a distance
    so large that any cluster holding one sits above the cut: average linkage merges
    the closest pair of clusters first and its merge heights never decrease, so
    cutting its dendrogram at ``1 - threshold`` gives the clusters of the greedy loop.

    Args:
        affinity: (n, n) symmetric pair affinities; views: (n,) view per detection;
        condensed: their condensed distances if already made (:func:`frame_affinity`).
    Returns:
        (n,) labels: each cluster labelled by its lowest detection index.
    """
    n = len(views)
    if n < 2:
        return np.arange(n)
    affinity = np.asarray(affinity, float)
    if condensed is not None:
        pass
    elif n >= COMPILED_MIN_DETECTIONS:  # the same numbers in one compiled pass
        from pipeline.association.fused import linkage_distances  # numba

        condensed = linkage_distances(affinity, np.asarray(views, np.int64))
    else:
        condensed = linkage_distances_reference(affinity, views)
    nn_chain, cluster_dist = _scipy_linkage()
    if nn_chain is not None:  # SciPy's own steps without its per-call checks (~0.5 ms)
        flat = np.zeros(n, np.intc)
        cluster_dist(nn_chain(condensed, n, 2), flat, 1.0 - threshold, n)  # 2: average
    else:
        from scipy.cluster.hierarchy import fcluster, linkage

        Z = linkage(condensed, method="average")
        flat = fcluster(Z, t=1.0 - threshold, criterion="distance")
    first = np.full(flat.max() + 1, n)
    np.minimum.at(first, flat, np.arange(n))
    return first[flat]


def linkage_distances_reference(affinity: np.ndarray, views: np.ndarray) -> np.ndarray:
    """(n (n - 1) / 2,) the condensed distances :func:`average_linkage` cuts (SciPy's
    order), from (n, n) affinities and (n,) views; frames of ``COMPILED_MIN_DETECTIONS``
    detections take them from :func:`pipeline.association.fused.linkage_distances`."""
    n = len(views)
    dist = np.where(np.isnan(affinity), 1.0, 1.0 - affinity)  # unknown counts as 0
    # a cannot-link outweighs the rest of any mean it enters: n^2 pairs of distance <= 3
    dist[np.asarray(views)[:, None] == np.asarray(views)[None, :]] = 4.0 * n * n + 10.0
    np.fill_diagonal(dist, 0.0)
    dist = 0.5 * (dist + dist.T)  # >= 0: affinities are <= 1
    from scipy.spatial.distance import squareform  # see _scipy_linkage

    return squareform(dist, checks=False)


def part_groups(flip: np.ndarray | None, num_joints: int, parts: int = 4) -> list[np.ndarray]:
    """The joints split into ``parts`` groups of consecutive left/right orbits of ``flip``
    (the joint set's flip index; None: no pairs), e.g. COCO-17's head, shoulders and
    elbows, wrists and hips, knees and ankles. A group holds both joints of each pair, so
    its mean ray does not move when a detection's labels are mirrored."""
    flip = tuple(range(num_joints)) if flip is None else tuple(int(j) for j in flip)
    return list(_part_groups(flip, num_joints, parts))


@functools.lru_cache(maxsize=16)
def _part_groups(flip: tuple[int, ...], num_joints: int, parts: int) -> tuple[np.ndarray, ...]:
    """:func:`part_groups` of one joint set, made once (it was ~40 us a frame)."""
    orbits = sorted({tuple(sorted({j, flip[j]})) for j in range(num_joints)})
    chunks = np.array_split(np.arange(len(orbits)), min(parts, len(orbits)))
    return tuple(np.array([j for k in c for j in orbits[k]], int) for c in chunks if len(c))


def _outer_dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(..., n, 3), (..., m, 3) -> (..., n, m) dot products as 3 outer products: a matrix product of
    depth 3 this size is left to OpenBLAS's threads, whose spinning costs 10-20 times
    the CPU time on a loaded machine."""
    out = a[..., :, None, 0] * b[..., None, :, 0]
    out += a[..., :, None, 1] * b[..., None, :, 1]
    out += a[..., :, None, 2] * b[..., None, :, 2]
    return out


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Dot products over the first axis (3 coordinates) of two coordinate-major arrays."""
    out = a[0] * b[0]
    out += a[1] * b[1]
    out += a[2] * b[2]
    return out


# bench/bench_scale.py swaps in the unchunked / unblocked ones
_pair_kernel, _screen = pair_ray_distances, screen_distances
COMPILED_MIN_DETECTIONS = 48
"""Frames with at least this many detections go through
:func:`pipeline.association.fused.fused_screened_distances` (one compiled pass, the same numbers in
float64); smaller ones through the NumPy screen and kernel, whose per-call cost is small
there, so a sample-sized scene never loads Numba (~0.9 s a process: its import and the
cached machine code). bench/bench_scale.py sets it out of reach for its NumPy baseline."""


def screened_distances(
    origins: np.ndarray,
    dirs: np.ndarray,
    weights: np.ndarray,
    views: np.ndarray,
    flip: np.ndarray | None,
    params: AssociationParams,
) -> tuple[np.ndarray, np.ndarray]:
    """(n, n) ray distances of one frame's detections as labelled and with one of the two
    mirrored (``flip``; NaN without it), mm, the full per-joint kernel
    (:func:`pair_ray_distances`) run only on the pairs of different views whose
    :func:`screen_distances` is below ``params.prune_mm``.

    On a dome the screen throws away 3/4 of the pairs (another person's); a pair it
    throws away keeps the screen's distance (>= prune_mm, an affinity <= 1 - prune_mm /
    max_distance_mm, negative by default) where it shares ``min_shared_joints`` joints,
    and no mirrored distance: its part rays, which mirroring does not move, already
    miss each other. NaN on the diagonal and for pairs of one view.
    """
    n, J = dirs.shape[:2]
    if n >= COMPILED_MIN_DETECTIONS:
        from pipeline.association.fused import fused_screened_distances  # numba

        return fused_screened_distances(origins, dirs, weights, views, flip, part_groups(flip, J),
                                        params)  # fmt: skip
    shared = shared_joints(np.isfinite(dirs).all(-1) & (weights > 0)) >= params.min_shared_joints
    screen = _screen(origins, dirs, weights, part_groups(flip, J), params.joint_clip_mm)
    other_view = views[:, None] != views[None, :]
    near = np.triu(other_view & (screen < params.prune_mm), 1)
    dist = np.where(shared & other_view & ~near & ~near.T, screen, np.nan).astype(float)
    mirrored = np.full((n, n), np.nan)
    ia, ib = np.nonzero(near)
    if len(ia):
        straight, mirror = _pair_kernel(origins, dirs, weights, ia, ib, params, flip=flip)
        dist[ia, ib] = dist[ib, ia] = straight
        if mirror is not None:
            mirrored[ia, ib] = mirrored[ib, ia] = mirror
    np.fill_diagonal(dist, np.nan)
    return dist, mirrored


@functools.lru_cache(maxsize=8)
def camera_centres(rig: CameraRig) -> np.ndarray:
    """(V, 3) ``rig.centers``, made once per rig (a Python loop over its cameras); read-only:
    the cache hands out this one array."""
    centres = rig.centers
    centres.flags.writeable = False
    return centres


@functools.lru_cache(maxsize=8)
def _pinhole_maps(rig: CameraRig) -> tuple[np.ndarray, np.ndarray]:
    """(V, 3, 3) per camera the map of homogeneous pixels to world rays (row vectors:
    ``[u, v, 1] @ inv(K).T @ R``) and (V,) whether it has no distortion."""
    maps = np.stack([np.linalg.inv(c.K).T @ c.R for c in rig])
    return maps, np.array([not np.any(c.dist) for c in rig])


def pinhole_rays(
    rig: CameraRig, views: np.ndarray, pixels: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(n, J, 3) unit world rays through (n, J, 2) pixels of the detections whose camera
    has no distortion, all views in one product (``Camera.pixels_to_rays`` per view costs
    ~0.1 ms a call in OpenCV's undistortion, which is the identity there), NaN for the
    others; and (n,) which detections those are."""
    maps, plain = _pinhole_maps(rig)
    plain = plain[views]
    if plain.all():  # the usual rig (and no detections): no gather, no scatter
        return _map_pixels(pixels, maps[views]), plain
    rays = np.full(pixels.shape[:-1] + (3,), np.nan)
    if plain.any():
        rays[plain] = _map_pixels(pixels[plain], maps[views[plain]])
    return rays, plain


def _map_pixels(pixels: np.ndarray, maps: np.ndarray) -> np.ndarray:
    """(m, J, 2) pixels, (m, 3, 3) maps -> (m, J, 3) unit rays ``[u, v, 1] @ map``."""
    d = pixels @ maps[:, :2] + maps[:, 2:]  # a batched (J, 2) @ (2, 3) per row
    with np.errstate(invalid="ignore"):
        d /= np.sqrt((d * d).sum(-1, keepdims=True))
    return d
