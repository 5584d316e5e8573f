"""Synthetic people for stage tests: SMPL-24 skeletons of the open body model in the world."""

from __future__ import annotations

import numpy as np
import torch

from pipeline.body.model import load_body_model
from pipeline.importers.calibration import read_voxelpose_calibration
from pipeline.synth.motion import root_to_world
from tests.conftest import REPO

SHELF = REPO / "sample_data" / "rigs" / "shelf_voxelpose.json"
CAMPUS = REPO / "sample_data" / "rigs" / "campus_voxelpose.json"


def shelf_rig():
    return read_voxelpose_calibration(SHELF)


def campus_rig():
    return read_voxelpose_calibration(CAMPUS)


def standing_people(positions_mm: np.ndarray, headings: np.ndarray, seed: int = 0) -> np.ndarray:
    """(P, 2) floor positions, (P,) headings -> (P, 24, 3) SMPL joints, world mm, feet near z=0."""
    model = load_body_model()
    rng = np.random.default_rng(seed)
    P = len(positions_mm)
    pose = np.zeros((P, 24, 3))
    pose[:, 1:] = rng.normal(0, 0.1, (P, 23, 3))
    pose[:, 0] = root_to_world(np.asarray(headings, float), np.zeros((P, 3)))
    betas = rng.normal(0, 1, (P, 10))
    with torch.no_grad():
        j = model.joints(torch.as_tensor(pose).float(), torch.as_tensor(betas).float()).numpy()
    j = j * 1000
    j[..., :2] += np.asarray(positions_mm)[:, None] - j[:, :1, :2]
    j[..., 2] -= j[..., 2].min(1, keepdims=True) - 60
    return j


def observe(rig, joints: np.ndarray, *, sigma_px: float = 2.0, seed: int = 0):
    """Project people into every view where they are inside the image.

    Returns views (n,), keypoints (n, 24, 3), person (n,) in a shuffled order.
    """
    rng = np.random.default_rng(seed)
    views, kps, person = [], [], []
    for v, cam in enumerate(rig):
        uv = cam.project(joints)  # (P, 24, 2)
        for p in range(joints.shape[0]):
            inside = (
                np.isfinite(uv[p]).all(-1)
                & (uv[p, :, 0] >= 0) & (uv[p, :, 0] < cam.width)
                & (uv[p, :, 1] >= 0) & (uv[p, :, 1] < cam.height)
            )  # fmt: skip
            if inside.mean() < 0.6:
                continue
            kp = np.concatenate([uv[p] + rng.normal(0, sigma_px, uv[p].shape), np.ones((24, 1))], 1)
            kp[~inside] = (np.nan, np.nan, 0.0)
            views.append(v)
            kps.append(kp)
            person.append(p)
    order = rng.permutation(len(views))
    return np.array(views)[order], np.array(kps)[order], np.array(person)[order]
