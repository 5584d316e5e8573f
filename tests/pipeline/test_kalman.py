"""Tests for pipeline.stages.kalman: agreement with filterpy, accuracy on synthetic walks,
edge cases."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from bench.reference_kalman import kalman_filter_filterpy
from pipeline.stages.kalman import (
    FilterResult,
    KalmanParams,
    kalman_filter,
)

FPS = 25.0
MEAN_FIELDS = ("filtered", "forward", "prior_mean", "innovation", "velocity")
VAR_FIELDS = ("filtered_var", "posterior_var", "prior_var", "innovation_var")


def synthetic_walk(
    num_frames: int = 250, num_people: int = 4, num_joints: int = 24, noise: float = 15.0, seed=0
) -> tuple[np.ndarray, np.ndarray]:
    """People walking at 0.5-1.5 m/s, joints swinging at 2 Hz (20-150 mm per axis), in mm.

    Returns:
        truth and noisy measurements (truth + N(0, noise^2) per axis), both
        (num_frames, num_people, num_joints, 3).
    """
    rng = np.random.default_rng(seed)
    t = np.arange(num_frames, dtype=float)[:, None, None]
    speed = rng.uniform(500.0, 1500.0, (1, num_people, 1)) / FPS  # mm/frame
    heading = rng.uniform(0.0, 2.0 * np.pi, (1, num_people, 1))
    root = np.stack(
        [speed * t * np.cos(heading), speed * t * np.sin(heading), np.zeros_like(speed * t)], -1
    )  # (T, P, 1, 3)
    offset = rng.normal(0.0, 200.0, (1, num_people, num_joints, 3))
    offset[..., 2] = rng.uniform(50.0, 1700.0, (1, num_people, num_joints))
    amp = rng.uniform(20.0, 150.0, (1, num_people, num_joints, 3))
    phase = rng.uniform(0.0, 2.0 * np.pi, (1, num_people, num_joints, 3))
    omega = 2.0 * np.pi * 2.0 / FPS  # 2 Hz in rad/frame
    truth = root + offset + amp * np.sin(omega * t[..., None] + phase)
    return truth, truth + rng.normal(0.0, noise, truth.shape)


def mpjpe(estimate: np.ndarray, truth: np.ndarray) -> float:
    """Mean per-joint position error, mm."""
    return float(np.mean(np.linalg.norm(estimate - truth, axis=-1)))


def accel_error(estimate: np.ndarray, truth: np.ndarray) -> float:
    """Mean over frames and joints of |a_est - a_true|, a = second difference, mm/frame^2."""

    def accel(x: np.ndarray) -> np.ndarray:
        return x[2:] - 2.0 * x[1:-1] + x[:-2]

    return float(np.mean(np.linalg.norm(accel(estimate) - accel(truth), axis=-1)))


def assert_matches_reference(
    measurements: np.ndarray, params: KalmanParams, smoothed_var_rtol: float = 1e-9
) -> None:
    """kalman_filter on (T, N, 3) equals kalman_filter_filterpy joint by joint.

    Tolerances are relative to the data: means to 1e-9 of the largest coordinate,
    variances to 1e-9 of the largest initial variance (P - K S K' cancels at that
    scale). The smoothed variance P + C (P_s - Pp) C' cancels twice (in det(Pp) and
    in the sum) and loses up to ~1e-4 relative in both implementations alike when
    p0_velocity / q and p0_velocity / r are large (checked against exact rational
    arithmetic; ~1e-2 at q = 1, r = 25, p0_velocity = 1e7), hence its own
    ``smoothed_var_rtol``.
    """
    fast = kalman_filter(measurements, params)
    finite = measurements[np.isfinite(measurements)]
    mean_atol = 1e-9 * max(1.0, np.abs(finite).max(initial=0.0))
    var_atol = 1e-9 * max(params.p0, params.p0_velocity)
    for n in range(measurements.shape[1]):
        ref = kalman_filter_filterpy(measurements[:, n], params)
        for name in MEAN_FIELDS:
            np.testing.assert_allclose(
                getattr(fast, name)[:, n], getattr(ref, name), rtol=1e-9, atol=mean_atol,
                err_msg=name,
            )  # fmt: skip
        for name in VAR_FIELDS:
            rtol = smoothed_var_rtol if name == "filtered_var" and params.smoother else 1e-9
            np.testing.assert_allclose(
                getattr(fast, name)[:, n], getattr(ref, name), rtol=rtol, atol=var_atol,
                err_msg=name,
            )  # fmt: skip
        np.testing.assert_allclose(  # an error e in y moves the distance by <= e / sqrt(r)
            fast.mahalanobis[:, n], ref.mahalanobis, rtol=1e-9, atol=mean_atol / params.r**0.5
        )
        np.testing.assert_array_equal(fast.rejected[:, n], ref.rejected)
        np.testing.assert_array_equal(fast.started[:, n], ref.started)


def gappy_measurements(seed: int = 0, num_frames: int = 60) -> np.ndarray:
    """(T, 6, 3) random-walk joints with sporadic NaNs, a late start, a long gap, an outlier."""
    rng = np.random.default_rng(seed)
    z = 1000.0 + np.cumsum(rng.normal(0.0, 20.0, (num_frames, 6, 3)), axis=0)
    z[rng.random((num_frames, 6)) < 0.15] = np.nan
    z[:9, 1] = np.nan  # late start
    z[20:35, 2] = np.nan  # gap longer than max_gap -> re-initialisation
    z[:, 3] = np.nan  # never seen
    z[30, 4] += 400.0  # outlier
    z[10, 5, 1] = np.nan  # one coordinate missing = joint missing
    return z


@pytest.mark.parametrize("model", ["constant_velocity", "random_walk"])
@pytest.mark.parametrize("smoother", [False, True])
@pytest.mark.parametrize("gate", [None, 3.5])
def test_matches_filterpy(model: str, smoother: bool, gate: float | None) -> None:
    params = KalmanParams(
        model=model, q=50.0 if model == "random_walk" else None, smoother=smoother, gate=gate,
        max_gap=8,
    )  # fmt: skip
    assert_matches_reference(gappy_measurements(), params, smoothed_var_rtol=1e-6)


@st.composite
def filter_cases(draw) -> tuple[np.ndarray, KalmanParams]:
    num_frames = draw(st.integers(0, 30))
    num_joints = draw(st.integers(1, 3))
    seed = draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    z = rng.normal(0.0, 500.0, 3) + np.cumsum(rng.normal(0.0, 30.0, (num_frames, num_joints, 3)), 0)
    z[rng.random((num_frames, num_joints)) < draw(st.floats(0.0, 0.6))] = np.nan
    for j in range(num_joints):  # late starts
        z[: draw(st.integers(0, num_frames)), j] = np.nan
    model = draw(st.sampled_from(["constant_velocity", "random_walk"]))
    params = KalmanParams(
        model=model,
        # A small q makes the constant-velocity RTS ill-conditioned (see assert_matches_reference).
        q=draw(st.floats(10.0 if model == "constant_velocity" else 0.0, 1e3)),
        r=draw(st.floats(25.0, 1e3)),  # 5-32 mm noise
        p0=draw(st.floats(1e3, 1e7)),
        p0_velocity=draw(st.floats(1e3, 1e7)),
        control_gain=draw(st.floats(0.0, 1.0)),
        smoother=draw(st.booleans()),
        gate=draw(st.one_of(st.none(), st.floats(1.0, 10.0))),
        max_gap=draw(st.one_of(st.none(), st.integers(0, 6))),
    )
    return z, params


@settings(
    max_examples=60, deadline=None, database=None, suppress_health_check=[HealthCheck.too_slow]
)
@given(filter_cases())
def test_matches_filterpy_property(case: tuple[np.ndarray, KalmanParams]) -> None:
    z, params = case
    assert_matches_reference(z, params, smoothed_var_rtol=1e-3)


def test_synthetic_walk_accuracy() -> None:
    truth, z = synthetic_walk()
    result = kalman_filter(z, KalmanParams(smoother=True))
    raw = (mpjpe(z, truth), accel_error(z, truth))
    fwd = (mpjpe(result.forward, truth), accel_error(result.forward, truth))
    rts = (mpjpe(result.filtered, truth), accel_error(result.filtered, truth))
    # Measured (seed 0), MPJPE mm / accel error mm/frame^2:
    # raw 23.93 / 58.72, forward 23.82 / 33.85 (-42%), RTS 13.97 / 5.52.
    assert fwd[1] <= 0.6 * raw[1], (raw, fwd)
    assert fwd[0] <= raw[0] + 2.0, (raw, fwd)
    assert rts[0] < fwd[0] and rts[1] < fwd[1], (fwd, rts)
    assert rts[0] < 0.7 * raw[0] and rts[1] < 0.15 * raw[1], (raw, rts)


def test_synthetic_walk_random_walk_with_control() -> None:
    truth, z = synthetic_walk(seed=1)
    result = kalman_filter(z, KalmanParams(model="random_walk", q=400.0, smoother=True))
    raw = (mpjpe(z, truth), accel_error(z, truth))
    fwd = (mpjpe(result.forward, truth), accel_error(result.forward, truth))
    rts = (mpjpe(result.filtered, truth), accel_error(result.filtered, truth))
    # Measured (seed 1): raw 23.85 / 58.56, forward 22.54 / 31.39, RTS 16.21 / 13.32.
    assert fwd[1] <= 0.6 * raw[1] and fwd[0] <= raw[0] + 2.0, (raw, fwd)
    assert rts[0] < fwd[0] and rts[1] < fwd[1], (fwd, rts)
    # The default q = 0 stops listening to the measurements (documented caution).
    stiff = kalman_filter(z, KalmanParams(model="random_walk"))
    assert mpjpe(stiff.forward, truth) > 10.0 * raw[0]


def test_leading_shape_is_kept_and_matches_flat() -> None:
    truth, z = synthetic_walk(num_frames=30, num_people=2, num_joints=5)
    z[3:6, 1, 2] = np.nan
    params = KalmanParams(smoother=True)
    result = kalman_filter(z, params)
    flat = kalman_filter(z.reshape(30, 10, 3), params)
    assert result.filtered.shape == result.velocity.shape == (30, 2, 5, 3)
    assert result.mahalanobis.shape == result.rejected.shape == (30, 2, 5)
    np.testing.assert_array_equal(result.filtered.reshape(30, 10, 3), flat.filtered)
    np.testing.assert_array_equal(result.prior_var.reshape(30, 10, 3), flat.prior_var)


def test_outlier_gives_large_mahalanobis_and_gate_rejects_it() -> None:
    truth, z = synthetic_walk(num_frames=60, num_people=1, num_joints=4, seed=1)
    z[40, 0, 2, 0] = truth[40, 0, 2, 0] + 300.0  # a 300 mm jump along x at one frame
    free = kalman_filter(z)
    d = free.mahalanobis[:, 0]  # (T, joints)
    assert d[40, 2] > 8.0  # measured 10.1; sqrt(S) ~ 29 mm in steady state
    others = np.concatenate([d[5:, [0, 1, 3]].ravel(), d[5:40, 2]])
    assert d[40, 2] > 3.0 * np.median(others) and d[40, 2] > others.max()
    gated = kalman_filter(z, KalmanParams(gate=6.0))
    assert gated.rejected[40, 0, 2] and gated.rejected.sum() == 1
    np.testing.assert_array_equal(gated.forward[40, 0, 2], gated.prior_mean[40, 0, 2])
    err_gated = np.linalg.norm(gated.forward[40, 0, 2] - truth[40, 0, 2])
    err_free = np.linalg.norm(free.forward[40, 0, 2] - truth[40, 0, 2])
    assert err_free > 150.0 and err_gated < 0.3 * err_free  # measured 48 vs 232 mm


def test_missing_frames_are_predicted() -> None:
    truth, z = synthetic_walk(num_frames=50, num_people=1, num_joints=3, seed=2)
    z[20:25, 0, 1] = np.nan
    for params in (KalmanParams(), KalmanParams(model="random_walk", q=400.0)):
        result = kalman_filter(z, params)
        gap = result.forward[20:25, 0, 1]
        assert np.isfinite(gap).all() and np.isfinite(result.filtered[20:25, 0, 1]).all()
        np.testing.assert_array_equal(gap, result.prior_mean[20:25, 0, 1])  # predict-only
        assert np.isnan(result.innovation[20:25, 0, 1]).all()
        assert np.isnan(result.mahalanobis[20:25, 0, 1]).all()
        assert np.all(np.diff(result.posterior_var[19:25, 0, 1, 0]) > 0)  # variance grows
        assert np.isfinite(result.innovation_var[20:25, 0, 1]).all()


def test_late_start_and_long_gap_reinitialise() -> None:
    truth, z = synthetic_walk(num_frames=60, num_people=1, num_joints=1, seed=3)
    z = z[:, 0]  # (T, 1, 3)
    z[:5] = np.nan
    z[20:35] = np.nan  # 15 frames > max_gap = 10
    result = kalman_filter(z, KalmanParams(smoother=True))
    f = result.filtered[:, 0]
    assert np.isnan(f[:5]).all() and np.isfinite(f[5:30]).all()
    assert np.isnan(f[30:35]).all()  # coasted over frames 20..29 (gap 10), dropped at 30
    assert np.isfinite(f[35:]).all()
    assert np.flatnonzero(result.started[:, 0]).tolist() == [5, 35]
    np.testing.assert_array_equal(result.prior_mean[35, 0], z[35, 0])  # re-initialised at z
    assert result.mahalanobis[35, 0] == 0.0 and result.innovation_var[35, 0, 0] == 1e6 + 225
    np.testing.assert_array_equal(result.velocity[5, 0], result.velocity[5, 0])
    assert np.isnan(result.velocity[:5]).all()


def test_random_walk_control_input_is_last_posterior_step() -> None:
    truth, z = synthetic_walk(num_frames=40, num_people=1, num_joints=2, seed=4)
    z[10:13, 0, 0] = np.nan
    B = 0.7
    result = kalman_filter(z, KalmanParams(model="random_walk", q=100.0, control_gain=B))
    x = result.forward
    # x_{t|t-1} = x_{t-1|t-1} + B (x_{t-1|t-1} - x_{t-2|t-2}); u = 0 right after the start.
    np.testing.assert_allclose(result.prior_mean[2:], x[1:-1] + B * (x[1:-1] - x[:-2]), atol=1e-9)
    np.testing.assert_allclose(result.prior_mean[1], x[0], atol=1e-9)
    assert np.isnan(result.velocity).all()
    # The control carries the motion: a ramp is tracked far better than with B = 0.
    ramp = np.arange(50.0)[:, None, None] * np.array([30.0, -10.0, 5.0])
    errs = [
        np.abs(kalman_filter(ramp, KalmanParams(model="random_walk", q=10.0, control_gain=g))
               .forward[10:] - ramp[10:]).max()
        for g in (0.0, 1.0)
    ]  # fmt: skip
    assert errs[1] < 0.1 * errs[0]


def test_constant_velocity_estimates_velocity() -> None:
    ramp = 100.0 + np.arange(40.0)[:, None, None] * np.array([30.0, -10.0, 5.0])
    result = kalman_filter(ramp, KalmanParams(smoother=True))
    v_true = np.array([30.0, -10.0, 5.0])
    np.testing.assert_allclose(result.velocity[:, 0], np.tile(v_true, (40, 1)), atol=1e-2)
    np.testing.assert_allclose(result.velocity[5:, 0], np.tile(v_true, (35, 1)), atol=1e-3)
    np.testing.assert_allclose(result.filtered, ramp, atol=1e-2)  # the p0 priors bias frame 0


def test_all_nan_stays_nan_without_warnings() -> None:
    z = np.full((20, 2, 3, 3), np.nan)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for params in (KalmanParams(smoother=True), KalmanParams(model="random_walk", gate=3.0)):
            result = kalman_filter(z, params)
            for name in MEAN_FIELDS + VAR_FIELDS + ("mahalanobis",):
                assert np.isnan(getattr(result, name)).all(), name
            assert not result.rejected.any() and not result.started.any()
            ref = kalman_filter_filterpy(z[:, 0, 0], params)
            assert np.isnan(ref.filtered).all()


@pytest.mark.parametrize("shape", [(0, 3), (0, 4, 3), (5, 0, 3), (5, 2, 0, 3), (1, 3), (1, 2, 3)])
@pytest.mark.parametrize("smoother", [False, True])
def test_empty_and_tiny_inputs(shape: tuple[int, ...], smoother: bool) -> None:
    z = np.ones(shape)
    result = kalman_filter(z, KalmanParams(smoother=smoother))
    assert isinstance(result, FilterResult)
    assert result.filtered.shape == shape and result.mahalanobis.shape == shape[:-1]
    assert result.innovation_var.shape == shape
    if len(shape) == 2:
        ref = kalman_filter_filterpy(z, KalmanParams(smoother=smoother))
        assert ref.filtered.shape == shape


def test_bad_inputs_raise() -> None:
    with pytest.raises(ValueError, match="num_frames"):
        kalman_filter(np.zeros((10, 2)))
    with pytest.raises(ValueError, match="num_frames"):
        kalman_filter(np.zeros(3))
    with pytest.raises(ValueError, match=r"\(num_frames, 3\)"):
        kalman_filter_filterpy(np.zeros((10, 2, 3)))
    with pytest.raises(ValueError, match="model"):
        KalmanParams(model="constant_acceleration")
    with pytest.raises(ValueError, match="r must"):
        KalmanParams(r=0.0)
    with pytest.raises(ValueError, match="max_gap"):
        KalmanParams(max_gap=-1)


def test_defaults() -> None:
    assert KalmanParams().q == 200.0 and KalmanParams().r == 225.0
    assert KalmanParams(model="random_walk").q == 0.0
    assert KalmanParams(model="random_walk", q=5.0).q == 5.0
