"""Realistic 2D detections in any keypoint layout, for the layout-identification tests.

The shipped Shelf sample's ground truth (SMPL-24 joints and COCO-17 keypoints of four
people walking, turning and reaching, mm, z up) gives every point the layouts name:
the COCO points as they are, the others placed from the body's own axes (the top of
the head above the head joint, heels behind and below the ankles, toes ahead of the
foot joint, ...). Projected into the rig's five cameras, with occlusion-free but
realistic confidences: points on the far side of the head (a face seen from behind)
are weak, some points are missed at random. People are seen from the front, the side
and the back, which is what identification has to cope with.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from pipeline.data.joint_sets import COCO17, SMPL24, JointSet
from pipeline.data.scene import load_scene

REPO = Path(__file__).resolve().parents[2]
SAMPLE = REPO / "sample_data" / "shelf_synth"
_FACE = {
    "nose", "left_eye", "right_eye", "left_eye_inner", "left_eye_outer", "right_eye_inner",
    "right_eye_outer", "left_mouth", "right_mouth", "chin",
}  # fmt: skip


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-9)


def body_points(smpl: np.ndarray, coco: np.ndarray) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Every named point of every layout, from SMPL-24 joints and COCO-17 keypoints.

    Args:
        smpl: (N, 24, 3) mm; coco: (N, 17, 3) mm, world z up.
    Returns:
        name -> (N, 3) mm, and (N, 3) the unit facing direction of each body.
    """
    S = {n: smpl[:, i] for i, n in enumerate(SMPL24.names)}
    P = {n: coco[:, i] for i, n in enumerate(COCO17.names)}
    up = np.array([0.0, 0.0, 1.0])
    left = _unit(P["left_shoulder"] - P["right_shoulder"] + P["left_hip"] - P["right_hip"])
    fwd = _unit(np.cross(left, up))
    head_dir = _unit(S["head"] - S["neck"])
    P["neck"] = 0.5 * (P["left_shoulder"] + P["right_shoulder"])
    P["thorax"] = S["neck"]
    P["upper_neck"] = S["neck"] + 0.6 * (S["head"] - S["neck"])
    P["head_top"] = S["head"] + 130.0 * head_dir
    P["chin"] = 0.5 * (S["head"] + P["nose"]) - 30.0 * head_dir
    P["mid_hip"] = 0.5 * (P["left_hip"] + P["right_hip"])
    P["pelvis"] = S["pelvis"]
    P["spine"] = S["spine2"]
    for side, sign in (("left", 1.0), ("right", -1.0)):
        ankle, foot = S[f"{side}_ankle"], S[f"{side}_foot"]
        P[f"{side}_heel"] = ankle - 60.0 * fwd - 40.0 * up
        P[f"{side}_big_toe"] = foot + 50.0 * fwd - 20.0 * sign * left - 20.0 * up
        P[f"{side}_small_toe"] = foot + 30.0 * fwd + 30.0 * sign * left - 20.0 * up
        P[f"{side}_foot_index"] = P[f"{side}_big_toe"]
        eye = P[f"{side}_eye"]
        P[f"{side}_eye_inner"] = eye - 12.0 * sign * left
        P[f"{side}_eye_outer"] = eye + 12.0 * sign * left
        P[f"{side}_mouth"] = P["nose"] - 40.0 * head_dir + 22.0 * sign * left
        hand, wrist = S[f"{side}_hand"], S[f"{side}_wrist"]
        P[f"{side}_index"] = hand + 0.6 * (hand - wrist) - 15.0 * sign * left
        P[f"{side}_pinky"] = hand + 0.4 * (hand - wrist) + 15.0 * sign * left
        P[f"{side}_thumb"] = wrist + 0.8 * (hand - wrist) - 30.0 * sign * left
        for k in range(21):  # wholebody hand points, spread around the hand
            P[f"{side}_hand_{_hand_name(k)}"] = wrist + (0.3 + 0.06 * k) * (hand - wrist)
    for k in range(68):  # wholebody face contour and features, on the face
        angle = np.pi * (k / 67.0 - 0.5)
        P[f"face_{k}"] = (
            P["nose"] + 50.0 * np.sin(angle) * left[:, :] - 40.0 * np.cos(angle) * (head_dir)
        )
    for n in SMPL24.names:  # smpl24 as a 2D layout: its own joints
        P.setdefault(n, S[n])
    return P, fwd


def _hand_name(k: int) -> str:
    if k == 0:
        return "wrist"
    finger = ("thumb", "index", "middle", "ring", "pinky")[(k - 1) // 4]
    return f"{finger}{(k - 1) % 4 + 1}"


def layout_detections(
    js: JointSet,
    *,
    frames: slice = slice(0, 250, 5),
    miss_rate: float = 0.1,
    mirror_views: tuple[int, ...] = (),
    seed: int = 0,
) -> dict[tuple[int, int], list[np.ndarray]]:
    """2D detections of the Shelf sample's people in layout ``js``.

    Returns:
        (view, frame) -> list of (js.num_joints, 3) x, y, confidence per person (OpenPose
        convention: a missed point is 0, 0, 0). Views in ``mirror_views`` are flipped
        left to right, as a mirrored video would be.
    """
    scene = load_scene(SAMPLE)
    gt = scene.gt
    keep = np.isin(gt.frame, np.arange(scene.num_frames)[frames])
    points, fwd = body_points(gt.joints3d[keep], gt.keypoints3d[keep])
    frame_of = gt.frame[keep]
    rng = np.random.default_rng(seed)
    out: dict[tuple[int, int], list[np.ndarray]] = {}
    for v, cam in enumerate(scene.rig):
        X = np.stack([points[n] for n in js.names], 1)  # (N, K, 3)
        uv = cam.project(X.reshape(-1, 3)).reshape(X.shape[0], -1, 2)
        to_cam = _unit(cam.center[None] - points["nose"])
        facing = (fwd * to_cam).sum(-1)  # > 0: the face is towards the camera
        conf = rng.uniform(0.55, 0.95, uv.shape[:2])
        face = np.array([n in _FACE or n.startswith("face_") for n in js.names])
        conf[:, face] = np.where(facing[:, None] > 0.2, conf[:, face], rng.uniform(0.0, 0.25))
        conf[rng.random(conf.shape) < miss_rate] = 0.0
        inside = (uv[..., 0] > 0) & (uv[..., 0] < cam.width) & (uv[..., 1] > 0)
        inside &= uv[..., 1] < cam.height
        conf[~inside] = 0.0
        if v in mirror_views:
            uv[..., 0] = cam.width - uv[..., 0]
        kp = np.concatenate([uv, conf[..., None]], -1)
        kp[conf == 0] = 0.0
        for row, f in enumerate(frame_of):
            if (conf[row] > 0).sum() >= 5:
                out.setdefault((v, int(f)), []).append(kp[row])
    return out


def write_openpose_tree(root: Path, dets: dict[tuple[int, int], list[np.ndarray]], names):
    """Write ``dets`` as OpenPose JSON folders ``root/<camera>/<camera>_<frame>_keypoints.json``."""
    for (v, f), people in dets.items():
        path = root / names[v] / f"{names[v]}_{f:012d}_keypoints.json"
        path.parent.mkdir(parents=True, exist_ok=True)
        body = {"people": [{"pose_keypoints_2d": p.reshape(-1).tolist()} for p in people]}
        path.write_text(json.dumps(body))
