import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.body import pose_limits
from pipeline.body.kinematics import rotvec_to_matrix
from pipeline.fit import limit_penalty


@pytest.mark.slow
@settings(max_examples=20, deadline=None)
@given(st.integers(0, 2**31 - 1), st.floats(0.1, 1.5))
def test_swing_twist_matches_the_numpy_reference(seed, scale):
    r = np.random.default_rng(seed).normal(0, scale, (16, 24, 3))
    R = torch.as_tensor(rotvec_to_matrix(r), dtype=torch.float32)
    want = pose_limits.swing_twist(r)[:, pose_limits.LIMITED]
    got = limit_penalty.swing_twist(R)[:, pose_limits.LIMITED].double().numpy()
    # angles near +-pi wrap; compare away from the wrap
    ok = np.abs(want) < 3.0
    np.testing.assert_allclose(got[ok], want[ok], atol=1e-4)
    excess = np.rad2deg(np.linalg.norm(limit_penalty.limit_excess(R).numpy(), axis=-1))
    np.testing.assert_allclose(excess, pose_limits.limit_excess(r), atol=0.05)


def test_penalty_is_zero_inside_and_has_finite_gradients():
    R = torch.eye(3).repeat(5, 24, 1, 1).requires_grad_(True)
    pen = limit_penalty.limit_penalty(R)
    assert float(pen.abs().max()) == 0.0
    r = np.random.default_rng(0).normal(0, 1.2, (8, 24, 3))
    R = torch.as_tensor(rotvec_to_matrix(r), dtype=torch.float32).requires_grad_(True)
    limit_penalty.limit_penalty(R).sum().backward()
    assert torch.isfinite(R.grad).all() and float(R.grad.abs().sum()) > 0


def test_small_angle_quaternion_equals_shepperd_at_every_angle():
    # angles 0..pi on random axes: both branches of small_angle_quaternion (<= 120 deg by
    # the w branch, beyond by Shepperd's method) against Shepperd's method everywhere
    rng = np.random.default_rng(1)
    axis = rng.normal(size=(2000, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    r = axis * np.linspace(0.0, np.pi, 2000)[:, None]
    R = torch.as_tensor(rotvec_to_matrix(r), dtype=torch.float32)
    want = limit_penalty.matrix_to_quaternion(R)
    got = limit_penalty.small_angle_quaternion(R)
    far = np.linalg.norm(r, axis=1) > 2 * np.pi / 3
    assert 0 < far.sum() < len(r)
    # antipodal quaternions at exactly pi (w = 0) are the same rotation
    sign = torch.where((got * want).sum(-1, keepdim=True) < 0, -1.0, 1.0)
    np.testing.assert_allclose((got * sign).numpy(), want.numpy(), atol=2e-6)
    Rg = R.clone().requires_grad_(True)
    limit_penalty.small_angle_quaternion(Rg).sum().backward()
    assert torch.isfinite(Rg.grad).all()


@pytest.mark.parametrize("margin_deg", [0.0, 5.0])
def test_penalty_is_the_squared_excess_summed_with_its_gradient(margin_deg):
    # limit_penalty sums the squares over swing_twist_rows without the (N, 24, 3) array
    # of limit_excess; both, values and gradients, on rotations up to pi (both quaternion
    # branches), with some joints far outside their limits.
    r = np.random.default_rng(3).normal(0, 1.3, (40, 24, 3))
    R = torch.as_tensor(rotvec_to_matrix(r), dtype=torch.float32)
    far = np.linalg.norm(r, axis=-1) > 2 * np.pi / 3
    assert far[:, pose_limits.LIMITED].any()
    Ra, Rb = R.clone().requires_grad_(True), R.clone().requires_grad_(True)
    want = (limit_penalty.limit_excess(Ra, margin_deg=margin_deg) ** 2).sum((-1, -2))
    got = limit_penalty.limit_penalty(Rb, margin_deg=margin_deg)
    assert float(want.min()) >= 0 and float(want.max()) > 1.0  # radians^2
    np.testing.assert_allclose(got.detach().numpy(), want.detach().numpy(), rtol=1e-5, atol=1e-6)
    want.sum().backward()
    got.sum().backward()
    np.testing.assert_allclose(Rb.grad.numpy(), Ra.grad.numpy(), rtol=1e-4, atol=1e-4)
