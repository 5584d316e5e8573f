"""Our result beside another tool's on the same input: per-keypoint 3D distances and
per-camera reprojection errors onto the same 2D.

Used by the peer benchmark (bench/bench_peer_pose2sim.py) and its test. Both results
are scored against the 2D detections *our* association gave the subject in each view,
so that the comparison uses one and the same 2D for both tools.

Units: world mm, image pixels. Shapes: F frames, V views, J joints.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.data.cameras import CameraRig


@dataclass(frozen=True, eq=False)
class TrackObservations:
    """The 2D detections a track was triangulated from.

    Attributes:
        track: the track index.
        keypoints: (F, V, J, 3) x, y px, confidence; NaN x, y and confidence 0 where the
            track has no detection in that view and frame.
    """

    track: int
    keypoints: np.ndarray


def closest_track(tracks: np.ndarray, reference: np.ndarray) -> tuple[int, float]:
    """The track whose joints are nearest ``reference`` (median over frames and joints).

    Args:
        tracks: (K, F, J, 3) mm; reference: (F, J, 3) mm, NaN where missing.
    Returns:
        (track index, its median distance in mm); (-1, inf) if no track overlaps.
    """
    best, best_d = -1, np.inf
    for k in range(tracks.shape[0]):
        d = np.linalg.norm(tracks[k] - reference, axis=-1)
        if np.isfinite(d).sum() and (m := float(np.nanmedian(d))) < best_d:
            best, best_d = k, m
    return best, best_d


def track_observations(
    det_keypoints: np.ndarray,
    det_view: np.ndarray,
    det_person: np.ndarray,
    person_frame: np.ndarray,
    person_track: np.ndarray,
    track: int,
    *,
    num_frames: int,
    num_views: int,
) -> TrackObservations:
    """Gather the 2D detections assigned to ``track``.

    Args:
        det_keypoints: (N, J, 3) the 2D joints that fed the stages (results.det_joints2d).
        det_view: (N,) view of each detection; det_person: (N,) person-frame row or -1;
        person_frame, person_track: (Q,) frame and track of each person-frame.
    """
    J = det_keypoints.shape[1]
    out = np.full((num_frames, num_views, J, 3), np.nan)
    out[..., 2] = 0.0
    rows = np.flatnonzero(det_person >= 0)
    rows = rows[person_track[det_person[rows]] == track]
    out[person_frame[det_person[rows]], det_view[rows]] = det_keypoints[rows]
    return TrackObservations(track=track, keypoints=out)


def reprojection_errors(
    rig: CameraRig, points: np.ndarray, observed: np.ndarray, *, min_confidence: float = 0.3
) -> np.ndarray:
    """(F, V, J) pixel distance between each view's 2D and the projection of ``points``.

    Args:
        points: (F, J, 3) world mm (NaN where missing).
        observed: (F, V, J, 3) the 2D (TrackObservations.keypoints).
        min_confidence: 2D joints below this are not scored (NaN), the likelihood
            threshold Pose2Sim's trial used (0.3).
    """
    F, V, J = observed.shape[:3]
    err = np.full((F, V, J), np.nan)
    for v, cam in enumerate(rig):
        uv = cam.project(points.reshape(-1, 3)).reshape(F, J, 2)
        d = np.linalg.norm(uv - observed[:, v, :, :2], axis=-1)
        seen = observed[:, v, :, 2] >= min_confidence
        err[:, v] = np.where(seen, d, np.nan)
    return err


def subject_observations(
    scene, results, reference: np.ndarray
) -> tuple[int, float, TrackObservations]:
    """The track nearest ``reference`` (:func:`closest_track`), its median distance (mm)
    and the 2D it was triangulated from (:func:`track_observations`).

    Args:
        scene: a :class:`pipeline.data.scene.Scene`; results: its
            :class:`pipeline.results.store.PipelineResults`; reference: (F, J, 3) mm.
    """
    track, dist = closest_track(results.track_raw, reference)
    obs = track_observations(
        results.det_joints2d,
        scene.detections.view,
        results.det_person,
        results.person_frame,
        results.person_track,
        track,
        num_frames=scene.num_frames,
        num_views=len(scene.rig),
    )
    return track, dist, obs


def per_joint_median_mm(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(J,) median over frames of |a - b| per joint (NaN where never both present).

    Args:
        a, b: (F, J, 3) mm.
    """
    d = np.linalg.norm(a - b, axis=-1)
    out = np.full(d.shape[1], np.nan)
    seen = np.isfinite(d).any(0)
    out[seen] = np.nanmedian(d[:, seen], axis=0)
    return out
