"""Offline track stitching: one track per person over the whole run.

The online tracker (:mod:`pipeline.stages.track`) decides frame by frame; on real
captures a person is still split over several tracks: the association briefly makes
two clusters of one person (two tracks side by side for a few frames, one of which
then carries on alone), or a person unseen for longer than the tracker waits is reborn
under a new id. The pipeline sees the whole run, so after tracking every pair of
tracks is judged as a whole:

- **duplicate**: the two tracks exist together in some frames and there they are the
  same body (median mean-joint distance <= ``duplicate_mm``): one person split by the
  association. They are joined; in a frame both have, the pose with more joints stays
  (the other row becomes untracked).
- **continuation**: one ends before (or a few frames after) the other starts, the second
  begins where the first could have walked to (distance <= ``radius_mm`` + ``speed_mm``
  per frame of the gap) and their bone lengths agree (mean difference <= ``bone_mm``).

Pairs are joined cheapest first (a duplicate before a continuation, then by distance),
each join re-judging the joined track against the rest, until no pair qualifies. Two
people never join while they exist together apart from each other: that is what keeps
stitching from merging people on synthetic scenes where everyone is tracked throughout.

Units: mm, frames.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.stages.track import bone_lengths, mean_joint_distance


@dataclass(frozen=True)
class StitchParams:
    enabled: bool = True
    """Join the tracks of one person after tracking."""
    duplicate_mm: float = 300.0
    """Two tracks that exist together are one person where their median mean-joint
    distance over the frames they share is at most this."""
    max_overlap_fraction: float = 0.5
    """... and where those shared frames are at most this share of the longer track's
    (two real people standing close for long are two tracks; a short second cluster of
    one person beside a long track is absorbed)."""
    max_gap: int = 250
    """Frames between the end of one track and the start of the next that a continuation
    may bridge."""
    radius_mm: float = 500.0
    """A continuation starts within this distance (mean joint) of where the first track
    ended, plus ``speed_mm`` per frame of the gap."""
    speed_mm: float = 40.0
    """How far a person may walk per unseen frame (40 mm at 25 fps: 1 m/s)."""
    bone_mm: float = 30.0
    """Mean bone-length difference allowed between the two tracks of a continuation."""


def _track_stats(labels, k, frames, joints, bones) -> dict | None:
    """Track ``k``'s rows and frames (sorted by frame) and median bone lengths; None if
    it has no row."""
    rows = np.flatnonzero(labels == k)
    rows = rows[np.argsort(frames[rows], kind="stable")]
    if rows.size == 0:
        return None
    lengths = bone_lengths(joints[rows], bones) if len(bones) else np.zeros((len(rows), 0))
    seen = np.isfinite(lengths).any(0)
    med = np.full(lengths.shape[1], np.nan)
    med[seen] = np.nanmedian(lengths[:, seen], axis=0)
    return {"rows": rows, "frames": frames[rows], "bones": med}


def _pair_cost(a, b, joints, params: StitchParams) -> float | None:
    """The cost of joining tracks ``a`` and ``b`` (their stats), or None if they are not
    one person. Duplicates cost their distance, continuations 1000 + their distance."""
    shared = np.intersect1d(a["frames"], b["frames"])
    if shared.size:
        longer = max(len(a["frames"]), len(b["frames"]))
        if shared.size > params.max_overlap_fraction * longer:
            return None
        ra = a["rows"][np.searchsorted(a["frames"], shared)]
        rb = b["rows"][np.searchsorted(b["frames"], shared)]
        d = np.diag(mean_joint_distance(joints[ra], joints[rb]))
        d = d[np.isfinite(d)]
        if d.size == 0 or np.median(d) > params.duplicate_mm:
            return None
        return float(np.median(d))
    first, second = (a, b) if a["frames"][-1] < b["frames"][0] else (b, a)
    gap = int(second["frames"][0] - first["frames"][-1])
    if gap > params.max_gap:
        return None
    end = joints[first["rows"][-1]][None]
    start = joints[second["rows"][0]][None]
    dist = float(mean_joint_distance(end, start)[0, 0])
    if not np.isfinite(dist) or dist > params.radius_mm + params.speed_mm * gap:
        return None
    diff = np.abs(first["bones"] - second["bones"])
    if len(diff):
        if np.isfinite(diff).sum() < 3 or float(np.nanmean(diff)) > params.bone_mm:
            return None
    return 1000.0 + dist


def stitch_tracks(
    track_of: np.ndarray,
    frames: np.ndarray,
    joints: np.ndarray,
    *,
    bones: np.ndarray,
    params: StitchParams = StitchParams(),
) -> np.ndarray:
    """Join the tracks of one person (module docstring).

    Args:
        track_of: (Q,) track of each person row, -1 untracked.
        frames: (Q,) frame of each row; joints: (Q, J, 3) mm, NaN missing.
        bones: (B, 2) joint pairs whose lengths identify a person.
    Returns:
        (Q,) track of each row, tracks numbered by first appearance; in a frame where
        two joined tracks both had a row, the row with fewer joints is -1.
    """
    labels = np.asarray(track_of, int).copy()
    if not params.enabled or labels.max(initial=-1) < 1:
        return labels
    frames = np.asarray(frames, int)
    bones = np.asarray(bones, int).reshape(-1, 2)
    num_joints = np.isfinite(joints).all(-1).sum(-1)
    num_tracks = int(labels.max(initial=-1)) + 1
    stats = {k: st for k in range(num_tracks)
             if (st := _track_stats(labels, k, frames, joints, bones)) is not None}  # fmt: skip
    costs: dict[tuple[int, int], float] = {}  # (a, b), a < b -> cost of a pair that qualifies

    def judge(a: int, b: int) -> None:
        cost = _pair_cost(stats[a], stats[b], joints, params)
        if cost is not None:
            costs[(a, b)] = cost

    for a in stats:
        for b in stats:
            if a < b:
                judge(a, b)
    while costs:  # join the cheapest pair, then re-judge only the joined track's pairs
        a, b = min(costs, key=costs.get)
        labels[labels == b] = a
        _one_row_per_frame(labels, a, frames, num_joints)
        costs = {p: c for p, c in costs.items() if a not in p and b not in p}
        del stats[b]
        stats[a] = _track_stats(labels, a, frames, joints, bones)
        for k in stats:
            if k != a:
                judge(min(a, k), max(a, k))
    return _renumber(labels, frames)


def _one_row_per_frame(labels, k, frames, num_joints) -> None:
    """Where track ``k`` has several rows in a frame, keep the one with most joints."""
    rows = np.flatnonzero(labels == k)
    order = rows[np.lexsort((-num_joints[rows], frames[rows]))]
    f = frames[order]
    extra = order[1:][f[1:] == f[:-1]]
    labels[extra] = -1


def _renumber(labels, frames) -> np.ndarray:
    """Tracks numbered 0.. by the frame they first appear in (gaps in the ids closed)."""
    ids = np.unique(labels[labels >= 0])
    if ids.size == 0:
        return labels
    first = np.array([frames[labels == k].min() for k in ids])
    order = ids[np.argsort(first, kind="stable")]
    new = np.full(int(ids.max()) + 1, -1)
    new[order] = np.arange(len(order))
    return np.where(labels >= 0, new[np.maximum(labels, 0)], -1)
