"""Bone scales on top of the shape space: the keypoints, joints, mesh and exported
skeletons of a scaled body agree, and the fit recovers proportions the betas cannot."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from pipeline.body.arrays import body_data, scale_bones_np
from pipeline.body.kinematics import (
    SCALED_BONES,
    bone_scale_matrix,
    keypoint_buffers,
    predict_targets,
)
from pipeline.body.model import BodyModel, load_body_model
from pipeline.core.rotations import axis_angle_to_matrix
from pipeline.data.joint_sets import SMPL24
from pipeline.data.scene import load_scene
from pipeline.fit.smpl import FitParams, SmplFit, fit_sequence
from tests.conftest import REPO

J = SMPL24.index


@pytest.fixture(scope="module")
def model() -> BodyModel:
    return load_body_model()


def random_bodies(n: int, seed: int):
    g = torch.Generator().manual_seed(seed)
    pose = torch.randn(n, 24, 3, generator=g) * 0.3
    betas = torch.randn(n, 10, generator=g)
    scales = torch.exp(torch.randn(n, 24, generator=g) * 0.1)
    return pose, betas, scales


def test_scaled_keypoints_are_the_regressor_on_the_scaled_mesh(model):
    """The fit's keypoint formula with bone scales equals the COCO regressor applied to
    the mesh skinned at the scaled joints; the joints are the scaled skeleton's."""
    pose, betas, scales = random_bodies(3, 0)
    out = model(pose, betas, bone_scales=scales)
    kp, joints = predict_targets(
        axis_angle_to_matrix(pose), betas, torch.zeros(3, 3), keypoint_buffers(model, "coco17"),
        bone_scales=scales,
    )  # fmt: skip
    assert float((kp - model.coco_keypoints(out.vertices)).abs().max()) < 2e-6  # metres
    assert float((joints - out.joints).abs().max()) < 2e-6
    # each bone has its scaled length
    rest = model.rest_joints(betas)
    scaled = scale_bones_np(rest.numpy(), scales.numpy(), model.parents)
    par = model.parents
    for j in (J["left_knee"], J["right_elbow"], J["left_wrist"]):
        want = scales[0, j] * (rest[0, j] - rest[0, par[j]]).norm()
        assert np.linalg.norm(scaled[0, j] - scaled[0, par[j]]) == pytest.approx(
            float(want), rel=1e-5
        )
    # unscaled is the plain model
    plain = model(pose, betas, bone_scales=torch.ones(3, 24))
    assert float((plain.vertices - model(pose, betas).vertices).abs().max()) < 1e-6


def test_numpy_chain_and_viewer_bones_follow_the_scales(model):
    pose, betas, scales = random_bodies(2, 1)
    out = model(pose, betas, bone_scales=scales)
    _, posed = body_data(model).pose_chain(pose.numpy(), betas.numpy(), scales.numpy())
    np.testing.assert_allclose(posed, out.joints.numpy(), atol=2e-6)


def test_scale_groups_pair_left_and_right():
    m = bone_scale_matrix()
    assert m.shape == (len(SCALED_BONES), 24) and (m.sum(1) == 2).all()
    assert m[:, J["spine1"]].sum() == 0 and m[:, J["head"]].sum() == 0  # kept as they are
    assert m[list(SCALED_BONES).index("thighs"), [J["left_knee"], J["right_knee"]]].all()


def long_legged_targets(model: BodyModel, factor: float) -> tuple[np.ndarray, SmplFit | None]:
    """(1, F, 17, 3) mm: the sample's person 2 for 30 frames, thighs and shins ``factor``
    times as long as its betas make them."""
    gt = load_scene(REPO / "sample_data" / "shelf_synth").gt
    rows = np.flatnonzero(gt.person_id == 2)[:30]
    scales = torch.ones(len(rows), 24)
    for j in ("left_knee", "right_knee", "left_ankle", "right_ankle"):
        scales[:, J[j]] = factor
    with torch.no_grad():
        out = model(
            torch.as_tensor(gt.smpl_pose[rows], dtype=torch.float32),
            torch.as_tensor(gt.smpl_betas[rows], dtype=torch.float32),
            bone_scales=scales,
        )
        kp = model.coco_keypoints(out.vertices).double().numpy() * 1000.0
    return kp[None] + gt.transl[rows][None, :, None], None


@pytest.mark.slow
def test_the_fit_reaches_legs_the_shape_space_cannot(model):
    targets, _ = long_legged_targets(model, 1.15)
    exact = FitParams(w_smooth=0.0, iters=300, w_offset=0.0)
    without, _ = fit_sequence(
        targets,
        "coco17",
        model,
        params=dataclasses.replace(exact, w_bone_scale=0.0),
        progress=False,
    )
    scaled, _ = fit_sequence(targets, "coco17", model, params=exact, progress=False)
    assert without.bone_scales is None
    s = scaled.bone_scales[0]
    assert s[J["left_knee"]] == s[J["right_knee"]] and s[J["left_ankle"]] == s[J["right_ankle"]]
    # the betas take part of the length (a taller body), the scales the rest: measured
    # thighs 1.06, shins 1.02 with the default weight, the arms within 2 % of 1
    assert s[J["left_knee"]] > 1.03 and s[J["left_ankle"]] > 1.0
    assert abs(s[J["left_elbow"]] - 1.0) < 0.05 and abs(s[J["left_wrist"]] - 1.0) < 0.05
    e_without, e_scaled = np.nanmean(without.residual), np.nanmean(scaled.residual)
    assert e_scaled < 0.8 * e_without, (e_scaled, e_without)  # measured 2.9 vs 4.3 mm
    # the mesh carries the scaled bones: its regressed keypoints are the fit's keypoints
    verts = scaled.vertices(0, 5) / 1000.0
    kp = 1000.0 * model.coco_keypoints(torch.as_tensor(verts[None], dtype=torch.float32))[0]
    np.testing.assert_allclose(kp.numpy(), scaled.keypoints[0, 5], atol=0.05)
    # stored and read back
    back = SmplFit.from_arrays(scaled.arrays("x_"), "x_", joint_set="coco17", model=model)
    np.testing.assert_array_equal(back.bone_scales, scaled.bone_scales)


@pytest.mark.slow
def test_exported_skeleton_has_the_scaled_bones(model, tmp_path):
    from pipeline.exports.skeleton import track_skeleton

    targets, _ = long_legged_targets(model, 1.15)
    fit, _ = fit_sequence(targets, "coco17", model, progress=False)
    skel = track_skeleton(fit, 0)
    knee = J["left_knee"]
    rest = skel.rest_joints
    plain = np.linalg.norm(rest[knee] - rest[model.parents[knee]])
    assert np.linalg.norm(skel.offsets[knee]) == pytest.approx(
        plain * fit.bone_scales[0, knee], rel=1e-6
    )
