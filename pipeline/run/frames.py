"""The one place where the stages are composed.

Per frame (re-runnable on its own, which is what the viewer does when a parameter
changes): 2D source selection (keypoints, or SMPL joints restored from the monocular
predictions) -> cross-view association -> triangulation. Then, over the sequence:
tracking -> the tracks' proportions (joints that contradict a person's bones
re-solved or flagged) -> Kalman filtering (forward and RTS-smoothed).

Units: mm, pixels, frames.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np

from pipeline.association.associate import associate_frame
from pipeline.config import PipelineConfig
from pipeline.core.progress import Progress, StageBar
from pipeline.data.joint_sets import SMPL24, JointSet
from pipeline.data.scene import Scene
from pipeline.results.store import FrameResult, SequenceResult
from pipeline.stages.kalman import FilterResult, kalman_filter
from pipeline.stages.proportions import PersonEvidence, check_proportions
from pipeline.stages.retime import retimed_frames, retimed_rows
from pipeline.stages.stitch import stitch_tracks
from pipeline.stages.track import Tracks, track_people, tracks_from_labels
from pipeline.stages.triangulate import triangulate_people

if TYPE_CHECKING:
    from pipeline.body.arrays import BodyModelData
    from pipeline.body.model import BodyModel


def source_joint_set(scene: Scene, config: PipelineConfig) -> JointSet:
    return SMPL24 if config.source == "smpl" else scene.joint_set


def restored_joints(scene: Scene, model: BodyModel | BodyModelData) -> np.ndarray | None:
    """(N, 24, 3) SMPL joints restored from the monocular predictions, or None.

    Rows with SMPL regressor output restore its joints; rows without it but with
    monocular 3D joints (``mono_joints3d``) project those the same way (joints they lack
    get confidence 0). Every joint of a row gets the row's mean keypoint confidence (the
    detector's score for that person), so that a weak detection stays weak whichever
    source is used.
    """
    det = scene.detections
    if not det.has_mono3d:
        return None
    # torch (the SMPL regressor's joints) only when a scene has monocular predictions
    from pipeline.body.model import torch_body_model
    from pipeline.stages.restore import restore_joints_2d, restore_mono_joints_2d

    conf = det.keypoints[..., 2]
    score = np.where((conf > 0).any(1), conf.sum(1) / np.maximum((conf > 0).sum(1), 1), 1.0)
    out = np.full((len(det), SMPL24.num_joints, 3), np.nan)
    out[..., 2] = 0.0
    if det.has_smpl:
        out = restore_joints_2d(
            det.smpl_pose,
            det.smpl_betas,
            det.cam_weak,
            det.bbox,
            torch_body_model(model),
            score=score,
        )
    mono = det.mono_valid
    if mono.any():
        out[mono] = restore_mono_joints_2d(
            det.mono_joints3d[mono], det.cam_weak[mono], det.bbox[mono], score=score[mono]
        )
    return out


def _source_2d(scene: Scene, config: PipelineConfig, restored: np.ndarray | None) -> np.ndarray:
    if config.source == "smpl":
        if restored is None:
            raise ValueError(
                f"{scene.root}: source 'smpl' needs smpl_pose/smpl_betas/cam_weak/bbox or "
                "mono_joints3d/cam_weak/bbox in detections.npz; this scene has only keypoints"
            )
        return restored
    return scene.detections.keypoints


def sync_offsets(scene: Scene, config: PipelineConfig) -> dict[int, float]:
    """Camera index -> the configured time offset (frames) of the cameras that have one."""
    return {scene.rig.index_of(c): d for c, d in config.sync.offsets if d != 0}


def select_2d(scene: Scene, config: PipelineConfig, restored: np.ndarray | None) -> np.ndarray:
    """(N, J, 3) the 2D joints of the configured source for every detection row, each
    camera with a ``sync.offsets`` entry re-timed (:mod:`pipeline.stages.retime`)."""
    joints2d = _source_2d(scene, config, restored)
    offsets = sync_offsets(scene, config)
    if not offsets:
        return joints2d
    det = scene.detections
    return retimed_rows(det.frame, det.view, joints2d, offsets)[1]


def row_frames(scene: Scene, config: PipelineConfig | None = None) -> np.ndarray:
    """(N,) the frame each detection row is used at: its recorded frame, moved by its
    camera's whole-frame ``sync.offsets`` (may fall outside the clip: then unused)."""
    det = scene.detections
    offsets = {} if config is None else sync_offsets(scene, config)
    return retimed_frames(det.frame, det.view, offsets) if offsets else det.frame


