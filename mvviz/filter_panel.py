"""Filter tuning, side by side: the run's Kalman filter (A) against an editable copy (B).

The GUI folder "Filter A/B" shows filter A (``results.config.kalman``) read-only and
filter B as controls. Any change to B re-filters the whole sequence with the vectorised
:func:`~pipeline.kalman.kalman_filter` (tens of milliseconds) on a worker thread with a
"latest wins" slot, so typing never queues work. Then:

- B's skeletons are drawn beside A's under ``/world/skeletons/filter_b/<track>`` (darker
  track colour, a "B" label; "Show B", x offset);
- a plot of the selected track and joint over time: x, y, z (raw dots, A and B lines,
  gate rejections as crosses) and both filters' Mahalanobis distances with their gates.
  The plot image is sent when what it shows changes (selection, filters, window), not
  on a frame change: the current frame is a playhead strip under the plot's frame axis,
  a ~0.5 kB image, so scrubbing sends that instead of a ~90 kB plot per frame;
- MPJPE, PCK@160, acceleration error and jitter of raw, A and B against the ground
  truth, scored exactly as :func:`pipeline.evaluate.evaluate` scores its rows.

"Apply B" swaps B's arrays into the results (:meth:`ViewerApp.set_results`) and saves B
into ``SCENE/mvviz_config.json`` (atomically), which ``mvviz run`` / ``mvviz view`` /
``python app.py`` read next time.

Units: arrays are millimetres and frames, as in the results; the scene is in metres.
"""

from __future__ import annotations

import dataclasses
import threading
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np
import viser
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.ticker import MaxNLocator

from mvviz.geometry import MM, OFFSET_FILTERED_M, ViewerData, bone_segments, track_color
from mvviz.workers import LatestWins
from pipeline import metrics
from pipeline.config import PipelineConfig, load_config, save_config
from pipeline.evaluate import _frames_of_gt, ground_truth_slots, stage_metrics, to_smpl_slots
from pipeline.files import SceneFormatError
from pipeline.kalman import MODELS, KalmanParams, kalman_filter
from pipeline.results import PipelineResults

if TYPE_CHECKING:
    from mvviz.app import ViewerApp

CONFIG_NAME = "mvviz_config.json"  # the scene's run config (mvviz/cli_run.py resolve_config)
B_ROOT = "/world/skeletons/filter_b"
B_BONE_WIDTH_M = 0.016  # A's filtered bones are 0.022 m
B_LABEL_LIFT_M = 0.12
PLOT_WIDTH, PLOT_HEIGHT, PLOT_DPI = 680, 860, 220  # shown ~300 px wide in the panel
PLOT_INTERVAL_S = 0.1  # at most ~10 plot renders per second while the selection changes
PLAYHEAD_HEIGHT = 36  # px of the strip marking the current frame (shown at ~1/3 scale)
WINDOWS = {"all": None, "±25": 25, "±50": 50, "±100": 100}  # plotted frames around the frame
Q_SCALES = {"÷4": 0.25, "÷2": 0.5, "×2": 2.0, "×4": 4.0}  # B's q scale buttons
A_COLOR, B_COLOR, RAW_COLOR = "#1f77b4", "#e6550d", "#6b6b6b"
MARKER_RGB = (25, 25, 25)


# --------------------------------------------------------------------------- filter runs


@dataclass(frozen=True, eq=False)
class FilterRun:
    """One filter over the whole sequence, tracks first. K tracks, F frames, J joints; mm."""

    params: KalmanParams
    forward: np.ndarray  # (K, F, J, 3) forward posterior mean
    smoothed: np.ndarray  # (K, F, J, 3) RTS
    prior: np.ndarray  # (K, F, J, 3) predicted mean before each update
    innovation: np.ndarray  # (K, F, J, 3)
    mahalanobis: np.ndarray  # (K, F, J)
    rejected: np.ndarray  # (K, F, J) bool, measurement rejected by the gate

    @property
    def shown(self) -> np.ndarray:
        """(K, F, J, 3) the configured output: smoothed if ``params.smoother``."""
        return self.smoothed if self.params.smoother else self.forward


