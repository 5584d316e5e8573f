"""pipeline.mocap: CMU name maps, resampling, derived face points, the SMPL fit to real
motion (its residual is the measurement), and BVH data for the pose prior."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from mvviz.cli import main
from pipeline.joint_sets import COCO17, SMPL24
from pipeline.mocap import (
    CMU_TO_COCO17,
    CMU_TO_SMPL24,
    FitParams,
    fit_clips,
    format_residuals,
    load_mocap_clip,
    resample,
)
from pipeline.pose_prior import load_pose_data, load_prior

CMU = Path(__file__).resolve().parents[2] / "sample_data" / "mocap" / "cmu131"


@pytest.fixture(scope="module")
def walk():
    return load_mocap_clip(CMU / "131_01.bvh", fps=30)


def test_clip_maps_joints_by_name_and_leaves_the_rest_nan(walk):
    assert walk.num_frames == 249 and walk.source_frames == 994 and walk.fps == 30
    assert walk.activity == "start, walk, stop" and "NSF EIA-0196217" in walk.licence
    ix = {n: i for i, n in enumerate(walk.joint_names)}
    for smpl, bvh in CMU_TO_SMPL24.items():
        np.testing.assert_array_equal(walk.smpl24[:, SMPL24.index[smpl]], walk.skeleton[:, ix[bvh]])
    unmapped = [n for n in SMPL24.names if n not in CMU_TO_SMPL24]
    assert set(unmapped) == {
        "pelvis", "spine1", "spine2", "spine3", "left_collar", "right_collar", "left_hand",
        "right_hand",
    }  # fmt: skip
    assert np.isnan(walk.smpl24[:, [SMPL24.index[n] for n in unmapped]]).all()
    for coco, bvh in CMU_TO_COCO17.items():
        np.testing.assert_array_equal(walk.coco17[:, COCO17.index[coco]], walk.skeleton[:, ix[bvh]])
    assert len(CMU_TO_COCO17) == 12 and np.isfinite(walk.coco17).all()


def test_derived_face_points_face_forward(walk):
    c = walk.coco17
    head = walk.smpl24[:, SMPL24.index["head"]]
    mid_ear = 0.5 * (c[:, COCO17.index["left_ear"]] + c[:, COCO17.index["right_ear"]])
    fwd = c[:, COCO17.index["nose"]] - mid_ear
    # the nose is ahead of the ears in the walking direction (the subject walks forward)
    pelvis_v = np.gradient(walk.skeleton[:, walk.joint_names.index("Hips"), :2], axis=0)
    moving = np.linalg.norm(pelvis_v, axis=1) > 20  # mm per frame at 30 fps: walking
    assert moving.sum() > 50
    cos = (fwd[moving, :2] * pelvis_v[moving]).sum(1) / (
        np.linalg.norm(fwd[moving, :2], axis=1) * np.linalg.norm(pelvis_v[moving], axis=1)
    )
    assert np.median(cos) > 0.8
    ears = np.linalg.norm(c[:, COCO17.index["left_ear"]] - c[:, COCO17.index["right_ear"]], axis=1)
    np.testing.assert_allclose(ears, 148.0, atol=1e-6)
    assert (c[:, COCO17.index["left_eye"], 2] > c[:, COCO17.index["nose"], 2]).mean() > 0.95
    assert np.linalg.norm(c[:, COCO17.index["nose"]] - head, axis=1).max() < 130


def test_resample():
    t = np.arange(121, dtype=float)[:, None] * np.array([[1.0, -2.0, 0.5]])  # linear in time
    np.testing.assert_array_equal(resample(t, 120, 30), t[::4])
    r = resample(t, 120, 25)
    assert r.shape == (26, 3)
    np.testing.assert_allclose(r, (np.arange(26) * 120 / 25)[:, None] * [[1.0, -2.0, 0.5]])
    np.testing.assert_array_equal(resample(t, 50, 50), t)


def test_fit_to_real_motion_reports_the_residual_per_joint(walk):
    hop = load_mocap_clip(CMU / "131_03.bvh", fps=30)
    clips = [
        replace(c, skeleton=c.skeleton[60:100], smpl24=c.smpl24[60:100], coco17=c.coco17[60:100])
        for c in (walk, hop)
    ]
    fits = fit_clips(clips, params=FitParams(iters=300))
    for f, c in zip(fits, clips, strict=True):
        assert f.clip == c.name
        assert f.pose_rotvecs.shape == (40, 24, 3) and f.betas.shape == (10,)
        assert set(f.residual_by_joint()) == set(CMU_TO_SMPL24)
        np.testing.assert_array_equal(np.isnan(f.residual), np.isnan(c.smpl24[..., 0]))
        groups = f.residual_by_group()
        # measured (300 iterations, whole clips): hips 22-25 mm, neck/head 18-29, shoulders
        # ~19, knees 11-13, elbows 12-14, ankles/feet/wrists 4-8; 13-14 mm over all
        assert groups["all"] < 25, groups
        assert max(groups.values()) < 50, groups
        assert groups["ankles"] < 20 and groups["wrists"] < 20, groups
    assert "hips" in format_residuals(fits)


def test_bvh_as_prior_data_and_the_cli_records_sources(tmp_path):
    poses = load_pose_data(CMU / "131_03.bvh")
    assert poses.shape == (276, 72) and np.isfinite(poses).all()
    out = tmp_path / "p.pt"
    args = ["train-prior", "--data", str(CMU / "131_03.bvh"), "--out", str(out)]
    assert main(args + ["--epochs", "1", "--latent", "4", "--hidden", "16"]) == 0
    info = load_prior(out).info
    (src,) = info["sources"]
    assert src["frames"] == 276 and src["source_frames"] == 1102
    assert src["activity"] == "start, hop, stop" and "NSF" in src["licence"]
    assert 0 < src["fit_residual_mm"] < 25
