"""Camera time offsets, found from the people themselves.

For a camera c and a whole shift s (frames; positive = c's frames lag the others, its
frame g shows what the others show at g - s), the other cameras' joints of every track
at frame g - s (:mod:`pipeline.diagnose.reference`, smoothed over +-2 frames with a
symmetric window, which lowers their noise without moving them in time) are projected
into c and compared with c's own 2D at frame g: per (frame, track) the
confidence-weighted mean of min(d^2, cap^2) over the joints both see, against c's
nearest detection (a person c does not see counts cap^2 whatever the shift: occlusion
adds a constant, not a minimum). The whole shift with the smallest mean, refined by the
vertex of the parabola through it and its neighbours, is the offset (see
:func:`shift_cost` for why that is enough for a sub-frame offset). Each track is matched
to c's nearest detection, never to a fixed one, so several people make it more robust.

Unlike a keypoint-speed correlation (Pose2Sim's), this uses the calibration and every
person at once, and gives a residual in pixels whose minimum says how well the camera
agrees with the others once shifted. How far the offset can be trusted is measured, not
guessed: its jackknife standard error over blocks of frames (``confidence`` =
exp(-error / 0.1 frame)); a scene where nobody moves has no information about time and
says so (a flat curve: confidence 0).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.data.cameras import Camera
from pipeline.data.scene import Scene
from pipeline.diagnose.reference import MIN_CONFIDENCE, camera_detections, track_points_without
from pipeline.results.store import PipelineResults

CAP_PX = 50.0
MAX_SHIFT = 12  # frames tried either way
CONF_POWER = 2.0
SMOOTH = 2  # half-width (frames) of the reference's symmetric temporal smoothing
MIN_JOINTS = 3  # a (frame, track) pair needs this many joints seen by both sides
OFFSET_TOLERANCE = 0.15  # frames: |offset| below this is "in sync"
TRUSTED_CONFIDENCE = 0.5
JACKKNIFE_BLOCKS = 8
MIN_CONTRAST = 0.05  # the best shift must beat the typical one by 5 % (px^2)
SPREAD_SCALE = 0.1  # frames: confidence = exp(-standard error / this); 0.5 <-> 0.07 frame


@dataclass(frozen=True, eq=False)
class SyncEstimate:
    """One camera's offset. ``shifts`` / ``residual_px``: the whole-frame curve."""

    camera: str
    offset_frames: float  # positive: this camera's frames lag the others
    confidence: float  # 0..1: exp(-offset_std_frames / SPREAD_SCALE)
    offset_std_frames: float  # jackknife standard error of the offset
    residual_best_px: float
    residual_zero_px: float  # at shift 0: how far off the camera is as recorded
    samples: int  # (frame, track) pairs behind the best residual
    shifts: np.ndarray  # (S,) whole-frame shifts tried
    residual_px: np.ndarray  # (S,) mean capped residual at each

    @property
    def offset(self) -> bool:
        """A trusted, non-zero offset."""
        return abs(self.offset_frames) >= OFFSET_TOLERANCE and self.trusted

    @property
    def trusted(self) -> bool:
        return self.confidence >= TRUSTED_CONFIDENCE

    def to_dict(self) -> dict:
        return {
            "offset_frames": round(float(self.offset_frames), 3),
            "confidence": round(float(self.confidence), 3),
            "offset_std_frames": round(float(self.offset_std_frames), 3),
            "residual_best_px": round(float(self.residual_best_px), 2),
            "residual_zero_px": round(float(self.residual_zero_px), 2),
            "samples": int(self.samples),
            "curve": {
                "shifts": self.shifts.astype(int).tolist(),
                "residual_px": [round(float(r), 2) for r in self.residual_px],
            },
        }


def smooth_in_time(points: np.ndarray, half_width: int) -> np.ndarray:
    """(K, F, J, 3) -> the same, averaged over a symmetric triangular window of
    ``half_width`` frames either side (NaN frames skipped; a missing frame stays missing).
    Symmetric, so a steady motion is not shifted in time: it lowers the reference's noise
    without biasing the offset."""
    if half_width <= 0:
        return points
    F = points.shape[1]
    seen = np.isfinite(points).all(-1, keepdims=True)
    x = np.where(seen, points, 0.0)
    acc, wsum = np.zeros_like(x), np.zeros(seen.shape)
    for k in range(-half_width, half_width + 1):
        w = half_width + 1 - abs(k)
        lo, hi = max(0, -k), min(F, F - k)
        acc[:, lo:hi] += w * x[:, lo + k : hi + k]
        wsum[:, lo:hi] += w * seen[:, lo + k : hi + k]
    out = acc / np.maximum(wsum, 1e-9)
    return np.where(seen, out, np.nan)