def run_filter(track_raw: np.ndarray, params: KalmanParams) -> FilterRun:
    """Filter ``track_raw`` (K, F, J, 3) mm as the pipeline does (forward and RTS at once)."""
    raw = np.asarray(track_raw, float)
    if raw.ndim != 4 or raw.shape[-1] != 3:
        raise ValueError(f"track_raw must be (num_tracks, num_frames, J, 3), got {raw.shape}")
    fr = kalman_filter(np.moveaxis(raw, 1, 0), dataclasses.replace(params, smoother=True))
    tracks = lambda a: np.moveaxis(a, 0, 1)  # noqa: E731  (F, K, ...) -> (K, F, ...)
    return FilterRun(
        params=params,
        forward=tracks(fr.forward),
        smoothed=tracks(fr.filtered),
        prior=tracks(fr.prior_mean),
        innovation=tracks(fr.innovation),
        mahalanobis=tracks(fr.mahalanobis),
        rejected=tracks(fr.rejected),
    )


def results_run(results: PipelineResults) -> FilterRun:
    """Filter A: the results' own arrays. A gate rejected exactly the measurements whose
    Mahalanobis distance exceeds it (the initialising one has distance 0)."""
    params = results.config.kalman
    rejected = np.zeros(results.track_mahalanobis.shape, bool)
    if params.gate is not None:
        with np.errstate(invalid="ignore"):
            rejected = results.track_mahalanobis > params.gate
        rejected &= np.isfinite(results.track_raw).all(-1)
    return FilterRun(
        params=params,
        forward=results.track_forward,
        smoothed=results.track_smoothed,
        prior=results.track_prior,
        innovation=results.track_innovation,
        mahalanobis=results.track_mahalanobis,
        rejected=rejected,
    )


def with_filter(results: PipelineResults, run: FilterRun) -> PipelineResults:
    """``results`` with ``run``'s arrays and parameters as its Kalman stage."""
    return dataclasses.replace(
        results,
        track_forward=run.forward,
        track_smoothed=run.smoothed,
        track_prior=run.prior,
        track_innovation=run.innovation,
        track_mahalanobis=run.mahalanobis,
        config=dataclasses.replace(results.config, kalman=run.params),
        cache_key="",  # no longer what a pipeline run with the old key produced
    )


def save_filter_config(scene_root: Path, params: KalmanParams, run_config: PipelineConfig) -> Path:
    """Write ``params`` as the kalman section of ``SCENE/mvviz_config.json`` (atomically).

    An existing file keeps its other sections; without one the run's config is written.
    """
    path = Path(scene_root) / CONFIG_NAME
    base = run_config
    if path.is_file():
        try:
            base = load_config(path)
        except SceneFormatError:
            pass  # unreadable: replace it with the run's config
    save_config(dataclasses.replace(base, kalman=params), path)
    return path


def describe(params: KalmanParams) -> str:
    """One line about a filter: model and its numbers."""
    model = params.model.replace("_", " ")
    parts = [f"{model}", f"q {params.q:g}", f"r {params.r:g}", f"p0 {params.p0:g}"]
    if params.model == "random_walk":
        parts.append(f"gain {params.control_gain:g}")
    parts.append("gate off" if params.gate is None else f"gate {params.gate:g}")
    parts.append("RTS" if params.smoother else "forward")
    return " · ".join(parts)


# --------------------------------------------------------------------------- metrics


def gt_dense(data: ViewerData) -> np.ndarray | None:
    """(F, G, 24, 3) ground truth per frame in SMPL-24 slots, mm; None without GT."""
    gt, res = data.scene.gt, data.results
    if gt is None:
        return None
    slots, _ = ground_truth_slots(gt, res.joint_set)
    return _frames_of_gt(gt, slots, res.num_frames)[0]


