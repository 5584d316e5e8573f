"""Stage 2, cross-view association: which detections of one frame, in different views,
are the same person.

Affinity of two detections in different views: for every joint both see, the
distance in millimetres between the two back-projected rays (the 3D form of the
symmetric epipolar distance, so one threshold works for every camera pair and
distance), averaged with weights ``conf_a * conf_b`` after clipping each joint's
distance (a swapped or wrong joint costs at most the clip), and mapped to an
affinity in [0, 1]: ``1 - d / max_distance_mm`` (negative = incompatible).

Clustering enforces multi-view consistency rather than pairwise greedy matching:
agglomerative clustering with average linkage, where two clusters merge only if the
mean affinity over *all* their cross pairs is above the threshold and no two members
come from the same view (a cannot-link constraint). A detection therefore joins a
person only if it agrees with every view of that person. Clusters seen in fewer than
``min_views`` views stay unassigned (false positives, or people only one camera sees).

Left/right swaps: 2D detectors (BlazePose, OpenPose) often label a person seen from
behind as if seen from the front, every left joint on the right. Given the joint set,
every pair is also scored with one detection mirrored (its left and right joints
exchanged) and the better of the two counts; each cluster then decides which of its
detections are mirrored (the assignment whose members agree best, taken only when it
clearly beats mirroring none; of it and its mirror image, the one whose triangulated nose
lies in front of the body, where the labels' left-to-right direction and "up" put the
front; without a nose, the one mirroring fewer detections). A cluster whose views all
agree is never mirrored: labels wrong in every view are the label check's business.
``Association.flipped`` says which; the stages after association use the
un-mirrored labels. On the real Pose2Sim demo, 36 of BlazePose's detections (the
woman's in cam02 and cam03, in 22 frames around f50-90) are mirrored: without this her
views split into two clusters that disagree and three tracks come out for two people.

Scale: a pair's per-joint distance is computed only where a cheap screen over the body
parts' mean rays finds the two close (``AssociationParams.prune_mm``, see
:func:`pipeline.association.affinity.screened_distances`); on a 31-camera dome with 20 people it
throws away 3/4 of the pairs.

Duplicates: two clusters with no view in common whose bodies triangulate to the same
place are one person (``AssociationParams.merge_distance_mm``).

Units: mm, pixels.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.association.affinity import (
    average_linkage,
    camera_centres,
    frame_affinity,
    pinhole_rays,
    screened_distances,
)
from pipeline.association.flips import resolve_flips
from pipeline.association.params import AssociationParams  # noqa: F401  (re-exported)
from pipeline.association.refine import (  # noqa: F401  (cluster_centers, re-exported)
    CentreRays,
    centre_rays,
    cluster_centers,
    label_counts,
    merge_duplicates,
    refine_clusters,
    split_inconsistent,
)
from pipeline.data.cameras import CameraRig
from pipeline.data.joint_sets import JointSet


@dataclass(frozen=True, eq=False)
class Association:
    """Clusters of one frame.

    Attributes:
        cluster: (n,) person index per detection of the frame, -1 if unassigned.
        affinity: (n, n) pairwise affinity (NaN for same-view pairs and the diagonal).
        ray_distance: (n, n) weighted mean ray distance, mm (NaN where not computed; for
            a pair the screen pruned, the screen's, >= ``AssociationParams.prune_mm``).
        members: (num_people, num_views) detection index (within the frame) per view, -1.
        linkage: (num_people,) mean affinity within each cluster.
        flipped: (n,) bool, detections whose left and right labels the cluster found
            swapped (their joints are to be read through ``joint_set.flip_index``).
    """

    cluster: np.ndarray
    affinity: np.ndarray
    ray_distance: np.ndarray
    members: np.ndarray
    linkage: np.ndarray
    flipped: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.flipped is None:
            object.__setattr__(self, "flipped", np.zeros(len(self.cluster), bool))

    @property
    def num_people(self) -> int:
        return int(self.members.shape[0])


def detection_rays(
    rig: CameraRig, views: np.ndarray, joints2d: np.ndarray, *, min_confidence: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Back-project detections.

    Args:
        views: (n,) view index per detection; joints2d: (n, J, 3) distorted px + confidence.
    Returns:
        origins (n, 3) camera centres, directions (n, J, 3) unit world rays (NaN if
        missing), weights (n, J) confidence (0 if missing).
    """
    n, J = joints2d.shape[:2]
    dirs, plain = pinhole_rays(rig, views, joints2d[..., :2])  # undistorted views at once
    conf = joints2d[..., 2]
    # NaN confidence compares false: not ok, weight 0
    ok = (conf >= min_confidence) & np.isfinite(joints2d[..., :2]).all(-1)
    for v in np.unique(views[~plain]):
        rows = np.flatnonzero(views == v)
        dirs[rows] = rig[int(v)].pixels_to_rays(joints2d[rows, :, :2])
    weights = np.where(ok, conf, 0.0)
    dirs[~ok] = np.nan
    origins = camera_centres(rig)[views] if n else np.zeros((0, 3))
    return origins, dirs, weights


def flip_candidates(
    origins: np.ndarray,
    dirs: np.ndarray,
    weights: np.ndarray,
    views: np.ndarray,
    params: AssociationParams,
) -> tuple[np.ndarray, np.ndarray]:
    """Pairs (ia < ib) worth scoring with one detection mirrored: in different views, and
    whose centre rays (the confidence-weighted mean ray of each detection, which mirroring
    the labels does not move) pass within ``joint_clip_mm`` of each other: the same body,
    maybe mirrored. Other pairs are other people either way. Cuts the mirrored scoring
    to about the pairs of one person per frame instead of all pairs."""
    c = centre_rays(dirs, weights)
    ia, ib = np.triu_indices(len(views), 1)
    keep = views[ia] != views[ib]
    ia, ib = ia[keep], ib[keep]
    cross = np.cross(c[ia], c[ib])
    norm = np.linalg.norm(cross, axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        gap = np.abs(((origins[ib] - origins[ia]) * cross).sum(-1)) / norm
    near = np.isfinite(gap) & (gap < params.joint_clip_mm)
    return ia[near], ib[near]


def pair_distances(
    a: tuple[np.ndarray, np.ndarray, np.ndarray],
    b: tuple[np.ndarray, np.ndarray, np.ndarray],
    params: AssociationParams,
) -> np.ndarray:
    """(P,) :func:`ray_distances` of P aligned pairs: ``a`` and ``b`` are (origins (P, 3),
    dirs (P, J, 3), weights (P, J)) of each pair's two detections."""
    (oa, da, wa), (ob, db, wb) = a, b
    cross = np.cross(da, db)  # (P, J, 3)
    norm = np.linalg.norm(cross, axis=-1)
    base = ob - oa  # (P, 3)
    with np.errstate(invalid="ignore", divide="ignore"):
        d = np.abs(np.einsum("pc,pjc->pj", base, cross)) / norm
        dd = (da * db).sum(-1)
        w0 = np.einsum("pc,pjc->pj", base, da)
        w1 = np.einsum("pc,pjc->pj", base, db)
        denom = 1 - dd**2
        s = (w0 - dd * w1) / denom
        t = (dd * w0 - w1) / denom
    clip = params.joint_clip_mm
    d = np.where((s <= 0) | (t <= 0) | ~np.isfinite(d), clip, np.minimum(d, clip))
    w = np.where(np.isfinite(norm) & (norm > 1e-6), wa * wb, 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = (w * d).sum(-1) / w.sum(-1)
    mean[(w > 0).sum(-1) < params.min_shared_joints] = np.nan
    return mean


def associate_frame(
    rig: CameraRig,
    views: np.ndarray,
    joints2d: np.ndarray,
    params: AssociationParams = AssociationParams(),
    *,
    enabled_views: np.ndarray | None = None,
    joint_set: JointSet | None = None,
) -> Association:
    """Cluster one frame's detections into people.

    Args:
        views: (n,) view index per detection.
        joints2d: (n, J, 3) distorted pixels + confidence.
        enabled_views: (num_views,) bool; detections of disabled views stay unassigned.
        joint_set: the layout of ``joints2d``; needed to resolve left/right swaps
            (``params.resolve_flips``), which are not looked for without it.
    """
    views = np.asarray(views, int)
    n, V = len(views), len(rig)
    if n == 0:
        return Association(
            cluster=np.zeros(0, int),
            affinity=np.zeros((0, 0)),
            ray_distance=np.zeros((0, 0)),
            members=np.zeros((0, V), int),
            linkage=np.zeros(0),
        )
    origins, dirs, weights = detection_rays(
        rig, views, joints2d, min_confidence=params.min_confidence
    )
    if enabled_views is not None:
        weights = weights * np.asarray(enabled_views, bool)[views][:, None]
    flip = None
    if params.resolve_flips and joint_set is not None:
        flip = joint_set.flip_index
        if (flip == np.arange(len(flip))).all():
            flip = None
    dist, mirrored = _frame_distances(origins, dirs, weights, views, flip, params)  # NaN: same view
    best, affinity, condensed = frame_affinity(dist, mirrored, views, params.max_distance_mm)
    cluster = _average_linkage(affinity, views, params.min_affinity, condensed=condensed)
    # one detection's centre ray, whatever its joints' labels: made once for every step
    geo = CentreRays.of(origins, dirs, weights)
    # Split, move, split again: a wrong cluster blocks the moves of the detections that
    # belong with its members, and the moves look at affinities only.
    for step in ("split", "refine", "split"):
        if step == "split" and params.split_inconsistent:
            cluster = split_inconsistent(
                origins, dirs, weights, views, cluster, affinity, params.min_affinity,
                max_mm=params.joint_clip_mm, geometry=geo,
            )  # fmt: skip
        elif step == "refine" and params.refine:
            cluster = refine_clusters(
                affinity, views, cluster, params.min_affinity, min_views=params.min_views,
                geometry=geo if params.split_inconsistent else None,
                max_mm=params.joint_clip_mm,
            )  # fmt: skip
    flipped = np.zeros(n, bool)
    if flip is not None:
        flipped = resolve_flips(rig, views, joints2d, cluster, dist, mirrored, joint_set)
        dirs, weights = dirs.copy(), weights.copy()
        dirs[flipped] = dirs[flipped][:, flip]
        weights[flipped] = weights[flipped][:, flip]

    if params.merge_distance_mm > 0:
        cluster = merge_duplicates(origins, dirs, weights, views, cluster, params, geometry=geo)

    out, members, linkage = _people(cluster, views, affinity, V, params.min_views)
    return Association(
        cluster=out,
        affinity=affinity,
        ray_distance=best,
        members=members,
        linkage=linkage,
        flipped=flipped & (out >= 0),
    )


_frame_distances = screened_distances  # bench/bench_scale.py swaps in the dense one


def _mirrored_distances(
    origins: np.ndarray,
    dirs: np.ndarray,
    weights: np.ndarray,
    views: np.ndarray,
    flip: np.ndarray,
    params: AssociationParams,
) -> np.ndarray:
    """(n, n) ray distance of each detection pair with the second one left/right mirrored
    (``flip``: the joint set's flip index), mm; NaN for pairs that are no flip candidate.
    Symmetric: dist(a, mirror b) = dist(mirror a, b)."""
    n = len(views)
    mirrored = np.full((n, n), np.nan)
    ia, ib = flip_candidates(origins, dirs, weights, views, params)
    if len(ia):
        m = pair_distances(
            (origins[ia], dirs[ia], weights[ia]),
            (origins[ib], dirs[ib][:, flip], weights[ib][:, flip]),
            params,
        )
        mirrored[ia, ib] = mirrored[ib, ia] = m
    return mirrored


def _people(
    cluster: np.ndarray, views: np.ndarray, affinity: np.ndarray, V: int, min_views: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Keep the clusters seen by at least ``min_views`` views; number people by their first
    detection. Returns (n,) person per detection (-1: none), (num_people, V) members
    (detection row per view, -1) and (num_people,) mean affinity within each person."""
    _, label, size = label_counts(cluster)
    keep = size >= min_views
    out = np.where(keep[label], (np.cumsum(keep) - 1)[label], -1)  # clusters in label order
    P = int(keep.sum())
    rows = np.flatnonzero(out >= 0)
    members = np.full((P, V), -1)
    members[out[rows], views[rows]] = rows
    # mean finite affinity within each person, from its (V, V) block of member pairs
    # gathered at once (a (m, m) block of every kept row was ~1.4 ms at 31 x 20; a loop
    # over people with a nanmean each ~10 % of the association). A pair of one view, and
    # a detection with itself, has no affinity (NaN).
    seen = members >= 0
    rows_of = np.where(seen, members, 0)
    sub = affinity[rows_of[:, :, None], rows_of[:, None, :]]  # (P, V, V)
    own = np.isfinite(sub) & seen[:, :, None] & seen[:, None, :]
    total = np.where(own, sub, 0.0).sum((1, 2))
    count = own.sum((1, 2))
    with np.errstate(invalid="ignore", divide="ignore"):
        linkage = np.where(count > 0, total / np.maximum(count, 1), np.nan)
    return out, members, linkage


def _average_linkage(
    affinity: np.ndarray, views: np.ndarray, threshold: float, *, condensed=None
) -> np.ndarray:
    """:func:`pipeline.association.affinity.average_linkage` (SciPy's hierarchical
    clustering): the same clusters as ``average_linkage_reference``
    (bench/reference_association.py) in O(n^2)."""
    return average_linkage(affinity, views, threshold, condensed=condensed)


