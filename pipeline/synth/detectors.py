"""Simulated per-view detectors for synthetic scenes, with a documented noise model.

(a) A 2D keypoint detector (:func:`simulate_keypoints`; COCO-17 by default, any layout
    of :mod:`pipeline.body.keypoints`): pixel noise that grows as confidence falls, the
    same for every keypoint of every layout, confidence that drops with occlusion
    (self-occlusion decided by the z-buffer, occlusion by another person by the
    z-buffer's mesh index), joints missed when occluded, occasional left/right swaps
    (a swapped ankle takes its heel and toes along, a swapped wrist its hand points),
    people dropped at image borders. Keypoints the layout defines but the body model
    cannot give (``defined`` False) are never reported.
    False positives come from :func:`ghost_people` in the scene generator.
(b) A monocular SMPL regressor in the MVSPIN role (:func:`simulate_regressor`): a noisy
    SMPL pose and shape per detection, root orientation in the camera frame, and a
    weak-perspective camera fitted so the predicted joints project near the true 2D
    joints. Its depth is wrong in a way only one view can be: some limbs are mirrored
    through the image plane (the classic monocular depth ambiguity), which keeps every
    2D joint where it was while moving the limb in depth.

Units: world mm, pixels, body model metres.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from pipeline.body.model import BodyModel, rigid_chain
from pipeline.core.rotations import axis_angle_to_matrix
from pipeline.data.cameras import Camera
from pipeline.data.joint_sets import _HAND_POINTS, COCO17, SMPL24, JointSet
from pipeline.stages.restore import fit_weak_perspective


@dataclass(frozen=True)
class DetectorNoise:
    """Noise model of the simulated detectors (defaults are the shipped sample's)."""

    pixel_sigma: float = 2.5
    """2D noise std (px) of a fully confident joint on a 400 px tall person; it scales
    with the person's image height and grows as ``1 + 2 (1 - confidence)``."""
    confidence_visible: float = 0.9
    confidence_jitter: float = 0.05
    self_occlusion_tolerance_mm: float = 120.0
    """A joint deeper than the visible surface by more than this is self-occluded."""
    self_occlusion_penalty: float = 0.3
    other_occlusion_penalty: float = 0.55
    miss_prob_occluded: float = 0.5
    """Probability that a joint hidden by another person is not reported at all."""
    swap_prob: float = 0.02
    """Per detection: probability that one left/right limb pair is swapped."""
    false_positives_per_view: float = 0.04
    """Mean ghost detections per view and frame (one view only, low confidence)."""
    border_drop_fraction: float = 0.4
    """A person with more than this fraction of keypoints outside the image is missed."""
    occluded_drop_fraction: float = 0.75
    """A person with more than this fraction of keypoints hidden by others is missed."""
    regressor_pose_sigma: float = 0.08
    """Axis-angle noise (rad) per body joint of the monocular SMPL prediction."""
    regressor_root_sigma: float = 0.05
    regressor_betas_sigma: float = 0.3
    regressor_depth_flip_prob: float = 0.15
    """Per limb and detection: probability its depth is mirrored through the image plane."""
    regressor_cam_sigma: float = 0.01
    bbox_scale: float = 1.2
    """SPIN-style square crop: this many times the larger side of the 2D joint box."""


SWAP_GROUPS = (
    ("left_wrist", "right_wrist"),
    ("left_elbow", "right_elbow"),
    ("left_ankle", "right_ankle"),
    ("left_knee", "right_knee"),
)
# Points that go with a swapped joint (same side), where the layout has them.
SWAP_FOLLOWERS: dict[str, tuple[str, ...]] = {
    "ankle": ("big_toe", "small_toe", "heel", "foot_index"),
    "wrist": ("pinky", "index", "thumb") + tuple(f"hand_{p}" for p in _HAND_POINTS),
}


def swap_indices(joint_set: JointSet, left: str, right: str) -> tuple[np.ndarray, np.ndarray]:
    """Indices of ``left`` and ``right`` and of the points that follow them
    (:data:`SWAP_FOLLOWERS`), paired left to right, for one left/right confusion."""
    pairs = [(left, right)]
    part = left.removeprefix("left_")
    pairs += [(f"left_{x}", f"right_{x}") for x in SWAP_FOLLOWERS.get(part, ())]
    pairs = [(a, b) for a, b in pairs if a in joint_set.index and b in joint_set.index]
    return (
        np.array([joint_set.index[a] for a, _ in pairs]),
        np.array([joint_set.index[b] for _, b in pairs]),
    )


_LIMBS = tuple(
    (SMPL24.index[a], SMPL24.index[b])
    for a, b in (
        ("left_shoulder", "left_elbow"),
        ("left_elbow", "left_wrist"),
        ("right_shoulder", "right_elbow"),
        ("right_elbow", "right_wrist"),
        ("left_hip", "left_knee"),
        ("left_knee", "left_ankle"),
        ("right_hip", "right_knee"),
        ("right_knee", "right_ankle"),
    )
)


def occlusion_confidence(
    rng: np.random.Generator,
    self_occluded: np.ndarray,
    other_occluded: np.ndarray,
    noise: DetectorNoise,
) -> np.ndarray:
    """(P, K) occlusion flags -> (P, K) confidences in (0, 1)."""
    c = (
        noise.confidence_visible
        - noise.self_occlusion_penalty * self_occluded
        - noise.other_occlusion_penalty * other_occluded
        + rng.normal(0, noise.confidence_jitter, self_occluded.shape)
    )
    return np.clip(c, 0.05, 0.99)


def simulate_keypoints(
    rng: np.random.Generator,
    camera: Camera,
    true_2d: np.ndarray,
    self_occluded: np.ndarray,
    other_occluded: np.ndarray,
    noise: DetectorNoise,
    *,
    joint_set: JointSet = COCO17,
    defined: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Noisy detections of the people one camera sees, in ``joint_set`` (K keypoints).

    Args:
        true_2d: (P, K, 2) true keypoint pixels (distortion included).
        self_occluded, other_occluded: (P, K) bool.
        defined: (K,) bool, the keypoints the body model gives (default all); the
            border and occlusion fractions that drop a person count only these.
    Returns:
        keypoints (P, K, 3) x, y, confidence (0 and NaN x, y where missed) and
        detected (P,) bool: people the detector reports at all.
    """
    P, K = true_2d.shape[:2]
    defined = np.ones(K, bool) if defined is None else np.asarray(defined, bool)
    inside = (
        np.isfinite(true_2d).all(-1)
        & (true_2d[..., 0] >= 0)
        & (true_2d[..., 0] < camera.width)
        & (true_2d[..., 1] >= 0)
        & (true_2d[..., 1] < camera.height)
    )
    detected = (1 - inside[:, defined].mean(1) <= noise.border_drop_fraction) & (
        (other_occluded & inside)[:, defined].mean(1) <= noise.occluded_drop_fraction
    )
    conf = occlusion_confidence(rng, self_occluded, other_occluded, noise)
    heights = np.array(
        [np.ptp(p[np.isfinite(p[:, 1]), 1]) if np.isfinite(p[:, 1]).any() else 1.0 for p in true_2d]
    )
    sigma = noise.pixel_sigma * np.maximum(heights, 50.0)[:, None] / 400.0 * (1 + 2 * (1 - conf))
    xy = true_2d + rng.normal(0, 1, true_2d.shape) * sigma[..., None]
    missed = ~inside | (other_occluded & (rng.uniform(size=conf.shape) < noise.miss_prob_occluded))
    conf = np.where(missed, 0.0, conf)
    xy[missed] = np.nan
    kp = np.concatenate([xy, conf[..., None]], -1)
    for p in range(P):  # occasional left/right confusion of one limb pair
        if rng.uniform() < noise.swap_prob:
            ia, ib = swap_indices(joint_set, *SWAP_GROUPS[rng.integers(len(SWAP_GROUPS))])
            kp[p, np.r_[ia, ib]] = kp[p, np.r_[ib, ia]]
    return kp, detected


def square_bbox(points_2d: np.ndarray, scale: float) -> np.ndarray:
    """(N, K, 2) pixels -> (N, 4) square crops around the finite points, ``scale`` x larger."""
    lo = np.nanmin(points_2d, axis=1)
    hi = np.nanmax(points_2d, axis=1)
    centre = 0.5 * (lo + hi)
    half = 0.5 * scale * np.max(hi - lo, axis=1, keepdims=True)
    half = np.maximum(half, 8.0)
    return np.concatenate([centre - half, centre + half], 1)


def _align_matrices(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """(N, 3), (N, 3) unit vectors -> (N, 3, 3) minimal rotations taking src to dst."""
    axis = np.cross(src, dst)
    s = np.linalg.norm(axis, axis=-1, keepdims=True)
    angle = np.arctan2(s[:, 0], (src * dst).sum(-1))
    axis = np.where(s > 1e-9, axis / np.maximum(s, 1e-12), 0.0)
    rv = torch.as_tensor(axis * angle[:, None], dtype=torch.float64)
    return axis_angle_to_matrix(rv).numpy()


def flip_limb_depths(
    local_rot: np.ndarray, rest_joints: np.ndarray, flip: np.ndarray, model: BodyModel
) -> np.ndarray:
    """Mirror chosen limbs through the image plane, keeping every joint's x, y.

    Args:
        local_rot: (N, 24, 3, 3) local rotations, root in the camera frame.
        rest_joints: (N, 24, 3) rest joints (metres).
        flip: (N, len(_LIMBS)) bool, which limbs to mirror per detection.
    Returns:
        (N, 24, 3, 3) new local rotations.
    """
    local = local_rot.copy()
    parents = model.parents
    rest_t = torch.as_tensor(rest_joints, dtype=torch.float64)
    for li, (a, b) in enumerate(_LIMBS):
        rows = np.flatnonzero(flip[:, li])
        if rows.size == 0:
            continue
        pos, T = rigid_chain(torch.as_tensor(local[rows]), rest_t[rows], model.tree)
        pos, G = pos.numpy(), T[..., :3, :3].numpy()
        bone = pos[:, b] - pos[:, a]
        bone /= np.linalg.norm(bone, axis=-1, keepdims=True)
        mirrored = bone * np.array([1.0, 1.0, -1.0])
        delta = _align_matrices(bone, mirrored)
        Ga_new = delta @ G[:, a]
        local[rows, a] = np.swapaxes(G[:, parents[a]], -1, -2) @ Ga_new
        local[rows, b] = np.swapaxes(Ga_new, -1, -2) @ G[:, b]  # child keeps its direction
    return local


def rotmat_to_axis_angle(R: np.ndarray) -> np.ndarray:
    """(..., 3, 3) -> (..., 3) axis-angle."""
    return Rotation.from_matrix(R.reshape(-1, 3, 3)).as_rotvec().reshape(R.shape[:-2] + (3,))


def simulate_regressor(
    rng: np.random.Generator,
    camera: Camera | np.ndarray,
    pose_world: np.ndarray,
    betas: np.ndarray,
    true_joints_2d: np.ndarray,
    model: BodyModel,
    noise: DetectorNoise,
) -> dict[str, np.ndarray]:
    """Monocular SMPL predictions for N detections in one camera (or in many: pass
    ``camera`` as (N, 3, 3) world-to-camera rotations, one per detection).

    Args:
        pose_world: (N, 24, 3) true pose, root orientation in the world frame.
        betas: (N, 10) true shape.
        true_joints_2d: (N, 24, 2) true SMPL joints in this view, pixels.
    Returns:
        ``smpl_pose`` (N, 72) root in the camera frame, ``smpl_betas`` (N, 10),
        ``cam_weak`` (N, 3), ``bbox`` (N, 4).
    """
    n = pose_world.shape[0]
    pose = pose_world.copy()
    pose[:, 1:] += rng.normal(0, noise.regressor_pose_sigma, pose[:, 1:].shape)
    pose[:, 0] += rng.normal(0, noise.regressor_root_sigma, (n, 3))
    rot = axis_angle_to_matrix(torch.as_tensor(pose, dtype=torch.float64)).numpy()
    R = camera.R if isinstance(camera, Camera) else np.asarray(camera, float)
    rot[:, 0] = R @ rot[:, 0]  # the regressor sees the body in its camera's frame
    pred_betas = betas + rng.normal(0, noise.regressor_betas_sigma, betas.shape)
    rest = model.rest_joints(torch.as_tensor(pred_betas, dtype=torch.float32)).double().numpy()
    flip = rng.uniform(size=(n, len(_LIMBS))) < noise.regressor_depth_flip_prob
    rot = flip_limb_depths(rot, rest, flip, model)
    pred_pose = rotmat_to_axis_angle(rot)
    joints_m = (
        model.joints(torch.as_tensor(pred_pose, dtype=torch.float32), torch.as_tensor(pred_betas))
        .double()
        .numpy()
    )
    bbox = square_bbox(true_joints_2d, noise.bbox_scale)
    cam = fit_weak_perspective(joints_m, true_joints_2d, bbox)
    cam[:, 0] *= 1 + rng.normal(0, noise.regressor_cam_sigma, n)
    cam[:, 1:] += rng.normal(0, noise.regressor_cam_sigma, (n, 2))
    return {
        "smpl_pose": pred_pose.reshape(n, 72),
        "smpl_betas": pred_betas,
        "cam_weak": cam,
        "bbox": bbox,
    }