def score(
    track: np.ndarray, track_raw: np.ndarray, joint_set: str, gt: np.ndarray | None
) -> dict[str, float]:
    """MPJPE, PCK@160, acceleration error, jitter of ``track`` (K, F, J, 3) mm, scored
    where ``track_raw`` has the joint, as :func:`pipeline.evaluate.evaluate` does.
    Without ground truth (``gt`` None) only the jitter (mean |acceleration|)."""
    measured = np.isfinite(track_raw).all(-1, keepdims=True)
    masked = np.where(measured, track, np.nan)
    if gt is None:
        acc = np.linalg.norm(metrics.acceleration(np.moveaxis(masked, 1, 0)), axis=-1)
        jit = float(np.nanmean(acc)) if np.isfinite(acc).any() else float("nan")
        return {"jitter": jit}
    out, _ = stage_metrics(to_smpl_slots(masked, joint_set), gt)
    return out


METRIC_COLUMNS = (
    ("mpjpe", "MPJPE", "{:.1f}"),
    ("pck", "PCK@160", "{:.3f}"),
    ("accel", "accel", "{:.2f}"),
    ("jitter", "jitter", "{:.2f}"),
)


def metrics_table(rows: dict[str, dict[str, float]]) -> str:
    """Markdown table of :func:`score` figures, one row per name."""
    cols = [c for c in METRIC_COLUMNS if any(c[0] in v for v in rows.values())]
    head = "| | " + " | ".join(c[1] for c in cols) + " |"
    lines = [head, "|:--|" + "--:|" * len(cols)]
    for name, v in rows.items():
        cells = [fmt.format(v[k]) if np.isfinite(v.get(k, np.nan)) else "—" for k, _, fmt in cols]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    has_gt = any("mpjpe" in v for v in rows.values())
    note = "vs ground truth; mm, accel error and jitter mm/frame²" if has_gt else "no ground truth"
    lines.append(f"\n<small>{note}; scored where raw is measured</small>")
    return "\n".join(lines)


# --------------------------------------------------------------------------- plots


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


# --------------------------------------------------------------------------- gui


@dataclass
class FilterPanel:
    """Handles of the "Filter A/B" folder."""

    folder: viser.GuiFolderHandle
    a_info: viser.GuiMarkdownHandle
    model: viser.GuiDropdownHandle
    q: viser.GuiNumberHandle
    q_scale: viser.GuiButtonGroupHandle
    r: viser.GuiNumberHandle
    p0: viser.GuiNumberHandle
    control_gain: viser.GuiNumberHandle
    smoother: viser.GuiCheckboxHandle
    gate_on: viser.GuiCheckboxHandle
    gate: viser.GuiNumberHandle
    reset: viser.GuiButtonHandle
    apply: viser.GuiButtonHandle
    show_b: viser.GuiCheckboxHandle
    offset: viser.GuiSliderHandle
    window: viser.GuiDropdownHandle
    plot: viser.GuiImageHandle
    playhead: viser.GuiImageHandle  # the current frame, under the plot
    metrics: viser.GuiMarkdownHandle
    status: viser.GuiMarkdownHandle

    def set_params(self, params: KalmanParams) -> None:
        """Show ``params`` in B's controls (each assignment fires its callback)."""
        self.model.value = params.model
        self.q.value = float(params.q)
        self.r.value = float(params.r)
        self.p0.value = float(params.p0)
        self.control_gain.value = float(params.control_gain)
        self.smoother.value = bool(params.smoother)
        self.gate_on.value = params.gate is not None
        if params.gate is not None:
            self.gate.value = float(params.gate)
        self.sync_enabled()

    def read_params(self, base: KalmanParams) -> KalmanParams:
        """B's parameters (``base`` gives the fields without a control); raises ValueError."""
        return dataclasses.replace(
            base,
            model=str(self.model.value),
            q=float(self.q.value),
            r=float(self.r.value),
            p0=float(self.p0.value),
            control_gain=float(self.control_gain.value),
            smoother=bool(self.smoother.value),
            gate=float(self.gate.value) if self.gate_on.value else None,
        )

    def sync_enabled(self) -> None:
        self.control_gain.disabled = self.model.value != "random_walk"
        self.gate.disabled = not self.gate_on.value


