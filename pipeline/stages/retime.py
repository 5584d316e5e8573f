"""Camera time offsets applied: each named camera's 2D re-timed before association
(``--set sync.offsets=cam02:+1.5,cam04:-3``, the offsets ``mvviz diagnose`` reports).

A camera with offset d (frames; positive = its frame g shows what the others show at
g - d) has, for the pipeline's frame t, its 2D of time t + d. With n = round(d) and
a = d - n in [-0.5, 0.5]: the row the camera recorded at frame g = t + n is used at frame
t (whole frames: the rows move, nothing else changes), and a fraction moves its joints
toward the same person's detection in the neighbouring frame g + sign(a), linearly:
(1 - |a|) x(g) + |a| x(g + sign a). The same person is that camera's detection at the
neighbouring frame nearest to it (one-to-one, within a gate that scales with the person's
size in the image). Rows keep their number and order, so the results' per-row arrays
still line up with the scene's detections; a row moved outside the clip gets a frame
outside ``[0, num_frames)`` and no frame's stages use it.

Pure functions over the detection columns; units: pixels, frames.
"""

from __future__ import annotations

import warnings

import numpy as np

from pipeline.core.assignment import gated_assignment

GATE_FRACTION = 0.25
"""A partner's mean joint distance must be under this fraction of the person's 2D extent
(bounding-box diagonal of its joints): people walk a few percent of their height per
frame; a different person is usually farther than a quarter of it."""
MIN_GATE_PX = 10.0
MIN_SHARED_JOINTS = 3


def offsets_setting(found: dict[str, float], applied: dict[str, float] | None = None) -> str:
    """The ``--set sync.offsets=`` value that applies ``found`` (camera -> frames, the
    offsets found in a run that had ``applied`` re-timing already: they add up), e.g.
    ``"cam02:+1.50,cam04:-3.00"``; empty when there is nothing to apply."""
    total = dict(applied or {})
    for name, d in found.items():
        total[name] = total.get(name, 0.0) + float(d)
    return ",".join(f"{k}:{v:+.2f}" for k, v in sorted(total.items()) if round(v, 2) != 0)


def split_offset(offset: float) -> tuple[int, float]:
    """``offset`` frames as (whole n, fraction a) with n = round half up, a in [-0.5, 0.5)."""
    n = int(np.floor(offset + 0.5))
    return n, float(offset - n)


def picture_frame(offsets: dict[str, float], camera: str, frame: int) -> int:
    """The frame of ``camera``'s recording (video or image folder) whose picture goes
    with the pipeline's ``frame`` when ``offsets`` (camera name -> frames it lags, as
    ``SyncConfig.by_camera()``) re-time it: ``frame`` + the whole part of its offset,
    where the rows used at ``frame`` were recorded. The sub-frame part moves only the 2D
    (a picture is never blended), so the viewer and every export show the same picture.
    May fall outside the recording (the caller shows none there)."""
    d = offsets.get(camera, 0.0)
    return int(frame) + split_offset(float(d))[0] if d else int(frame)


def retimed_frames(frame: np.ndarray, view: np.ndarray, offsets: dict[int, float]) -> np.ndarray:
    """(N,) the frame each row is used at (:func:`retimed_rows`' first output, alone)."""
    out = np.array(frame, int, copy=True)
    for v, d in offsets.items():
        out[view == v] -= split_offset(float(d))[0]
    return out


def retimed_rows(
    frame: np.ndarray,
    view: np.ndarray,
    joints2d: np.ndarray,
    offsets: dict[int, float],
) -> tuple[np.ndarray, np.ndarray]:
    """The frame each detection row is used at, and its re-timed 2D.

    Args:
        frame: (N,) int frame each row was recorded at.
        view: (N,) int camera of each row.
        joints2d: (N, J, 3) x px, y px, confidence (NaN or confidence 0 = missing).
        offsets: camera index -> offset in frames (positive: that camera lags).
    Returns:
        ``(frames, joints2d)``: (N,) int and (N, J, 3), new arrays (the inputs untouched).
    """
    frame = np.asarray(frame, int)
    out = np.array(joints2d, float, copy=True)
    for v, d in offsets.items():
        rows = np.flatnonzero(view == v)
        a = split_offset(float(d))[1]
        if abs(a) > 1e-9 and len(rows):
            out[rows] = _interpolated(frame[rows], joints2d[rows], a)
    return retimed_frames(frame, view, offsets), out


