"""Procedural motion: limits respected, heading convention, pose library."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pipeline.body import pose_limits
from pipeline.synth.motion import (
    GAIT_ANKLE_DEG,
    GAIT_CONTACT_PHASE,
    HIGH,
    LOW,
    PARAM_NAMES,
    activity_params,
    gait_ankle,
    plan_people,
    pose_from_params,
    root_to_world,
    sample_pose_library,
    walk_params,
)


def test_heading_zero_faces_world_x_with_z_up():
    R = Rotation.from_rotvec(
        root_to_world(np.array([0.0, np.pi / 2]), np.zeros((2, 3)))
    ).as_matrix()
    np.testing.assert_allclose(R[0] @ [0, 0, 1], [1, 0, 0], atol=1e-12)  # facing +x
    np.testing.assert_allclose(R[0] @ [0, 1, 0], [0, 0, 1], atol=1e-12)  # up is +z
    np.testing.assert_allclose(R[1] @ [0, 0, 1], [0, 1, 0], atol=1e-12)  # heading 90 deg: +y


def test_plans_respect_parameter_limits():
    rng = np.random.default_rng(0)
    area = np.stack(np.meshgrid(np.arange(-2000, 2000, 200), np.arange(-2000, 2000, 200)), -1)
    people = plan_people(rng, area.reshape(-1, 2).astype(float), 3, 200, 25.0)
    for p in people:
        assert p.params.shape == (200, len(PARAM_NAMES))
        assert (p.params >= LOW - 1e-9).all() and (p.params <= HIGH + 1e-9).all()
        step = np.linalg.norm(np.diff(p.position, axis=0), axis=1)
        assert step.max() < 1600 / 25 * 1.01  # never faster than 1.6 m/s
    for a in range(3):
        for b in range(a + 1, 3):
            assert np.linalg.norm(people[a].position - people[b].position, axis=1).min() >= 650


def test_activities_differ_and_are_clipped():
    t = np.linspace(0, 2, 20)
    u = np.full(8, 0.5)
    crouch = pose_from_params(activity_params("crouch", t, u))
    reach = pose_from_params(activity_params("reach", t, u))
    walk = pose_from_params(walk_params(np.linspace(0, 1, 20), np.full(20, 1.2)))
    assert np.abs(crouch[-1] - reach[-1]).max() > 0.5
    assert np.ptp(walk[:, 4, 0]) > 0.3  # left knee swings during a gait cycle
    wild = pose_from_params(np.full(len(PARAM_NAMES), 10.0))
    np.testing.assert_allclose(wild, pose_from_params(HIGH))


def test_pose_library_has_zero_root():
    lib = sample_pose_library(50, seed=1)
    assert lib.shape == (50, 72)
    assert np.abs(lib[:, :3]).max() == 0
    assert np.abs(lib[:, 3:]).max() > 0.5


def test_walk_default_keeps_the_sine_ankles_of_the_shipped_samples():
    # The shipped samples and the shipped prior's library were made with this sine.
    phase, speed = np.linspace(0, 2, 37), np.full(37, 1.1)
    ankle = walk_params(phase, speed)[:, PARAM_NAMES.index("ankle_l")]
    np.testing.assert_allclose(ankle, 1.1 / 1.3 * 0.15 * np.sin(2 * np.pi * phase - 0.6))


def test_gait_ankles_follow_the_measured_curve():
    # Perry & Burnfield's values at the ends of the gait phases (degrees, + plantarflexion).
    pct = np.array([k[0] for k in GAIT_ANKLE_DEG], float)
    want = np.array([k[1] for k in GAIT_ANKLE_DEG])
    np.testing.assert_allclose(np.rad2deg(gait_ankle(pct / 100)), want, atol=1e-9)
    fine = np.rad2deg(gait_ankle(np.linspace(0, 1, 1001)))
    assert fine.min() == pytest.approx(-10.0) and fine.max() == pytest.approx(20.0)  # no overshoot
    # At 1.3 m/s (amplitude 1) the left ankle's peak plantarflexion is at toe off, 62 % of
    # the cycle after initial contact, and the right ankle is half a cycle behind.
    phase = np.linspace(0, 1, 2001)[:-1]
    p = walk_params(phase, np.full(len(phase), 1.3), gait_ankles=True)
    left, right = p[:, PARAM_NAMES.index("ankle_l")], p[:, PARAM_NAMES.index("ankle_r")]
    assert np.rad2deg(left.max()) == pytest.approx(20.0, abs=1e-3)  # on a 1/2000 grid
    assert (phase[left.argmax()] - GAIT_CONTACT_PHASE) % 1 == pytest.approx(0.62, abs=1e-3)
    np.testing.assert_allclose(right, np.roll(left, -1000), atol=1e-12)
    # Only the ankles differ from the default gait.
    legacy = walk_params(phase, np.full(len(phase), 1.3))
    other = [i for i, n in enumerate(PARAM_NAMES) if not n.startswith("ankle_")]
    np.testing.assert_array_equal(p[:, other], legacy[:, other])


def test_gait_ankles_stay_inside_the_limits_at_the_fastest_walk():
    phase = np.linspace(0, 1, 400)
    for speed in (0.3, 1.2, 2.5):  # 2.5 m/s: walk_params' largest amplitude (1.3)
        p = walk_params(phase, np.full(len(phase), speed), gait_ankles=True)
        assert (p >= LOW).all() and (p <= HIGH).all()  # nothing for pose_from_params to clip
        assert pose_limits.limit_excess(pose_from_params(p)).max() < 1e-6


@pytest.mark.slow
def test_long_crowded_scenes_are_planned_by_windows_keeping_distance():
    """20 people for 600 frames on a 31-camera dome's floor: whole random paths never
    keep their distance there; planned by windows they do, at every frame, and walk on
    without jumps across the windows' seams. A short scene is planned whole, as ever."""
    from pipeline.synth import motion
    from pipeline.synth.rigs import dome_capture_radius, dome_rig
    from pipeline.synth.scene_gen import visible_floor_area

    area = visible_floor_area(dome_rig(31, radius_mm=5000.0), min_views=2,
                              within_mm=dome_capture_radius(5000.0))  # fmt: skip
    people = plan_people(np.random.default_rng(7), area, 20, 600, 30.0)
    pos = np.stack([p.position for p in people])  # (P, F, 2)
    assert pos.shape == (20, 600, 2) and all(
        p.params.shape == (600, len(PARAM_NAMES)) for p in people
    )
    gap = np.linalg.norm(pos[:, None] - pos[None], axis=-1)
    gap[np.arange(20), np.arange(20)] = np.inf
    assert gap.min() >= 650.0
    step = np.linalg.norm(np.diff(pos, axis=1), axis=-1)  # mm per frame
    assert step.max() < 1.6 * 1000 / 30  # no faster than the fastest walk (1.5 m/s)
    seam = int(motion.PLAN_WINDOW_S * 30)
    assert step[:, seam - 1].max() < 1.6 * 1000 / 30  # across a seam too
    assert len({tuple(np.round(p.betas, 6)) for p in people}) == 20
    with pytest.raises(RuntimeError, match="could not place person"):
        motion._plan_whole(np.random.default_rng(7), area, 20, 600, 30.0, 650.0, 5)
    # short and roomy: whole paths, the draws plan_people always made
    small = np.stack(np.meshgrid(np.arange(-2000, 2000, 200), np.arange(-2000, 2000, 200)), -1)
    small = small.reshape(-1, 2).astype(float)
    a = plan_people(np.random.default_rng(3), small, 3, 200, 25.0)
    b = motion._plan_whole(np.random.default_rng(3), small, 3, 200, 25.0, 650.0, 200)
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x.params, y.params)
        np.testing.assert_array_equal(x.betas, y.betas)