def enabled_view_mask(scene: Scene, config: PipelineConfig) -> np.ndarray:
    unknown = set(config.disabled_views) - set(scene.rig.names)
    if unknown:
        raise ValueError(f"disabled_views names unknown cameras {sorted(unknown)}")
    return np.array([c.name not in config.disabled_views for c in scene.rig])


def group_by_frame(frame: np.ndarray, num_frames: int) -> list[np.ndarray]:
    """Rows per frame: ``out[f]`` holds, in increasing order, the indices ``i`` with
    ``frame[i] == f``, for ``f`` in ``range(num_frames)`` (rows of other frames are left out).

    Args:
        frame: (n,) int frame of each row.
    """
    frame = np.asarray(frame)
    order = np.argsort(frame, kind="stable")
    bounds = np.searchsorted(frame[order], np.arange(num_frames + 1))
    return [order[bounds[i] : bounds[i + 1]] for i in range(num_frames)]


def frame_rows(scene: Scene, config: PipelineConfig | None = None) -> list[np.ndarray]:
    """Detection rows per frame, computed once (index with the frame number); with
    ``config``, at the frames its ``sync.offsets`` move them to (:func:`row_frames`)."""
    return group_by_frame(row_frames(scene, config), scene.num_frames)


def run_frame(
    scene: Scene,
    frame: int,
    config: PipelineConfig,
    joints2d_all: np.ndarray,
    *,
    rows: np.ndarray | None = None,
) -> FrameResult:
    """Association and triangulation of one frame."""
    if rows is None:
        rows = np.flatnonzero(row_frames(scene, config) == frame)
    enabled = enabled_view_mask(scene, config)
    views = scene.detections.view[rows]
    joints2d = joints2d_all[rows].copy()
    joints2d[~enabled[views], :, 2] = 0.0  # a disabled camera contributes nothing
    joint_set = source_joint_set(scene, config)
    assoc = associate_frame(
        scene.rig, views, joints2d, config.association, enabled_views=enabled, joint_set=joint_set
    )
    if assoc.flipped.any():  # detections with left and right swapped, read un-mirrored
        joints2d[assoc.flipped] = joints2d[assoc.flipped][:, joint_set.flip_index]
    P, V, J = assoc.num_people, len(scene.rig), joints2d.shape[1]
    kp = np.full((P, V, J, 3), np.nan)
    kp[..., 2] = 0.0
    for p in range(P):
        for v in range(V):
            m = assoc.members[p, v]
            if m >= 0:
                kp[p, v] = joints2d[m]
    tp = config.triangulation
    tri = triangulate_people(
        scene.rig,
        kp,
        min_confidence=tp.min_confidence,
        outlier_threshold_px=tp.outlier_threshold_px,
        min_views=tp.min_views,
    )
    return FrameResult(
        frame=frame, rows=rows, joints2d=joints2d, association=assoc, triangulation=tri
    )


FRAMES_STAGE = "associate+triangulate"  # the stage name :func:`run_frames` reports


