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

Units: mm, pixels.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.cameras import CameraRig


@dataclass(frozen=True)
class AssociationParams:
    max_distance_mm: float = 250.0
    """Mean ray-to-ray distance at which affinity reaches zero."""
    joint_clip_mm: float = 500.0
    """Per-joint distance clip: a single wrong joint cannot dominate."""
    min_affinity: float = 0.3
    """Average-linkage threshold for merging clusters."""
    min_confidence: float = 0.1
    min_shared_joints: int = 3
    min_views: int = 2


@dataclass(frozen=True, eq=False)
class Association:
    """Clusters of one frame.

    Attributes:
        cluster: (n,) person index per detection of the frame, -1 if unassigned.
        affinity: (n, n) pairwise affinity (NaN for same-view pairs and the diagonal).
        ray_distance: (n, n) weighted mean ray distance, mm (NaN where not computed).
        members: (num_people, num_views) detection index (within the frame) per view, -1.
        linkage: (num_people,) mean affinity within each cluster.
    """

    cluster: np.ndarray
    affinity: np.ndarray
    ray_distance: np.ndarray
    members: np.ndarray
    linkage: np.ndarray

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
    dirs = np.full((n, J, 3), np.nan)
    conf = np.nan_to_num(joints2d[..., 2])
    ok = (conf >= min_confidence) & np.isfinite(joints2d[..., :2]).all(-1)
    for v in np.unique(views):
        rows = np.flatnonzero(views == v)
        dirs[rows] = rig[int(v)].pixels_to_rays(joints2d[rows, :, :2])
    weights = np.where(ok, conf, 0.0)
    dirs[~ok] = np.nan
    origins = rig.centers[views] if n else np.zeros((0, 3))
    return origins, dirs, weights


def ray_distances(
    origins: np.ndarray, dirs: np.ndarray, weights: np.ndarray, params: AssociationParams
) -> np.ndarray:
    """(n, n) confidence-weighted mean of clipped ray-to-ray distances, mm.

    NaN where two detections share fewer than ``min_shared_joints`` joints.
    """
    n = origins.shape[0]
    # Closest points of lines a + s da and b + t db; distance |(b - a) . (da x db)| / |da x db|.
    cross = np.cross(dirs[:, None], dirs[None, :])  # (n, n, J, 3)
    norm = np.linalg.norm(cross, axis=-1)
    base = origins[None, :] - origins[:, None]  # (n, n, 3)
    with np.errstate(invalid="ignore", divide="ignore"):
        d = np.abs(np.einsum("abc,abjc->abj", base, cross)) / norm
        # Both closest points must lie in front of their cameras, else the rays diverge.
        dd = np.einsum("ajc,bjc->abj", dirs, dirs)
        w0 = np.einsum("abc,ajc->abj", base, dirs)
        w1 = np.einsum("abc,bjc->abj", base, dirs)
        denom = 1 - dd**2
        s = (w0 - dd * w1) / denom
        t = (dd * w0 - w1) / denom
    behind = (s <= 0) | (t <= 0)
    clip = params.joint_clip_mm
    d = np.where(behind | ~np.isfinite(d), clip, np.minimum(d, clip))
    w = weights[:, None, :] * weights[None, :, :]
    w = np.where(np.isfinite(norm) & (norm > 1e-6), w, 0.0)
    shared = (w > 0).sum(-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = (w * d).sum(-1) / w.sum(-1)
    mean[shared < params.min_shared_joints] = np.nan
    mean[np.arange(n), np.arange(n)] = np.nan
    return mean


def associate_frame(
    rig: CameraRig,
    views: np.ndarray,
    joints2d: np.ndarray,
    params: AssociationParams = AssociationParams(),
    *,
    enabled_views: np.ndarray | None = None,
) -> Association:
    """Cluster one frame's detections into people.

    Args:
        views: (n,) view index per detection.
        joints2d: (n, J, 3) distorted pixels + confidence.
        enabled_views: (num_views,) bool; detections of disabled views stay unassigned.
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
    dist = ray_distances(origins, dirs, weights, params)
    same_view = views[:, None] == views[None, :]
    dist[same_view] = np.nan
    affinity = 1.0 - dist / params.max_distance_mm
    cluster = _average_linkage(affinity, views, params.min_affinity)

    # Keep clusters seen by enough views; number people by their first detection.
    people, linkage = [], []
    out = np.full(n, -1)
    for c in np.unique(cluster):
        rows = np.flatnonzero(cluster == c)
        if len(rows) < params.min_views:
            continue
        members = np.full(V, -1)
        members[views[rows]] = rows
        out[rows] = len(people)
        people.append(members)
        sub = affinity[np.ix_(rows, rows)]
        linkage.append(float(np.nanmean(sub)) if np.isfinite(sub).any() else np.nan)
    return Association(
        cluster=out,
        affinity=affinity,
        ray_distance=dist,
        members=np.array(people, int).reshape(-1, V),
        linkage=np.array(linkage),
    )


def _average_linkage(affinity: np.ndarray, views: np.ndarray, threshold: float) -> np.ndarray:
    """Agglomerative clustering with average linkage and same-view cannot-links.

    Returns (n,) cluster labels. Merges the pair of clusters with the highest mean
    cross affinity while it is >= threshold; pairs with an unknown affinity (NaN)
    count as 0 in the mean, so a detection must agree with most of a cluster.
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
