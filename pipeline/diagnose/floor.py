"""The floor and "up", from the people's feet: is the world z-up with the floor at z = 0?

People stand upright, so the mean of their shoulders-minus-ankles vectors is a first
"up"; the floor is then the plane through each person's lower ankle while it is planted
(its speed in the slowest third), fitted robustly, its normal the final "up" when the
feet cover enough floor to tilt a plane (else the body axis stays "up"), shifted down by
the ankle joint's height above the sole (``ANKLE_HEIGHT_MM``). A scene whose up is
not +z or whose floor is not at 0 is re-expressed by one rigid transform applied to
everything 3D in it (cameras, ground truth incl. SMPL parameters, reference tracks);
its 2D is untouched.
"""

from __future__ import annotations

import dataclasses
import warnings
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial.transform import Rotation

from pipeline.body.arrays import BodyModelData, body_data
from pipeline.data.cameras import CameraRig
from pipeline.data.references import ReferenceTrack
from pipeline.data.scene import GroundTruth, Scene

if TYPE_CHECKING:
    from pipeline.body.model import BodyModel

ANKLE_HEIGHT_MM = 90.0  # ankle joint above the sole, standing; detectors' ankles differ by
# +-25 mm (the open model's COCO ankle stands at ~105 mm, OpenPose's on the demo at ~75)
UP_TOLERANCE_DEG = {"feet plane": 5.0, "body axis": 20.0}
"""How far from +z "up" may be before the scene is called not z-up: a plane through
planted feet is good to a degree or two; the mean body axis leans with the posture (on
Pose2Sim's real trials, whose floor plane is level to ~1 degree, the body axis is 7-10
degrees off)."""
SNAP_DEG = 20.0  # a fix snaps "up" to the nearest world axis within this
FLOOR_TOLERANCE_MM = 100.0
"""Ankle keypoints sit at different heights by detector (the open model's COCO ankle
~105 mm above the sole, OpenPose's on Pose2Sim's trials ~20 mm above their z = 0 floor),
so only a floor this far from 0 is reported."""
MIN_FOOT_POINTS = 30
MIN_FLOOR_EXTENT_MM = 300.0  # std of the planted feet across the floor, both ways


@dataclass(frozen=True, eq=False)
class FloorEstimate:
    """The floor plane ``up . x = height_mm`` (world mm) and what it says of the scene."""

    up: np.ndarray  # (3,) unit normal, pointing from the feet to the head
    height_mm: float  # the floor's signed distance from the origin along ``up``
    angle_to_z_deg: float
    points: int  # planted-foot samples behind it
    spread_mm: float  # robust spread of those samples about the plane
    method: str = "feet plane"  # or "body axis" (the feet did not cover enough floor)

    @property
    def z_up(self) -> bool:
        return self.angle_to_z_deg <= UP_TOLERANCE_DEG[self.method]

    @property
    def snapped_up(self) -> np.ndarray:
        """The signed world axis nearest to ``up`` if within ``SNAP_DEG``, else ``up``: a
        scene exported y-up or z-down is off by a whole axis, not by a noisy tilt."""
        k = int(np.argmax(np.abs(self.up)))
        axis = np.zeros(3)
        axis[k] = np.sign(self.up[k])
        angle = np.degrees(np.arccos(np.clip(abs(self.up[k]), -1, 1)))
        return axis if angle <= SNAP_DEG else self.up

    @property
    def floor_at_zero(self) -> bool:
        return abs(self.height_mm) <= FLOOR_TOLERANCE_MM

    @property
    def ok(self) -> bool:
        return self.z_up and self.floor_at_zero

    def to_dict(self) -> dict:
        return {
            "up": [round(float(v), 4) for v in self.up],
            "angle_to_z_deg": round(self.angle_to_z_deg, 2),
            "floor_height_mm": round(self.height_mm, 1),
            "z_up": bool(self.z_up),
            "floor_at_zero": bool(self.floor_at_zero),
            "samples": int(self.points),
            "spread_mm": round(self.spread_mm, 1),
            "method": self.method,
        }

    def fix_transform(self) -> np.ndarray:
        """(4, 4) world -> world' with :attr:`snapped_up` on +z and the floor at z' = 0."""
        up = self.snapped_up
        T = np.eye(4)
        T[:3, :3] = level_rotation(up)
        # The floor's height along the snapped axis: the plane up . x = h meets it there.
        T[2, 3] = -self.height_mm / max(float(up @ self.up), 1e-6)
        return T


def level_rotation(up: np.ndarray) -> np.ndarray:
    """(3, 3) rotation taking unit ``up`` to +z that turns the scene as little as possible
    about the vertical: world x stays in the x-z plane (x' is world x made horizontal;
    world y when x is vertical). So a z-down scene gets a half turn about x and a y-up
    one a quarter turn about x, exactly, whatever the noise in ``up``."""
    z = up / np.linalg.norm(up)
    ref = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = ref - (ref @ z) * z
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(z, x), z])  # rows: world' axes in world coordinates


def _named(names: list[str], word: str) -> list[int]:
    return [i for i, n in enumerate(names) if word in n]