def _interpolated(frame: np.ndarray, kp: np.ndarray, a: float) -> np.ndarray:
    """One camera's rows (n,) / (n, J, 3), each moved a fraction ``a`` of a frame toward
    its partner at frame + sign(a)."""
    out = np.array(kp, float, copy=True)
    step = 1 if a > 0 else -1
    w = abs(a)
    partner = partners(frame, kp, step)
    i = np.flatnonzero(partner >= 0)
    j = partner[i]
    seen_i, seen_j = _seen(kp[i]), _seen(kp[j])  # (m, J)
    both = seen_i & seen_j
    mixed = (1 - w) * kp[i, :, :2] + w * kp[j, :, :2]
    out[i, :, :2] = np.where(both[..., None], mixed, kp[i, :, :2])
    conf = np.where(both, np.minimum(kp[i, :, 2], kp[j, :, 2]), kp[i, :, 2])
    # A joint the neighbouring frame misses keeps this frame's position: up to |a|
    # of a frame off in time, so it is trusted less, as a row without a partner.
    out[i, :, 2] = np.where(seen_i & ~both, conf * (1 - w), conf)
    has = partner >= 0
    # No partner (the person enters, leaves, or is missed in the neighbouring frame):
    # the row keeps its own frame's 2D, |a| of a frame away from the time it is used at.
    # Dropping it would lose a view of that person; keeping it at full confidence would
    # weigh a stale view as much as the re-timed ones. Its confidence is scaled by
    # 1 - |a| (at least 0.5), so triangulation leans on the cameras in time.
    out[~has, :, 2] *= 1 - w
    return out


def _seen(kp: np.ndarray) -> np.ndarray:
    return (np.nan_to_num(kp[..., 2]) > 0) & np.isfinite(kp[..., :2]).all(-1)


def partners(frame: np.ndarray, kp: np.ndarray, step: int) -> np.ndarray:
    """For each row of one camera, the row showing the same person at frame + ``step``
    (-1 if none): one-to-one per pair of frames, by the mean distance over the joints both
    see, gated by :data:`GATE_FRACTION` of the person's extent.

    Args:
        frame: (n,) int; kp: (n, J, 3) pixels and confidence.
    """
    out = np.full(len(frame), -1)
    seen = _seen(kp)
    order = np.argsort(frame, kind="stable")
    fs = frame[order]
    uniq, start = np.unique(fs, return_index=True)
    bounds = dict(zip(uniq.tolist(), zip(start, np.r_[start[1:], len(fs)], strict=True),
                      strict=True))  # fmt: skip
    for f, (lo, hi) in bounds.items():
        nb = bounds.get(f + step)
        if nb is None:
            continue
        a_rows, b_rows = order[lo:hi], order[nb[0] : nb[1]]
        cost = _pair_cost(kp[a_rows], seen[a_rows], kp[b_rows], seen[b_rows])
        ia, ib = gated_assignment(cost)
        out[a_rows[ia]] = b_rows[ib]
    return out


def _pair_cost(ka, sa, kb, sb) -> np.ndarray:
    """(A, B) mean joint distance px, inf where fewer than MIN_SHARED_JOINTS are shared or
    the distance is beyond the gate."""
    both = sa[:, None] & sb[None]  # (A, B, J)
    diff = np.nan_to_num(ka[:, None, :, :2]) - np.nan_to_num(kb[None, :, :, :2])
    dist = np.linalg.norm(diff, axis=-1)
    count = both.sum(-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(both, dist, 0.0).sum(-1) / count
    gate = np.maximum(GATE_FRACTION * _extent(ka, sa), MIN_GATE_PX)[:, None]
    return np.where((count >= MIN_SHARED_JOINTS) & (mean < gate), mean, np.inf)


def _extent(kp: np.ndarray, seen: np.ndarray) -> np.ndarray:
    """(n,) bounding-box diagonal px of each row's seen joints (0 with none)."""
    xy = np.where(seen[..., None], kp[..., :2], np.nan)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # a row with no joint seen: NaN
        span = np.nanmax(xy, 1) - np.nanmin(xy, 1)
    return np.nan_to_num(np.linalg.norm(span, axis=-1))