def make_filter_gui(server: viser.ViserServer, a: KalmanParams) -> FilterPanel:
    """The "Filter A/B" folder, B's controls showing ``a``."""
    gui = server.gui
    blank = np.full((PLOT_HEIGHT, PLOT_WIDTH, 3), 255, np.uint8)
    with gui.add_folder("Filter A/B") as folder:
        a_info = gui.add_markdown(f"**A** (run): {describe(a)}")
        model = gui.add_dropdown("B model", MODELS, initial_value=a.model)
        q = gui.add_number("B q", float(a.q), min=0.0, step=0.1)
        q_scale = gui.add_button_group("B q scale", tuple(Q_SCALES))
        r = gui.add_number("B r (mm²)", float(a.r), min=1e-3, step=0.1)
        p0 = gui.add_number("B p0 (mm²)", float(a.p0), min=1e-3, step=1.0)
        gain = gui.add_number("B control gain", float(a.control_gain), step=0.05)
        smoother = gui.add_checkbox("B RTS smoother", bool(a.smoother))
        gate_on = gui.add_checkbox("B gate", a.gate is not None)
        gate = gui.add_number("B gate (Mahal.)", float(a.gate or 6.0), min=0.1, step=0.1)
        reset = gui.add_button("Reset B to A", icon=viser.Icon.ARROW_BACK_UP)
        apply = gui.add_button("Apply B", icon=viser.Icon.CHECK, color="green")
        status = gui.add_markdown("")
        metrics_md = gui.add_markdown("")
        show_b = gui.add_checkbox("Show B skeletons", False)
        offset = gui.add_slider("B x offset (m)", min=-3.0, max=3.0, step=0.1, initial_value=1.0)
        window = gui.add_dropdown("Plot frames", tuple(WINDOWS), initial_value="all")
        plot = gui.add_image(blank, format="png")
        playhead = gui.add_image(blank[:PLAYHEAD_HEIGHT], format="png")
    panel = FilterPanel(
        folder, a_info, model, q, q_scale, r, p0, gain, smoother, gate_on, gate, reset, apply,
        show_b, offset, window, plot, playhead, metrics_md, status,
    )  # fmt: skip
    panel.sync_enabled()
    return panel


# --------------------------------------------------------------------------- worker


# --------------------------------------------------------------------------- the panel


