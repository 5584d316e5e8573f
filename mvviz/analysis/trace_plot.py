"""The filter panel's plot: one joint of one track over time, filters A and B side by side.

:class:`TracePlot` draws x, y, z (raw dots, A and B lines, gate rejections as crosses) and
both filters' Mahalanobis distances with their gates, with matplotlib's Agg canvas (no
pyplot, no GUI). The artists are made once; :meth:`TracePlot.render` only sets data and
limits. The current frame is not drawn into the plot (that would re-send ~90 kB per frame
change) but into :meth:`TracePlot.playhead`, a strip as wide as the plot shown under it.

Units: mm and frames, as in the results.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import cv2
import numpy as np

from mvviz.analysis.filter_runs import FilterRun
from mvviz.scene.geometry import ViewerData

if TYPE_CHECKING:
    from matplotlib.lines import Line2D

PLOT_WIDTH, PLOT_HEIGHT, PLOT_DPI = 680, 860, 220  # shown ~300 px wide in the panel
PLAYHEAD_HEIGHT = 36  # px of the strip marking the current frame (shown at ~1/3 scale)
A_COLOR, B_COLOR, RAW_COLOR = "#1f77b4", "#e6550d", "#6b6b6b"
MARKER_RGB = (25, 25, 25)


@dataclass(frozen=True, eq=False)
class JointTrace:
    """One joint of one track over the sequence (F frames), mm."""

    title: str
    raw: np.ndarray  # (F, 3)
    a: np.ndarray  # (F, 3) filter A's output
    b: np.ndarray  # (F, 3)
    maha_a: np.ndarray  # (F,)
    maha_b: np.ndarray  # (F,)
    rejected_a: np.ndarray  # (F,) bool
    rejected_b: np.ndarray  # (F,) bool
    gate_a: float | None
    gate_b: float | None


def joint_trace(
    data: ViewerData, run_a: FilterRun, run_b: FilterRun, track: int | None, joint: int
) -> JointTrace | None:
    """The trace of (``track``, ``joint``); None when the selection is not valid."""
    if track is None or not 0 <= track < data.num_tracks:
        return None
    if not 0 <= joint < data.joint_set.num_joints:
        return None
    k, j = track, joint
    return JointTrace(
        title=f"track {k} · {data.joint_set.names[j]}",
        raw=data.results.track_raw[k, :, j],
        a=run_a.shown[k, :, j],
        b=run_b.shown[k, :, j],
        maha_a=run_a.mahalanobis[k, :, j],
        maha_b=run_b.mahalanobis[k, :, j],
        rejected_a=run_a.rejected[k, :, j],
        rejected_b=run_b.rejected[k, :, j],
        gate_a=run_a.params.gate,
        gate_b=run_b.params.gate,
    )


def plot_range(num_frames: int, frame: int, window: int | None) -> tuple[int, int]:
    """Frames ``[lo, hi)`` to plot: all, or ``frame +- window`` kept inside the sequence."""
    if window is None or 2 * window + 1 >= num_frames:
        return 0, num_frames
    lo = int(np.clip(frame - window, 0, num_frames - 2 * window - 1))
    return lo, lo + 2 * window + 1


def _limits(values: list[np.ndarray]) -> tuple[float, float]:
    """y limits spanning the finite values, padded (at least +-2 mm)."""
    v = np.concatenate([np.ravel(x) for x in values])
    v = v[np.isfinite(v)]
    if v.size == 0:
        return -1.0, 1.0
    lo, hi = float(v.min()), float(v.max())
    pad = max(0.06 * (hi - lo), 2.0)
    return lo - pad, hi + pad


class TracePlot:
    """Matplotlib (Agg, no pyplot) figure of a :class:`JointTrace`: x, y, z over time and
    the Mahalanobis distances. The artists are made once and :meth:`render` only sets
    their data and limits, then caches the pixels; :meth:`image` paints the current-frame
    line on a copy of them. Use from one thread."""

    def __init__(
        self, *, width: int = PLOT_WIDTH, height: int = PLOT_HEIGHT, dpi: int = PLOT_DPI
    ) -> None:
        # matplotlib (~0.5 s to import) loads with the first plot, not with the viewer
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
        from matplotlib.ticker import MaxNLocator

        fig = self.fig = Figure(figsize=(width / dpi, height / dpi), dpi=dpi, facecolor="white")
        self.canvas = FigureCanvasAgg(fig)
        self.axes = fig.subplots(4, 1, sharex=True, gridspec_kw={"height_ratios": [1, 1, 1, 1.15]})
        fig.subplots_adjust(left=0.18, right=0.97, top=0.93, bottom=0.085, hspace=0.15)
        nan = np.full(1, np.nan)
        self.lines: list[dict[str, Line2D]] = []
        for i, ax in enumerate(self.axes):
            ax.tick_params(labelsize=7, length=2, pad=1.5)
            ax.grid(True, lw=0.3, color="#dddddd")
            if i < 3:
                ax.set_ylabel(f"{'xyz'[i]} (mm)", fontsize=7.5, labelpad=1)
                self.lines.append({
                    "raw": ax.plot(nan, nan, ".", ms=2.2, color=RAW_COLOR, label="raw")[0],
                    "a": ax.plot(nan, nan, "-", lw=0.9, color=A_COLOR, label="A")[0],
                    "b": ax.plot(nan, nan, "-", lw=0.9, color=B_COLOR, label="B")[0],
                    "rejected_a": ax.plot(nan, nan, "x", ms=3, mew=0.8, color=A_COLOR)[0],
                    "rejected_b": ax.plot(nan, nan, "x", ms=3, mew=0.8, color=B_COLOR)[0],
                })  # fmt: skip
            else:
                ax.set_ylabel("Mahalanobis", fontsize=7.5, labelpad=1)
                ax.set_xlabel("frame", fontsize=7.5, labelpad=1)
                ax.xaxis.set_major_locator(MaxNLocator(integer=True))
                self.lines.append({
                    "a": ax.plot(nan, nan, "-", lw=0.8, color=A_COLOR)[0],
                    "b": ax.plot(nan, nan, "-", lw=0.8, color=B_COLOR)[0],
                    "gate_a": ax.plot(nan, nan, "--", lw=0.8, color=A_COLOR)[0],
                    "gate_b": ax.plot(nan, nan, "--", lw=0.8, color=B_COLOR)[0],
                })  # fmt: skip
        self.axes[0].legend(
            loc="lower right", bbox_to_anchor=(1.0, 1.0), ncol=3, fontsize=7, frameon=False,
            borderaxespad=0.1, handlelength=1.0, handletextpad=0.4, columnspacing=0.9,
            markerscale=2,
        )  # fmt: skip
        self.title = self.axes[0].set_title("", fontsize=8, loc="left", pad=3)
        self._pixels = np.zeros((height, width, 3), np.uint8)
        self.render(None, 0, 1)

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) of the images, pixels."""
        return self._pixels.shape[1], self._pixels.shape[0]

    def render(self, trace: JointTrace | None, lo: int, hi: int) -> None:
        """Draw frames ``[lo, hi)`` of ``trace`` (None: empty, with a hint to select one)."""
        t = np.arange(lo, hi, dtype=float)
        s = slice(lo, hi)
        empty = np.full(hi - lo, np.nan)
        for i, lines in enumerate(self.lines[:3]):
            raw = trace.raw[s, i] if trace else empty
            a = trace.a[s, i] if trace else empty
            b = trace.b[s, i] if trace else empty
            lines["raw"].set_data(t, raw)
            lines["a"].set_data(t, a)
            lines["b"].set_data(t, b)
            for name in ("rejected_a", "rejected_b"):
                rej = getattr(trace, name)[s] if trace else np.zeros(hi - lo, bool)
                lines[name].set_data(t[rej], raw[rej])
            self.axes[i].set_ylim(*_limits([raw, a, b]))
        ma = trace.maha_a[s] if trace else empty
        mb = trace.maha_b[s] if trace else empty
        m = self.lines[3]
        m["a"].set_data(t, ma)
        m["b"].set_data(t, mb)
        tops = [1.0]
        for name in ("gate_a", "gate_b"):
            g = getattr(trace, name) if trace else None
            m[name].set_data([lo - 1, hi + 1], [np.nan, np.nan] if g is None else [g, g])
            tops += [] if g is None else [1.15 * g]
        finite = np.concatenate([ma[np.isfinite(ma)], mb[np.isfinite(mb)]])
        if finite.size:
            tops.append(1.15 * float(np.percentile(finite, 99)))
        self.axes[3].set_ylim(0.0, max(tops))
        self.axes[3].set_xlim(lo - 0.5, max(hi - 1, lo + 1) + 0.5)
        self.title.set_text(trace.title if trace else "select a track and joint")
        self.canvas.draw()
        self._pixels = np.asarray(self.canvas.buffer_rgba())[..., :3].copy()

    def frame_x(self, frame: int) -> float:
        """Image column (pixels from the left) of ``frame`` on the plots' x axis."""
        return float(self.axes[0].transData.transform((frame, 0.0))[0])

    def image(self, frame: int | None = None) -> np.ndarray:
        """(height, width, 3) uint8: the last render, with a line at ``frame`` if given."""
        img = self._pixels.copy()
        if frame is None:
            return img
        H, W = img.shape[:2]
        x = self.frame_x(frame)
        for ax in self.axes:
            x0, y0, x1, y1 = ax.bbox.extents  # display pixels, origin bottom left
            if not x0 - 1 <= x <= x1 + 1:
                continue
            c0, c1 = max(int(round(x)) - 1, 0), min(int(round(x)) + 1, W)
            r0, r1 = max(int(H - y1), 0), min(int(np.ceil(H - y0)), H)
            img[r0:r1, c0:c1] = MARKER_RGB
        return img

    def playhead(self, frame: int) -> np.ndarray:
        """(PLAYHEAD_HEIGHT, width, 3) uint8: a strip as wide as the plot with a marker
        under ``frame``'s column; shown right below the plot. Flat colours, no text (the
        frame number is in the timeline): its PNG is a few hundred bytes."""
        W = self._pixels.shape[1]
        strip = np.full((PLAYHEAD_HEIGHT, W, 3), 255, np.uint8)
        x0, _, x1, _ = self.axes[3].bbox.extents
        strip[1, int(x0) : int(np.ceil(x1))] = (200, 200, 200)  # the axis' extent
        x = self.frame_x(frame)
        if not x0 - 1 <= x <= x1 + 1:  # outside the plotted window
            return strip
        xi = int(round(x))
        tri = np.array([[xi, 2], [xi - 16, 26], [xi + 16, 26]], np.int32)
        cv2.fillPoly(strip, [tri], MARKER_RGB)
        strip[26:PLAYHEAD_HEIGHT, max(xi - 3, 0) : xi + 4] = MARKER_RGB  # stem
        return strip