def projected_people(points: np.ndarray, camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """(K, F, J, 3) world mm -> per frame the tracks present, in ``camera``: (F, m, J, 2)
    pixels and (F, m, J) seen, m the most tracks present in one frame (tracks are
    fragments of the clip, so per frame is much smaller than K x F)."""
    seen = np.isfinite(points).all(-1)
    uv = camera.project(np.where(seen[..., None], points, 0.0))
    seen &= np.isfinite(uv).all(-1)  # behind the camera: not evidence
    present = seen.sum(-1) >= MIN_JOINTS  # (K, F)
    K, F, J = seen.shape
    m = max(int(present.sum(0).max(initial=0)), 1)
    out_uv = np.zeros((F, m, J, 2), np.float32)
    out_seen = np.zeros((F, m, J), bool)
    k, f = np.nonzero(present.T)[::-1]  # frame-major
    order = np.lexsort((k, f))
    k, f = k[order], f[order]
    slot = np.arange(len(f)) - np.searchsorted(f, f)
    out_uv[f, slot] = uv[k, f]
    out_seen[f, slot] = seen[k, f]
    return out_uv, out_seen


def shift_cost(
    uv: np.ndarray,
    seen: np.ndarray,
    detections: np.ndarray,
    frames: np.ndarray,
    shift: int,
    *,
    cap_px: float = CAP_PX,
) -> tuple[np.ndarray, np.ndarray]:
    """Per frame of ``frames``: the summed truncated squared residual (px^2) and the
    number of (frame, track) pairs behind it, at a whole ``shift``; (G,) each.

    Args:
        uv, seen: (F, m, J, 2) / (F, m, J) the other cameras' joints in this camera, per
            frame the tracks present (:func:`projected_people`).
        detections: (F, n, J, 3) the camera's 2D per frame, NaN padded.
        frames: (G,) the camera's frames to score; frame g meets the tracks at g - shift.
    Per pair: the nearest detection's mean of min(d^2, cap^2) over the joints both see
    (cap^2 when they share fewer than ``MIN_JOINTS``: a person this camera misses),
    weighted by confidence. Near the offset d a locally linear motion of v px per frame
    gives E = sigma^2 + v^2 (s - d)^2: a parabola in s, so whole shifts are
    enough to find a sub-frame d (no interpolation, which would average noise away at
    half-frames and bias the offset toward them).
    """
    F = uv.shape[0]
    src = frames - shift
    ok = (src >= 0) & (src < F)
    g, src = frames[ok], src[ok]
    sums, counts = np.zeros(len(frames)), np.zeros(len(frames), int)
    if len(g) == 0:
        return sums, counts
    p = uv[src]  # (G, m, J, 2)
    s_ = seen[src]  # (G, m, J)
    d = detections[g]  # (G, n, J, 3)
    conf = np.nan_to_num(d[..., 2]).astype(np.float32)
    # Weighted by confidence: the detector's noise grows as its confidence drops.
    wdet = np.where((conf >= MIN_CONFIDENCE) & np.isfinite(d[..., :2]).all(-1),
                    conf**CONF_POWER, 0.0).astype(np.float32)  # fmt: skip
    dxy = np.nan_to_num(d[..., :2]).astype(np.float32)  # (G, n, J, 2)
    cap2 = np.float32(cap_px * cap_px)
    diff = p[:, :, None] - dxy[:, None]  # (G, m, n, J, 2)
    d2 = np.square(diff).sum(-1)  # (G, m, n, J)
    np.minimum(d2, cap2, out=d2)
    w = wdet[:, None] * s_[:, :, None]  # joints both see, weighted
    den = w.sum(-1)
    per_det = (w * d2).sum(-1) / np.maximum(den, 1e-9)
    count = (w > 0).sum(-1)  # joints the track and the detection share
    per_det = np.where(count >= MIN_JOINTS, per_det, cap2)
    nearest = per_det.min(axis=-1, initial=cap2)  # (G, m)
    pairs = s_.sum(-1) >= MIN_JOINTS
    sums[ok] = np.where(pairs, nearest, 0.0).sum(1)
    counts[ok] = pairs.sum(1)
    return sums, counts


def estimate_camera_offset(
    scene: Scene,
    results: PipelineResults,
    view: int,
    *,
    reference_exclude: frozenset[int] = frozenset(),
    max_shift: int = MAX_SHIFT,
    frames: np.ndarray | None = None,
    cap_px: float = CAP_PX,
) -> SyncEstimate:
    """The offset of camera ``view`` against the others (minus ``reference_exclude``)."""
    cam = scene.rig[view]
    points = track_points_without(scene, results, frozenset({view}) | reference_exclude)
    points = smooth_in_time(points, SMOOTH)
    uv, seen = projected_people(points, cam)
    dets, index = camera_detections(scene, results, view)
    have = np.flatnonzero((index >= 0).any(1))
    if frames is not None:
        have = np.intersect1d(have, frames)
    shifts = np.arange(-max_shift, max_shift + 1)
    scored = [shift_cost(uv, seen, dets, have, int(s), cap_px=cap_px) for s in shifts]
    sums = np.stack([a for a, _ in scored])  # (S, G)
    counts = np.stack([b for _, b in scored])
    total = counts.sum(1)
    with np.errstate(invalid="ignore", divide="ignore"):
        cost = sums.sum(1) / total
    if not np.isfinite(cost).any():
        nan = float("nan")
        return SyncEstimate(cam.name, 0.0, 0.0, nan, nan, nan, 0, shifts, np.sqrt(cost))
    k, offset = _curve_minimum(cost, shifts)
    spread = _jackknife_spread(sums, counts, shifts, blocks=JACKKNIFE_BLOCKS)
    typical = float(np.nanmedian(cost))
    if typical <= 0 or (typical - cost[k]) / typical < MIN_CONTRAST:
        spread = float("inf")  # a flat curve: time changes nothing, there is no offset to see
    rms = np.sqrt(cost)
    return SyncEstimate(
        camera=cam.name,
        offset_frames=offset,
        confidence=float(np.exp(-spread / SPREAD_SCALE)),
        offset_std_frames=spread,
        residual_best_px=float(rms[k]),
        residual_zero_px=float(rms[shifts == 0][0]),
        samples=int(total[k]),
        shifts=shifts,
        residual_px=rms,
    )


def _curve_minimum(cost: np.ndarray, shifts: np.ndarray) -> tuple[int, float]:
    """Index of the smallest whole shift, and the sub-frame minimum of the parabola
    through it and its neighbours."""
    k = int(np.nanargmin(cost))
    offset = float(shifts[k])
    if 0 < k < len(shifts) - 1 and np.isfinite(cost[k - 1 : k + 2]).all():
        offset += _parabola_vertex(*cost[k - 1 : k + 2])
    return k, offset


def _jackknife_spread(
    sums: np.ndarray, counts: np.ndarray, shifts: np.ndarray, *, blocks: int
) -> float:
    """Standard error (frames) of the offset: jackknife over contiguous blocks of frames.
    A scene where the people do not move, or few frames, gives a large one."""
    G = sums.shape[1]
    if G < 2 * blocks:
        return float("inf")
    edges = np.linspace(0, G, blocks + 1).astype(int)
    est = []
    for b in range(blocks):
        keep = np.ones(G, bool)
        keep[edges[b] : edges[b + 1]] = False
        with np.errstate(invalid="ignore", divide="ignore"):
            c = sums[:, keep].sum(1) / counts[:, keep].sum(1)
        if not np.isfinite(c).any():
            return float("inf")
        est.append(_curve_minimum(c, shifts)[1])
    est = np.array(est)
    return float(np.sqrt((blocks - 1) / blocks * ((est - est.mean()) ** 2).sum()))


def _parabola_vertex(a: float, b: float, c: float) -> float:
    """Offset (in grid steps, within +-0.5) of the vertex of the parabola through three
    equally spaced values with the middle one the smallest."""
    den = a - 2 * b + c
    return 0.0 if den <= 0 else float(np.clip(0.5 * (a - c) / den, -0.5, 0.5))


def estimate_offsets(
    scene: Scene,
    results: PipelineResults,
    *,
    max_shift: int = MAX_SHIFT,
    frames: np.ndarray | None = None,
    reference_exclude: frozenset[int] = frozenset(),
) -> dict[str, SyncEstimate]:
    """Every camera's offset (two passes, see the module docstring); the cameras in
    ``reference_exclude`` (e.g. calibration suspects) are in no other camera's reference."""
    V = len(scene.rig)

    def run(exclude_of) -> list[SyncEstimate]:
        return [
            estimate_camera_offset(
                scene, results, v, reference_exclude=exclude_of(v) | (reference_exclude - {v}),
                max_shift=max_shift, frames=frames,
            )
            for v in range(V)
        ]  # fmt: skip

    estimates = run(lambda v: frozenset())
    bad: frozenset[int] = frozenset()
    while True:
        # The worst remaining camera: the largest drop in residual its shift buys.
        gain = {
            v: e.residual_zero_px - e.residual_best_px
            for v, e in enumerate(estimates)
            if e.offset and v not in bad | reference_exclude
        }
        # keep >= 2 reference cameras per estimate
        if not gain or V - len(bad | reference_exclude) - 1 < 3:
            break
        bad = bad | {max(gain, key=gain.get)}
        estimates = run(lambda v, bad=bad: bad - {v})
    return {e.camera: e for e in estimates}


def offsets_over_windows(
    scene: Scene, results: PipelineResults, *, window: int = 100, max_shift: int = 10
) -> list[tuple[int, int, dict[str, SyncEstimate]]]:
    """Offsets per window of ``window`` frames (start, stop, estimates): a drift shows as
    an offset that changes from window to window."""
    out = []
    for start in range(0, results.num_frames, window):
        stop = min(start + window, results.num_frames)
        if stop - start < max(10, window // 4) and out:
            break  # a short tail says little; the previous window covers it
        frames = np.arange(start, stop)
        out.append((start, stop, estimate_offsets(scene, results, frames=frames,
                                                  max_shift=max_shift)))  # fmt: skip
    return out
