"""Procedural motion: limits respected, heading convention, pose library."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from pipeline.synth.motion import (
    HIGH,
    LOW,
    PARAM_NAMES,
    activity_params,
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