class FilterTuning:
    """The "Filter A/B" panel at work: B's run, its skeletons, plots and metrics.

    ``run_a``/``run_b`` are the two filters' :class:`FilterRun`; ``metrics`` the last
    :func:`score` rows (raw, A, B); ``plot_image``/``playhead_image`` the last plot and
    playhead sent; ``timings`` the last re-filter / skeleton / plot / metrics times in
    ms. Everything drawn follows the app: :attr:`ViewerApp.state_changed` brings frame,
    selection and new results.
    """

    def __init__(self, app: ViewerApp) -> None:
        self.app = app
        self._lock = threading.RLock()  # the scene nodes and the runs below
        data = app.state.data
        self._data = data
        self.run_a = results_run(data.results)
        self.run_b: FilterRun | None = self.run_a  # None: being re-filtered
        self.gui = make_filter_gui(app.server, self.run_a.params)
        self.metrics: dict[str, dict[str, float]] = {}
        self.plot_image: np.ndarray | None = None  # the last plot sent (no frame marker)
        self.playhead_image: np.ndarray | None = None  # the last playhead strip sent
        self.timings: dict[str, float] = {}
        self.message = ""
        self._gt = gt_dense(data)
        self._score_cache: dict[tuple, dict[str, float]] = {}
        self._plot = TracePlot()
        self._plot_key: tuple | None = None
        self._marker_frame: int | None = None
        self._last_plot_t = 0.0
        self._drawn_key: tuple | None = None
        self._auto_show = True  # "Show B" turns on at B's first edit, unless touched
        self._nodes: dict[str, viser.SceneNodeHandle] = {}
        self._build_nodes()
        self._bind()
        # the app has no stop hook: its stop flag ends the worker and skips GUI writes
        self._halted = app._stopped.is_set
        self._worker = LatestWins(self._work, name="mvviz-filter-ab", halted=self._halted)
        app.state_changed.append(self._on_state_changed)
        self._worker.request()

    # ------------------------------------------------------------------ public

    @property
    def params_b(self) -> KalmanParams:
        """B's parameters as its controls show them (raises ValueError if invalid)."""
        return self.gui.read_params(self.run_a.params)

    def scale_q(self, label: str) -> None:
        """Multiply B's q by one of :data:`Q_SCALES` ("÷2", "×2", ...)."""
        self.gui.q.value = float(f"{float(self.gui.q.value) * Q_SCALES[label]:.4g}")

    def reset_b(self) -> None:
        """Set B's controls to filter A."""
        self.gui.set_params(self.run_a.params)
        self._worker.request()

    def apply_b(self) -> Path:
        """Make B the current filter: swap its arrays into the app's results and save its
        parameters to ``SCENE/mvviz_config.json``. Returns the config path."""
        params = self.params_b
        with self._lock:
            data, run = self._data, self.run_b
        if run is None or run.params != params:
            run = run_filter(data.results.track_raw, params)
        path = save_filter_config(data.scene.root, params, data.results.config)
        self.app.set_results(with_filter(data.results, run))
        self.message = (
            f"✓ {time.strftime('%H:%M:%S')}: B applied and saved to `{path}` "
            f"(`mvviz run` / `python app.py` use it next time)"
        )
        self._worker.request()
        return path

    def wait_idle(self, timeout: float = 10.0) -> bool:
        """Block until B's re-filter, skeletons, plot and metrics are up to date."""
        return self._worker.wait_idle(timeout)

    def stop(self) -> None:
        self._worker.stop()

    # ------------------------------------------------------------------ gui callbacks

    def _bind(self) -> None:
        g = self.gui

        def edited(_) -> None:
            g.sync_enabled()
            self._worker.request()

        for h in (g.model, g.q, g.r, g.p0, g.control_gain, g.smoother, g.gate_on, g.gate):
            h.on_update(edited)  # B's parameters
        g.offset.on_update(edited)
        g.window.on_update(edited)

        @g.show_b.on_update
        def _(_) -> None:
            self._auto_show = False
            self._worker.request()

        @g.q_scale.on_click
        def _(event) -> None:
            self.scale_q(event.target.value)

        @g.reset.on_click
        def _(_) -> None:
            self.reset_b()

        @g.apply.on_click
        def _(_) -> None:
            try:
                self.apply_b()
            except (ValueError, OSError) as exc:
                self.message = f"Apply B failed: {exc}"
                self._worker.request()

    def _on_state_changed(self, st, reason: str) -> None:
        """After each app render: follow new results, draw B at the new frame."""
        with self._lock:
            if st.data is not self._data and st.data is self.app.state.data:
                self._rebuild(st.data)
            self._draw_b(st.frame, st.layers.offset_filtered)
        self._worker.request()

    # ------------------------------------------------------------------ scene nodes

    def _build_nodes(self) -> None:
        scene, K = self.app.server.scene, self._data.num_tracks
        empty = np.zeros((1, 2, 3), np.float32)
        self._nodes = {B_ROOT: scene.add_frame(B_ROOT, show_axes=False, visible=False)}
        for k in range(K):
            col, base = (track_color(k) * 0.55).astype(np.uint8), f"{B_ROOT}/{k}"  # darker
            # world-width lines take one uniform colour (see SceneLayers._lines)
            self._nodes[f"{base}/bones"] = scene.add_line_segments(
                f"{base}/bones", empty, col, thickness=B_BONE_WIDTH_M,
                thickness_units="world", visible=False,
            )  # fmt: skip
            self._nodes[f"{base}/joints"] = scene.add_point_cloud(
                f"{base}/joints", np.zeros((1, 3), np.float32), col, point_size=0.025,
                point_shape="circle", precision="float32", visible=False,
            )  # fmt: skip
            self._nodes[f"{base}/label"] = scene.add_label(
                f"{base}/label", f"B {k}", anchor="bottom-center", visible=False
            )
        self._drawn_key = None

    def _remove_nodes(self) -> None:
        with warnings.catch_warnings():  # already gone with /world/skeletons: fine
            warnings.simplefilter("ignore")
            for h in reversed(list(self._nodes.values())):
                h.remove()
        self._nodes = {}

    def _rebuild(self, data: ViewerData) -> None:
        """New results (applied B, a re-run): A is theirs, B re-filters their raw tracks."""
        self._remove_nodes()
        self._data = data
        self.run_a = results_run(data.results)
        self.gui.a_info.content = f"**A** (run): {describe(self.run_a.params)}"
        try:
            params = self.params_b
        except ValueError:
            params = self.run_a.params
        # the worker re-filters B off this (render) thread; until then B is not drawn
        self.run_b = self.run_a if params == self.run_a.params else None
        self._gt = gt_dense(data)
        self._score_cache.clear()
        self._build_nodes()

    def _draw_b(self, frame: int, offset_filtered: bool) -> None:
        """B's skeletons at ``frame`` (call with the lock held)."""
        show, dx = bool(self.gui.show_b.value), float(self.gui.offset.value)
        key = (self._data, self.run_b, frame, show, dx, offset_filtered)
        if key == self._drawn_key:
            return
        t0 = time.perf_counter()
        group = self._nodes[B_ROOT]
        try:
            base = OFFSET_FILTERED_M if offset_filtered else np.zeros(3)
            group.position = base + np.array([dx, 0.0, 0.0])
            group.visible = show and self.run_b is not None
            if group.visible:
                self._draw_b_skeletons(frame)
        except RuntimeError:  # nodes removed with a results change: the rebuild redraws
            return
        self._drawn_key = key
        self.timings["skeletons_ms"] = (time.perf_counter() - t0) * 1e3

    def _draw_b_skeletons(self, frame: int) -> None:
        bones = self._data.joint_set.bones
        points = self.run_b.shown[:, frame] * MM  # (K, J, 3) m
        for k in range(self._data.num_tracks):
            base, pts = f"{B_ROOT}/{k}", points[k]
            ok = np.isfinite(pts).all(1)
            seg = bone_segments(pts, bones)
            line, pc, label = (self._nodes[f"{base}/{n}"] for n in ("bones", "joints", "label"))
            if len(seg):
                line.points = seg.astype(np.float32)
            line.visible = len(seg) > 0
            if ok.any():
                pc.points = pts[ok].astype(np.float32)
                top = pts[ok][np.argmax(pts[ok, 2])]
                label.position = top + np.array([0.0, 0.0, B_LABEL_LIFT_M])
            pc.visible = label.visible = bool(ok.any())

    # ------------------------------------------------------------------ worker

    def _work(self) -> None:
        t_start = time.perf_counter()
        try:
            params = self.params_b
        except (ValueError, TypeError) as exc:
            self.gui.status.content = f"**B is not valid:** {exc}"
            return
        with self._lock:
            data, run_b = self._data, self.run_b
        if run_b is None or params != run_b.params:  # 1. re-filter the whole sequence
            t0 = time.perf_counter()
            run = run_filter(data.results.track_raw, params)
            self.timings["filter_ms"] = (time.perf_counter() - t0) * 1e3
            with self._lock:
                if data is not self._data:
                    self._worker.request()  # results changed meanwhile: redo on theirs
                    return
                self.run_b = run
            if self._auto_show and params != self.run_a.params:
                self._auto_show = False
                self.gui.show_b.value = True
        st = self.app.state
        with self._lock:  # 2. skeletons (a no-op when nothing they show changed)
            self._draw_b(st.frame, st.layers.offset_filtered)
        self._update_plot()  # 3. plots, 4. metrics
        self._update_metrics()
        self.timings["work_ms"] = (time.perf_counter() - t_start) * 1e3
        self._show_status()

    def _update_plot(self) -> None:
        st = self.app.state
        with self._lock:
            data, run_a, run_b = self._data, self.run_a, self.run_b
        if run_b is None:
            return  # new results: the worker's next pass re-filters B first
        frame, sel = int(st.frame), st.selection
        lo, hi = plot_range(data.num_frames, frame, WINDOWS.get(self.gui.window.value))
        key = (data, run_a, run_b, sel.track, sel.joint, lo, hi)
        if key != self._plot_key:
            wait = self._last_plot_t + PLOT_INTERVAL_S - time.monotonic()
            if wait > 0:
                self._worker.request(delay=wait)
                return
            t0 = time.perf_counter()
            self._plot.render(joint_trace(data, run_a, run_b, sel.track, sel.joint), lo, hi)
            img = self._plot.image()
            self.timings["plot_ms"] = (time.perf_counter() - t0) * 1e3
            if self._halted():
                return
            self.gui.plot.image = img
            self.plot_image, self._plot_key, self._marker_frame = img, key, None
            self._last_plot_t = time.monotonic()
        if frame != self._marker_frame:
            strip = self._plot.playhead(frame)
            if self._halted():
                return
            self.gui.playhead.image = strip
            self.playhead_image, self._marker_frame = strip, frame

    def _score(self, data: ViewerData, what: object, track: np.ndarray) -> dict[str, float]:
        """Scores cached per (results, run): A's and raw's survive B's edits."""
        key = (data, what)
        if key not in self._score_cache:
            res = data.results
            self._score_cache[key] = score(track, res.track_raw, res.joint_set, self._gt)
        return self._score_cache[key]

    def _update_metrics(self) -> None:
        with self._lock:
            data, run_a, run_b = self._data, self.run_a, self.run_b
        if run_b is None:
            return
        t0 = time.perf_counter()
        rows = {
            "raw": self._score(data, "raw", data.results.track_raw),
            "A": self._score(data, run_a, run_a.shown),
            "B": self._score(data, run_b, run_b.shown),
        }
        keep = ((data, "raw"), (data, run_a), (data, run_b))
        for stale in [k for k in self._score_cache if k not in keep]:
            del self._score_cache[stale]
        if rows == self.metrics:
            return
        self.metrics = rows
        if not self._halted():
            self.gui.metrics.content = metrics_table(rows)
        self.timings["metrics_ms"] = (time.perf_counter() - t0) * 1e3

    def _show_status(self) -> None:
        t = self.timings
        parts = [f"{name} {t[k]:.0f} ms" for name, k in (
            ("re-filter", "filter_ms"), ("plot", "plot_ms"), ("metrics", "metrics_ms"),
        ) if k in t]  # fmt: skip
        a, b = self.run_a.params, self.run_b.params if self.run_b else None
        same = "B = A" if b == a else "B: …" if b is None else f"B: {describe(b)}"
        lines = [f"<small>{same}<br/>{' · '.join(parts)}</small>"]
        if self.message:
            lines.append(self.message)
        if not self._halted():
            self.gui.status.content = "\n\n".join(lines)


def make_filter_panel(app: ViewerApp) -> FilterTuning:
    """The "Filter A/B" folder in ``app``'s GUI, following the app's state."""
    return FilterTuning(app)
