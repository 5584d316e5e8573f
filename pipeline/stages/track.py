"""Stage 4, tracking: stable person IDs over time.

Each frame's triangulated people are matched to the existing tracks by the Hungarian
algorithm on the mean 3D joint distance to each track's *predicted* pose (its last
pose moved on by its recent per-joint velocity), gated by a distance that widens with
the time since the track was last seen. Tracks survive gaps of up to ``max_gap``
frames (occlusion, a missed association) and then die; people that match no track
and have enough joints are born as new tracks. Predicting with velocity is what keeps
two people who pass close from swapping IDs.

Units: mm, frames.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.core.assignment import gated_assignment


@dataclass(frozen=True)
class TrackingParams:
    max_distance_mm: float = 400.0
    """Gate on the mean joint distance to a track's prediction one frame on."""
    gap_widening_mm: float = 60.0
    """The gate widens by this much per unseen frame."""
    max_gap: int = 12
    """Frames a track survives unseen."""
    min_joints: int = 6
    """A person needs this many triangulated joints to be matched or to start a track."""
    velocity_damping: float = 0.7
    """Weight of the last velocity when predicting across a gap (1 = constant velocity)."""
    reid_max_gap: int = 100
    """Frames a lost track can still be re-identified (0 disables re-identification)."""
    reid_radius_mm: float = 1000.0
    """A re-identified person reappears within this distance (mean joint) of where lost."""
    reid_bone_mm: float = 25.0
    """Mean bone-length difference allowed when re-identifying."""
    min_hits: int = 3
    """A track seen in fewer frames than this is no person and is dropped (its rows are
    left untracked): a cluster of false detections that triangulates in one frame, or a
    one-frame mis-association beside a real person. On the noisy sample 18 of 22 tracks
    were such one-frame (and one three-frame) ghosts. Such a track is not re-identified
    either. 1 keeps every track."""


@dataclass(frozen=True, eq=False)
class Tracks:
    """Tracking result.

    Attributes:
        track_of: (Q,) track index of each input person-frame row, -1 if not tracked.
        joints: (K, F, J, 3) raw joints of each track in each frame, NaN where absent.
        first_frame, last_frame: (K,) frames a track was first and last seen.
        births: (K,) same as first_frame (a birth event per track).
    """

    track_of: np.ndarray
    joints: np.ndarray
    first_frame: np.ndarray
    last_frame: np.ndarray

    @property
    def num_tracks(self) -> int:
        return int(self.joints.shape[0])


