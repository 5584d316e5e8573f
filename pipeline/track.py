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
from scipy.optimize import linear_sum_assignment


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


def _mean_joint_distance(a: np.ndarray, b: np.ndarray, min_shared: int = 3) -> np.ndarray:
    """(A, J, 3), (B, J, 3) -> (A, B) mean distance over joints both have (inf if < min_shared)."""
    d = np.linalg.norm(a[:, None] - b[None], axis=-1)  # (A, B, J)
    ok = np.isfinite(d)
    n = ok.sum(-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(ok, d, 0).sum(-1) / n
    return np.where(n >= min_shared, mean, np.inf)


def track_people(
    frames: np.ndarray,
    joints: np.ndarray,
    num_frames: int,
    params: TrackingParams = TrackingParams(),
) -> Tracks:
    """Assign track IDs to triangulated people.

    Args:
        frames: (Q,) frame of each person row (any order).
        joints: (Q, J, 3) triangulated joints, mm, NaN where missing.
        num_frames: length of the sequence.
    """
    frames = np.asarray(frames, int)
    Q, J = joints.shape[0], joints.shape[1] if joints.ndim == 3 else 0
    track_of = np.full(Q, -1)
    last_pose: list[np.ndarray] = []  # (J, 3) per track
    velocity: list[np.ndarray] = []  # (J, 3) per track, mm/frame
    last_seen: list[int] = []
    first_seen: list[int] = []
    enough = np.isfinite(joints).all(-1).sum(-1) >= params.min_joints if Q else np.zeros(0, bool)
    for f in range(num_frames):
        rows = np.flatnonzero((frames == f) & enough)
        active = [k for k in range(len(last_seen)) if f - last_seen[k] <= params.max_gap]
        matched_rows: set[int] = set()
        if rows.size and active:
            gaps = np.array([f - last_seen[k] for k in active])
            damp = params.velocity_damping ** np.maximum(gaps - 1, 0)
            pred = np.stack(
                [
                    last_pose[k] + velocity[k] * g * d
                    for k, g, d in zip(active, gaps, damp, strict=True)
                ]
            )
            cost = _mean_joint_distance(pred, joints[rows])  # (tracks, people)
            gate = params.max_distance_mm + params.gap_widening_mm * (gaps - 1)
            big = 1e9
            c = np.where(cost <= gate[:, None], cost, big)
            ti, pi = linear_sum_assignment(c)
            for t, p in zip(ti, pi, strict=True):
                if c[t, p] >= big:
                    continue
                k, r = active[t], rows[p]
                new = joints[r]
                dt = f - last_seen[k]
                step = (new - last_pose[k]) / dt
                # Keep the old estimate for joints missing now; velocity only where both exist.
                velocity[k] = np.where(
                    np.isfinite(step), step, velocity[k] * params.velocity_damping
                )
                last_pose[k] = np.where(np.isfinite(new), new, last_pose[k] + velocity[k] * dt)
                last_seen[k] = f
                track_of[r] = k
                matched_rows.add(int(r))
        for r in rows:
            if int(r) in matched_rows:
                continue
            track_of[r] = len(last_seen)
            last_pose.append(joints[r].copy())
            velocity.append(np.where(np.isfinite(joints[r]), 0.0, 0.0))
            last_seen.append(f)
            first_seen.append(f)
    K = len(last_seen)
    out = np.full((K, num_frames, J, 3), np.nan)
    tracked = track_of >= 0
    out[track_of[tracked], frames[tracked]] = joints[tracked]
    return Tracks(
        track_of=track_of,
        joints=out,
        first_frame=np.array(first_seen, int),
        last_frame=np.array(last_seen, int),
    )