def run_frames(
    scene: Scene,
    config: PipelineConfig,
    joints2d_all: np.ndarray,
    *,
    rows_per_frame: list[np.ndarray] | None = None,
    cancelled: Callable[[], bool] | None = None,
    progress: Progress = True,
) -> list[FrameResult] | None:
    """Association and triangulation of every frame (:func:`run_frame`).

    Args:
        joints2d_all: (N, J, 3) the 2D joints of every detection row (:func:`select_2d`).
        rows_per_frame: :func:`frame_rows` of ``scene``, if already computed.
        cancelled: checked before each frame; once it returns true the run stops and
            returns None.
        progress: see :mod:`pipeline.core.progress` (stage :data:`FRAMES_STAGE`, in frames).
    """
    rows = frame_rows(scene, config) if rows_per_frame is None else rows_per_frame
    frames: list[FrameResult] = []
    with StageBar(FRAMES_STAGE, scene.num_frames, progress, unit="frame") as bar:
        for f in range(scene.num_frames):
            if cancelled is not None and cancelled():
                return None
            frames.append(run_frame(scene, f, config, joints2d_all, rows=rows[f]))
            bar.update()
    return frames


def run_sequence(
    frames: list[FrameResult],
    num_frames: int,
    config: PipelineConfig,
    joint_set: JointSet,
    scene: Scene | None = None,
) -> SequenceResult:
    """Tracking and filtering over the per-frame people (with ``scene``, the proportion
    check re-solves joints from its views; without, it only flags them)."""
    if frames and frames[0].triangulation.points.ndim == 3:
        J = frames[0].triangulation.points.shape[1]
    else:
        J = 0
    person_frame = np.concatenate(
        [np.full(fr.triangulation.points.shape[0], fr.frame) for fr in frames] or [np.zeros(0)]
    ).astype(int)
    person_joints = np.concatenate(
        [fr.triangulation.points.reshape(-1, J, 3) for fr in frames] or [np.zeros((0, J, 3))]
    )
    evidence = None
    if scene is not None:
        V = len(scene.rig)
        joints2d = np.zeros((len(scene.detections.view), J, 3))
        members, used = [np.zeros((0, V), int)], [np.zeros((0, J, V), bool)]
        for fr in frames:
            joints2d[fr.rows] = fr.joints2d  # un-mirrored, disabled views at confidence 0
            a = fr.association
            members.append(np.where(a.members >= 0, fr.rows[np.maximum(a.members, 0)], -1))
            used.append(fr.triangulation.used.reshape(-1, J, V))
        evidence = person_evidence(
            scene, config, joints2d, np.concatenate(members), np.concatenate(used)
        )
    return sequence_of_people(person_frame, person_joints, num_frames, config, joint_set, evidence)


def person_evidence(
    scene: Scene,
    config: PipelineConfig,
    joints2d: np.ndarray,
    members: np.ndarray,
    used: np.ndarray,
) -> PersonEvidence:
    """The 2D evidence of the person-frames for :func:`check_proportions`.

    Args:
        joints2d: (N, J, 3) the 2D joints that fed the stages (un-mirrored).
        members: (Q, V) detection row per view, -1. used: (Q, J, V) bool.
    """
    members = np.where(enabled_view_mask(scene, config)[None], members, -1)
    tp = config.triangulation
    return PersonEvidence(
        rig=scene.rig, joints2d=joints2d, members=members, used=used,
        min_confidence=tp.min_confidence, outlier_threshold_px=tp.outlier_threshold_px,
    )  # fmt: skip


def sequence_of_people(
    person_frame: np.ndarray,
    person_joints: np.ndarray,
    num_frames: int,
    config: PipelineConfig,
    joint_set: JointSet,
    evidence: PersonEvidence | None = None,
) -> SequenceResult:
    """:func:`run_sequence` from the per-frame people as columns: (Q,) frame and (Q, J, 3)
    triangulated joints of each person-frame, in frame order (what
    :mod:`pipeline.run.chunked` keeps of the frames instead of their results), and the
    2D ``evidence`` the proportion check re-solves joints from (None: flagged only)."""
    tracks = tracks_of_people(person_frame, person_joints, num_frames, config, joint_set)
    tracks, resolved, contradicted = proportions_of_tracks(
        tracks, person_frame, person_joints, num_frames, config, joint_set, evidence
    )
    filtered = filter_tracks(tracks.joints, tracks.last_frame, config, skip=contradicted)
    return SequenceResult(
        person_track=tracks.track_of, tracks=tracks, filtered=filtered,
        track_resolved=resolved, track_contradicted=contradicted,
    )  # fmt: skip


