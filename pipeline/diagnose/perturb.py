"""Known faults put into a good scene, so the diagnoses can be checked against the truth:
a camera that lags (whole or sub-frame), a camera rotated or moved after calibration.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.spatial.transform import Rotation

from pipeline.data.cameras import CameraRig
from pipeline.data.scene import Detections, Scene


def delay_camera(scene: Scene, camera: str, frames: float) -> Scene:
    """The scene as if ``camera`` recorded ``frames`` late (its frame g shows time g - frames).

    Whole frames move that camera's rows; a fraction interpolates its 2D between the two
    frames around g - frames, person by person (``gt_person_id`` says who is who, so a
    sub-frame delay needs a synthetic scene). Rows shifted out of the clip are dropped.
    """
    det = scene.detections
    v = scene.rig.index_of(camera)
    mine = det.view == v
    whole = float(frames).is_integer()
    if whole:
        shifted = det.take(mine)
        shifted = dataclasses.replace(shifted, frame=shifted.frame + int(frames))
    else:
        if det.gt_person_id is None:
            raise ValueError("a sub-frame delay needs gt_person_id (a synthetic scene)")
        shifted = _interpolated_rows(det.take(mine), float(frames))
    keep = (shifted.frame >= 0) & (shifted.frame < scene.num_frames)
    others = det.take(~mine)
    merged = _concat(others, shifted.take(keep))
    return dataclasses.replace(scene, detections=merged)


def _interpolated_rows(det: Detections, delay: float) -> Detections:
    """Rows at frame g holding each person's 2D at time g - delay (linear)."""
    lo = int(np.floor(delay))
    a = delay - lo  # the row at g mixes times g - lo - 1 (weight a) and g - lo (1 - a)
    pairs = zip(det.frame, det.gt_person_id, strict=True)
    key = {(int(f), int(p)): i for i, (f, p) in enumerate(pairs)}
    rows_a, rows_b, frames = [], [], []
    for (f, p), i in key.items():
        j = key.get((f - 1, p))
        if p < 0 or j is None:
            continue
        rows_a.append(j)  # time f - 1
        rows_b.append(i)  # time f
        frames.append(f + lo)  # the row at g = f + lo shows time f - a ... see below
    ia, ib = np.array(rows_a, int), np.array(rows_b, int)
    kp_a, kp_b = det.keypoints[ia], det.keypoints[ib]
    # time g - delay = (f + lo) - (lo + a) = f - a: between f - 1 (weight a) and f.
    kp = a * kp_a + (1 - a) * kp_b
    kp[..., 2] = np.minimum(kp_a[..., 2], kp_b[..., 2])
    out = det.take(ib)
    return dataclasses.replace(out, frame=np.array(frames, int), keypoints=kp)


def _concat(a: Detections, b: Detections) -> Detections:
    kw = {}
    for f in dataclasses.fields(Detections):
        x, y = getattr(a, f.name), getattr(b, f.name)
        kw[f.name] = None if x is None or y is None else np.concatenate([x, y])
    return Detections(**kw)


def perturb_camera_pose(
    scene: Scene,
    camera: str,
    *,
    rotation_deg: float = 0.0,
    axis: tuple[float, float, float] = (0.0, 0.0, 1.0),
    translation_mm: tuple[float, float, float] = (0.0, 0.0, 0.0),
) -> Scene:
    """The scene with ``camera``'s calibration wrong: its recorded pose rotated about its
    own centre by ``rotation_deg`` (about world ``axis``) and moved by ``translation_mm``
    (world), while its 2D stays as recorded."""
    v = scene.rig.index_of(camera)
    cam = scene.rig[v]
    dR = Rotation.from_rotvec(np.radians(rotation_deg) * np.asarray(axis, float)
                              / np.linalg.norm(axis)).as_matrix()  # fmt: skip
    centre = cam.center + np.asarray(translation_mm, float)
    R = cam.R @ dR.T  # world axes rotated by dR, seen from the camera
    t = -R @ centre
    cams = list(scene.rig)
    cams[v] = dataclasses.replace(cam, R=R, t=t)
    return dataclasses.replace(scene, rig=CameraRig(tuple(cams)))
