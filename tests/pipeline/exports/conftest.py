"""Export fixtures: a tiny fitted run (campus rig, 2 people, 12 frames, no video), the
same run with gaps cut into track 1, and synthetic fits with large rotations."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from pipeline.body.model import load_body_model
from pipeline.config import PipelineConfig
from pipeline.data.joint_sets import get_joint_set
from pipeline.data.scene import load_scene
from pipeline.fit.smpl import SmplFit
from pipeline.importers.calibration import read_voxelpose_calibration
from pipeline.results.store import PipelineResults
from pipeline.run.pipeline import run_or_load
from pipeline.synth.motion import root_to_world
from pipeline.synth.scene_gen import SynthConfig, write_synth_scene
from tests.conftest import REPO

CAMPUS = REPO / "sample_data" / "rigs" / "campus_voxelpose.json"
GAPS = (0, 1, 5, 6, 11)
"""Frames of track 1 cut out of the gappy run: its start, an interior gap, its end."""


@pytest.fixture(scope="session")
def model():
    return load_body_model()


@pytest.fixture(scope="session")
def fitted_run(tmp_path_factory, model):
    """(scene, results): 2 people, 12 frames, with both SMPL stages."""
    root = tmp_path_factory.mktemp("exports") / "scene"
    config = SynthConfig(num_people=2, num_frames=12, seed=3, render_video=False)
    write_synth_scene(root, read_voxelpose_calibration(CAMPUS), model, config, progress=False)
    scene = load_scene(root)
    results, _ = run_or_load(scene, PipelineConfig(), model, progress=False)
    assert results.num_tracks >= 2 and results.smpl_vae is not None
    return scene, results


def cut_fit(fit: SmplFit, k: int, frames) -> SmplFit:
    """``fit`` with track ``k`` absent at ``frames`` (NaN, as the fit leaves absent frames)."""
    arrays = {n: np.array(getattr(fit, n), float) for n in
              ("pose_rotvecs", "transl", "joints", "keypoints", "residual")}  # fmt: skip
    for a in arrays.values():
        a[k, list(frames)] = np.nan
    return dataclasses.replace(fit, **arrays)


@pytest.fixture(scope="session")
def gappy_results(fitted_run) -> PipelineResults:
    """The fitted run with track 1 missing at :data:`GAPS` in every stage."""
    _, res = fitted_run
    cut = {}
    for name in ("track_raw", "track_forward", "track_smoothed"):
        a = np.array(getattr(res, name), float)
        a[1, list(GAPS)] = np.nan
        cut[name] = a
    return dataclasses.replace(
        res, smpl=cut_fit(res.smpl, 1, GAPS), smpl_vae=cut_fit(res.smpl_vae, 1, GAPS), **cut
    )


def synthetic_fit(model, *, num_tracks=2, num_frames=6, seed=0, scale=1.2) -> SmplFit:
    """Random poses (every joint up to ~``scale`` rad, root any turn), random betas and
    translations, joints by the model: a fit the writers cannot tell from a real one."""
    rng = np.random.default_rng(seed)
    K, F = num_tracks, num_frames
    pose = rng.normal(0, scale / 2, (K, F, 24, 3))
    heading = rng.uniform(-np.pi, np.pi, K * F)
    pose[:, :, 0] = root_to_world(heading, rng.normal(0, 0.5, (K * F, 3))).reshape(K, F, 3)
    betas = rng.normal(0, 1, (K, 10))
    transl = rng.normal(0, 1500, (K, F, 3))
    with torch.no_grad():
        j = (
            model.joints(
                torch.as_tensor(pose.reshape(K * F, 24, 3)).float(),
                torch.as_tensor(np.repeat(betas, F, 0)).float(),
            )
            .double()
            .numpy()
        )
    joints = 1000 * j.reshape(K, F, 24, 3) + transl[:, :, None]
    T = get_joint_set("smpl24").num_joints
    return SmplFit(
        joint_set="smpl24", pose_rotvecs=pose, betas=betas, transl=transl, joints=joints,
        keypoints=joints.copy(), residual=np.zeros((K, F, T)), seconds=0.0, stage="smpl",
        model=model,
    )  # fmt: skip
