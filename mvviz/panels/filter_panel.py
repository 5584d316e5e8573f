"""Filter tuning, side by side: the run's Kalman filter (A) against an editable copy (B).

The GUI folder "Filter A/B" shows filter A (``results.config.kalman``) read-only and
filter B as controls. Any change to B re-filters the whole sequence with the vectorised
:func:`~pipeline.stages.kalman.kalman_filter` (tens of milliseconds) on a worker thread with a
"latest wins" slot, so typing never queues work. Then:

- B's skeletons are drawn under ``/world/skeletons/filter_b/<track>`` as a distinct
  overlay: dashed bones in a darker track colour with a "B" label, over A's skeletons
  or, with "B drawn: strip", in a strip shifted past everyone's x range (so they never
  land on another person); hidden while B = A ("Reset B to A" removes them);
- a plot of the selected track and joint over time (:mod:`mvviz.analysis.trace_plot`): x, y, z
  (raw dots, A and B lines, gate rejections as crosses) and both filters' Mahalanobis
  distances with their gates. The plot image is sent when what it shows changes
  (selection, filters, window), not on a frame change: the current frame is a playhead
  strip under the plot's frame axis, a ~0.5 kB image, so scrubbing sends that instead
  of a ~90 kB plot per frame;
- MPJPE, PCK@160, acceleration error and jitter of raw, A and B against the ground
  truth, scored exactly as :func:`pipeline.evaluation.evaluate.evaluate` scores its rows.

"Apply B" swaps B's arrays into the results (``host.set_results``) and saves B
into ``SCENE/mvviz_config.json`` (atomically), which ``mvviz run`` / ``mvviz view`` /
``python app.py`` read next time; a read-only viewer disables and refuses it.

Units: arrays are millimetres and frames, as in the results; the scene is in metres.
"""

from __future__ import annotations

import dataclasses
import threading
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import viser

from mvviz.analysis.filter_runs import FilterRun, results_run, run_filter, with_filter
from mvviz.analysis.trace_plot import (
    PLAYHEAD_HEIGHT,
    PLOT_HEIGHT,
    PLOT_WIDTH,
    TracePlot,
    joint_trace,
    plot_range,
)
from mvviz.panels.contract import PanelHost
from mvviz.scene.geometry import MM, OFFSET_FILTERED_M, ViewerData, bone_segments, track_color
from mvviz.workers import LatestWins, yielding_to
from pipeline.config import CONFIG_FILE, PipelineConfig, load_config, save_config
from pipeline.core.files import SceneFormatError
from pipeline.evaluation import metrics
from pipeline.evaluation.evaluate import (
    ground_truth_slots,
    gt_per_frame,
    stage_metrics,
    to_smpl_slots,
)
from pipeline.stages.kalman import MODELS, KalmanParams

B_ROOT = "/world/skeletons/filter_b"
B_BONE_WIDTH_M = 0.034  # A's filtered bones are 0.022 m: B's dashes sleeve them
B_LABEL_LIFT_M = 0.12
B_DASHES = 4  # dashes per bone
PLACEMENTS = ("over A, dashed", "strip beside everyone")
STRIP_GAP_M = 1.0  # between the people's x range and B's strip
PLOT_INTERVAL_S = 0.1  # at most ~10 plot renders per second while the selection changes
FIRST_PLOT_DELAY_S = 3.0
"""The first plot (matplotlib's import and figure, ~0.5-1 s of CPU) waits this long after
the panel is made, so that it does not compete with the start of the viewer and the first
page load; the plot sits in a tab that is not open at the start."""
WINDOWS = {"all": None, "±25": 25, "±50": 50, "±100": 100}  # plotted frames around the frame
Q_SCALES = {"÷4": 0.25, "÷2": 0.5, "×2": 2.0, "×4": 4.0}  # B's q scale buttons


def save_filter_config(scene_root: Path, params: KalmanParams, run_config: PipelineConfig) -> Path:
    """Write ``params`` as the kalman section of ``SCENE/mvviz_config.json`` (atomically).

    An existing file keeps its other sections; without one the run's config is written.
    """
    path = Path(scene_root) / CONFIG_FILE
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
    return gt_per_frame(gt, slots, res.num_frames)[0]


