"""The Kalman filter and RTS smoother of :mod:`pipeline.stages.kalman`, one joint at a
time with ``filterpy.kalman.KalmanFilter`` and its ``rts_smoother``: the slow textbook
reference the vectorised filter is checked against (tests/pipeline/test_kalman.py, to
1e-9) and timed against (bench/bench_kalman.py, bench/bench_pipeline.py).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from pipeline.stages.kalman import FilterResult, KalmanParams, _check_measurements


def _filterpy_factory(params: KalmanParams) -> Callable[[], Any]:
    """A function returning a fresh ``filterpy.kalman.KalmanFilter`` of the model, before x."""
    cv = params.model == "constant_velocity"
    I3 = np.eye(3)
    # imported here: filterpy pulls scipy.stats (~0.4 s), which nothing else at start needs
    from filterpy.common import Q_discrete_white_noise
    from filterpy.kalman import KalmanFilter

    def new_filter() -> KalmanFilter:
        kf = KalmanFilter(dim_x=6 if cv else 3, dim_z=3)
        if cv:  # state [x, y, z, vx, vy, vz]
            kf.F = np.block([[I3, I3], [0 * I3, I3]])
            kf.H = np.hstack([I3, 0 * I3])
            kf.Q = Q_discrete_white_noise(2, dt=1.0, var=params.q, block_size=3, order_by_dim=False)
            kf.P = np.diag([params.p0] * 3 + [params.p0_velocity] * 3)
        else:
            kf.F, kf.H, kf.Q = I3.copy(), I3.copy(), params.q * I3
            kf.B = params.control_gain * I3
            kf.P = params.p0 * I3
        kf.R = params.r * I3
        return kf

    return new_filter


def _filterpy_forward(
    zs: np.ndarray, params: KalmanParams, new_filter: Callable[[], Any]
) -> tuple[dict[str, np.ndarray], list[dict[str, list]]]:
    """The reference loop over frames with filterpy's ``predict(u)`` / ``update(z)``.

    Returns the per-frame outputs (``prior``, ``post``, ``prior_var``, ``post_var``,
    ``y``, ``S``, ``vel``: (T, 3); ``maha``: (T,); ``rejected``, ``started``: (T,) bool)
    and the initialised segments (per segment: frames, x, P, Bu) for the smoother.
    """
    T = zs.shape[0]
    cv = params.model == "constant_velocity"
    dim_x = 6 if cv else 3
    nan3 = np.full((T, 3), np.nan)
    out = {k: nan3.copy() for k in ("prior", "post", "prior_var", "post_var", "y", "S", "vel")}
    out["maha"] = np.full(T, np.nan)
    out["rejected"], out["started"] = np.zeros(T, dtype=bool), np.zeros(T, dtype=bool)
    segments: list[dict[str, list]] = []
    kf = None
    gap = 0
    u = np.zeros((3, 1))
    x_last = None
    for t in range(T):
        z = zs[t]
        has_z = bool(np.isfinite(z).all())
        Bu = np.zeros((dim_x, 1))
        if kf is not None:
            kf.predict(u=u if not cv else None)  # x = F x + B u ; P = F P F' + Q
            if not cv:
                Bu = kf.B @ u
        elif has_z:
            kf = new_filter()
            kf.x = np.zeros((dim_x, 1))
            kf.x[:3, 0] = z  # x = z (velocity 0)
            out["started"][t] = True
            gap = 0
            x_last = kf.x.copy()
            segments.append({"frames": [], "x": [], "P": [], "Bu": []})
        if kf is None:
            continue
        x_prior, P_prior = kf.x.copy(), kf.P.copy()
        accepted = False
        if has_z:
            kf.update(z)  # y = z - H x ; S = H P H' + R ; K = P H' S^-1 ; x = x + K y
            d = kf.mahalanobis
            out["y"][t], out["S"][t], out["maha"][t] = kf.y[:, 0], np.diag(kf.S), d
            accepted = params.gate is None or out["started"][t] or d <= params.gate
            if not accepted:  # rejected by the gate: posterior = prior
                kf.x, kf.P = x_prior.copy(), P_prior.copy()
                out["rejected"][t] = True
        else:
            out["S"][t] = np.diag(kf.H @ kf.P @ kf.H.T + kf.R)  # S = H P H' + R
            kf.update(None)  # no measurement: posterior = prior
        gap = 0 if accepted else gap + 1
        if params.max_gap is not None and gap > params.max_gap:
            kf = None  # dropped: outputs stay NaN at this frame
            out["y"][t], out["S"][t], out["maha"][t], out["rejected"][t] = (
                np.nan,
                np.nan,
                np.nan,
                False,
            )
            continue
        out["prior"][t], out["prior_var"][t] = x_prior[:3, 0], np.diag(P_prior)[:3]
        out["post"][t], out["post_var"][t] = kf.x[:3, 0], np.diag(kf.P)[:3]
        if cv:
            out["vel"][t] = kf.x[3:, 0]
        seg = segments[-1]
        seg["frames"].append(t)
        seg["x"].append(kf.x[:, 0].copy())
        seg["P"].append(kf.P.copy())
        seg["Bu"].append(Bu[:, 0])
        u = kf.x - x_last  # u = x_{t|t} - x_{t-1|t-1}
        x_last = kf.x.copy()
    return out, segments


def _filterpy_smooth(
    out: dict[str, np.ndarray],
    segments: list[dict[str, list]],
    params: KalmanParams,
    new_filter: Callable[[], Any],
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """filterpy's ``rts_smoother`` on each segment: (T, 3) position, variance, velocity.

    The random walk runs in coordinates shifted by ``D_k = F D_{k-1} + B u_k``.
    """
    filtered, filtered_var, filt_vel = out["post"].copy(), out["post_var"].copy(), out["vel"].copy()
    F = new_filter().F
    for seg in segments:
        if not seg["frames"]:
            continue
        Xs, Ps = np.array(seg["x"]), np.array(seg["P"])
        D = np.zeros_like(Xs)  # D_k = F D_{k-1} + B u_k
        for k in range(1, len(D)):
            D[k] = F @ D[k - 1] + seg["Bu"][k]
        xs, Pss, _, _ = new_filter().rts_smoother(Xs - D, Ps)
        xs = xs + D
        f = seg["frames"]
        filtered[f] = xs[:, :3]
        filtered_var[f] = np.diagonal(Pss, axis1=1, axis2=2)[:, :3]
        if params.model == "constant_velocity":
            filt_vel[f] = xs[:, 3:]
    return filtered, filtered_var, filt_vel


def kalman_filter_filterpy(
    measurements: np.ndarray, params: KalmanParams | None = None
) -> FilterResult:
    """Reference: one joint, ``filterpy.kalman.KalmanFilter`` step by step.

    Same semantics as :func:`kalman_filter` (initialisation, gate, max_gap),
    written as a plain loop over frames with filterpy's ``predict(u)`` /
    ``update(z)`` and ``rts_smoother`` on each initialised segment. filterpy's
    ``rts_smoother`` has no control term, so for the random walk it runs in
    coordinates shifted by the accumulated control ``D_k = F D_{k-1} + B u_k``
    (in which the model has no control input) and shifts back.

    Args:
        measurements: (num_frames, 3) one joint's positions, mm; NaN = missing.
        params: filter parameters (default ``KalmanParams()``).

    Returns:
        FilterResult with leading shape (num_frames,).
    """
    params = KalmanParams() if params is None else params
    zs = _check_measurements(measurements)
    if zs.ndim != 2:
        raise ValueError(f"measurements must be (num_frames, 3), got shape {zs.shape}")
    new_filter = _filterpy_factory(params)
    out, segments = _filterpy_forward(zs, params, new_filter)
    filtered, filtered_var, filt_vel = out["post"].copy(), out["post_var"].copy(), out["vel"].copy()
    if params.smoother:
        filtered, filtered_var, filt_vel = _filterpy_smooth(out, segments, params, new_filter)
    return FilterResult(
        filtered=filtered,
        filtered_var=filtered_var,
        forward=out["post"],
        posterior_var=out["post_var"],
        prior_mean=out["prior"],
        prior_var=out["prior_var"],
        innovation=out["y"],
        innovation_var=out["S"],
        mahalanobis=out["maha"],
        velocity=filt_vel,
        rejected=out["rejected"],
        started=out["started"],
    )
