"""Stage 2, cross-view association (:mod:`pipeline.association.associate`): which detections of a
cluster have their left and right labels swapped (see the module docstring there).

Units: mm.
"""

from __future__ import annotations

import functools

import numpy as np

from pipeline.data.cameras import CameraRig
from pipeline.data.joint_sets import JointSet
from pipeline.stages.triangulate import triangulate_people

FLIP_GAIN = 0.7
"""Mirroring must bring a cluster's mean pair ray distance below this fraction..."""
FLIP_MIN_MM = 15.0
"""...and lower it by more than this many millimetres."""
MAX_EXHAUSTIVE_FLIPS = 9
"""Clusters up to this size try every assignment of mirrored members; larger ones are
built greedily (each member oriented to agree with those already placed)."""


def resolve_flips(
    rig: CameraRig,
    views: np.ndarray,
    joints2d: np.ndarray,
    cluster: np.ndarray,
    dist: np.ndarray,
    mirrored: np.ndarray,
    joint_set: JointSet,
) -> np.ndarray:
    """(n,) which detections of each cluster have left and right swapped.

    Args:
        dist, mirrored: (n, n) mean ray distances of two detections as labelled, and with
            one of them mirrored (NaN where unknown).
    Returns:
        bool per detection; see the module docstring for the rule.
    """
    flipped = np.zeros(len(views), bool)
    # unknown distances count as the largest known one (and >= 0)
    clip = max(np.fmax.reduce(d, axis=None, initial=0.0) for d in (dist, mirrored))
    # Only a cluster with a pair closer mirrored by more than FLIP_MIN_MM can flip: the
    # gain of any assignment is a mean of such differences over the pairs it splits
    # (at most FLIP_MIN_MM else), and the greedy build compares the same means. An
    # unknown mirrored distance (clip) gains nothing: NaN compares false. Only the pairs
    # inside clusters are looked at (~1/20 of a dome frame's).
    ia, ib = _cluster_pairs(cluster)
    d = dist[ia, ib]
    with np.errstate(invalid="ignore"):
        gainful = np.where(np.isfinite(d), d, clip) - mirrored[ia, ib] > FLIP_MIN_MM
    for c in np.unique(cluster[ia[gainful]]):
        rows = np.flatnonzero(cluster == c)
        same, cross = dist[np.ix_(rows, rows)], mirrored[np.ix_(rows, rows)]
        bits = _orient(
            np.where(np.isfinite(same), same, clip), np.where(np.isfinite(cross), cross, clip)
        )
        if not bits.any():
            continue  # every view agrees: nothing for association to decide
        # The views split into two mirrored camps: which camp has the labels right?
        if _faces_backwards(rig, views[rows], joints2d[rows], bits, joint_set):
            bits = ~bits
        elif "nose" not in joint_set.index and bits.sum() * 2 > len(bits):
            bits = ~bits
        flipped[rows] = bits
    return flipped


def _cluster_pairs(cluster: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(ia, ib) every ordered pair of detections with one label in (n,) ``cluster``
    (a detection with itself too), by cluster."""
    order = np.argsort(cluster, kind="stable")
    _, start, size = np.unique(cluster[order], return_index=True, return_counts=True)
    reps = np.repeat(size, size)  # each member's cluster size, once per partner
    ia = np.repeat(order, reps)
    first = np.repeat(np.repeat(start, size), reps)  # its cluster's first position
    offset = np.arange(len(ia)) - np.repeat(np.cumsum(reps) - reps, reps)
    return ia, order[first + offset]


def _orient(S: np.ndarray, X: np.ndarray) -> np.ndarray:
    """(m,) orientation bits minimising the mean pair distance: S where two members share
    an orientation, X where they differ; the first member is never flipped. Mirroring
    is taken only when it clearly helps (:data:`FLIP_GAIN`, :data:`FLIP_MIN_MM`): a
    near-symmetric pose (standing, arms down) fits both ways within the noise, and a
    wrong flip there costs more than it can win."""
    m = len(S)
    if m <= MAX_EXHAUSTIVE_FLIPS:
        iu, bits, differ = _assignments(m)
        cost = np.where(differ, X[iu], S[iu]).mean(1)
        best = int(np.argmin(cost))
        gain = cost[0] - cost[best]  # code 0: nobody mirrored
        if gain > FLIP_MIN_MM and cost[best] < FLIP_GAIN * cost[0]:
            return bits[best]
        return bits[0]
    # Greedy for large clusters: place members from the most central one out.
    order = np.argsort(S.sum(1))
    bits = np.zeros(m, bool)
    for i, k in enumerate(order[1:], start=1):
        placed = order[:i]
        keep = np.where(bits[placed], X[k, placed], S[k, placed]).mean()
        swap = np.where(bits[placed], S[k, placed], X[k, placed]).mean()
        bits[k] = keep - swap > FLIP_MIN_MM and swap < FLIP_GAIN * keep
    return bits ^ bits[0]


@functools.cache
def _assignments(m: int) -> tuple[tuple[np.ndarray, np.ndarray], np.ndarray, np.ndarray]:
    """Every orientation of m members with the first unflipped: the pair indices, the
    (2^(m-1), m) bits and whether each pair's members differ."""
    iu = np.triu_indices(m, 1)
    codes = np.arange(2 ** (m - 1))
    bits = np.zeros((len(codes), m), bool)
    bits[:, 1:] = (codes[:, None] >> np.arange(m - 1)) & 1
    return iu, bits, bits[:, iu[0]] != bits[:, iu[1]]


def _faces_backwards(
    rig: CameraRig, views: np.ndarray, joints2d: np.ndarray, bits: np.ndarray, js: JointSet
) -> bool:
    """Whether the body triangulated with ``bits`` has its nose behind it: the labels'
    left-to-right direction crossed with up (+z) must point where the nose is."""
    names = ("nose", "left_shoulder", "right_shoulder")
    if not all(n in js.index for n in names) or len(views) < 2:
        return False
    kp = joints2d.copy()
    kp[bits] = kp[bits][:, js.flip_index]
    sel = [js.index[n] for n in names]
    cams = np.full((1, len(rig), 3, 3), np.nan)
    cams[..., 2] = 0.0
    cams[0, views] = kp[:, sel]
    nose, left, right = triangulate_people(rig, cams, outlier_threshold_px=np.inf).points[0]
    if not np.isfinite([nose, left, right]).all():
        return False
    forward = np.cross(left - right, [0.0, 0.0, 1.0])
    return float(np.dot(nose - 0.5 * (left + right), forward)) < 0.0
