"""Stage 2, cross-view association (:mod:`pipeline.association.associate`): the geometric checks and
local moves after the greedy linkage: clusters whose centre rays meet nowhere are split
(:func:`split_inconsistent`), single detections move to the cluster they agree with most
(:func:`refine_clusters`) and two clusters that triangulate to one place merge
(:func:`merge_duplicates`).

Units: mm.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from pipeline.association import affinity as ray_affinity
from pipeline.association.affinity import average_linkage

if TYPE_CHECKING:
    from pipeline.association.params import AssociationParams


def label_counts(cluster: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``np.unique(cluster, return_inverse=True, return_counts=True)`` for (n,) labels
    that are small non-negative integers (a frame's clusters), by one bincount: the
    association asks this ~8 times a frame and np.unique's sort cost ~40 us a call."""
    if len(cluster) == 0 or cluster.min() < 0:
        return np.unique(cluster, return_inverse=True, return_counts=True)
    counts = np.bincount(cluster)
    labels = np.flatnonzero(counts)
    column = np.cumsum(counts > 0) - 1
    return labels, column[cluster], counts[labels]


def centre_rays(dirs: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """(n, 3) each detection's confidence-weighted mean ray (unit; zero if it has none):
    the direction of its body's centre, whatever its joints are labelled."""
    c = (np.where(np.isfinite(dirs), dirs, 0.0) * weights[..., None]).sum(1)
    return c / np.maximum(np.linalg.norm(c, axis=-1, keepdims=True), 1e-12)


def cluster_centers(
    origins: np.ndarray,
    dirs: np.ndarray,
    weights: np.ndarray,
    cluster: np.ndarray,
    labels,
    *,
    geometry: CentreRays | None = None,
) -> np.ndarray:
    """(len(labels), 3) each cluster's body centre, mm: the point nearest (least squares)
    the centre rays (:func:`centre_rays`) of its detections; NaN for fewer than two.

    Args:
        origins: (n, 3) camera centres; dirs: (n, J, 3) unit rays (NaN if missing);
        weights: (n, J) confidences (0 if missing); geometry: their
        :class:`CentreRays`, if already made.
    """
    geo = CentreRays.of(origins, dirs, weights) if geometry is None else geometry
    member = (cluster[:, None] == np.asarray(labels)[None, :]) & geo.has_ray[:, None]
    centres = geo.centres(member)
    centres[member.sum(0) < 2] = np.nan
    return centres


def merge_duplicates(
    origins: np.ndarray,
    dirs: np.ndarray,
    weights: np.ndarray,
    views: np.ndarray,
    cluster: np.ndarray,
    params: AssociationParams,
    *,
    geometry: CentreRays | None = None,
) -> np.ndarray:
    """Merge clusters that are one person (see ``AssociationParams.merge_distance_mm``).

    Closest pair first; a merge needs the two clusters' views to be disjoint and each
    cluster seen by ``min_views`` views (a single stray detection is not a body).
    Arguments as :func:`cluster_centers` (``geometry``: their :class:`CentreRays`, if
    already made); returns the new (n,) labels.
    """
    cluster = cluster.copy()
    geo = CentreRays.of(origins, dirs, weights) if geometry is None else geometry
    while True:
        labels, _, counts = label_counts(cluster)
        labels = labels[counts >= params.min_views]
        if len(labels) < 2:
            return cluster
        centers = cluster_centers(origins, dirs, weights, cluster, labels, geometry=geo)
        gap = np.linalg.norm(centers[:, None] - centers[None], axis=-1)
        gap[~np.isfinite(gap)] = np.inf
        np.fill_diagonal(gap, np.inf)
        pair = None
        for flat in np.argsort(gap, axis=None):
            i, j = np.unravel_index(flat, gap.shape)
            if gap[i, j] >= params.merge_distance_mm:
                break
            if not set(views[cluster == labels[i]]) & set(views[cluster == labels[j]]):
                pair = (labels[i], labels[j])
                break
        if pair is None:
            return cluster
        cluster[cluster == pair[1]] = pair[0]


@dataclass(frozen=True, eq=False)
class CentreRays:
    """Each detection's centre ray (:func:`centre_rays`) and what finding the point
    nearest a set of them needs. origins, rays: (n, 3); has_ray: (n,) bool;
    proj: (n, 9) projectors off each ray (3 x 3, flattened); proj_origin: (n, 3)
    ``proj @ origin``; origin_along: (n,) ``origin . ray``; origin_sq: (n,) ``|origin|^2``."""

    origins: np.ndarray
    rays: np.ndarray
    has_ray: np.ndarray
    proj: np.ndarray
    proj_origin: np.ndarray
    origin_along: np.ndarray
    origin_sq: np.ndarray

    @classmethod
    def of(cls, origins: np.ndarray, dirs: np.ndarray, weights: np.ndarray) -> CentreRays:
        rays = centre_rays(dirs, weights)  # zero for a detection without joints
        proj = np.eye(3) - rays[:, :, None] * rays[:, None, :]
        return cls(
            origins=origins,
            rays=rays,
            has_ray=np.linalg.norm(rays, axis=-1) > 0.5,
            proj=proj.reshape(-1, 9),
            proj_origin=np.einsum("nab,nb->na", proj, origins),
            origin_along=(origins * rays).sum(-1),
            origin_sq=(origins * origins).sum(-1),
        )

    def centres(self, member: np.ndarray) -> np.ndarray:
        """(n, C) bool membership -> (C, 3) each set's body centre, mm: the point nearest
        (least squares) its members' rays, all sets in one batched solve."""
        # As float matrix products: einsum over a bool (n, C) cost ~4x as much a frame.
        m = (member & self.has_ray[:, None]).T.astype(float)  # (C, n)
        A = (m @ self.proj).reshape(-1, 3, 3) + 1e-9 * np.eye(3)
        return np.linalg.solve(A, (m @ self.proj_origin)[..., None])[..., 0]

    def distances(self, points: np.ndarray) -> np.ndarray:
        """(C, 3) points -> (C, n) distance of each point to each detection's centre ray
        (to its origin where the point lies behind it), mm: :func:`_ray_point_distance`
        by (C, n) matrix products, no (C, n, 3) temporaries. With v = point - origin,
        |v|^2 = |p|^2 - 2 p.o + |o|^2 and t = max(v.r, 0): distance^2 = |v|^2 - t^2."""
        along = np.maximum(points @ self.rays.T - self.origin_along, 0.0)  # (C, n)
        sq = (points * points).sum(-1)[:, None] - 2.0 * (points @ self.origins.T)
        sq += self.origin_sq - along * along
        return np.sqrt(np.maximum(sq, 0.0))


def _ray_point_distance(origins: np.ndarray, rays: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(m, 3) origins and unit rays, (..., 3) points -> (..., m) distance of each point
    to each ray (to its origin where the point lies behind it), mm."""
    v = points[..., None, :] - origins  # (..., m, 3)
    t = np.maximum((v * rays).sum(-1), 0.0)
    return np.linalg.norm(v - t[..., None] * rays, axis=-1)


def _consistent_core(origins: np.ndarray, rays: np.ndarray, max_mm: float) -> np.ndarray:
    """(m,) bool, the largest set of centre rays (m, 3) passing within ``max_mm`` of one
    point: the meeting point of each pair is a candidate body, and the one most rays
    pass near wins (ties: the smallest sum of distances)."""
    ia, ib = np.triu_indices(len(origins), 1)
    # closest points of the two lines: solve for s, t in o_a + s r_a ~ o_b + t r_b
    w = origins[ia] - origins[ib]
    b = (rays[ia] * rays[ib]).sum(-1)
    d, e = (rays[ia] * w).sum(-1), (rays[ib] * w).sum(-1)
    denom = np.maximum(1.0 - b**2, 1e-9)
    s, t = (b * e - d) / denom, (e - b * d) / denom
    mid = 0.5 * (origins[ia] + s[:, None] * rays[ia] + origins[ib] + t[:, None] * rays[ib])
    dist = _ray_point_distance(origins, rays, mid)  # (pairs, m)
    near = dist <= max_mm
    score = near.sum(1) - np.where(near, dist, 0).sum(1) / (max_mm * len(origins) + 1.0)
    return near[int(np.argmax(score))]


def split_inconsistent(
    origins: np.ndarray,
    dirs: np.ndarray,
    weights: np.ndarray,
    views: np.ndarray,
    cluster: np.ndarray,
    affinity: np.ndarray,
    threshold: float,
    *,
    max_mm: float,
    geometry: CentreRays | None = None,
) -> np.ndarray:
    """Split the clusters whose members' centre rays (:func:`centre_rays`) do not all pass
    within ``max_mm`` of the cluster's body centre (the point nearest them): the largest
    subset that meets at one point keeps the label (:func:`_consistent_core`), the rest
    are clustered again among themselves (:func:`pipeline.association.affinity.average_linkage`
    on ``affinity``). Repeated until every cluster is consistent. Arguments as
    :func:`cluster_centers` (``geometry``: their :class:`CentreRays`, if already made);
    returns the new (n,) labels (new clusters take unused labels)."""
    cluster = cluster.copy()
    geo = CentreRays.of(origins, dirs, weights) if geometry is None else geometry
    rays = geo.rays
    checked: set[int] = set()  # labels found consistent (their members never change)
    for _ in range(len(views)):
        labels, col, counts = label_counts(cluster)
        fresh = np.array([int(x) not in checked for x in labels], bool)  # ~20 labels
        todo = (counts >= 3) & fresh  # 2 rays always meet
        if not todo.any():
            return cluster
        member = (col[:, None] == np.flatnonzero(todo)[None]) & geo.has_ray[:, None]  # (n, C)
        far = geo.distances(geo.centres(member)) > max_mm  # (C, n)
        far &= member.T
        checked.update(int(x) for x in labels[todo])
        for k in np.flatnonzero(far.any(1)):
            rows = np.flatnonzero(member[:, k])
            rest = rows[~_consistent_core(origins[rows], rays[rows], max_mm)]
            if len(rest):
                sub = average_linkage(affinity[np.ix_(rest, rest)], views[rest], threshold)
                cluster[rest] = cluster.max() + 1 + sub
    return cluster


def refine_clusters(
    affinity: np.ndarray,
    views: np.ndarray,
    cluster: np.ndarray,
    threshold: float,
    *,
    min_views: int = 2,
    geometry: CentreRays | None = None,
    max_mm: float = np.inf,
) -> np.ndarray:
    """Local moves on the clustering's objective, the sum over pairs in one cluster of
    ``affinity - threshold`` (unknown affinity counts as 0, as in the linkage): while some
    detection gains by it, the one that gains most moves to another cluster that has no
    detection of its view and whose members it agrees with above the threshold on
    average. So a detection goes where most views back it: one strong wrong partner
    (a single pair) loses to fourteen views that agree almost as well. A move that
    would leave its cluster with fewer than ``min_views`` detections (a person no more)
    is taken only if the others left behind have a better cluster too: on the real
    Pose2Sim demo the woman is seen in two views for a few frames, and one of them
    agrees about as well with the man's three; moving it would lose her. Given the
    ``geometry``, a detection joins no cluster of two or more whose body centre its
    centre ray misses by more than ``max_mm``: far away, pairwise affinities can be high
    for detections whose rays meet nowhere (see :func:`split_inconsistent`). Every move
    raises the objective, so it ends.

    Args:
        affinity: (n, n) pair affinities (NaN unknown); views: (n,) view per detection;
        cluster: (n,) labels from :func:`pipeline.association.affinity.average_linkage`.
    Returns:
        (n,) new labels (the same label values; a detection left alone keeps its own).
    """
    n = len(views)
    if n < 3:
        return cluster
    excess = np.where(np.isnan(affinity), -threshold, affinity - threshold)
    np.fill_diagonal(excess, 0.0)
    # Columns for the clusters at the start (a cluster a move empties keeps its column: no
    # gain > 0 there, so never a target); one move updates two columns, not all of them.
    labels, col, _ = label_counts(cluster)
    C, V = len(labels), int(views.max()) + 1
    member = np.zeros((n, C), bool)
    member[np.arange(n), col] = True
    gain = excess @ member  # (n, C): agreement above threshold with each cluster
    seen = np.zeros((C, V), int)
    np.add.at(seen, (col, views), 1)
    size = np.bincount(col, minlength=C)
    dist = None
    if geometry is not None:
        dist = np.zeros((C, n))  # each cluster's body centre to each detection's ray
        _refine_geometry(geometry, member, np.arange(C), dist)
    has_ray = geometry.has_ray if geometry is not None else np.ones(n, bool)
    choose = _best_move
    if n >= ray_affinity.COMPILED_MIN_DETECTIONS:  # the same move, one compiled pass
        from pipeline.association.fused import best_move as choose  # numba
    for _ in range(n):
        i, c, gained = choose(
            gain, col, seen, views, size, dist if dist is not None else np.zeros((0, 0)),
            has_ray, float(max_mm), int(min_views),
        )  # fmt: skip
        if gained <= 1e-9:
            break
        a = col[i]
        gain[:, a] -= excess[:, i]
        gain[:, c] += excess[:, i]
        seen[a, views[i]] -= 1
        seen[c, views[i]] += 1
        size[a] -= 1
        size[c] += 1
        member[i, a], member[i, c], col[i] = False, True, c
        if dist is not None:
            _refine_geometry(geometry, member, np.array([a, c]), dist)
    return labels[col]


def _best_move(gain, col, seen, views, size, dist, has_ray, max_mm, min_views):
    """The move :func:`refine_clusters` takes next: (detection i, cluster c, its gain;
    a gain <= 1e-9: none). gain (n, C) each detection's agreement with each cluster,
    col (n,) its cluster's column, seen (C, V) each cluster's detections per view, size
    (C,), dist (C, n) each cluster's body centre to each detection's centre ray ((0, 0):
    no geometry), has_ray (n,). Frames of ``COMPILED_MIN_DETECTIONS`` detections take
    it from :func:`pipeline.association.fused.best_move` (the same move)."""
    n = len(col)
    allowed = (seen[:, views].T == 0) & (gain > 0)  # no detection of its view; agrees
    if dist.size:
        solid = np.bincount(col[has_ray], minlength=len(size)) >= 2  # a centre needs two rays
        allowed &= ~solid[None] | (dist.T <= max_mm) | ~has_ray[:, None]
    own = gain[np.arange(n), col]
    better = np.where(allowed, gain - own[:, None], -np.inf)
    has_home = (better > 1e-9).any(1)
    # stranded[k]: detections of cluster k without a better cluster of their own
    stranded = np.bincount(col, weights=~has_home, minlength=len(size))
    left = size[col] - 1  # detections left behind by a move
    keeps = (left >= min_views) | (left == 0) | (stranded[col] - ~has_home == 0)
    better[~keeps] = -np.inf
    i, c = np.unravel_index(np.argmax(better), better.shape)
    return int(i), int(c), float(better[i, c])


def _refine_geometry(
    geometry: CentreRays, member: np.ndarray, cols: np.ndarray, dist: np.ndarray
) -> None:
    """dist[cols] = the distance of each detection's centre ray to the body centre of
    each cluster in ``cols`` (member: (n, C) bool)."""
    sets = member[:, cols] & geometry.has_ray[:, None]
    dist[cols] = geometry.distances(geometry.centres(sets))