def score(
    track: np.ndarray, track_raw: np.ndarray, joint_set: str, gt: np.ndarray | None
) -> dict[str, float]:
    """MPJPE, PCK@160, acceleration error, jitter of ``track`` (K, F, J, 3) mm, scored
    where ``track_raw`` has the joint, as :func:`pipeline.evaluation.evaluate.evaluate` does.
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


# --------------------------------------------------------------------------- gui


@dataclass
class FilterHandles:
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
    placement: viser.GuiDropdownHandle  # one of PLACEMENTS
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


def make_filter_handles(server: viser.ViserServer, a: KalmanParams) -> FilterHandles:
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
        show_b = gui.add_checkbox("Show B skeletons", False, hint="dashed; hidden while B = A")
        placement = gui.add_dropdown("B drawn", PLACEMENTS, initial_value=PLACEMENTS[0])
        window = gui.add_dropdown("Plot frames", tuple(WINDOWS), initial_value="all")
        plot = gui.add_image(blank, format="png")
        playhead = gui.add_image(blank[:PLAYHEAD_HEIGHT], format="png")
    panel = FilterHandles(
        folder, a_info, model, q, q_scale, r, p0, gain, smoother, gate_on, gate, reset, apply,
        show_b, placement, window, plot, playhead, metrics_md, status,
    )  # fmt: skip
    panel.sync_enabled()
    return panel


def dashed_segments(segments: np.ndarray, dashes: int) -> np.ndarray:
    """(S, 2, 3) segments -> (S * dashes, 2, 3): each cut into ``2 * dashes - 1`` equal
    pieces, every other one kept (a dashed line from end to end)."""
    n = 2 * dashes - 1
    t = np.arange(0, n, 2)[:, None] / n  # (dashes, 1) start of each dash
    a, b = segments[:, None, 0], segments[:, None, 1]  # (S, 1, 3)
    start, stop = a + (b - a) * t, a + (b - a) * (t + 1.0 / n)
    return np.stack([start, stop], 2).reshape(-1, 2, 3)


def strip_offset(data: ViewerData) -> np.ndarray:
    """(3,) m: the shift along x that moves a skeleton from where people go to a strip
    beyond all of them (the x range of every raw joint of the run plus
    :data:`STRIP_GAP_M`), so a shifted B lands on nobody."""
    x = data.results.track_raw[..., 0]
    x = x[np.isfinite(x)]
    width = float(x.max() - x.min()) * MM if len(x) else 0.0
    return np.array([width + STRIP_GAP_M, 0.0, 0.0])


# --------------------------------------------------------------------------- worker


# --------------------------------------------------------------------------- the panel


class FilterPanel:
    """The "Filter A/B" panel at work: B's run, its skeletons, plots and metrics.

    ``run_a``/``run_b`` are the two filters' :class:`FilterRun`; ``metrics`` the last
    :func:`score` rows (raw, A, B); ``plot_image``/``playhead_image`` the last plot and
    playhead sent; ``timings`` the last re-filter / skeleton / plot / metrics times in
    ms. Everything drawn follows the host (:class:`~mvviz.panels.contract.PanelHost`): its
    state-change callbacks bring frame, selection and new results.
    """

    def __init__(self, host: PanelHost) -> None:
        self.host = host
        self._lock = threading.RLock()  # the scene nodes and the runs below
        data = host.state.data
        self._data = data
        self.run_a = results_run(data.results)
        self.run_b: FilterRun | None = self.run_a  # None: being re-filtered
        self.gui = make_filter_handles(host.server, self.run_a.params)
        self.gui.apply.disabled = host.writes.read_only is not None
        self.metrics: dict[str, dict[str, float]] = {}
        self.plot_image: np.ndarray | None = None  # the last plot sent (no frame marker)
        self.playhead_image: np.ndarray | None = None  # the last playhead strip sent
        self.timings: dict[str, float] = {}
        self.message = ""
        self._gt = gt_dense(data)
        self._score_cache: dict[tuple, dict[str, float]] = {}
        self._plot: TracePlot | None = None  # made at the first plot (imports matplotlib)
        self._plot_key: tuple | None = None
        self._marker_frame: int | None = None
        self._last_plot_t = time.monotonic() + FIRST_PLOT_DELAY_S - PLOT_INTERVAL_S
        self._drawn_key: tuple | None = None
        self._auto_show = True  # "Show B" turns on at B's first edit, unless touched
        self._nodes: dict[str, viser.SceneNodeHandle] = {}
        self._build_nodes()
        self._bind()
        # the host's stop flag ends the worker and skips GUI writes
        self._halted = host.stopped.is_set
        self._rendering = lambda: host.rendering  # noqa: E731 - read at each call
        self._worker = LatestWins(self._work, name="mvviz-filter-ab", halted=self._halted)
        self._unsubscribe = host.subscribe(self._on_state_changed)
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
        """Make B the current filter: swap its arrays into the shown results and save its
        parameters to ``SCENE/mvviz_config.json``. Returns the config path; raises
        :class:`~mvviz.safe_paths.WriteRefused` (nothing applied) when the viewer is
        read-only or the file would be written out of the scene."""
        self.host.writes.scene_file(self.host.state.scene.root, CONFIG_FILE)
        params = self.params_b
        with self._lock:
            data, run = self._data, self.run_b
        if run is None or run.params != params:
            run = run_filter(data.results.track_raw, params, skip=data.results.track_contradicted)
        path = save_filter_config(data.scene.root, params, data.results.config)
        self.host.set_results(with_filter(data.results, run))
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
        """Stop following the host and end the worker (the host calls it at its stop)."""
        self._unsubscribe()
        self._worker.stop()

    # ------------------------------------------------------------------ gui callbacks

    def _bind(self) -> None:
        g = self.gui

        def edited(_) -> None:
            g.sync_enabled()
            self._worker.request()

        for h in (g.model, g.q, g.r, g.p0, g.control_gain, g.smoother, g.gate_on, g.gate):
            h.on_update(edited)  # B's parameters
        g.placement.on_update(edited)
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
        """After each render: follow new results, draw B at the new frame."""
        with self._lock:
            if st.data is not self._data and st.data is self.host.state.data:
                self._rebuild(st.data)
            self._draw_b(st.frame, st.layers.offset_filtered)
        self._worker.request()

    # ------------------------------------------------------------------ scene nodes

    def _build_nodes(self) -> None:
        scene, K = self.host.server.scene, self._data.num_tracks
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

    @property
    def b_differs(self) -> bool:
        """B has been re-filtered with parameters other than A's (what is drawn)."""
        return self.run_b is not None and self.run_b.params != self.run_a.params

    def _draw_b(self, frame: int, offset_filtered: bool) -> None:
        """B's skeletons at ``frame`` (call with the lock held)."""
        show, placement = bool(self.gui.show_b.value), self.gui.placement.value
        key = (self._data, self.run_a, self.run_b, frame, show, placement, offset_filtered)
        if key == self._drawn_key:
            return
        t0 = time.perf_counter()
        group = self._nodes[B_ROOT]
        try:
            base = OFFSET_FILTERED_M if offset_filtered else np.zeros(3)  # follow A
            strip = placement == PLACEMENTS[1]
            group.position = base + (strip_offset(self._data) if strip else np.zeros(3))
            group.visible = show and self.b_differs
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
            seg = dashed_segments(bone_segments(pts, bones), B_DASHES)
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
            same = params == self.run_a.params  # reset to A: A's run, nothing to filter
            with yielding_to(self._rendering):  # the frame changes first
                run = (
                    self.run_a
                    if same
                    else run_filter(
                        data.results.track_raw, params, skip=data.results.track_contradicted
                    )
                )
            self.timings["filter_ms"] = (time.perf_counter() - t0) * 1e3
            with self._lock:
                if data is not self._data:
                    self._worker.request()  # results changed meanwhile: redo on theirs
                    return
                self.run_b = run
            if self._auto_show and params != self.run_a.params:
                self._auto_show = False
                self.gui.show_b.value = True
        st = self.host.state
        with self._lock:  # 2. skeletons (a no-op when nothing they show changed)
            self._draw_b(st.frame, st.layers.offset_filtered)
        self._update_plot()  # 3. plots, 4. metrics
        self._update_metrics()
        self.timings["work_ms"] = (time.perf_counter() - t_start) * 1e3
        self._show_status()

    def _update_plot(self) -> None:
        st = self.host.state
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
            if self._plot is None:
                self._plot = TracePlot()
            with yielding_to(self._rendering):
                self._plot.render(joint_trace(data, run_a, run_b, sel.track, sel.joint), lo, hi)
                img = self._plot.image()
            self.timings["plot_ms"] = (time.perf_counter() - t0) * 1e3
            if self._halted():
                return
            self.gui.plot.image = img
            self.plot_image, self._plot_key, self._marker_frame = img, key, None
            self._last_plot_t = time.monotonic()
        if frame != self._marker_frame and self._plot is not None:
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
            with yielding_to(self._rendering):  # seconds on long scenes: frames first
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
        same = (
            "B = A (nothing of B drawn)" if b == a else "B: …" if b is None else f"B: {describe(b)}"
        )
        lines = [f"<small>{same}<br/>{' · '.join(parts)}</small>"]
        if self.message:
            lines.append(self.message)
        if not self._halted():
            self.gui.status.content = "\n\n".join(lines)


def make_filter_panel(host: PanelHost) -> FilterPanel:
    """The "Filter A/B" folder in ``host``'s GUI, following its state."""
    return FilterPanel(host)
