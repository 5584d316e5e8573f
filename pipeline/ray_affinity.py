"""The per-frame association's heavy kernels, at the scale of a dome (16-31 views,
10-20 people: 100-600 detections a frame).

- :func:`ray_distances`: the confidence-weighted mean ray-to-ray distance of every pair
  of detections, as J matrix products of depth 3 instead of (n, n, J, 3) arrays.
- :func:`average_linkage`: agglomerative clustering with average linkage and
  same-view cannot-links, by SciPy's O(n^2) hierarchical clustering instead of a
  Python loop that rebuilds an (n, n) view-conflict matrix per merge (O(n^3 V)).

Both give what :mod:`pipeline.associate` computed before (its
``ray_distances_reference`` / ``average_linkage_reference``, kept for the tests and
``bench/bench_scale.py``). Units: mm.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from scipy.cluster.hierarchy import fcluster, linkage
from scipy.spatial.distance import squareform

if TYPE_CHECKING:
    from pipeline.associate import AssociationParams

__all__ = ["average_linkage", "ray_distances"]


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
    traffic than :func:`ray_distances_reference`, which gives the same numbers): with
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


def average_linkage(affinity: np.ndarray, views: np.ndarray, threshold: float) -> np.ndarray:
    """Agglomerative clustering with average linkage and same-view cannot-links.

    Merges the pair of clusters with the highest mean cross affinity while it is
    ``>= threshold``; an unknown affinity (NaN) counts as 0 in the mean, and two clusters
    holding detections of one view never merge.

    Done as UPGMA on the distance ``1 - affinity`` with a same-view pair at a distance
    so large that any cluster holding one sits above the cut: average linkage merges
    the closest pair of clusters first and its merge heights never decrease, so
    cutting its dendrogram at ``1 - threshold`` gives the clusters of the greedy loop.

    Args:
        affinity: (n, n) symmetric pair affinities; views: (n,) view per detection.
    Returns:
        (n,) labels: each cluster labelled by its lowest detection index.
    """
    n = len(views)
    if n < 2:
        return np.arange(n)
    dist = 1.0 - np.nan_to_num(np.asarray(affinity, float), nan=0.0)
    # a cannot-link outweighs the rest of any mean it enters: n^2 pairs of distance <= 3
    dist[np.asarray(views)[:, None] == np.asarray(views)[None, :]] = 4.0 * n * n + 10.0
    np.fill_diagonal(dist, 0.0)
    dist = 0.5 * (dist + dist.T)  # >= 0: affinities are <= 1
    Z = linkage(squareform(dist, checks=False), method="average")
    flat = fcluster(Z, t=1.0 - threshold, criterion="distance")
    first = np.full(flat.max() + 1, n)
    np.minimum.at(first, flat, np.arange(n))
    return first[flat]
