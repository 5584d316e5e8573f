"""pipeline.body.pose_limits: swing-twist round trip, limits against synthetic motion and
anatomy, skeleton plausibility measures."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scipy.spatial.transform import Rotation

from pipeline.body import pose_limits
from pipeline.data.joint_sets import SMPL24
from pipeline.synth.motion import HIGH, LOW, pose_from_params, sample_pose_library

J = SMPL24.index


def with_angles(joint: str, angles_deg: tuple[float, float, float]) -> np.ndarray:
    """(1, 24, 3) rest pose with one joint set to (swing_a, swing_b, twist) degrees."""
    ang = np.zeros((1, 24, 3))
    ang[0, J[joint]] = np.deg2rad(angles_deg)
    return pose_limits.from_swing_twist(ang)


def test_zero_pose_has_no_violations():
    zero = np.zeros((3, 24, 3))
    assert (pose_limits.limit_excess(zero) == 0).all()
    assert pose_limits.violations_per_1000(zero) == 0.0


def test_knee_bent_backwards_violates_and_forwards_does_not():
    pose = np.zeros((2, 24, 3))
    pose[0, J["left_knee"]] = [np.deg2rad(-40), 0, 0]  # hyperextension by 40 deg
    pose[1, J["right_knee"]] = [np.deg2rad(90), 0, 0]  # ordinary flexion
    excess = pose_limits.limit_excess(pose)
    np.testing.assert_allclose(excess[0, J["left_knee"]], 40.0, atol=1e-6)
    assert excess[1].max() == 0.0
    assert pose_limits.limit_violations(pose)[0, J["left_knee"]]
    assert pose_limits.violations_per_1000(pose) == 500.0


def test_elbow_flexes_one_way_on_each_side():
    # motion.py: the left elbow flexes by Ry(-angle), the right one by Ry(+angle)
    pose = np.zeros((2, 24, 3))
    pose[0, J["left_elbow"]] = [0, -np.deg2rad(100), 0]
    pose[0, J["right_elbow"]] = [0, np.deg2rad(100), 0]
    pose[1, J["left_elbow"]] = [0, np.deg2rad(30), 0]  # bent backwards
    excess = pose_limits.limit_excess(pose)
    assert excess[0].max() == 0.0
    np.testing.assert_allclose(excess[1, J["left_elbow"]], 30.0, atol=1e-6)


def test_wrist_past_its_limit_violates():
    ok = with_angles("left_wrist", (-60.0, 0.0, 0.0))
    bad = with_angles("right_wrist", (-120.0, 0.0, 0.0))
    assert pose_limits.limit_excess(ok).max() == 0.0
    np.testing.assert_allclose(pose_limits.limit_excess(bad)[0, J["right_wrist"]], 40.0, atol=1e-6)


def test_synthetic_motion_respects_the_limits():
    # Library poses and the whole PARAM_LIMITS box (corners included) of motion.py.
    rng = np.random.default_rng(0)
    params = np.concatenate(
        [
            rng.uniform(LOW, HIGH, (3000, len(LOW))),
            np.where(rng.uniform(size=(3000, len(LOW))) < 0.5, LOW, HIGH),
        ]
    )
    for poses in (sample_pose_library(3000, seed=1).reshape(-1, 24, 3), pose_from_params(params)):
        assert pose_limits.limit_excess(poses).max() < 1e-6


def test_right_joints_mirror_the_left():
    rng = np.random.default_rng(2)
    pose = rng.normal(0, 0.8, (200, 24, 3))
    mirrored = pose * np.array([1.0, -1.0, -1.0])
    flip = np.array(
        [
            SMPL24.index[n.replace("left_", "#").replace("right_", "left_").replace("#", "right_")]
            for n in SMPL24.names
        ]
    )
    mirrored = mirrored[:, flip]
    np.testing.assert_allclose(
        pose_limits.limit_excess(mirrored), pose_limits.limit_excess(pose)[:, flip], atol=1e-9
    )


@settings(max_examples=50, deadline=None)
@given(arrays(np.float64, (4, 24, 3), elements=st.floats(-2.5, 2.5)))
def test_swing_twist_round_trip(rotvecs):
    back = pose_limits.from_swing_twist(pose_limits.swing_twist(rotvecs))
    a = Rotation.from_rotvec(rotvecs.reshape(-1, 3))
    b = Rotation.from_rotvec(back.reshape(-1, 3))
    assert (a.inv() * b).magnitude().max() < 1e-9


def test_swing_twist_separates_bone_twist():
    # A pure rotation about the forearm (x for the left arm) is twist only.
    pose = np.zeros((1, 24, 3))
    pose[0, J["left_elbow"]] = [0.7, 0, 0]
    ang = pose_limits.swing_twist(pose)[0, J["left_elbow"]]
    np.testing.assert_allclose(ang, [0.0, 0.0, 0.7], atol=1e-12)


def rigid_walk(num_frames: int = 30) -> np.ndarray:
    """(1, F, 24, 3) a rigid T-pose skeleton translating at constant speed, mm."""
    import torch

    from pipeline.body.model import load_body_model

    rest = 1000 * load_body_model().rest_joints(torch.zeros(1, 10))[0].numpy()
    t = np.arange(num_frames)[:, None, None]
    return (rest[None] + t * np.array([10.0, 0.0, 0.0]))[None]


def test_bone_length_std_and_jitter_of_a_rigid_skeleton_are_zero():
    x = rigid_walk()
    assert pose_limits.bone_length_std(x)[0] < 1e-6
    assert pose_limits.joint_jitter(x, pose_limits.FOOT_JOINTS) < 1e-6
    noisy = x + np.random.default_rng(0).normal(0, 5.0, x.shape)
    assert 3.0 < pose_limits.bone_length_std(noisy)[0] < 10.0
    assert pose_limits.joint_jitter(noisy, pose_limits.WRIST_JOINTS) > 5.0


def test_hinge_flexion_signs_knees():
    import torch

    from pipeline.body.model import load_body_model

    model = load_body_model()
    pose = torch.zeros(2, 24, 3)
    pose[0, J["left_knee"], 0] = 0.8  # flexion
    pose[1, J["left_knee"], 0] = -0.5  # backwards
    pose[:, J["left_elbow"], 1] = -1.0
    joints = model.joints(pose).numpy()
    f = pose_limits.hinge_flexion(joints)
    assert 40 < f[0, 0] < 60  # 46 deg of flexion; the rest leg is not quite straight
    assert f[1, 0] < -15  # 28.6 deg back from the rest leg's ~9 deg bend
    np.testing.assert_allclose(f[:, 2], np.rad2deg(1.0), atol=3.0)
    assert pose_limits.hinge_violations_per_1000(joints) == 500.0


def test_skeleton_plausibility_keys_and_nan_tolerance():
    x = rigid_walk()
    x[0, 5:8] = np.nan
    out = pose_limits.skeleton_plausibility(x)
    assert set(out) == {
        "bone_length_std_mm",
        "hinge_violations_per_1000",
        "foot_jitter",
        "wrist_jitter",
    }
    assert all(np.isfinite(v) for v in out.values())
