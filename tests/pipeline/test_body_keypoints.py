"""pipeline.body.keypoints: the table is complete, its landmarks land where anatomy puts
them (rest and posed), every layout's virtual vertices equal the table on the full LBS
mesh, the free-joint and torso rules reproduce the COCO-17 / SMPL-24 choices, and every
layout's fit recovers the body."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from pipeline.body.keypoints import (
    FITTABLE_JOINT_SETS,
    SMPL_VERTEX_IDS,
    keypoint_regressor,
    landmark_regressors,
    layout_keypoints,
    layout_ties,
)
from pipeline.body.kinematics import keypoint_buffers, predict_targets
from pipeline.body.model import BodyModel, load_body_model, rigid_chain
from pipeline.core.rotations import axis_angle_to_matrix
from pipeline.data.joint_sets import JOINT_SETS, SMPL24, get_joint_set
from pipeline.data.scene import load_scene
from pipeline.fit.smpl import FitParams, fit_sequence
from tests.conftest import REPO, tiny_body_model_arrays

LAYOUTS = ("body25", "body25b", "halpe26", "coco23", "coco_wholebody133", "blazepose33")
_J = SMPL24.index


@pytest.fixture(scope="module")
def model() -> BodyModel:
    return load_body_model()


@pytest.fixture(scope="module")
def marks(model) -> dict[str, np.ndarray]:
    """Landmark positions on the rest body, metres."""
    v = model.v_template.double().numpy()
    return {k: w @ v[ids] for k, (ids, w) in landmark_regressors(model).items()}


def test_table_covers_every_layout_and_says_why():
    assert set(FITTABLE_JOINT_SETS) == set(JOINT_SETS)
    for name, js in JOINT_SETS.items():
        ties = layout_ties(name)
        assert len(ties) == js.num_joints
        assert all(t.why for t in ties), name
    names = get_joint_set("coco_wholebody133").names
    wb = dict(zip(names, layout_ties("coco_wholebody133"), strict=True))
    assert not wb["face_0"].fitted and not wb["left_hand_index2"].fitted
    assert wb["left_hand_index1"].source == "left_index_knuckle" and wb["face_30"].fitted
    assert sum(t.fitted for t in wb.values()) == 23 + 7 + 2 * 5


def test_coco_layout_is_the_model_regressor_bit_for_bit(model):
    g = torch.Generator().manual_seed(0)
    out = model(torch.randn(3, 24, 3, generator=g) * 0.3, torch.randn(3, 10, generator=g))
    kp = layout_keypoints(keypoint_regressor(model, "coco17"), out.vertices, out.joints)
    assert torch.equal(kp, model.coco_keypoints(out.vertices))
    body25 = layout_keypoints(keypoint_regressor(model, "body25"), out.vertices, out.joints)
    b = get_joint_set("body25").index
    np.testing.assert_allclose(
        body25[:, b["mid_hip"]], 0.5 * (kp[:, 11] + kp[:, 12]), atol=1e-6
    )  # mid_hip = mean of the COCO hips
    np.testing.assert_allclose(body25[:, b["neck"]], 0.5 * (kp[:, 5] + kp[:, 6]), atol=1e-6)


def test_rest_landmarks_sit_where_anatomy_puts_them(model, marks):
    J = model.J_template.double().numpy() * 1000
    mm = {k: v * 1000 for k, v in marks.items()}
    # head top: above the head joint (inside the skull base) by a head's height, midline
    rise = mm["head_top"][1] - J[_J["head"], 1]
    assert 100 < rise < 250 and abs(mm["head_top"][0]) < 5
    assert mm["head_top"][1] == pytest.approx(model.v_template[:, 1].max() * 1000)
    for side, sign in (("left", 1), ("right", -1)):
        ankle, foot = J[_J[f"{side}_ankle"]], J[_J[f"{side}_foot"]]
        heel, big, small = mm[f"{side}_heel"], mm[f"{side}_big_toe"], mm[f"{side}_small_toe"]
        assert heel[2] < ankle[2] - 30 and heel[1] < ankle[1] - 20  # behind and below
        assert big[2] > foot[2] + 30 and small[2] > foot[2]  # toes in front of the ball
        assert sign * big[0] < sign * small[0] - 30  # big toe medial, 3-8 cm apart
        assert big[2] > small[2]  # the big toe reaches further forward
        wrist, hand = J[_J[f"{side}_wrist"]], J[_J[f"{side}_hand"]]
        index, pinky = mm[f"{side}_index_knuckle"], mm[f"{side}_pinky_knuckle"]
        assert index[2] - pinky[2] > 40  # palms down: the index side faces forward
        for k in (index, pinky, mm[f"{side}_middle_knuckle"], mm[f"{side}_ring_knuckle"]):
            assert abs(k[0] - hand[0]) < 15 and np.linalg.norm(k - hand) < 50
        thumb = mm[f"{side}_thumb"]
        assert thumb[2] > index[2] and 30 < np.linalg.norm(thumb - wrist) < 100
        inner, outer = mm[f"{side}_eye_inner"], mm[f"{side}_eye_outer"]
        assert 5 < sign * inner[0] < sign * outer[0] < 60  # inner medial of outer
        assert abs(inner[1] - outer[1]) < 10 and inner[2] > outer[2]  # outer further back
        mouth = mm[f"{side}_mouth"]
        assert 10 < sign * mouth[0] < 35 and 20 < inner[1] - mouth[1] < 100


def test_landmarks_follow_their_segment_when_posed(model):
    # A walking-like pose with a turned root: in each segment's own frame the landmark
    # keeps its rest offset (rigid parts) within a few mm.
    pose = torch.zeros(1, 24, 3)
    pose[0, 0] = torch.tensor([0.3, 1.2, -0.2])
    pose[0, _J["left_hip"]] = torch.tensor([-0.6, 0.0, 0.1])
    pose[0, _J["left_knee"]] = torch.tensor([0.9, 0.0, 0.0])
    pose[0, _J["left_ankle"]] = torch.tensor([-0.3, 0.2, 0.0])
    pose[0, _J["right_wrist"]] = torch.tensor([0.0, 0.5, 0.4])
    pose[0, _J["head"]] = torch.tensor([0.3, -0.4, 0.0])
    with torch.no_grad():
        out = model(pose)
        _, T = rigid_chain(
            axis_angle_to_matrix(pose), model.rest_joints(torch.zeros(1, 10)), model.tree
        )
    v_rest = model.v_template.double().numpy()
    v_posed = out.vertices[0].double().numpy()
    J_rest = model.J_template.double().numpy()
    G, p = T[0, :, :3, :3].double().numpy(), T[0, :, :3, 3].double().numpy()
    checks = {
        "head_top": "head", "left_heel": "left_ankle", "left_big_toe": "left_ankle",
        "left_small_toe": "left_ankle", "right_index_knuckle": "right_wrist",
        "right_pinky_knuckle": "right_wrist", "left_eye_outer": "head", "right_mouth": "head",
    }  # fmt: skip
    for name, (ids, w) in landmark_regressors(model).items():
        if name not in checks:
            continue
        j = _J[checks[name]]
        rest = w @ v_rest[ids] - J_rest[j]
        local = G[j].T @ (w @ v_posed[ids] - p[j])
        assert np.linalg.norm(local - rest) < 0.006, name  # metres
    # and the relations hold in the posed body's frames: heel behind and below the ankle
    heel_ids = landmark_regressors(model)["left_heel"][0]
    ankle = _J["left_ankle"]
    local = G[ankle].T @ (v_posed[heel_ids[0]] - p[ankle])
    assert local[2] < -0.03 and local[1] < -0.02


@pytest.mark.slow
@pytest.mark.parametrize("joint_set", sorted(JOINT_SETS))
def test_virtual_vertices_equal_the_table_on_the_full_mesh(model, joint_set):
    g = torch.Generator().manual_seed(5)
    pose, betas = torch.randn(3, 24, 3, generator=g) * 0.4, torch.randn(3, 10, generator=g)
    transl = torch.randn(3, 3, generator=g)
    out = model(pose, betas, transl)
    want = layout_keypoints(keypoint_regressor(model, joint_set), out.vertices, out.joints)
    buf = keypoint_buffers(model, joint_set)
    kp, _ = predict_targets(axis_angle_to_matrix(pose), betas, transl, buf)
    fitted = torch.as_tensor(buf.fitted)
    assert torch.isnan(want[:, ~fitted]).all()
    assert (kp[:, fitted] - want[:, fitted]).abs().max() < 3e-6  # metres


@pytest.mark.parametrize("joint_set", ["body25", "blazepose33", "coco_wholebody133"])
def test_virtual_vertices_with_pose_blend_shapes(joint_set):
    arrays = tiny_body_model_arrays(seed=3)
    rng = np.random.default_rng(0)
    V = arrays["v_template"].shape[0]
    reg = rng.uniform(0, 1, (17, V)) * (rng.uniform(size=(17, V)) < 0.05)
    arrays["coco_regressor"] = reg / reg.sum(1, keepdims=True).clip(1e-9)
    arrays["posedirs"] = rng.normal(0, 0.01, (V, 3, 207))
    m = BodyModel(arrays)
    pose = torch.as_tensor(rng.normal(0, 0.5, (4, 24, 3)), dtype=torch.float32)
    betas = torch.as_tensor(rng.normal(0, 1, (4, 10)), dtype=torch.float32)
    out = m(pose, betas)
    buf = keypoint_buffers(m, joint_set)
    kp, _ = predict_targets(axis_angle_to_matrix(pose), betas, torch.zeros(4, 3), buf)
    want = layout_keypoints(keypoint_regressor(m, joint_set), out.vertices, out.joints)
    f = torch.as_tensor(buf.fitted)
    assert (kp[:, f] - want[:, f]).abs().max() < 2e-6


def test_smpl_topology_uses_the_known_vertex_ids():
    arrays = tiny_body_model_arrays(seed=1)
    rng = np.random.default_rng(2)
    seg = rng.integers(0, 24, 6890)
    joints = arrays["J_regressor"] @ arrays["v_template"]
    arrays["v_template"] = joints[seg] + rng.normal(0, 0.02, (6890, 3))
    arrays["weights"] = np.eye(24)[seg]
    arrays["J_regressor"] = np.eye(24)[seg].T / np.eye(24)[seg].sum(0)[:, None]
    arrays["shapedirs"] = np.zeros((6890, 3, 10))
    arrays["posedirs"] = np.zeros((6890, 3, 207))
    marks = landmark_regressors(BodyModel(arrays))
    for name, vid in SMPL_VERTEX_IDS.items():
        np.testing.assert_array_equal(marks[name][0], [vid])
    assert "left_eye_inner" not in marks  # no COCO regressor: the face rules cannot run


def test_free_joint_and_torso_rules(model):
    old_free = {
        "coco17": {
            "spine1", "spine2", "spine3", "neck", "head", "left_collar", "right_collar",
            "left_wrist", "right_wrist", "left_hand", "right_hand", "left_ankle",
            "right_ankle", "left_foot", "right_foot",
        },
        "smpl24": {"head", "left_hand", "right_hand", "left_foot", "right_foot"},
    }  # fmt: skip
    old_torso = {
        "coco17": ["left_shoulder", "right_shoulder", "left_hip", "right_hip"],
        "smpl24": [
            "pelvis", "left_hip", "right_hip", "spine3", "neck", "left_shoulder",
            "right_shoulder",
        ],
    }  # fmt: skip

    def free(js):
        return {SMPL24.names[j] for j in np.flatnonzero(keypoint_buffers(model, js).free_weight)}

    for js in ("coco17", "smpl24"):
        assert free(js) == old_free[js]
        names = get_joint_set(js).names
        assert [names[i] for i in keypoint_buffers(model, js).torso] == old_torso[js]
    # feet points pin the ankles, hand points the wrists
    assert free("body25") == old_free["coco17"] - {"left_ankle", "right_ankle"}
    assert free("blazepose33") == old_free["coco17"] - {
        "left_ankle", "right_ankle", "left_wrist", "right_wrist",
    }  # fmt: skip


@pytest.mark.slow
@pytest.mark.parametrize("joint_set", LAYOUTS)
def test_fit_recovers_the_body_from_each_layout(model, joint_set):
    # Exact keypoints of one GT person of the sample scene in the layout -> the fitted
    # SMPL-24 joints match the truth (COCO-17 measured 11.3 mm in the same test).
    gt = load_scene(REPO / "sample_data" / "shelf_synth").gt
    rows = np.flatnonzero(gt.person_id == 2)[:20]
    reg = keypoint_regressor(model, joint_set)
    with torch.no_grad():
        out = model(
            torch.as_tensor(gt.smpl_pose[rows], dtype=torch.float32),
            torch.as_tensor(gt.smpl_betas[rows], dtype=torch.float32),
        )
        kp = layout_keypoints(reg, out.vertices, out.joints).double().numpy() * 1000
    kp += gt.transl[rows, None]
    fit, _ = fit_sequence(
        kp[None], joint_set, model, params=FitParams(w_smooth=0.0, iters=300), progress=False
    )
    assert np.nanmean(fit.residual) < 5.0
    assert np.isnan(fit.keypoints[0][:, ~reg.fitted]).all()
    err = np.linalg.norm(fit.joints[0] - gt.joints3d[rows], axis=-1).mean()
    assert err < 12.0
