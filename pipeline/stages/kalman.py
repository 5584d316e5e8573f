"""Kalman filtering (and RTS smoothing) of 3D joint trajectories.

Units: millimetres, one filter step per frame (dt = 1 frame), so velocities are
mm/frame and accelerations mm/frame^2. Measurements are triangulated joints
``(num_frames, ..., 3)``; every leading axis after time (people, joints, ...) is
an independent trajectory, and results keep the measurements' leading shape.

Models (textbook symbols as in filterpy: x, P, F, Q, H, R, K, y, S):

``"constant_velocity"`` (default). Per axis the state is (position, velocity)::

    F = [[1, 1], [0, 1]]   H = [1, 0]   R = r
    Q = q * [[1/4, 1/2], [1/2, 1]]       (dt = 1)

  This is the piecewise-constant white-acceleration model (filterpy's
  ``Q_discrete_white_noise(2, dt=1, var=q)``): ``q`` is the variance of the
  per-frame acceleration, (mm/frame^2)^2.

``"random_walk"``. Per axis the state is the position alone::

    F = 1   H = 1   R = r   Q = q  (default q = 0)   x = F x + B u

  The motion an F = I model lacks is carried by a control input: ``u_t =
  x_{t-1|t-1} - x_{t-2|t-2}``, the displacement between the last two posterior
  means (0 on the first step after (re)initialisation), with ``B =
  control_gain`` (a scalar times I). So ``B = 1`` extrapolates the last posterior
  step in full, ``0 < B < 1`` damps it, ``B = 0`` is a plain random walk. ``u``
  is treated as a known input: it enters the prior mean, not the covariance,
  and the RTS smoother subtracts it too (``x_{k+1|k} = F x_{k|k} + B u_{k+1}``).
  Caution: with the default ``q = 0`` the gain falls like 1/t, so after a few
  dozen frames the filter ignores the measurements and follows its own
  extrapolation (on the synthetic walk of the tests: MPJPE ~630 mm against 24 mm
  raw). Give ``q > 0`` for real sequences: ``q = 400, control_gain = 0.8`` gives
  22.2 mm / accel error 31.5 forward, 16.1 mm / 13.4 smoothed there.

The three axes of a joint are filtered independently with identical F, H, Q, R,
so the 3- or 6-dimensional filter is block diagonal: one 1x1 (random walk) or
2x2 (constant velocity) filter per axis, and the covariance is the same for the
three axes of a joint. That is what lets :func:`kalman_filter` run elementwise
over all people, joints and axes at once with closed-form 1x1/2x2 algebra.

Missing data and track life cycle, per joint:

- A joint counts as measured at a frame when all three coordinates are finite.
  Without a measurement the step is predict-only (posterior = prior).
- Until its first measurement a trajectory is uninitialised and every output
  is NaN. At that measurement the prior is set to it (position z, variance p0;
  velocity 0 with variance p0_velocity, uncorrelated) and then updated with it
  as usual, so that frame has innovation 0, Mahalanobis distance 0 and S = p0 + r.
- Optional gate: a measurement whose Mahalanobis distance exceeds ``gate`` is
  rejected (reported in ``rejected``) and the step is predict-only; its
  innovation and distance are still reported. The initialising measurement is
  never gated. Choose it generously: when the motion is not white acceleration
  the innovations are larger than S predicts (on the synthetic walk with 2 Hz
  swings, mean y' S^-1 y is ~6 instead of 3), so ~6 rather than the chi(3)
  99.9% point 4.0.
- Coasting is bounded: when a trajectory has gone more than ``max_gap``
  consecutive frames without an accepted measurement it is dropped (all outputs
  NaN from that frame) and re-initialised at its next measurement rather than
  coasting on a prediction whose variance has grown useless. Smoothing never
  crosses a re-initialisation.

Defaults: ``r = 225`` (15 mm triangulation noise), ``p0 = p0_velocity = 1e6``
(diffuse: the first two measurements set position and velocity), and for the
constant-velocity model ``q = 200`` (mm/frame^2)^2, i.e. a 14 mm/frame^2 = 8.8
m/s^2 acceleration std, tuned on synthetic walks at 25 fps (0.5-1.5 m/s, 2 Hz
swings of 20-150 mm, 15 mm noise): the forward filter cuts the acceleration error
by 42% at unchanged MPJPE (24 mm), the RTS smoother reaches 14 mm and -90%.
Smaller q smooths more but lags (q = 100: +5 mm MPJPE); larger q follows the
noise (q = 500: only -34% acceleration error).

The slow reference built on ``filterpy.kalman.KalmanFilter`` and its
``rts_smoother`` (bench/reference_kalman.py) is what the tests check this filter
against.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

MODELS = ("constant_velocity", "random_walk")
# Tuned on synthetic walks at 25 fps (0.5-1.5 m/s, 2 Hz limb swing, 15 mm noise):
# see tests/pipeline/test_kalman.py::test_synthetic_walk_accuracy.
DEFAULT_Q = {"constant_velocity": 200.0, "random_walk": 0.0}


@dataclass(frozen=True)
class KalmanParams:
    """Parameters of :func:`kalman_filter` (millimetres, frames).

    Attributes:
        model: ``"constant_velocity"`` or ``"random_walk"`` (see the module docstring).
        q: process noise. Constant velocity: per-frame acceleration variance,
            (mm/frame^2)^2, ``Q = q [[1/4, 1/2], [1/2, 1]]``. Random walk: position
            variance added per frame, mm^2. ``None`` takes the model's default
            (``DEFAULT_Q``: 200 for constant velocity, 0 for random walk).
        r: measurement variance per axis, mm^2 (225 = 15 mm triangulation noise).
        p0: initial position variance, mm^2 (large: the first measurement wins).
        p0_velocity: initial velocity variance, (mm/frame)^2 (constant velocity only).
        control_gain: B of the random-walk model's control input (0 disables it;
            unused by the constant-velocity model).
        smoother: also run the Rauch-Tung-Striebel smoother; ``filtered`` is then
            the smoothed estimate.
        gate: Mahalanobis distance above which a measurement is rejected, or None.
        max_gap: frames a trajectory may coast without an accepted measurement
            before it is dropped and re-initialised at the next one; None = never.
    """

    model: str = "constant_velocity"
    q: float | None = None
    r: float = 225.0
    p0: float = 1e6
    p0_velocity: float = 1e6
    control_gain: float = 0.8
    smoother: bool = False
    gate: float | None = None
    max_gap: int | None = 10

    def __post_init__(self) -> None:
        if self.model not in MODELS:
            raise ValueError(f"model must be one of {MODELS}, got {self.model!r}")
        if self.q is None:
            object.__setattr__(self, "q", DEFAULT_Q[self.model])
        if not (np.isfinite(self.q) and self.q >= 0):
            raise ValueError(f"q must be finite and >= 0, got {self.q}")
        for name in ("r", "p0", "p0_velocity"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be finite and > 0, got {value}")
        if not np.isfinite(self.control_gain):
            raise ValueError(f"control_gain must be finite, got {self.control_gain}")
        if self.gate is not None and not self.gate > 0:
            raise ValueError(f"gate must be None or > 0, got {self.gate}")
        if self.max_gap is not None and not (int(self.max_gap) == self.max_gap >= 0):
            raise ValueError(f"max_gap must be None or an integer >= 0, got {self.max_gap}")


@dataclass(frozen=True, eq=False)
class FilterResult:
    """Per-frame filter output; ``...`` is the measurements' leading shape after time.

    Entries are NaN wherever the trajectory is not initialised (before its first
    measurement, or dropped after a gap longer than ``max_gap``).

    Attributes:
        filtered: (num_frames, ..., 3) estimate, mm: the smoothed mean when
            ``params.smoother`` is set, else the forward posterior mean.
        filtered_var: (num_frames, ..., 3) position variance of ``filtered``, mm^2.
        forward: (num_frames, ..., 3) forward posterior mean x_{t|t}, mm.
        posterior_var: (num_frames, ..., 3) forward posterior position variance, mm^2.
        prior_mean: (num_frames, ..., 3) predicted mean x_{t|t-1}, mm.
        prior_var: (num_frames, ..., 3) predicted position variance, mm^2.
        innovation: (num_frames, ..., 3) y = z - H x_{t|t-1}, mm; NaN without a measurement.
        innovation_var: (num_frames, ..., 3) S = H P H' + R, mm^2 (also without a
            measurement: the spread a measurement would have had).
        mahalanobis: (num_frames, ...) sqrt(sum_axes y^2 / S); NaN without a measurement.
        velocity: (num_frames, ..., 3) velocity of ``filtered``, mm/frame (constant
            velocity model; NaN for the random walk).
        rejected: (num_frames, ...) bool, measurement present but rejected by the gate
            (or skipped: ``skip``).
        started: (num_frames, ...) bool, trajectory (re)initialised at this frame.
    """

    filtered: np.ndarray
    filtered_var: np.ndarray
    forward: np.ndarray
    posterior_var: np.ndarray
    prior_mean: np.ndarray
    prior_var: np.ndarray
    innovation: np.ndarray
    innovation_var: np.ndarray
    mahalanobis: np.ndarray
    velocity: np.ndarray
    rejected: np.ndarray
    started: np.ndarray


def _check_measurements(measurements: np.ndarray) -> np.ndarray:
    z = np.asarray(measurements, dtype=np.float64)
    if z.ndim < 2 or z.shape[-1] != 3:
        raise ValueError(f"measurements must be (num_frames, ..., 3), got shape {z.shape}")
    return z


class Belief(NamedTuple):
    """Gaussian belief of N trajectories, elementwise per axis (one 2x2 or 1x1 filter per axis).

    Attributes:
        x: (N, 3) position mean, mm; NaN where the trajectory is not alive.
        v: (N, 3) velocity mean, mm/frame (stays 0 for the random walk).
        Ppp: (N,) position variance, mm^2, shared by the three axes; NaN where not alive.
        Ppv: (N,) position-velocity covariance, mm^2/frame (0 for the random walk).
        Pvv: (N,) velocity variance, (mm/frame)^2 (constant velocity only).
    """

    x: np.ndarray
    v: np.ndarray
    Ppp: np.ndarray
    Ppv: np.ndarray
    Pvv: np.ndarray


def predict(b: Belief, u: np.ndarray, *, cv: bool, q: float, B: float) -> Belief:
    """Prior of the next frame: x = F x + B u, P = F P F' + Q.

    Constant velocity: ``F = [[1, 1], [0, 1]]``, ``Q = q [[1/4, 1/2], [1/2, 1]]``, no
    control. Random walk: ``F = 1``, ``Q = q``, ``u`` (N, 3) the last posterior step, mm.
    """
    if cv:
        return Belief(
            b.x + b.v,  # x = x + v dt
            b.v,
            b.Ppp + (2.0 * b.Ppv + b.Pvv + 0.25 * q),  # P_pp = P_pp + 2 P_pv + P_vv + q/4
            b.Ppv + (b.Pvv + 0.5 * q),  # P_pv = P_pv + P_vv + q/2
            b.Pvv + q,  # P_vv = P_vv + q
        )
    x = b.x + B * u if B != 0.0 else b.x  # x = x + B u,  u = x_{t-1|t-1} - x_{t-2|t-2}
    return b._replace(x=x, Ppp=b.Ppp + q)  # P = P + Q


def initialise(
    b: Belief, z: np.ndarray, new: np.ndarray, *, p0: float, p0_velocity: float
) -> Belief:
    """(Re)start the trajectories flagged ``new`` (N,) at their measurement ``z`` (N, 3), mm.

    x = z, v = 0, P = diag(p0, p0_velocity); the other trajectories are unchanged.
    """
    new3 = new[:, None]
    return Belief(
        np.where(new3, z, b.x),  # x = z
        np.where(new3, 0.0, b.v),
        np.where(new, p0, b.Ppp),  # P = P0
        np.where(new, 0.0, b.Ppv),
        np.where(new, p0_velocity, b.Pvv),
    )


def gate_measurements(
    y: np.ndarray, S: np.ndarray, observed: np.ndarray, new: np.ndarray, gate: float
) -> tuple[np.ndarray, np.ndarray]:
    """Accept a measurement when sqrt(y' S^-1 y) <= gate or it (re)starts its trajectory.

    Args:
        y: (N, 3) innovation z - H x, mm. S: (N,) innovation variance per axis, mm^2.
        observed, new: (N,) bool, measured / (re)initialised at this frame.

    Returns:
        (N,) 1.0 where the measurement updates, else 0.0; (N,) bool rejected by the gate.
    """
    d = np.sqrt((y * y).sum(axis=-1) / S)  # sqrt(y' S^-1 y)
    accept = observed & ((d <= gate) | new)
    return accept.astype(np.float64), observed & ~accept


def update(b: Belief, y: np.ndarray, S: np.ndarray, m: np.ndarray, *, cv: bool) -> Belief:
    """Posterior: K = P H' S^-1, x = x + K y, P = P - K S K' (H = [1, 0] or 1).

    Args:
        y: (N, 3) innovation z - H x, mm. S: (N,) H P H' + R, mm^2.
        m: (N,) 1.0 where the measurement is used, 0.0 where not (K = 0: posterior = prior).
    """
    Kp = b.Ppp / S * m  # K_p = P_pp / S
    x = b.x + Kp[:, None] * y  # x = x + K y
    if not cv:
        return b._replace(x=x, Ppp=b.Ppp - Kp * b.Ppp)  # P = P - K S K'
    Kv = b.Ppv / S * m  # K_v = P_pv / S
    return Belief(
        x,
        b.v + Kv[:, None] * y,  # v = v + K_v y
        b.Ppp - Kp * b.Ppp,  # P = P - K S K'  (pp)
        b.Ppv - Kp * b.Ppv,  # (pv)
        b.Pvv - Kv * b.Ppv,  # (vv)
    )


def drop_lost(b: Belief, lost: np.ndarray) -> Belief:
    """Mark the trajectories flagged ``lost`` (N,) as not alive (NaN mean and variance)."""
    return b._replace(x=np.where(lost[:, None], np.nan, b.x), Ppp=np.where(lost, np.nan, b.Ppp))


class _Steps(NamedTuple):
    """Per-frame record of the forward pass: means (T, N, 3), variances and flags (T, N)."""

    prior_mean: np.ndarray
    prior_pp: np.ndarray
    post_mean: np.ndarray
    post_pp: np.ndarray
    post_vel: np.ndarray
    post_pv: np.ndarray
    post_vv: np.ndarray
    innovation: np.ndarray
    rejected: np.ndarray
    started: np.ndarray


def _forward_pass(
    z_all: np.ndarray, observed: np.ndarray, skip: np.ndarray, params: KalmanParams
) -> _Steps:
    """The loop over frames: predict, (re)initialise, gate, update, drop.

    ``z_all`` (T, N, 3) mm with NaN rows where ``observed`` (T, N) is False; ``skip``
    (T, N) measurements not taken while their trajectory is alive and would not be dropped
    for the gap (a trajectory that is not, after a drop or before its start, or that
    would be, takes them: a doubtful point beats none).
    """
    T, N = observed.shape
    cv = params.model == "constant_velocity"
    shape3, shape1 = (T, N, 3), (T, N)
    nan3, nan1 = (lambda: np.full(shape3, np.nan)), (lambda: np.full(shape1, np.nan))
    s = _Steps(
        prior_mean=nan3(), prior_pp=nan1(), post_mean=nan3(), post_pp=nan1(),
        post_vel=nan3(), post_pv=nan1(), post_vv=nan1(), innovation=nan3(),
        rejected=np.zeros(shape1, dtype=bool), started=np.zeros(shape1, dtype=bool),
    )  # fmt: skip
    z_fill = np.where(observed[..., None], z_all, 0.0)  # NaN-free; missing rows get K = 0
    q, r, B = float(params.q), float(params.r), float(params.control_gain)
    gate, max_gap = params.gate, params.max_gap
    # NaN in x / Ppp marks a trajectory that is not alive; it stays NaN through the steps.
    b = Belief(
        np.full((N, 3), np.nan), np.zeros((N, 3)), np.full(N, np.nan), np.zeros(N), np.zeros(N)
    )
    x_last = np.full((N, 3), np.nan)  # previous posterior mean (random-walk control)
    u = np.zeros((N, 3))
    alive = np.zeros(N, dtype=bool)
    gap = np.zeros(N)
    for t in range(T):
        b = predict(b, u, cv=cv, q=q, B=B)  # 1. x = F x + B u, P = F P F' + Q
        skipped = skip[t] & alive & observed[t]
        if max_gap is not None:
            skipped &= gap + 1.0 <= max_gap  # a skip must not make it drop (below)
        taken = observed[t] & ~skipped
        new = observed[t] & ~alive  # 2. (re)initialise: first measurement since start/drop
        if new.any():
            b = initialise(b, z_all[t], new, p0=params.p0, p0_velocity=params.p0_velocity)
            x_last = np.where(new[:, None], z_all[t], x_last)  # so that u = 0 on the next step
            alive = alive | new
            s.started[t] = new
        s.prior_mean[t], s.prior_pp[t] = b.x, b.Ppp
        y = z_fill[t] - b.x  # 3. y = z - H x
        S = b.Ppp + r  # S = H P H' + R
        s.innovation[t] = y
        if gate is None:
            m = taken.astype(np.float64)
        else:
            m, s.rejected[t] = gate_measurements(y, S, taken, new, gate)
        s.rejected[t] |= skipped
        b = update(b, y, S, m, cv=cv)  # K = 0 without an accepted measurement
        gap = (gap + 1.0) * (1.0 - m)  # 4. drop trajectories that coasted > max_gap frames
        if max_gap is not None:
            lost = alive & (gap > max_gap)
            if lost.any():
                b = drop_lost(b, lost)
                alive = alive & ~lost
        s.post_mean[t], s.post_pp[t] = b.x, b.Ppp
        if cv:
            s.post_vel[t], s.post_pv[t], s.post_vv[t] = b.v, b.Ppv, b.Pvv
        else:
            u = b.x - x_last  # u_{t+1} = x_{t|t} - x_{t-1|t-1}
            x_last = b.x
    return s


def _skip_mask(skip: np.ndarray | None, shape: tuple, observed: np.ndarray) -> np.ndarray:
    """``skip`` (frames and trajectories: ``shape``) as (T, N) bool of observed entries."""
    if skip is None:
        return np.zeros(observed.shape, bool)
    if np.shape(skip) != shape:
        raise ValueError(
            f"skip must be {shape} (frames and trajectories of the measurements), "
            f"got {np.shape(skip)}"
        )
    return np.asarray(skip, bool).reshape(observed.shape) & observed


def kalman_filter(
    measurements: np.ndarray, params: KalmanParams | None = None, *, skip: np.ndarray | None = None
) -> FilterResult:
    """Filter every trajectory in ``measurements`` at once (loop over time only).

    The steps are the pure functions :func:`predict`, :func:`initialise`,
    :func:`gate_measurements`, :func:`update`, :func:`drop_lost` (loop in
    ``_forward_pass``) and the smoother ``_rts``.

    Args:
        measurements: (num_frames, ..., 3) joint positions, mm; NaN = missing.
        params: filter parameters (default ``KalmanParams()``).
        skip: (num_frames, ...) bool, measurements the filter does not take while their
            trajectory is alive (it coasts there as through a gap); they are reported
            ``rejected``, with their innovation.

    Returns:
        FilterResult with leading shape (num_frames, ...).
    """
    params = KalmanParams() if params is None else params
    z_all = _check_measurements(measurements)
    T, lead = z_all.shape[0], z_all.shape[1:-1]
    N = int(np.prod(lead, dtype=np.int64))
    z_all = z_all.reshape(T, N, 3)
    cv = params.model == "constant_velocity"
    observed = np.isfinite(z_all).all(axis=-1)  # (T, N)
    s = _forward_pass(z_all, observed, _skip_mask(skip, z_all.shape[:1] + lead, observed), params)

    # Outputs derived from the stored steps; blank frames where the trajectory is not
    # alive (before its start, or on/after a drop) and innovations without a measurement.
    dead = ~np.isfinite(s.post_pp)
    innovation = s.innovation
    innovation[~observed] = np.nan
    innov_var = s.prior_pp + params.r  # S = H P H' + R
    maha = np.sqrt((innovation * innovation).sum(axis=-1) / innov_var)  # sqrt(y' S^-1 y)
    blanked = (s.prior_mean, innovation, s.post_vel, s.prior_pp, innov_var, maha, s.post_pv)
    for a in (*blanked, s.post_vv):
        a[dead] = np.nan
    rejected = s.rejected & ~dead

    filt_mean, filt_pp, filt_vel = s.post_mean, s.post_pp, s.post_vel
    if params.smoother and T > 0:
        # Step k+1 continues step k's trajectory: the smoother may link them.
        link = np.zeros((T, N), dtype=bool)
        link[1:] = ~dead[:-1] & ~dead[1:] & ~s.started[1:]
        filt_mean, filt_pp, filt_vel = _rts(
            cv, float(params.q), link, s.post_mean, s.post_pp, s.post_pv, s.post_vv, s.post_vel,
            s.prior_mean, s.prior_pp,
        )  # fmt: skip
        filt_mean[dead] = np.nan

    def out3(a: np.ndarray) -> np.ndarray:
        return a.reshape((T, *lead, 3))

    def out1(a: np.ndarray) -> np.ndarray:
        return a.reshape((T, *lead))

    def var3(a: np.ndarray) -> np.ndarray:
        return out3(np.repeat(a[..., None], 3, axis=-1))

    if not cv:
        filt_vel = np.full((T, N, 3), np.nan)
    return FilterResult(
        filtered=out3(filt_mean),
        filtered_var=var3(filt_pp),
        forward=out3(s.post_mean),
        posterior_var=var3(s.post_pp),
        prior_mean=out3(s.prior_mean),
        prior_var=var3(s.prior_pp),
        innovation=out3(innovation),
        innovation_var=var3(innov_var),
        mahalanobis=out1(maha),
        velocity=out3(filt_vel),
        rejected=out1(rejected),
        started=out1(s.started),
    )


def _rts(
    cv: bool,
    q: float,
    link: np.ndarray,
    x_post: np.ndarray,
    Ppp_post: np.ndarray,
    Ppv_post: np.ndarray,
    Pvv_post: np.ndarray,
    v_post: np.ndarray,
    x_prior: np.ndarray,
    Ppp_prior: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rauch-Tung-Striebel smoother over the forward pass, elementwise per axis.

    ``x_s[k] = x[k] + C_k (x_s[k+1] - x_prior[k+1])`` with ``C_k = P[k] F' Pp[k+1]^-1``
    and ``P_s[k] = P[k] + C_k (P_s[k+1] - Pp[k+1]) C_k'``; the prior at k+1 includes
    the control term. ``C_k = 0`` where ``link[k+1]`` is False (no trajectory across).
    Means (T, N, 3) and variances (T, N) as produced by :func:`kalman_filter`.
    The variance recursion is the textbook one (as filterpy's): it cancels twice,
    in det(Pp) and in the sum, so with a small q and a large p0_velocity / r the
    smoothed variance right after a start can be off by ~1e-4 relative (the means
    are not affected at that level).

    Returns:
        smoothed position (T, N, 3), position variance (T, N), velocity (T, N, 3).
    """
    T = x_post.shape[0]
    lk = link[1:]
    # Gains are data independent: compute them for all k at once (NaN-free where unlinked).
    a = np.where(lk, Ppp_prior[1:], 1.0)
    if cv:  # Pp[k+1] = F P[k] F' + Q; its pp entry was stored by the forward pass
        b = np.where(lk, Ppv_post[:-1] + (Pvv_post[:-1] + 0.5 * q), 0.0)
        c = np.where(lk, Pvv_post[:-1] + q, 1.0)
        det = a * c - b * b  # det(Pp)
        # P F' with F = [[1, 1], [0, 1]]: [[pp + pv, pv], [pv + vv, vv]]
        pp, pv, vv = Ppp_post[:-1], Ppv_post[:-1], Pvv_post[:-1]
        m00, m01, m10, m11 = pp + pv, pv, pv + vv, vv
        # C = (P F') Pp^-1, Pp^-1 = [[c, -b], [-b, a]] / det
        C00 = np.where(lk, (m00 * c - m01 * b) / det, 0.0)
        C01 = np.where(lk, (m01 * a - m00 * b) / det, 0.0)
        C10 = np.where(lk, (m10 * c - m11 * b) / det, 0.0)
        C11 = np.where(lk, (m11 * a - m10 * b) / det, 0.0)
    else:
        C00 = np.where(lk, Ppp_post[:-1] / a, 0.0)  # C = P / Pp

    # Differences are taken only where linked; unlinked entries multiply a zero gain.
    xs = np.nan_to_num(x_post)
    xp = np.nan_to_num(x_prior)
    Ps = np.nan_to_num(Ppp_post)
    if cv:
        vs = np.nan_to_num(v_post)
        vp = np.zeros_like(vs)
        vp[1:] = np.nan_to_num(v_post[:-1])  # F = [[1, 1], [0, 1]] keeps v in the prior
        Pvs, Pvvs = np.nan_to_num(Ppv_post), np.nan_to_num(Pvv_post)
    for k in range(T - 2, -1, -1):
        dx = xs[k + 1] - xp[k + 1]  # x_s[k+1] - x_prior[k+1]
        dP = Ps[k + 1] - a[k]  # P_s[k+1] - Pp[k+1]  (pp)
        if cv:
            dv = vs[k + 1] - vp[k + 1]  # velocity part
            dPpv = Pvs[k + 1] - b[k]  # (pv)
            dPvv = Pvvs[k + 1] - c[k]  # (vv)
            c00, c01, c10, c11 = C00[k], C01[k], C10[k], C11[k]
            xs[k] += c00[:, None] * dx + c01[:, None] * dv  # x += C (x_s - x_prior)
            vs[k] += c10[:, None] * dx + c11[:, None] * dv
            # P += C dP C'
            Ps[k] += c00 * c00 * dP + 2.0 * c00 * c01 * dPpv + c01 * c01 * dPvv
            Pvs[k] += c00 * c10 * dP + (c00 * c11 + c01 * c10) * dPpv + c01 * c11 * dPvv
            Pvvs[k] += c10 * c10 * dP + 2.0 * c10 * c11 * dPpv + c11 * c11 * dPvv
        else:
            c00 = C00[k]
            xs[k] += c00[:, None] * dx  # x += C (x_s - x_prior)
            Ps[k] += c00 * c00 * dP  # P += C^2 (P_s - Pp)
    dead = ~np.isfinite(Ppp_post)
    Ps[dead] = np.nan
    if cv:
        vs[dead] = np.nan
        return xs, Ps, vs
    return xs, Ps, np.full_like(xs, np.nan)
