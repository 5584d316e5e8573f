"""Where the other cameras put each joint: every person re-triangulated without some views.

A camera's own detections cannot vouch for it (a triangulation that uses them is pulled
toward them), so the diagnoses compare a camera with the joints the *other* cameras
give. The views kept are those the run's triangulation used for that joint (its
outlier rejection already dropped the views that disagree), minus the excluded ones.
"""

from __future__ import annotations

import numpy as np

from pipeline.data.scene import Scene
from pipeline.results.store import PipelineResults
from pipeline.run.frames import row_frames
from pipeline.stages.triangulate import triangulate_dlt

MIN_CONFIDENCE = 0.3  # as the triangulation's default: weaker 2D joints are not evidence


def track_person_rows(results: PipelineResults) -> np.ndarray:
    """(K, F) the person-frame row (into the Q arrays) of each track in each frame, -1."""
    out = np.full((results.num_tracks, results.num_frames), -1, int)
    q = np.flatnonzero(results.person_track >= 0)
    out[results.person_track[q], results.person_frame[q]] = q
    return out


def triangulate_without(
    scene: Scene,
    results: PipelineResults,
    exclude: set[int] | frozenset[int],
    *,
    min_confidence: float = MIN_CONFIDENCE,
) -> np.ndarray:
    """(Q, J, 3) every person-frame's joints from its used views minus ``exclude``, mm.

    NaN where fewer than two views remain. Weighted like the pipeline's DLT (by the 2D
    confidence), on undistorted normalised coordinates.
    """
    Q, J = results.person_joints.shape[:2]
    V = len(scene.rig)
    points = np.full((Q, J, V, 2), np.nan)
    weights = np.zeros((Q, J, V))
    for v, cam in enumerate(scene.rig):
        if v in exclude:
            continue
        rows = results.person_members[:, v]
        have = np.flatnonzero(rows >= 0)
        if len(have) == 0:
            continue
        kp = results.det_joints2d[rows[have]]  # (n, J, 3)
        points[have, :, v] = cam.undistort_to_normalised(kp[..., :2])
        conf = np.nan_to_num(kp[..., 2])
        used = results.person_used[have, :, v]
        weights[have, :, v] = np.where((conf >= min_confidence) & used, conf, 0.0)
    proj = np.stack([np.hstack([c.R, c.t[:, None]]) for c in scene.rig])
    if Q == 0:
        return np.zeros((0, J, 3))
    return triangulate_dlt(proj, points, weights)


def track_points_without(
    scene: Scene, results: PipelineResults, exclude: set[int] | frozenset[int]
) -> np.ndarray:
    """(K, F, J, 3) each track's joints per frame from the views not in ``exclude``, mm."""
    pts = triangulate_without(scene, results, exclude)
    rows = track_person_rows(results)
    J = results.person_joints.shape[1]
    out = np.full(rows.shape + (J, 3), np.nan)
    have = rows >= 0
    out[have] = pts[rows[have]]
    return out


def camera_detections(
    scene: Scene, results: PipelineResults, view: int
) -> tuple[np.ndarray, np.ndarray]:
    """One camera's 2D, padded per frame: (F, n, J, 3) joints (NaN padding) and (F, n)
    detection row (-1 padding), n the most people that camera saw in one frame."""
    det = scene.detections
    used_at = row_frames(scene, results.config)  # where a re-timed run used each row
    rows = np.flatnonzero((det.view == view) & (used_at >= 0) & (used_at < results.num_frames))
    F = results.num_frames
    counts = np.bincount(used_at[rows], minlength=F)[:F]
    n = max(int(counts.max(initial=0)), 1)
    J = results.det_joints2d.shape[1]
    joints = np.full((F, n, J, 3), np.nan)
    index = np.full((F, n), -1, int)
    order = rows[np.argsort(used_at[rows], kind="stable")]
    frame = used_at[order]
    slot = np.arange(len(order)) - np.searchsorted(frame, frame)  # rank within its frame
    joints[frame, slot] = results.det_joints2d[order]
    index[frame, slot] = order
    return joints, index