def estimate_floor(tracks_mm: np.ndarray, joint_names: list[str]) -> FloorEstimate | None:
    """From (K, F, J, 3) tracks (e.g. RTS-smoothed) in a joint set with shoulders and
    ankles; None when there are too few planted feet to tell."""
    shoulders, ankles = _named(joint_names, "shoulder"), _named(joint_names, "ankle")
    if len(shoulders) < 2 or len(ankles) < 2:
        return None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # frames a track does not cover
        body = np.nanmean(tracks_mm[:, :, shoulders], 2) - np.nanmean(tracks_mm[:, :, ankles], 2)
    body = body.reshape(-1, 3)
    body = body[np.isfinite(body).all(1)]
    if len(body) < MIN_FOOT_POINTS:
        return None
    up = body.mean(0)
    up /= np.linalg.norm(up)
    feet = _planted_feet(tracks_mm[:, :, ankles], up)
    if len(feet) < MIN_FOOT_POINTS:
        return None
    body_up, method = up, "feet plane"
    for _ in range(3):  # plane through the planted ankles, refined without the outliers
        h = feet @ up
        keep = np.abs(h - np.median(h)) < 3 * max(_mad(h), 10.0)
        centred = feet[keep] - feet[keep].mean(0)
        _, sv, vt = np.linalg.svd(centred, full_matrices=False)
        if sv[1] / np.sqrt(keep.sum()) < MIN_FLOOR_EXTENT_MM:
            # Feet in one spot (someone standing, balancing): the plane's tilt is not
            # determined by them; the body axis is the better "up".
            up, method = body_up, "body axis"
            break
        up = vt[-1] if vt[-1] @ up > 0 else -vt[-1]
    h = feet[keep] @ up
    angle = float(np.degrees(np.arccos(np.clip(up[2], -1, 1))))
    height = float(np.median(h) - ANKLE_HEIGHT_MM)
    return FloorEstimate(up, height, angle, int(keep.sum()), _mad(h), method)


def _mad(x: np.ndarray) -> float:
    return float(1.4826 * np.median(np.abs(x - np.median(x))))


def _planted_feet(ankles: np.ndarray, up: np.ndarray) -> np.ndarray:
    """(K, F, A, 3) ankle tracks -> (n, 3) positions of each person's lower ankle (along
    ``up``: a raised foot, as in a balance trial, is never the floor) while it is in the
    slowest third of its speeds (a planted foot)."""
    h = np.where(np.isfinite(ankles).all(-1), ankles @ up, np.inf)  # (K, F, A)
    low = np.argmin(h, axis=-1)  # (K, F)
    foot = np.take_along_axis(ankles, low[..., None, None], axis=2)[:, :, 0]  # (K, F, 3)
    speed = np.linalg.norm(np.diff(foot, axis=1), axis=-1)  # (K, F-1)
    pos = foot[:, 1:]
    ok = np.isfinite(speed) & np.isfinite(pos).all(-1)
    if not ok.any():
        return np.zeros((0, 3))
    slow = ok & (speed <= np.percentile(speed[ok], 33))
    return pos[slow]


# --------------------------------------------------------------------------- the fix


def transform_scene(
    scene: Scene, T: np.ndarray, model: BodyModel | BodyModelData | None = None
) -> Scene:
    """The scene re-expressed in world' = T world (a rigid (4, 4), mm): cameras, ground
    truth (joints, keypoints, and SMPL root orientation and translation, which needs the
    body model when the truth has SMPL parameters) and reference tracks."""
    R, t = T[:3, :3], T[:3, 3]

    def points(x: np.ndarray) -> np.ndarray:
        return x @ R.T + t

    cams = [
        dataclasses.replace(c, R=c.R @ R.T, t=c.t - c.R @ R.T @ t) for c in scene.rig
    ]  # camera' = camera o T^-1
    gt = scene.gt
    if gt is not None:
        gt = _transform_gt(gt, R, t, points, model)
    refs = {
        k: ReferenceTrack(r.name, points(r.joints), r.source) for k, r in scene.references.items()
    }
    return dataclasses.replace(scene, rig=CameraRig(tuple(cams)), gt=gt, references=refs)


def _transform_gt(
    gt: GroundTruth, R, t, points, model: BodyModel | BodyModelData | None
) -> GroundTruth:
    kw = {"joints3d": points(gt.joints3d)}
    if gt.keypoints3d is not None:
        kw["keypoints3d"] = points(gt.keypoints3d)
    if gt.smpl_pose is not None and gt.transl is not None:
        if model is None:
            raise ValueError("transforming SMPL ground truth needs the body model")
        pose = gt.smpl_pose.copy()
        pose[:, :3] = (Rotation.from_matrix(R) * Rotation.from_rotvec(pose[:, :3])).as_rotvec()
        # The root turns about the rest pelvis j0 (metres), not the origin:
        # R (M(pose) + transl) + t = M(pose') + R transl + t + 1000 (R j0 - j0).
        j0 = 1000.0 * body_data(model).rest_joints(gt.smpl_betas)[:, 0]
        kw["smpl_pose"] = pose
        kw["transl"] = gt.transl @ R.T + t + j0 @ R.T - j0
    return dataclasses.replace(gt, **kw)
