"""Real motion capture -> our joints and our body model: name maps, resampling, SMPL fit.

A BVH clip (:mod:`pipeline.importers.bvh`) is a skeleton of its own: other joints,
other proportions than our body model. This module

1. maps the mocap skeleton's joints onto SMPL-24 and COCO-17 by anatomy
   (:data:`CMU_TO_SMPL24`, :data:`CMU_TO_COCO17`; NaN where there is no counterpart),
2. resamples a clip to a scene's frame rate (linear interpolation of positions: a
   moving bone shortens by under 0.5 mm at 120 -> 25 fps),
3. fits our body model to the SMPL-24 trajectories (:func:`fit_clips`, step I of
   :func:`pipeline.fit.smpl.fit_sequence`, no prior) and reports the residual per
   joint: how far our body model's proportions are from the mocap skeleton's. The
   fitted poses (F, 24, 3) are training data for the pose prior
   (:func:`bvh_training_poses`, ``mvviz train-prior --data X.bvh``).

Units: world millimetres, z up (as every scene); the body model in metres.

The CMU / cgspeed skeleton (31 joints; README of ``sample_data/mocap/cmu131``). A BVH
joint's position is the *start* of the bone named after it, so ``LeftHip`` is the hip
joint centre, ``LeftKnee`` the knee, ``LeftAnkle`` the ankle, ``LeftToe`` the ball of
the foot (the toes' bone starts there), ``LeftShoulder`` the gleno-humeral joint,
``LeftElbow``, ``LeftWrist`` the elbow and wrist; ``Neck`` is the top of CMU's
``lowerneck`` bone, the base of the neck (SMPL's neck joint); ``Head`` the top of
``upperneck``, the base of the skull (SMPL's head joint sits there too, inside the
skull). No counterpart, NaN in SMPL-24 slots:

* ``pelvis``: CMU's root ``Hips`` is the Vicon pelvis origin, ~90 mm above the hip
  centres and behind them; SMPL's pelvis is a regressed point (17 mm above the hip
  line in the open body model, ~85 mm in SMPL): neither is an anatomical landmark.
* ``spine1-3``: CMU's ``Chest``/``Chest2`` are 110 and 220 mm above the root, SMPL's
  spine joints elsewhere; ``left/right_collar``: CMU's collars have zero offsets (they
  sit on the midline at ``Chest2``), SMPL's are lateral, near the sterno-clavicular
  joints; ``left/right_hand``: CMU's ``lhand`` coincides with the wrist and its
  ``LFingers`` is 37 mm past it, SMPL's hand joint is at the knuckles.

COCO-17: shoulders, elbows, wrists, hips, knees and ankles are the joints of the same
name. The five face points do not exist in a mocap skeleton; they are *derived*:
``Head + R_head @ offset`` with the offsets of :data:`FACE_OFFSETS_MM`, measured on the
default body model at rest (its COCO regressor's face points minus its head joint,
mean shape), in the head's frame (x left, y up, z forward: the rest frame of both the
CMU skeleton and SMPL). They are plausible, not measured: a scene made from mocap
scores only the twelve measured joints (:func:`pipeline.evaluation.evaluate.evaluate` maps COCO-17
to SMPL-24 slots by those twelve).
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from pipeline.body.keypoints import keypoint_regressor, layout_keypoints
from pipeline.body.model import BodyModel, load_body_model
from pipeline.core.files import SceneFormatError
from pipeline.data.joint_sets import COCO17, SMPL24
from pipeline.fit.smpl import FitParams, fit_sequence
from pipeline.importers.bvh import bvh_to_world_mm, read_bvh, world_axes

CMU_SCALE_TO_M = 0.056444
"""Metres per unit of the CMU cgspeed BVH files (CMU's ASF unit: 1/0.45 inch)."""

CMU_TO_SMPL24: dict[str, str] = {
    "left_hip": "LeftHip", "right_hip": "RightHip",
    "left_knee": "LeftKnee", "right_knee": "RightKnee",
    "left_ankle": "LeftAnkle", "right_ankle": "RightAnkle",
    "left_foot": "LeftToe", "right_foot": "RightToe",
    "neck": "Neck", "head": "Head",
    "left_shoulder": "LeftShoulder", "right_shoulder": "RightShoulder",
    "left_elbow": "LeftElbow", "right_elbow": "RightElbow",
    "left_wrist": "LeftWrist", "right_wrist": "RightWrist",
}  # fmt: skip
"""SMPL-24 joint -> CMU/cgspeed BVH joint (see the module docstring); the other eight
SMPL joints (pelvis, spine1-3, collars, hands) have no counterpart."""

CMU_TO_COCO17: dict[str, str] = {n: CMU_TO_SMPL24[n] for n in COCO17.names if n in CMU_TO_SMPL24}
"""COCO-17 keypoint -> CMU joint for the twelve body joints; the face is derived."""

FACE_OFFSETS_MM: dict[str, tuple[float, float, float]] = {
    "nose": (0.0, 12.0, 112.0),
    "left_eye": (30.0, 44.0, 90.0),
    "right_eye": (-30.0, 44.0, 90.0),
    "left_ear": (74.0, 25.0, 8.0),
    "right_ear": (-74.0, 25.0, 8.0),
}
"""COCO face points in the head's frame (x left, y up, z forward), mm from the head
joint: the default body model's at rest (mean shape), rounded to the millimetre."""

FACE_PARENT = "Head"

SKELETON_MAPS: dict[str, dict[str, str]] = {"cmu_cgspeed": CMU_TO_SMPL24}

# Groups of the residual report.
RESIDUAL_GROUPS: dict[str, tuple[str, ...]] = {
    "hips": ("left_hip", "right_hip"),
    "knees": ("left_knee", "right_knee"),
    "ankles": ("left_ankle", "right_ankle"),
    "feet": ("left_foot", "right_foot"),
    "neck": ("neck",),
    "head": ("head",),
    "shoulders": ("left_shoulder", "right_shoulder"),
    "elbows": ("left_elbow", "right_elbow"),
    "wrists": ("left_wrist", "right_wrist"),
}


@dataclass(frozen=True, eq=False)
class MocapClip:
    """A mocap clip in our world, at ``fps``. F frames.

    Attributes:
        path: the BVH file.
        name: its stem (e.g. ``"131_01"``).
        fps: frame rate of the arrays (after resampling).
        source_fps: the file's frame rate.
        source_frames: the file's frame count.
        skeleton: (F, J, 3) every BVH joint (End Sites included), world mm.
        joint_names: (J,) BVH joint names of ``skeleton``.
        smpl24: (F, 24, 3) SMPL-24 slots from :data:`CMU_TO_SMPL24`, NaN without
            counterpart.
        coco17: (F, 17, 3) COCO-17: twelve mapped joints, five derived face points.
        activity: what the clip shows (from ``clips.json`` beside it, else ``"unknown"``).
        licence: the clip's terms (``clips.json``, else ``"unknown"``).
    """

    path: Path
    name: str
    fps: float
    source_fps: float
    source_frames: int
    skeleton: np.ndarray
    joint_names: tuple[str, ...]
    smpl24: np.ndarray
    coco17: np.ndarray
    activity: str = "unknown"
    licence: str = "unknown"

    @property
    def num_frames(self) -> int:
        return int(self.skeleton.shape[0])

    def info(self) -> dict:
        """Where the clip came from, for training records and scene metadata."""
        return {
            "file": self.path.name,
            "frames": self.num_frames,
            "fps": round(self.fps, 3),
            "source_frames": self.source_frames,
            "source_fps": round(self.source_fps, 3),
            "activity": self.activity,
            "licence": self.licence,
        }


# --------------------------------------------------------------------------- clips


def resample(x: np.ndarray, fps_in: float, fps_out: float) -> np.ndarray:
    """(F, ...) samples at ``fps_in`` -> (F', ...) at ``fps_out`` over the same span,
    by linear interpolation in time (exact subsampling for an integer ratio)."""
    if not (fps_in > 0 and fps_out > 0):
        raise ValueError(f"frame rates must be > 0, got {fps_in} and {fps_out}")
    F = x.shape[0]
    if F == 0 or abs(fps_in - fps_out) < 1e-6 * fps_in:
        return x.copy()
    ratio = fps_in / fps_out
    if abs(ratio - round(ratio)) < 1e-3:
        return x[:: int(round(ratio))].copy()
    t = np.arange(0.0, (F - 1) / fps_in + 1e-9, 1.0 / fps_out) * fps_in
    i0 = np.clip(np.floor(t).astype(int), 0, F - 1)
    i1 = np.minimum(i0 + 1, F - 1)
    w = (t - i0).reshape((-1,) + (1,) * (x.ndim - 1))
    return (1 - w) * x[i0] + w * x[i1]


def smpl24_from_skeleton(
    skeleton: np.ndarray, joint_names: tuple[str, ...], name_map: dict[str, str]
) -> np.ndarray:
    """(F, J, 3) mocap joints -> (F, 24, 3) SMPL-24 slots (NaN where unmapped)."""
    idx = {n: i for i, n in enumerate(joint_names)}
    missing = [b for b in name_map.values() if b not in idx]
    if missing:
        raise ValueError(f"the skeleton has no joint {missing[0]!r} (joints: {joint_names})")
    out = np.full(skeleton.shape[:1] + (SMPL24.num_joints, 3), np.nan)
    for smpl, bvh in name_map.items():
        out[:, SMPL24.index[smpl]] = skeleton[:, idx[bvh]]
    return out


def coco17_from_skeleton(
    skeleton: np.ndarray,
    joint_names: tuple[str, ...],
    head_rotation_world: np.ndarray,
    name_map: dict[str, str] = CMU_TO_COCO17,
) -> np.ndarray:
    """(F, 17, 3) COCO-17 world mm: the mapped joints, and the face from
    :data:`FACE_OFFSETS_MM` rotated by the head (``head_rotation_world`` (F, 3, 3):
    from the head joint's own frame, x left, y up, z forward at rest, to the world)."""
    idx = {n: i for i, n in enumerate(joint_names)}
    out = np.full(skeleton.shape[:1] + (COCO17.num_joints, 3), np.nan)
    for coco, bvh in name_map.items():
        out[:, COCO17.index[coco]] = skeleton[:, idx[bvh]]
    head = skeleton[:, idx[FACE_PARENT]]
    for name, off in FACE_OFFSETS_MM.items():
        out[:, COCO17.index[name]] = head + head_rotation_world @ np.asarray(off)
    return out


def _sidecar(path: Path) -> dict:
    """``clips.json`` beside a BVH file (scale, axes, activity, licence), or {}."""
    side = path.parent / "clips.json"
    if not side.is_file():
        return {}
    try:
        data = json.loads(side.read_text())
    except json.JSONDecodeError as exc:
        raise SceneFormatError(side, None, f"not valid JSON ({exc})") from None
    if not isinstance(data, dict):
        raise SceneFormatError(side, None, "expected a JSON object")
    return data


def load_mocap_clip(
    path: str | os.PathLike,
    *,
    fps: float | None = None,
    scale_to_m: float | None = None,
    y_up: bool | None = None,
    skeleton: str | None = None,
) -> MocapClip:
    """Read a BVH clip into our world, resampled to ``fps`` (default: the file's).

    ``scale_to_m``, ``y_up`` and ``skeleton`` default to the ``clips.json`` beside the
    file (``sample_data/mocap/cmu131/clips.json``), else to the CMU cgspeed values
    (0.056444 m per unit, Y up, ``cmu_cgspeed`` names).
    """
    path = Path(path)
    side = _sidecar(path)
    motion = read_bvh(path)
    scale = float(scale_to_m or side.get("scale_to_m", CMU_SCALE_TO_M))
    up = bool(side.get("y_up", True) if y_up is None else y_up)
    kind = skeleton or side.get("skeleton", "cmu_cgspeed")
    if kind not in SKELETON_MAPS:
        raise SceneFormatError(
            path, "skeleton", f"unknown skeleton {kind!r}; known {list(SKELETON_MAPS)}"
        )
    name_map = SKELETON_MAPS[kind]
    missing = [b for b in list(name_map.values()) + [FACE_PARENT] if b not in motion.index]
    if missing:
        raise SceneFormatError(path, "HIERARCHY", f"no joint {missing[0]!r}: not a {kind} skeleton")
    world = bvh_to_world_mm(motion, scale_to_m=scale, y_up=up)
    A = world_axes(y_up=up)
    head_R = A @ motion.rotations[:, motion.index[FACE_PARENT]]  # head frame -> world
    out_fps = motion.fps if fps is None else float(fps)
    world = resample(world, motion.fps, out_fps)
    head_R = _resample_rotations(head_R, motion.fps, out_fps)
    clip_meta = side.get("clips", {}).get(path.name, {})
    return MocapClip(
        path=path,
        name=path.stem,
        fps=out_fps,
        source_fps=motion.fps,
        source_frames=motion.num_frames,
        skeleton=world,
        joint_names=motion.names,
        smpl24=smpl24_from_skeleton(world, motion.names, name_map),
        coco17=coco17_from_skeleton(world, motion.names, head_R),
        activity=str(clip_meta.get("activity", "unknown")),
        licence=str(side.get("licence", "unknown")),
    )


def clip_from_body(
    name: str,
    pose_rotvecs: np.ndarray,
    betas: np.ndarray,
    transl_mm: np.ndarray,
    model: BodyModel,
    *,
    fps: float,
    activity: str,
    licence: str,
    source_frames: int | None = None,
    source_fps: float | None = None,
) -> MocapClip:
    """A clip whose skeleton is our body model posed by ``pose_rotvecs`` (F, 24, 3) with
    ``betas`` (10,) and ``transl_mm`` (F, 3): motion of the synthetic library or fitted
    poses of a real trial, played by :mod:`pipeline.synth.mocap_scene` like a BVH clip.
    ``smpl24`` are the model's joints, ``coco17`` its COCO regressor's keypoints (all
    measured: no derived face), ``skeleton`` = ``smpl24`` (root ``pelvis``); world mm, the
    lowest vertex of the clip on the floor (z = 0). ``path`` is ``Path(name)``."""
    pose = np.asarray(pose_rotvecs, float).reshape(-1, 24, 3)
    F = len(pose)
    reg = keypoint_regressor(model, COCO17.name)
    with torch.no_grad():
        out = model(
            torch.as_tensor(pose, dtype=torch.float32),
            torch.as_tensor(np.tile(np.asarray(betas, float), (F, 1)), dtype=torch.float32),
        )
        kp = layout_keypoints(reg, out.vertices, out.joints).double().numpy() * 1000.0
    t = np.asarray(transl_mm, float).reshape(F, 1, 3).copy()
    t[..., 2] -= float((out.vertices.double().numpy() * 1000.0 + t)[..., 2].min())
    joints = out.joints.double().numpy() * 1000.0 + t
    return MocapClip(
        path=Path(name),
        name=name,
        fps=float(fps),
        source_fps=float(source_fps or fps),
        source_frames=int(source_frames or F),
        skeleton=joints,
        joint_names=tuple(SMPL24.names),
        smpl24=joints,
        coco17=kp + t,
        activity=activity,
        licence=licence,
    )


def _resample_rotations(R: np.ndarray, fps_in: float, fps_out: float) -> np.ndarray:
    """(F, 3, 3) rotations resampled like :func:`resample`, re-orthonormalised."""
    out = resample(R, fps_in, fps_out)
    u, _, vt = np.linalg.svd(out)
    return u @ vt


# --------------------------------------------------------------------------- body fit


@dataclass(frozen=True, eq=False)
class MocapFit:
    """Our body model fitted to one clip's SMPL-24 trajectories. F frames.

    Attributes:
        clip: the clip's name.
        pose_rotvecs: (F, 24, 3) local axis-angle, root in the world frame.
        betas: (10,) shape.
        transl: (F, 3) mm; the body is ``1000 * model(pose, betas) + transl``.
        joints: (F, 24, 3) the fitted model's joints, world mm.
        residual: (F, 24) |model joint - mocap joint| mm, NaN for unmapped joints.
    """

    clip: str
    pose_rotvecs: np.ndarray
    betas: np.ndarray
    transl: np.ndarray
    joints: np.ndarray
    residual: np.ndarray

    def residual_by_joint(self) -> dict[str, float]:
        """Mean residual (mm) of every mapped SMPL-24 joint."""
        return {
            n: float(np.nanmean(self.residual[:, j]))
            for j, n in enumerate(SMPL24.names)
            if np.isfinite(self.residual[:, j]).any()
        }

    def residual_by_group(self) -> dict[str, float]:
        """Mean residual (mm) per group of :data:`RESIDUAL_GROUPS`, and ``all``."""
        out = {
            g: float(np.nanmean(self.residual[:, [SMPL24.index[n] for n in names]]))
            for g, names in RESIDUAL_GROUPS.items()
        }
        out["all"] = float(np.nanmean(self.residual))
        return out


def fit_clips(
    clips: list[MocapClip],
    model: BodyModel | None = None,
    *,
    params: FitParams = FitParams(iters=300),  # noqa: B008  (frozen dataclass)
    progress: bool = False,
) -> list[MocapFit]:
    """Fit our body model to each clip (one track per clip, in one batch; no prior).

    The default 300 iterations (the pipeline's fit uses 120) let the residual settle:
    it is the measurement here, not a by-product.
    """
    model = model or load_body_model()
    if not clips:
        return []
    F = max(c.num_frames for c in clips)
    tracks = np.full((len(clips), F, SMPL24.num_joints, 3), np.nan)
    for k, c in enumerate(clips):
        tracks[k, : c.num_frames] = c.smpl24
    fit, _ = fit_sequence(tracks, SMPL24.name, model, params=params, progress=progress)
    out = []
    for k, c in enumerate(clips):
        n = c.num_frames
        out.append(
            MocapFit(
                clip=c.name,
                pose_rotvecs=fit.pose_rotvecs[k, :n],
                betas=fit.betas[k],
                transl=fit.transl[k, :n],
                joints=fit.joints[k, :n],
                residual=fit.residual[k, :n],
            )
        )
    return out


def format_residuals(fits: list[MocapFit]) -> str:
    """Residual per joint group (mm, mean over frames) as a plain-text table."""
    groups = list(RESIDUAL_GROUPS) + ["all"]
    head = f"{'clip':<10}" + "".join(f"{g:>10}" for g in groups)
    lines = ["SMPL fit to mocap joints: residual per joint group (mm, mean)", head]
    lines.append("-" * len(head))
    for f in fits:
        r = f.residual_by_group()
        lines.append(f"{f.clip:<10}" + "".join(f"{r[g]:10.1f}" for g in groups))
    return "\n".join(lines)


def bvh_training_poses(
    path: str | os.PathLike,
    *,
    model: BodyModel | None = None,
    fps: float = 30.0,
    params: FitParams = FitParams(iters=300),  # noqa: B008
) -> tuple[np.ndarray, dict, MocapFit]:
    """Poses (N, 72) of a BVH clip for the pose prior: our body model fitted to it at
    ``fps``; with the clip's record (:meth:`MocapClip.info` plus the mean residual) and
    the fit."""
    clip = load_mocap_clip(path, fps=fps)
    (fit,) = fit_clips([clip], model, params=params)
    ok = np.isfinite(fit.pose_rotvecs).all((1, 2))
    info = dict(clip.info(), fit_residual_mm=round(float(np.nanmean(fit.residual)), 1))
    return fit.pose_rotvecs[ok].reshape(-1, 72), info, fit