def mean_joint_distance(a: np.ndarray, b: np.ndarray, min_shared: int = 3) -> np.ndarray:
    """(A, J, 3), (B, J, 3) -> (A, B) mean distance over joints both have (inf if < min_shared)."""
    d = np.linalg.norm(a[:, None] - b[None], axis=-1)  # (A, B, J)
    ok = np.isfinite(d)
    n = ok.sum(-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(ok, d, 0).sum(-1) / n
    return np.where(n >= min_shared, mean, np.inf)


def bone_lengths(joints: np.ndarray, bones: np.ndarray) -> np.ndarray:
    """(..., J, 3) joints, (B, 2) bone index pairs -> (..., B) lengths, NaN if an end is missing."""
    if len(bones) == 0:
        return np.zeros(joints.shape[:-2] + (0,))
    return np.linalg.norm(joints[..., bones[:, 0], :] - joints[..., bones[:, 1], :], axis=-1)


def _match_active(
    f: int,
    rows: np.ndarray,
    active: list[int],
    joints: np.ndarray,
    last_pose: list[np.ndarray],
    velocity: list[np.ndarray],
    last_seen: list[int],
    params: TrackingParams,
) -> list[tuple[int, int]]:
    """Gated Hungarian between the ``active`` tracks and frame ``f``'s people ``rows``:
    (track, row) pairs."""
    gaps = np.array([f - last_seen[k] for k in active])
    damp = params.velocity_damping ** np.maximum(gaps - 1, 0)
    pred = np.stack(
        [last_pose[k] + velocity[k] * g * d for k, g, d in zip(active, gaps, damp, strict=True)]
    )
    # Where the motion predicts, or where it was last seen: a velocity from one
    # noisy step (a joint re-solved from another camera pair jumps by 10-25 cm on
    # the real Pose2Sim demo) must not throw a track off its person.
    last = np.stack([last_pose[k] for k in active])
    cost = np.fmin(
        mean_joint_distance(pred, joints[rows]), mean_joint_distance(last, joints[rows])
    )  # (tracks, people)
    gate = params.max_distance_mm + params.gap_widening_mm * (gaps - 1)
    ti, pi = gated_assignment(cost, cost <= gate[:, None])
    return [(active[t], rows[p]) for t, p in zip(ti, pi, strict=True)]


def _follow(
    k: int,
    dt: int,
    new: np.ndarray,
    last_pose: list[np.ndarray],
    velocity: list[np.ndarray],
    params: TrackingParams,
) -> None:
    """Track ``k`` moves to pose ``new`` (J, 3), ``dt`` frames after it was last seen: its
    velocity (mm/frame) only where both poses have a joint (else damped), its old
    estimate kept (extrapolated) for joints missing now."""
    step = (new - last_pose[k]) / dt
    velocity[k] = np.where(np.isfinite(step), step, velocity[k] * params.velocity_damping)
    last_pose[k] = np.where(np.isfinite(new), new, last_pose[k] + velocity[k] * dt)


def track_people(
    frames: np.ndarray,
    joints: np.ndarray,
    num_frames: int,
    params: TrackingParams = TrackingParams(),
    *,
    bones: np.ndarray | None = None,
) -> Tracks:
    """Assign track IDs to triangulated people.

    Args:
        frames: (Q,) frame of each person row (any order).
        joints: (Q, J, 3) triangulated joints, mm, NaN where missing.
        num_frames: length of the sequence.
        bones: (B, 2) joint index pairs used to compare body proportions when
            re-identifying a lost track; None disables re-identification.
    """
    bones = np.zeros((0, 2), int) if bones is None else np.asarray(bones, int).reshape(-1, 2)
    frames = np.asarray(frames, int)
    Q = joints.shape[0]
    track_of = np.full(Q, -1)
    last_pose: list[np.ndarray] = []  # (J, 3) per track
    velocity: list[np.ndarray] = []  # (J, 3) per track, mm/frame
    last_seen: list[int] = []
    first_seen: list[int] = []
    bone_sum: list[np.ndarray] = []  # running sums of bone lengths, for re-identification
    bone_count: list[np.ndarray] = []
    enough = np.isfinite(joints).all(-1).sum(-1) >= params.min_joints if Q else np.zeros(0, bool)
    for f in range(num_frames):
        rows = np.flatnonzero((frames == f) & enough)
        active = [k for k in range(len(last_seen)) if f - last_seen[k] <= params.max_gap]
        matched_rows: set[int] = set()
        if rows.size and active:
            for k, r in _match_active(
                f, rows, active, joints, last_pose, velocity, last_seen, params
            ):
                _follow(k, f - last_seen[k], joints[r], last_pose, velocity, params)
                last_seen[k] = f
                track_of[r] = k
                matched_rows.add(int(r))
                _add_bones(bone_sum, bone_count, k, joints[r], bones)
        unmatched = [int(r) for r in rows if int(r) not in matched_rows]
        hits = np.bincount(track_of[track_of >= 0], minlength=len(last_seen))
        lost = [
            k
            for k in range(len(last_seen))
            if params.max_gap < f - last_seen[k] <= params.reid_max_gap
            and len(bones)
            and hits[k] >= params.min_hits
        ]
        if unmatched and lost:
            for k, r in _reidentify(
                unmatched, lost, joints, last_pose, bone_sum, bone_count, bones, params
            ):
                last_pose[k] = np.where(np.isfinite(joints[r]), joints[r], last_pose[k])
                velocity[k] = np.zeros_like(velocity[k])
                last_seen[k] = f
                track_of[r] = k
                _add_bones(bone_sum, bone_count, k, joints[r], bones)
                unmatched.remove(r)
        for r in unmatched:  # a new track
            track_of[r] = len(last_seen)
            last_pose.append(joints[r].copy())
            velocity.append(np.zeros_like(joints[r]))
            last_seen.append(f)
            first_seen.append(f)
            bone_sum.append(np.zeros(len(bones)))
            bone_count.append(np.zeros(len(bones)))
            _add_bones(bone_sum, bone_count, track_of[r], joints[r], bones)
    return _pack(track_of, frames, joints, num_frames, first_seen, last_seen, params.min_hits)


def _pack(track_of, frames, joints, num_frames, first_seen, last_seen, min_hits) -> Tracks:
    """The :class:`Tracks` of the tracks seen in ``min_hits`` frames or more, numbered in
    order of birth; rows of shorter ones become untracked (-1)."""
    hits = np.bincount(track_of[track_of >= 0], minlength=len(last_seen))
    keep = hits >= min_hits
    new_id = np.where(keep, np.cumsum(keep) - 1, -1)
    track_of = np.where(track_of >= 0, new_id[np.maximum(track_of, 0)], -1)
    J = joints.shape[1] if joints.ndim == 3 else 0
    out = np.full((int(keep.sum()), num_frames, J, 3), np.nan)
    tracked = track_of >= 0
    out[track_of[tracked], frames[tracked]] = joints[tracked]
    return Tracks(
        track_of=track_of,
        joints=out,
        first_frame=np.array(first_seen, int)[keep],
        last_frame=np.array(last_seen, int)[keep],
    )


def tracks_from_labels(
    track_of: np.ndarray, frames: np.ndarray, joints: np.ndarray, num_frames: int
) -> Tracks:
    """The :class:`Tracks` of person rows labelled ``track_of`` (tracks 0..K-1, each in
    at most one row per frame; -1 untracked), e.g. after stitching."""
    track_of = np.asarray(track_of, int)
    frames = np.asarray(frames, int)
    K = int(track_of.max(initial=-1)) + 1
    J = joints.shape[1] if joints.ndim == 3 else 0
    out = np.full((K, num_frames, J, 3), np.nan)
    tracked = track_of >= 0
    out[track_of[tracked], frames[tracked]] = joints[tracked]
    first = np.full(K, num_frames, int)
    last = np.full(K, -1, int)
    np.minimum.at(first, track_of[tracked], frames[tracked])
    np.maximum.at(last, track_of[tracked], frames[tracked])
    return Tracks(track_of=track_of, joints=out, first_frame=first, last_frame=last)


def _add_bones(bone_sum, bone_count, k, pose, bones) -> None:
    lengths = bone_lengths(pose, bones)
    ok = np.isfinite(lengths)
    bone_sum[k][ok] += lengths[ok]
    bone_count[k][ok] += 1


def _reidentify(unmatched, lost, joints, last_pose, bone_sum, bone_count, bones, params):
    """Hungarian between unmatched people and lost tracks on place + body proportions."""
    cost = np.full((len(lost), len(unmatched)), np.inf)
    place = mean_joint_distance(np.stack([last_pose[k] for k in lost]), joints[unmatched])
    for i, k in enumerate(lost):
        mean_bones = np.where(bone_count[k] > 0, bone_sum[k] / np.maximum(bone_count[k], 1), np.nan)
        for j, r in enumerate(unmatched):
            diff = np.abs(bone_lengths(joints[r], bones) - mean_bones)
            if np.isfinite(diff).sum() < 3:
                continue
            bone_diff = float(np.nanmean(diff))
            if place[i, j] <= params.reid_radius_mm and bone_diff <= params.reid_bone_mm:
                cost[i, j] = place[i, j] + 20.0 * bone_diff  # 1 mm of bone ~ 2 cm of place
    ti, pi = gated_assignment(cost)
    return [(lost[t], unmatched[p]) for t, p in zip(ti, pi, strict=True)]


def match_to_tracks(
    people: np.ndarray, reference: np.ndarray, max_distance_mm: float, *, min_shared: int = 3
) -> np.ndarray:
    """Hungarian matching of people to tracks on the mean distance over shared joints.

    Args:
        people: (P, J, 3) mm, NaN where missing.
        reference: (K, J, 3) mm, each track's pose in the same frame, NaN where unknown.
        max_distance_mm: pairs farther apart (or sharing < ``min_shared`` joints) never match.
    Returns:
        (P,) track index per person, -1 where unmatched.
    """
    out = np.full(len(people), -1)
    if len(people) == 0 or len(reference) == 0:
        return out
    cost = mean_joint_distance(people, reference, min_shared)
    rows, cols = gated_assignment(cost, cost <= max_distance_mm)
    out[rows] = cols
    return out