def proportions_of_tracks(
    tracks: Tracks,
    person_frame: np.ndarray,
    person_joints: np.ndarray,
    num_frames: int,
    config: PipelineConfig,
    joint_set: JointSet,
    evidence: PersonEvidence | None,
) -> tuple[Tracks, np.ndarray, np.ndarray]:
    """The tracks with their joints checked against their bones
    (:mod:`pipeline.stages.proportions`): (tracks with re-solved joints, (K, F, J)
    re-solved, (K, F, J) contradicted)."""
    check = check_proportions(
        person_joints, tracks.track_of, tracks.num_tracks, np.array(joint_set.bones),
        evidence, config.proportions,
    )  # fmt: skip
    K, J = tracks.num_tracks, tracks.joints.shape[2]
    resolved = np.zeros((K, num_frames, J), bool)
    contradicted = np.zeros((K, num_frames, J), bool)
    rows = tracks.track_of >= 0
    k, f = tracks.track_of[rows], np.asarray(person_frame, int)[rows]
    resolved[k, f] = check.resolved[rows]
    contradicted[k, f] = check.contradicted[rows]
    if check.resolved.any():
        tracks = tracks_from_labels(tracks.track_of, person_frame, check.joints, num_frames)
    return tracks, resolved, contradicted


def tracks_of_people(
    person_frame: np.ndarray,
    person_joints: np.ndarray,
    num_frames: int,
    config: PipelineConfig,
    joint_set: JointSet,
) -> Tracks:
    """Tracking, then the tracks of one person joined over the whole run
    (:mod:`pipeline.stages.stitch`)."""
    bones = np.array(joint_set.bones)
    tracks = track_people(person_frame, person_joints, num_frames, config.tracking, bones=bones)
    if not config.stitch.enabled:
        return tracks
    labels = stitch_tracks(
        tracks.track_of, person_frame, person_joints, bones=bones, params=config.stitch
    )
    return tracks_from_labels(labels, person_frame, person_joints, num_frames)


def filter_tracks(
    joints: np.ndarray,
    last_frame: np.ndarray,
    config: PipelineConfig,
    *,
    skip: np.ndarray | None = None,
) -> FilterResult:
    """The Kalman forward filter and RTS smoother of tracks, each ending at its last frame.

    Every joint of every track is its own trajectory, so any subset of the tracks filters
    to the same numbers as the whole (what :mod:`pipeline.run.streamed` does in blocks).

    Args:
        joints: (K, F, J, 3) the tracks' raw joints, mm, NaN where absent.
        last_frame: (K,) the frame each track was last seen.
        skip: (K, F, J) bool, measurements the filter does not take (contradicted).

    Returns:
        FilterResult over (F, K, J, ...).
    """
    measurements = np.moveaxis(joints, 1, 0)  # (F, K, J, 3)
    # Always smooth too: the forward and RTS outputs are both in the result, and the
    # configured ``smoother`` flag only picks which one is "the" filtered trajectory.
    filtered = kalman_filter(
        measurements,
        dataclasses.replace(config.kalman, smoother=True),
        skip=None if skip is None else np.moveaxis(skip, 1, 0),
    )
    # A track that has died does not coast on: its filter output ends at its last
    # measurement (coasting through gaps inside a track's life is kept).
    frames_idx = np.arange(joints.shape[1])[:, None]
    after = frames_idx > np.asarray(last_frame)[None, :]  # (F, K)
    if after.any():
        # In place: the arrays are the filter's own, made for this call, and a copy of
        # each of its 11 float (F, K, J[, 3]) arrays doubled the stage's peak on long runs.
        for f in dataclasses.fields(filtered):
            a = getattr(filtered, f.name)
            if a.dtype.kind == "f":
                a[after] = np.nan
    return filtered
