"""pipeline.fit.smpl: exact keypoint skinning, SMPL forward -> fit round trips on the
sample scene's ground truth (SMPL-24 and COCO-17 targets), missing data, the prior stage."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from pipeline.body.kinematics import (
    keypoint_buffers,
    matrix_to_rot6d,
    predict_targets,
    rot6d_to_matrix,
)
from pipeline.body.model import BodyModel, load_body_model
from pipeline.core.rotations import axis_angle_to_matrix
from pipeline.data.joint_sets import SMPL24, get_joint_set
from pipeline.data.scene import load_scene
from pipeline.evaluation.evaluate import ground_truth_slots, gt_per_frame, stage_metrics
from pipeline.fit.smpl import FitParams, SmplFit, fit_sequence, plausibility, target_slots
from tests.conftest import REPO, tiny_body_model_arrays

SCENE = REPO / "sample_data" / "shelf_synth"
# Exact targets: no temporal prior (GT motion has real accelerations), more iterations.
EXACT = FitParams(w_smooth=0.0, iters=300, w_offset=0.0)  # model-made targets: no offsets


@pytest.fixture(scope="module")
def model() -> BodyModel:
    return load_body_model()


@pytest.fixture(scope="module")
def gt():
    return load_scene(SCENE).gt


def height_mm(model: BodyModel, betas: np.ndarray) -> float:
    """Standing height (vertex extent along the model's y) of the rest body, mm."""
    with torch.no_grad():
        v = model(torch.zeros(1, 72), torch.as_tensor(betas, dtype=torch.float32)[None]).vertices
    return 1000.0 * float(v[0, :, 1].max() - v[0, :, 1].min())


def test_rot6d_round_trip_and_gram_schmidt():
    R = axis_angle_to_matrix(torch.randn(100, 3, generator=torch.Generator().manual_seed(0)))
    np.testing.assert_allclose(rot6d_to_matrix(matrix_to_rot6d(R)), R, atol=1e-6)
    M = rot6d_to_matrix(torch.randn(100, 6, generator=torch.Generator().manual_seed(1)))
    np.testing.assert_allclose(M @ M.transpose(1, 2), torch.eye(3).expand(100, 3, 3), atol=1e-6)
    np.testing.assert_allclose(torch.linalg.det(M), torch.ones(100), atol=1e-6)


@pytest.mark.parametrize("with_posedirs", [False, True])
def test_keypoint_skinning_equals_regressor_on_full_mesh(with_posedirs):
    # The collapsed "regressor x skinning" buffers reproduce coco_regressor @ LBS vertices,
    # pose blend shapes included (a tiny random model with random posedirs).
    arrays = tiny_body_model_arrays(seed=3)
    rng = np.random.default_rng(0)
    V = arrays["v_template"].shape[0]
    reg = rng.uniform(0, 1, (17, V)) * (rng.uniform(size=(17, V)) < 0.05)
    arrays["coco_regressor"] = reg / reg.sum(1, keepdims=True).clip(1e-9)
    if with_posedirs:
        arrays["posedirs"] = rng.normal(0, 0.01, (V, 3, 207))
    m = BodyModel(arrays)
    pose = torch.as_tensor(rng.normal(0, 0.5, (6, 24, 3)), dtype=torch.float32)
    betas = torch.as_tensor(rng.normal(0, 1, (6, 10)), dtype=torch.float32)
    transl = torch.as_tensor(rng.normal(0, 1, (6, 3)), dtype=torch.float32)
    out = m(pose, betas, transl)
    for js, want in (("coco17", m.coco_keypoints(out.vertices)), ("smpl24", out.joints)):
        kp, joints = predict_targets(
            axis_angle_to_matrix(pose), betas, transl, keypoint_buffers(m, js)
        )
        np.testing.assert_allclose(kp, want, atol=2e-6)
        np.testing.assert_allclose(joints, out.joints, atol=2e-6)


def test_keypoint_products_per_body_equal_those_per_row(model):
    # predict_targets with one betas per body (rows_per_body: the fit's tracks) gives the
    # numbers of every row carrying its body's betas, and the same gradients.
    g = torch.Generator().manual_seed(7)
    sizes = [3, 1, 0, 5]  # a body without rows is allowed (a track absent from a chunk)
    N = sum(sizes)
    R = rot6d_to_matrix(torch.randn(N, 24, 6, generator=g))
    transl = torch.randn(N, 3, generator=g)
    buf = keypoint_buffers(model, "coco17")
    outs = []
    for per_body in (False, True):
        betas = torch.randn(len(sizes), 10, generator=torch.Generator().manual_seed(8))
        betas.requires_grad_(True)
        rows = torch.repeat_interleave(betas, torch.as_tensor(sizes), 0)
        kp, joints = (predict_targets(R, betas, transl, buf, rows_per_body=sizes) if per_body
                      else predict_targets(R, rows, transl, buf))  # fmt: skip
        (kp.square().sum() + joints.sum()).backward()
        outs.append((kp.detach(), joints.detach(), betas.grad))
    (kp0, j0, g0), (kp1, j1, g1) = outs
    assert kp1.shape == (N, 17, 3) and float(kp0.abs().max()) > 0.1
    assert float((kp0 - kp1).abs().max()) < 2e-6  # metres
    assert torch.equal(j0, j1)
    assert float((g0 - g1).abs().max()) < 1e-4 * float(g0.abs().max())
    with pytest.raises(ValueError, match="rows_per_body"):
        predict_targets(R, betas.detach(), transl, buf, rows_per_body=[3, 1, 0, 4])


def test_keypoint_skinning_on_the_open_model(model):
    g = torch.Generator().manual_seed(4)
    pose, betas = torch.randn(4, 24, 3, generator=g) * 0.4, torch.randn(4, 10, generator=g)
    out = model(pose, betas)
    kp, _ = predict_targets(
        axis_angle_to_matrix(pose), betas, torch.zeros(4, 3), keypoint_buffers(model, "coco17")
    )
    assert (kp - model.coco_keypoints(out.vertices)).abs().max() < 2e-6  # metres


@pytest.mark.slow
@pytest.mark.parametrize("joint_set", ["smpl24", "coco17"])
def test_fit_recovers_pose_and_shape_of_model_joints(model, gt, joint_set):
    # 20 frames of one person, targets produced by the body model itself (the scene's GT
    # was rendered from 1000 * model(pose, betas) + transl).
    rows = np.flatnonzero(gt.person_id == 2)[:20]
    targets = (gt.joints3d if joint_set == "smpl24" else gt.keypoints3d)[rows]
    fit, none = fit_sequence(targets[None], joint_set, model, params=EXACT, progress=False)
    assert none is None
    err = np.linalg.norm(fit.keypoints[0] - targets, axis=-1)
    assert err.mean() < 5.0 and np.nanmean(fit.residual) < 5.0
    np.testing.assert_allclose(fit.residual[0], err, atol=1e-3)
    assert abs(height_mm(model, fit.betas[0]) - height_mm(model, gt.smpl_betas[rows[0]])) < 10.0
    smpl_err = np.linalg.norm(fit.joints[0] - gt.joints3d[rows], axis=-1).mean()
    assert smpl_err < (5.0 if joint_set == "smpl24" else 12.0)
    # the mesh agrees with the joints and the GT convention (1000 * model + transl)
    verts = fit.vertices(0, 7)
    kp = 1000.0 * model.coco_keypoints(torch.as_tensor(verts[None] / 1000.0, dtype=torch.float32))
    if joint_set == "coco17":
        np.testing.assert_allclose(kp[0].numpy(), fit.keypoints[0, 7], atol=0.05)
    assert np.linalg.norm(verts.mean(0) - fit.joints[0, 7, 0]) < 300.0


def test_sample_scene_sequence_mpjpe(model, gt):
    # 20 frames of all four people, exact COCO-17 keypoints3d as targets, default params:
    # measured 4.0 mm (keypoints vs keypoints3d) and 6.6 mm (SMPL joints vs joints3d).
    F = 20
    keep = gt.frame < F
    tracks = np.full((4, F, 17, 3), np.nan)
    tracks[gt.person_id[keep], gt.frame[keep]] = gt.keypoints3d[keep]
    fit, _ = fit_sequence(tracks, "coco17", model, progress=False)
    kp_dense, _ = gt_per_frame(gt, ground_truth_slots(gt, "coco17")[0], F)
    joints_dense, _ = gt_per_frame(gt, gt.joints3d, F)
    kp_row, _ = stage_metrics(target_slots(fit), kp_dense)
    joints_row, _ = stage_metrics(fit.joints, joints_dense)
    assert kp_row["recall"] == 1.0
    assert kp_row["mpjpe"] < 6.0
    assert joints_row["mpjpe"] < 12.0


@pytest.mark.slow
def test_missing_joints_and_absent_frames(model, gt):
    rows = np.flatnonzero(gt.person_id == 1)[:12]
    tracks = np.full((2, 12, 24, 3), np.nan)
    tracks[0] = gt.joints3d[rows]
    tracks[0, 3] = np.nan  # an absent frame inside the track
    tracks[0, 5, [SMPL24.index["left_wrist"], SMPL24.index["head"]]] = np.nan  # missing joints
    fit, _ = fit_sequence(tracks, "smpl24", model, params=EXACT, progress=False)
    present = np.ones((2, 12), bool)
    present[0, 3] = False
    present[1] = False  # track 1 never appears
    np.testing.assert_array_equal(fit.present, present)
    for name in ("pose_rotvecs", "transl", "joints", "keypoints", "residual"):
        arr = getattr(fit, name)
        assert np.isnan(arr[~present]).all() and np.isfinite(arr[0, 5, 0]).all(), name
    assert np.isnan(fit.betas[1]).all() and np.isfinite(fit.betas[0]).all()
    assert np.isnan(fit.residual[0, 5, SMPL24.index["left_wrist"]])
    # the unobserved wrist still sits near the truth thanks to the rest of the arm
    wrist = SMPL24.index["left_wrist"]
    assert np.linalg.norm(fit.joints[0, 5, wrist] - gt.joints3d[rows[5], wrist]) < 60.0
    assert np.isnan(fit.vertices(0, 3)).all()
    back = SmplFit.from_arrays(fit.arrays("smpl_"), "smpl_", joint_set="smpl24", model=model)
    for name in ("pose_rotvecs", "betas", "transl", "joints", "keypoints", "residual"):
        np.testing.assert_array_equal(getattr(back, name), getattr(fit, name))


def test_bad_input_raises(model):
    with pytest.raises(ValueError, match="expected tracks"):
        fit_sequence(np.zeros((1, 5, 24, 3)), "coco17", model, progress=False)
    with pytest.raises(ValueError, match="unknown joint set"):
        fit_sequence(np.zeros((1, 5, 25, 3)), "body_25x", model, progress=False)
    with pytest.raises(ValueError, match="has no coco_regressor"):  # BODY_25 reads COCO rows
        fit_sequence(
            np.zeros((1, 5, 25, 3)), "body25", BodyModel(tiny_body_model_arrays()), progress=False
        )
    with pytest.raises(ValueError, match="weights"):
        fit_sequence(
            np.zeros((1, 5, 17, 3)), "coco17", model, weights=np.ones((1, 5)), progress=False
        )


@pytest.mark.slow
def test_prior_correction_makes_noisy_fits_plausible(model, gt):
    # Noisy targets (25 mm per axis): step I bends joints past their limits to follow the
    # noise; the VAE-corrected fit has no more violations and is not less accurate.
    from pipeline.fit.prior import load_prior

    F = 25
    keep = gt.frame < F
    truth = np.full((4, F, 17, 3), np.nan)
    truth[gt.person_id[keep], gt.frame[keep]] = gt.keypoints3d[keep]
    noisy = truth + np.random.default_rng(0).normal(0, 25.0, truth.shape)
    fit1, fit2 = fit_sequence(noisy, "coco17", model, prior=load_prior(), progress=False)
    assert fit2 is not None and fit2.stage == "smpl_vae"
    p1, p2 = plausibility(fit1), plausibility(fit2)
    assert p2["limit_violations_per_1000"] <= p1["limit_violations_per_1000"]
    e1 = np.nanmean(np.linalg.norm(fit1.keypoints - truth, axis=-1))
    e2 = np.nanmean(np.linalg.norm(fit2.keypoints - truth, axis=-1))
    assert e2 < e1 + 2.0 and e2 < 25.0
    np.testing.assert_array_equal(fit2.betas, fit1.betas)
    assert set(p1) == {
        "limit_violations_per_1000", "bone_length_std_mm", "hinge_violations_per_1000",
        "foot_jitter", "wrist_jitter",
    }  # fmt: skip


@pytest.mark.slow
def test_foot_offsets_follow_a_detectors_toes_without_moving_the_ankles(model, gt):
    # BODY_25B targets made by the body model, with the toes and heels where a detector
    # puts them rather than on the model's landmark vertices: 30 mm up and 40 mm back in
    # each point's ankle/foot frame, constant over the clip (Pose2Sim's OpenPose feet sit
    # 30-55 mm off). Without foot offsets the fit bends the ankles to chase them
    # (measured: feet 9.4 mm, SMPL ankles 31.8 mm from the truth); with them the feet
    # are followed (2.9 mm) and the ankles stay put (8.5 mm).
    rows = np.flatnonzero(gt.person_id == 2)[:20]
    buf = keypoint_buffers(model, "body25b")
    foot = buf.foot_offset.numpy() > 0
    names = [n for n, f in zip(get_joint_set("body25b").names, foot, strict=True) if f]
    assert sorted(names) == sorted(f"{s}_{p}" for s in ("left", "right")
                                   for p in ("big_toe", "small_toe", "heel"))  # fmt: skip
    offsets = torch.zeros(len(rows), buf.num_targets, 3)
    offsets[:, foot] = torch.tensor([0.0, 0.03, -0.04])
    with torch.no_grad():
        pose = torch.as_tensor(gt.smpl_pose[rows], dtype=torch.float32).reshape(-1, 24, 3)
        kp, _ = predict_targets(
            axis_angle_to_matrix(pose),
            torch.as_tensor(gt.smpl_betas[rows], dtype=torch.float32),
            torch.as_tensor(gt.transl[rows] / 1000.0, dtype=torch.float32),
            buf,
            offsets,
        )
    targets = 1000.0 * kp.double().numpy()[None]
    ankles = [SMPL24.index["left_ankle"], SMPL24.index["right_ankle"]]
    feet_mm, ankle_mm = {}, {}
    for on in (False, True):
        params = FitParams(w_smooth=0.0, iters=300, foot_offsets=on)
        fit, _ = fit_sequence(targets, "body25b", model, params=params, progress=False)
        feet_mm[on] = float(np.median(fit.residual[0][:, foot]))
        d = fit.joints[0][:, ankles] - gt.joints3d[rows][:, ankles]
        ankle_mm[on] = float(np.linalg.norm(d, axis=-1).mean())
        if not on:
            assert np.all(fit.keypoint_offsets[0, foot] == 0.0)
    assert feet_mm[True] < 5.0 < 7.0 < feet_mm[False], feet_mm
    assert ankle_mm[True] < 15.0 and ankle_mm[True] < ankle_mm[False] - 10.0, ankle_mm


def test_only_heels_and_toes_get_foot_offsets(model):
    for js in ("coco17", "smpl24"):
        assert keypoint_buffers(model, js).foot_offset.sum() == 0, js
    for js in ("body25", "halpe26", "blazepose33"):
        buf = keypoint_buffers(model, js)
        names = get_joint_set(js).names
        got = {names[i] for i in np.flatnonzero(buf.foot_offset.numpy())}
        assert got and all("heel" in n or "toe" in n or "foot" in n for n in got), got
        assert not got & {"left_ankle", "right_ankle"}
        assert (buf.offset_mask.numpy() >= buf.foot_offset.numpy()).all()


@pytest.mark.slow
def test_limb_offsets_follow_keypoints_off_the_limb_joints(model, gt):
    # COCO-17 targets made by the body model with the knees and elbows 25 mm off the
    # model's (forward and up in the thigh / upper-arm frame), constant over the clip, as
    # a detector's skin-surface knee is off the joint centre. Only FitParams.limb_offsets
    # lets each keypoint keep its own constant offset in its parent body part's frame.

    rows = np.flatnonzero(gt.person_id == 2)[:20]
    names = get_joint_set("coco17").names
    limb = [names.index(f"{s}_{p}") for s in ("left", "right") for p in ("knee", "elbow")]
    buf = keypoint_buffers(model, "coco17")
    assert np.all(buf.offset_mask.numpy()[limb] == 0.0)  # no limb offsets by default
    buf_all = dataclasses.replace(buf, offset_mask=torch.ones(buf.num_targets))
    offsets = torch.zeros(len(rows), buf.num_targets, 3)
    offsets[:, limb] = torch.tensor([0.0, 0.015, 0.02])  # 25 mm
    with torch.no_grad():
        pose = torch.as_tensor(gt.smpl_pose[rows], dtype=torch.float32).reshape(-1, 24, 3)
        kp, _ = predict_targets(
            axis_angle_to_matrix(pose),
            torch.as_tensor(gt.smpl_betas[rows], dtype=torch.float32),
            torch.as_tensor(gt.transl[rows] / 1000.0, dtype=torch.float32),
            buf_all,
            offsets,
        )
    targets = 1000.0 * kp.double().numpy()[None]
    joints = [SMPL24.index[n] for n in (names[j] for j in limb)]
    limb_mm, joint_mm, learnt_mm = {}, {}, {}
    for on in (False, True):
        params = FitParams(w_smooth=0.0, iters=300, limb_offsets=on)
        fit, _ = fit_sequence(targets, "coco17", model, params=params, progress=False)
        limb_mm[on] = float(np.median(fit.residual[0][:, limb]))
        d = fit.joints[0][:, joints] - gt.joints3d[rows][:, joints]
        joint_mm[on] = float(np.linalg.norm(d, axis=-1).mean())
        learnt_mm[on] = np.linalg.norm(fit.keypoint_offsets[0, limb], axis=-1)
    # Measured: without limb offsets the limb joints follow the keypoints (residual 2.0
    # mm, SMPL knees and elbows 25.7 mm off the truth); with them the offsets take 5-12 mm
    # of the 25 (the rest is absorbed by pose and shape: the regularised offset is only
    # partly identifiable) and the joints end 19.7 mm off.
    assert np.all(learnt_mm[False] == 0.0)
    assert limb_mm[True] < 5.0 and limb_mm[False] < 5.0, limb_mm
    assert joint_mm[True] < joint_mm[False] - 4.0, joint_mm
    assert np.all((learnt_mm[True] > 3.0) & (learnt_mm[True] < 25.0)), learnt_mm[True]
