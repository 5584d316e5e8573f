"""Shared test fixtures: paths to the repository and its real rigs, a tiny body model."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
# the real Shelf/Campus rigs, shipped byte-identical to ../shared/data/calibration
RIGS = REPO / "sample_data" / "rigs"
SHELF_CALIB = RIGS / "shelf_voxelpose.json"
CAMPUS_CALIB = RIGS / "campus_voxelpose.json"
# real captures with peers' results, beside the repository (never shipped): tests that
# read them skip when absent; MVVIZ_SHARED_DATA points elsewhere
SHARED_DATA = Path(os.environ.get("MVVIZ_SHARED_DATA", REPO.parent / "shared" / "data"))
SHELF_REAL = SHARED_DATA / "shelf_real"


def tiny_body_model_arrays(seed: int = 0) -> dict[str, np.ndarray]:
    """A small SMPL-layout model: 24 joints on SMPL's tree, 8 vertices per joint.

    Each joint owns a little cube of vertices around its rest position, skinned rigidly
    to that joint, and its regressor is the mean of its own cube (so the cube's centre
    is the joint in every pose).
    """
    from pipeline.data.joint_sets import SMPL24_PARENTS

    rng = np.random.default_rng(seed)
    parents = np.array(SMPL24_PARENTS)
    joints = np.zeros((24, 3))
    for j in range(1, 24):
        joints[j] = joints[parents[j]] + rng.normal(0, 0.15, 3)
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]) * 0.02
    v = (joints[:, None] + corners[None]).reshape(-1, 3)
    weights = np.kron(np.eye(24), np.ones((8, 1)))  # (192, 24)
    J_reg = np.kron(np.eye(24), np.ones((1, 8)) / 8)  # cube centre = joint
    shapedirs = rng.normal(0, 0.01, (v.shape[0], 3, 10))
    faces = np.array([[0, 1, 2], [1, 3, 2]])
    faces = (faces[None] + 8 * np.arange(24)[:, None, None]).reshape(-1, 3)
    kintree = np.stack([parents, np.arange(24)])
    return {
        "v_template": v,
        "shapedirs": shapedirs,
        "posedirs": np.zeros((v.shape[0], 3, 207)),
        "J_regressor": J_reg,
        "weights": weights,
        "kintree_table": kintree,
        "faces": faces,
    }


@pytest.fixture
def tiny_model_arrays():
    return tiny_body_model_arrays()
