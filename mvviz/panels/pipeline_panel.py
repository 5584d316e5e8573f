"""The "Pipeline" panel: the timeline drives the pipeline.

Changing a parameter (2D source, association thresholds, triangulation outlier threshold
and minimum views, which cameras are used) re-runs 2D source selection, association and
triangulation of the CURRENT frame at once (:func:`pipeline.run.frames.run_frame`, a few ms) and
shows the effect where the user stands: a copy of the shown results with that frame's
per-frame rows replaced (:func:`patch_frame`, its people matched to the existing tracks)
is swapped into the viewer's data in place of the results, and the viewer redraws.
Meanwhile the sequence-wide stages run on a background thread with a progress bar:
every frame's association and triangulation, tracking and Kalman filtering
(:func:`pipeline.run.pipeline.run_stages`), whose results replace the preview through
``host.set_results``; then, if the config fits SMPL bodies, the fit, whose
results replace those once more. A newer change cancels a run between frames and
stages (latest wins; a fit in progress is finished and dropped). Frames the user
visits before the tracks land are re-run as they are reached.

The panel lists what differs from the run's config, resets to it, saves into
``SCENE/mvviz_config.json`` (and the re-run results at the default results path, so the
next start is warm) and exports the current run as a rerun recording: a file name inside
the export folder, refused if it leads out or names an existing file while "Overwrite" is
off (:mod:`mvviz.safe_paths`). A read-only viewer disables and refuses saving and export.

Units: mm, pixels, frames, as in the pipeline.
"""

from __future__ import annotations

import dataclasses
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import viser

from mvviz.panels.contract import PanelHost
from mvviz.panels.run_compare import RunCompare, make_run_compare
from mvviz.safe_paths import WriteRefused, shown_path
from mvviz.scene.geometry import ViewerData, lazy_detection_rays, person_indices
from pipeline.body.arrays import BodyModelData, load_body_model_data
from pipeline.body.keypoints import FITTABLE_JOINT_SETS
from pipeline.config import CONFIG_FILE, PipelineConfig, save_config
from pipeline.core.progress import LatestProgress
from pipeline.data.joint_sets import get_joint_set
from pipeline.data.scene import Scene
from pipeline.results.store import (
    EDGE_FIELDS,
    PERSON_FIELDS,
    FrameResult,
    PipelineResults,
    cache_key,
    default_results_path,
    pack_frame,
    save_results,
)
from pipeline.run.frames import (
    frame_rows,
    restored_joints,
    run_frame,
    select_2d,
    source_joint_set,
)
from pipeline.run.pipeline import fit_bodies, pack_run, run_stages
from pipeline.stages.track import match_to_tracks

if TYPE_CHECKING:
    from pipeline.body.model import BodyModel

# --------------------------------------------------------------------------- pure parts


def _flatten(d: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flatten(v, f"{prefix}{k}."))
        else:
            out[prefix + k] = v
    return out


def _fmt(value: Any) -> str:
    return "null" if value is None else f"{value:g}" if isinstance(value, float) else str(value)


def _names(views: tuple[str, ...] | list[str]) -> str:
    return ", ".join(views) if views else "none"


def config_diff(run: PipelineConfig, current: PipelineConfig) -> list[str]:
    """The fields of ``current`` that differ from ``run``, in the config's field order:
    ``"section.field: old -> new"``, and the cameras as ``"disabled cameras: 3"`` (with
    the run's list in parentheses when it disabled some too)."""
    a, b = _flatten(run.to_dict()), _flatten(current.to_dict())
    lines = []
    for key, new in b.items():
        old = a.get(key)
        if key == "disabled_views":
            if set(old) != set(new):
                line = f"disabled cameras: {_names(new)}"
                lines.append(line + (f" (run config: {_names(old)})" if old else ""))
        elif old != new:
            lines.append(f"{key}: {_fmt(old)} -> {_fmt(new)}")
    return lines


def _renumbered_people(
    results: PipelineResults, frame: int, num_people: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where the person-frame rows go when ``frame``'s are replaced by ``num_people`` new
    ones: ``(before, after, det_person)``, the rows kept on each side of the frame and
    the detections' person rows renumbered (-1 for the frame's own detections)."""
    pf = results.person_frame
    before, after = np.flatnonzero(pf < frame), np.flatnonzero(pf > frame)
    n0 = len(before)
    new_q = np.full(len(pf), -1)
    new_q[before] = np.arange(n0)
    new_q[after] = n0 + num_people + np.arange(len(after))
    det_person = np.where(results.det_person >= 0, new_q[np.maximum(results.det_person, 0)], -1)
    return before, after, det_person


def _unmirrored(
    results: PipelineResults, fr: FrameResult, joints2d_all: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(det_joints2d, det_flipped) with the left/right swaps of the other frames kept
    and ``fr``'s frame taking its own."""
    flip = get_joint_set(results.joint_set).flip_index
    det_flipped = np.zeros(len(joints2d_all), bool)
    if results.det_flipped is not None and len(results.det_flipped) == len(joints2d_all):
        det_flipped[:] = results.det_flipped
    det_flipped[fr.rows] = fr.association.flipped
    det_joints2d = joints2d_all.copy()
    det_joints2d[det_flipped] = joints2d_all[det_flipped][:, flip]
    return det_joints2d, det_flipped


def patch_frame(
    results: PipelineResults,
    fr: FrameResult,
    config: PipelineConfig,
    joints2d_all: np.ndarray,
) -> PipelineResults:
    """``results`` with frame ``fr.frame``'s per-frame stages replaced by ``fr``.

    The frame's person-frame rows, detection assignments and affinity edges are replaced
    (:func:`~pipeline.results.store.pack_frame`); its new people take the tracks they match
    (:func:`~pipeline.stages.track.match_to_tracks` against each track's raw pose in that
    frame, else its filtered one, gated by the tracking distance) and the tracks' raw
    joints in that frame follow; unmatched people are untracked. The filtered
    trajectories are left as they were: they belong to the sequence stages.

    Args:
        results: results of the same joint set as ``joints2d_all``.
        fr: the re-run frame (``run_frame`` with ``config`` on ``joints2d_all``).
        joints2d_all: (N, J, 3) the 2D joints that fed ``fr``, for every detection row.
    Returns:
        A new :class:`PipelineResults` (with ``config`` and no cache key).
    """
    if joints2d_all.shape[1:] != results.det_joints2d.shape[1:]:
        raise ValueError(
            f"joints2d_all has shape {joints2d_all.shape}; the results' joint set needs "
            f"(N, {results.det_joints2d.shape[1]}, 3)"
        )
    f, a = fr.frame, fr.association
    cols = pack_frame(fr, results.num_views, joints2d_all.shape[1])
    # 1. person-frame rows: those before the frame, the frame's new people, those after
    before, after, det_person = _renumbered_people(results, f, a.num_people)
    det_person[fr.rows] = -1
    assigned = a.cluster >= 0
    det_person[fr.rows[assigned]] = len(before) + a.cluster[assigned]

    def splice(old: np.ndarray, new: np.ndarray) -> np.ndarray:
        return np.concatenate([old[before], np.asarray(new, old.dtype), old[after]])

    # 2. tracks: match the new people to each track's pose in this frame
    points = cols.person_joints
    raw, filt = results.track_raw[:, f], results.track_filtered[:, f]  # (K, J, 3)
    reference = np.where(np.isfinite(raw), raw, filt)
    track = match_to_tracks(points, reference, config.tracking.max_distance_mm)
    track_raw = results.track_raw.copy()
    track_raw[:, f] = np.nan
    track_raw[track[track >= 0], f] = points[track >= 0]
    # 3. affinity edges: the other frames' ones, then the frame's
    keep = ~np.isin(results.edge_a, fr.rows)
    det_joints2d, det_flipped = _unmirrored(results, fr, joints2d_all)
    return dataclasses.replace(
        results,
        config=config,
        det_joints2d=det_joints2d,
        det_flipped=det_flipped,
        det_person=det_person,
        **{k: splice(getattr(results, k), getattr(cols, k)) for k in PERSON_FIELDS},
        person_track=splice(results.person_track, track),
        **{k: np.concatenate([getattr(results, k)[keep], getattr(cols, k)]) for k in EDGE_FIELDS},
        track_raw=track_raw,
        cache_key="",
    )


def frame_only_results(
    scene: Scene, fr: FrameResult, config: PipelineConfig, joints2d_all: np.ndarray,
    restored: np.ndarray | None,
) -> PipelineResults:  # fmt: skip
    """Results holding only frame ``fr.frame`` (each of its people a track): the preview
    when the joint set changed (another 2D source), so no stored frame fits beside it."""
    return pack_run(scene, [fr], config, joints2d_all, restored=restored)


def preview_data(data: ViewerData, results: PipelineResults) -> ViewerData:
    """``data`` showing ``results`` that keep its joint set, tracks and SMPL fits (a
    :func:`patch_frame` preview): the per-results indices of :func:`~mvviz.scene.geometry.prepare`
    are recomputed, the bodies reused (``prepare`` would skin every fit again)."""
    # rays and image-plane points kept if no detection's 2D joints changed (a frame
    # re-run with the same source); else computed again from the new joints as indexed
    old, new = data.results.det_joints2d[..., :2], results.det_joints2d[..., :2]
    same = (old == new) | (np.isnan(old) & np.isnan(new))
    changed = np.flatnonzero(~same.all((1, 2)))
    rays_ = {"det_rays": data.det_rays, "det_plane": data.det_plane}  # computed as indexed
    if len(changed):
        rays_ = lazy_detection_rays(data.scene, results, data.cameras)
    return dataclasses.replace(
        data,
        results=results,
        **rays_,
        **person_indices(results, data.num_frames),
        filtered=results.track_filtered,
        min_confidence=results.config.triangulation.min_confidence,
    )


# --------------------------------------------------------------------------- GUI


@dataclass
class PipelineHandles:
    folder: viser.GuiFolderHandle
    source: viser.GuiDropdownHandle
    max_distance: viser.GuiSliderHandle  # association.max_distance_mm
    min_affinity: viser.GuiSliderHandle  # association.min_affinity
    assoc_min_views: viser.GuiSliderHandle  # association.min_views
    outlier_px: viser.GuiSliderHandle  # triangulation.outlier_threshold_px
    tri_min_views: viser.GuiSliderHandle  # triangulation.min_views
    cameras: dict[str, viser.GuiCheckboxHandle]  # camera name -> used
    changes: viser.GuiMarkdownHandle
    progress: viser.GuiProgressBarHandle
    status: viser.GuiMarkdownHandle
    reset: viser.GuiButtonHandle
    save: viser.GuiButtonHandle
    export_path: viser.GuiTextHandle  # a name inside host.writes.export_dir
    overwrite: viser.GuiCheckboxHandle
    export: viser.GuiButtonHandle
    export_progress: viser.GuiProgressBarHandle
    export_status: viser.GuiMarkdownHandle

    @property
    def inputs(self) -> list[viser.GuiInputHandle]:
        """Every control that changes the config."""
        return [
            self.source, self.max_distance, self.min_affinity, self.assoc_min_views,
            self.outlier_px, self.tri_min_views, *self.cameras.values(),
        ]  # fmt: skip


def _slider(server: viser.ViserServer, label: str, lo, hi, step, value, hint: str):
    return server.gui.add_slider(
        label, min=min(lo, value), max=max(hi, value), step=step, initial_value=value, hint=hint
    )


def make_pipeline_handles(
    server: viser.ViserServer, scene: Scene, config: PipelineConfig, *,
    sources: tuple[str, ...], export_name: str, export_dir: Path,
) -> PipelineHandles:  # fmt: skip
    V = len(scene.rig)
    a, t = config.association, config.triangulation
    with server.gui.add_folder("Pipeline", expand_by_default=False) as folder:
        source = server.gui.add_dropdown(
            "2D source", sources, initial_value=config.source,
            hint="keypoints: the 2D detector; smpl: joints of the monocular SMPL predictions",
        )  # fmt: skip
        source.disabled = len(sources) < 2
        max_distance = _slider(
            server, "Assoc. max dist (mm)", 50.0, 1000.0, 10.0, a.max_distance_mm,
            "mean ray-to-ray distance at which affinity reaches zero",
        )  # fmt: skip
        min_affinity = _slider(
            server, "Assoc. min affinity", 0.0, 1.0, 0.01, a.min_affinity,
            "average-linkage threshold for merging clusters",
        )  # fmt: skip
        assoc_min_views = _slider(
            server, "Assoc. min views", 1, V, 1, a.min_views, "views a person needs"
        )
        outlier_px = _slider(
            server, "Outlier threshold (px)", 1.0, 100.0, 1.0, t.outlier_threshold_px,
            "a view whose reprojection error exceeds this is dropped for that joint",
        )  # fmt: skip
        tri_min_views = _slider(
            server, "Triang. min views", 2, V, 1, t.min_views, "views a joint needs"
        )
        with server.gui.add_folder("Cameras used"):
            cameras = {
                name: server.gui.add_checkbox(
                    f"camera {name}", initial_value=name not in config.disabled_views
                )
                for name in scene.rig.names
            }
        changes = server.gui.add_markdown("")
        progress = server.gui.add_progress_bar(0.0, visible=False, animated=True)
        status = server.gui.add_markdown("")
        reset = server.gui.add_button("Reset to run config", icon=viser.Icon.ARROW_BACK_UP)
        save = server.gui.add_button("Save into run config", icon=viser.Icon.DEVICE_FLOPPY)
        path = server.gui.add_text(
            "RRD path", initial_value=export_name, hint=f"a file name inside {export_dir}"
        )
        overwrite = server.gui.add_checkbox("Overwrite", initial_value=False)
        export = server.gui.add_button("Export .rrd", icon=viser.Icon.FILE_EXPORT)
        export_progress = server.gui.add_progress_bar(0.0, visible=False)
        export_status = server.gui.add_markdown("")
    return PipelineHandles(
        folder, source, max_distance, min_affinity, assoc_min_views, outlier_px, tri_min_views,
        cameras, changes, progress, status, reset, save, path, overwrite, export,
        export_progress, export_status,
    )  # fmt: skip


# --------------------------------------------------------------------------- controller


class PipelinePanel:
    """The panel's GUI and what it runs.

    Threads: GUI callbacks re-run the current frame at once; ``_previewer`` re-runs
    frames reached by the timeline while the tracks are pending; one worker runs the
    sequence-wide stages of the newest request. Lock order: ``_lock`` may be held while
    calling ``host.set_results`` (which takes the viewer's render lock); the render thread
    never waits for ``_lock`` (its state-change callback only queues work).
    """

    def __init__(self, host: PanelHost) -> None:
        self.host = host
        self.scene: Scene = host.state.scene
        self.run_results: PipelineResults = host.state.results  # as loaded (or last saved)
        self.run_config: PipelineConfig = self.run_results.config
        self.base = self.run_results  # the newest complete results (every stage)
        self.config = self.run_config  # what the GUI asks for
        self.last_preview_ms = float("nan")  # the last frame re-run, server side
        self._model = host.model
        self._shown = self.run_results  # what this panel last put on screen
        self._patched: set[int] = set()  # frames re-run for ``config`` while pending
        self.pending = False  # the tracks for ``config`` have not landed yet
        self.config_path = self.scene.root / CONFIG_FILE
        self._save_pending = False
        self._generation = 0
        self._muted = False
        self._lock = threading.RLock()
        self._cv = threading.Condition(self._lock)
        self._job: tuple[int, PipelineConfig] | None = None
        self._running = False
        self._closed = False  # stop(): the worker ends
        self._export_thread: threading.Thread | None = None
        self._previewer = ThreadPoolExecutor(1, thread_name_prefix="mvviz-pipeline-preview")
        self._preview_queued = False
        self._rows_sync = self.run_config.sync
        self._rows = frame_rows(self.scene, self.run_config)  # re-timed as the run was
        self._restored = self.run_results.det_restored
        self._joints2d_cache: tuple[tuple | None, np.ndarray | None] = (None, None)
        has_smpl = self._restored is not None or self.scene.detections.has_mono3d
        sources = ("keypoints", "smpl") if has_smpl else ("keypoints",)
        if self.run_config.source not in sources:
            sources += (self.run_config.source,)
        self.gui = make_pipeline_handles(
            host.server, self.scene, self.run_config, sources=sources, export_name="run.rrd",
            export_dir=host.writes.export_dir,
        )  # fmt: skip
        if host.writes.read_only is not None:
            self.gui.save.disabled = self.gui.export.disabled = True
            self.gui.export_status.content = f"<small>{host.writes.read_only}</small>"
        for handle in self.gui.inputs:
            handle.on_update(self._on_input)
        self.gui.reset.on_click(lambda _: self.reset())
        self.gui.save.on_click(lambda _: self.save())
        self.gui.export.on_click(lambda _: self.export())
        with self.gui.folder:  # "Compare with the saved config": whole-run A/B
            self.compare: RunCompare = make_run_compare(
                host, current=self.complete_results, model=lambda: self.model
            )
        self._unsubscribe = host.subscribe(self._on_state_changed)
        threading.Thread(target=self._worker, name="mvviz-rerun", daemon=True).start()
        self._show_changes()

    # ------------------------------------------------------------------ public

    @property
    def model(self) -> BodyModel | BodyModelData:
        """The body model (the shipped one unless the host has another)."""
        if self._model is None:
            self._model = load_body_model_data()
        return self._model

    def diff_lines(self) -> list[str]:
        return config_diff(self.run_config, self.config)

    def gui_config(self) -> PipelineConfig:
        """The config the GUI shows: its fields over the newest complete results' config
        (so fields another panel tunes, e.g. the Kalman filter's, are kept)."""
        g, base = self.gui, self.base.config
        assoc = dataclasses.replace(
            base.association,
            max_distance_mm=float(g.max_distance.value),
            min_affinity=float(g.min_affinity.value),
            min_views=int(round(g.assoc_min_views.value)),
        )
        tri = dataclasses.replace(
            base.triangulation,
            outlier_threshold_px=float(g.outlier_px.value),
            min_views=int(round(g.tri_min_views.value)),
        )
        disabled = tuple(name for name, cb in g.cameras.items() if not cb.value)
        return dataclasses.replace(
            base, source=str(g.source.value), disabled_views=disabled, association=assoc,
            triangulation=tri,
        )  # fmt: skip

    def set_config(self, config: PipelineConfig) -> None:
        """Show ``config``: re-run the current frame now and the sequence in the
        background (superseding an older run). The GUI is not changed (:meth:`set_gui`)."""
        with self._lock:
            self._generation += 1
            self._adopt_foreign_results()
            self.config = config
            self._patched.clear()
            if config == self.base.config:  # back to results we have
                self.pending = self._save_pending = False
                self._job = None
                if self._shown is not self.base:
                    self._show(self.base, full=False)
                self._set_progress(None, "")
            else:
                self.pending = True
                self._preview_frame(self.host.state.frame)
                self._job = (self._generation, config)
                self._set_progress(0.0, "re-running the sequence…")
                self._cv.notify_all()
        self._show_changes()

    def set_gui(self, config: PipelineConfig) -> None:
        """Put ``config``'s values into the controls without re-running anything."""
        g = self.gui
        with self._lock:
            self._muted = True
            try:
                g.source.value = config.source
                g.max_distance.value = config.association.max_distance_mm
                g.min_affinity.value = config.association.min_affinity
                g.assoc_min_views.value = config.association.min_views
                g.outlier_px.value = config.triangulation.outlier_threshold_px
                g.tri_min_views.value = config.triangulation.min_views
                for name, cb in g.cameras.items():
                    cb.value = name not in config.disabled_views
            finally:
                self._muted = False

    def reset(self) -> None:
        """Back to the run's config and results (a running re-run is dropped)."""
        with self._lock:
            self._generation += 1
            self._job = None
            self.set_gui(self.run_config)
            self.base = self.run_results
            self.config = self.run_config
            self.pending = self._save_pending = False
            self._patched.clear()
            if self.host.state.results is not self.run_results:
                self._show(self.run_results, full=False)
            self._set_progress(None, "reset to the run config")
        self._show_changes()

    def save(self) -> Path | None:
        """Write the GUI's config to ``SCENE/mvviz_config.json`` (atomically), and its
        results to the default results path now or when its re-run lands; the saved
        config becomes the run config. None (and why, in the status) if refused."""
        with self._lock:
            try:
                path = self.host.writes.scene_file(self.scene.root, CONFIG_FILE)
            except WriteRefused as exc:
                self.gui.status.content = f"not saved: {exc}"
                return None
            save_config(self.config, path)
            self.run_config = self.config
            msg = f"saved `{self.config_path.name}`"
            if self.base.config == self.config:
                msg += "; " + self._save_results()
            else:
                self._save_pending = True
                msg += "; the results will be saved when the re-run lands"
            self.gui.status.content = msg
        self._show_changes()
        return self.config_path

    def export(self, path: str | Path | None = None) -> threading.Thread | None:
        """Write the current run (once a re-run in progress lands) as a rerun recording
        named ``path`` (default: the GUI's) in the export folder, on a background thread,
        which is returned; None (and why, in the status) if refused."""
        g = self.gui
        with self._lock:
            if self._export_thread is not None and self._export_thread.is_alive():
                return self._export_thread
            try:
                name = g.export_path.value if path is None else path
                path = self.host.writes.export_file(name, overwrite=g.overwrite.value)
            except WriteRefused as exc:
                g.export_status.content = f"export refused: {exc}"
                return None
            g.export.disabled = True
            self._export_thread = threading.Thread(
                target=self._export, args=(path,), name="mvviz-export-rrd", daemon=True
            )
            self._export_thread.start()
            return self._export_thread

    def complete_results(self) -> PipelineResults:
        """The newest complete results (every stage), once a re-run in progress lands
        (blocks until then): what the exports write, never a preview."""
        with self._cv:
            self._cv.wait_for(lambda: self._job is None and not self._running)
            return self.base

    def wait_idle(self, timeout: float = 60.0) -> bool:
        """Block until no re-run, preview or export runs (for tests and scripts)."""
        end = time.monotonic() + timeout
        left = lambda: max(end - time.monotonic(), 0.0)  # noqa: E731
        with self._cv:
            if not self._cv.wait_for(lambda: self._job is None and not self._running, left()):
                return False
        self._previewer.submit(lambda: None).result(left())
        if self._export_thread is not None:
            self._export_thread.join(left())
            if self._export_thread.is_alive():
                return False
        return self.host.wait_idle(left())

    def stop(self) -> None:
        """Stop following the host, drop a re-run in progress (it ends at its next frame
        or stage; a fit in progress finishes) and end the worker and the previewer."""
        self._unsubscribe()
        self.compare.stop()
        with self._cv:
            self._generation += 1
            self._job, self._closed = None, True
            self._cv.notify_all()
        self._previewer.shutdown(wait=False)

    # ------------------------------------------------------------------ previews

    def _on_input(self, _event) -> None:
        with self._lock:
            if not self._muted:
                self.set_config(self.gui_config())

    def _on_state_changed(self, state, reason: str) -> None:
        """Render thread: queue a re-run of a newly shown frame while tracks are pending."""
        if not self.pending or "frame" not in reason.split(","):
            return
        if state.frame in self._patched or self._preview_queued:
            return
        self._preview_queued = True
        self._previewer.submit(self._preview_current_frame)

    def _preview_current_frame(self) -> None:
        with self._lock:
            self._preview_queued = False
            f = self.host.state.frame
            if self.pending and f not in self._patched:
                self._adopt_foreign_results()
                self._preview_frame(f)

    def _adopt_foreign_results(self) -> None:
        """Another panel swapped results in: build on those from now on."""
        shown = self.host.state.results
        if shown is not self._shown:
            self.base = self._shown = shown
            self._patched.clear()

    def _joints2d(self, config: PipelineConfig) -> np.ndarray:
        if config.source == "smpl" and self._restored is None:
            self._restored = restored_joints(self.scene, self.model)
        key = (config.source, config.sync)  # re-timing a sub-frame offset takes ~0.1 s
        if self._joints2d_cache[0] != key:
            self._joints2d_cache = (key, select_2d(self.scene, config, self._restored))
        return self._joints2d_cache[1]

    def _rows_for(self, config: PipelineConfig) -> list[np.ndarray]:
        """Detection rows per frame for ``config`` (its sync offsets move rows)."""
        with self._lock:
            if config.sync != self._rows_sync:
                self._rows_sync, self._rows = config.sync, frame_rows(self.scene, config)
            return self._rows

    def _preview_frame(self, f: int) -> None:
        """Re-run frame ``f`` for ``self.config`` and show it (caller holds the lock)."""
        t0 = time.perf_counter()
        config = self.config
        joints2d = self._joints2d(config)
        fr = run_frame(self.scene, f, config, joints2d, rows=self._rows_for(config)[f])
        shown, js = self._shown, source_joint_set(self.scene, config).name
        if shown.config == config and shown.joint_set == js:
            new = patch_frame(shown, fr, config, joints2d)  # keeps the frames re-run before
        elif self.base.joint_set == js:
            new = patch_frame(self.base, fr, config, joints2d)
        else:
            new = frame_only_results(self.scene, fr, config, joints2d, self._restored)
        self._show(new, full=False)
        self._patched.add(f)
        self.last_preview_ms = (time.perf_counter() - t0) * 1e3

    def _show(self, results: PipelineResults, *, full: bool) -> None:
        """Put ``results`` on screen (caller holds the lock): with ``full`` (new complete
        results) through ``host.set_results``; else, if they keep the shown joint set,
        tracks and fits (a preview, or the results it was made from), by replacing the
        viewer's data only (``host.show_data``): the scene nodes stay."""
        host, old = self.host, self.host.state.data
        r = old.results
        same = results.joint_set == r.joint_set and results.num_tracks == r.num_tracks
        same = same and results.smpl is r.smpl and results.smpl_vae is r.smpl_vae
        self._shown = results
        if full or not same:
            host.set_results(results)
        else:
            host.show_data(preview_data(old, results))

    # ------------------------------------------------------------------ sequence

    def _worker(self) -> None:
        while True:
            with self._cv:
                self._cv.wait_for(lambda: self._job is not None or self._closed)
                if self._closed:
                    return
                (gen, config), self._job = self._job, None
                self._running = True
            try:
                self._sequence_run(gen, config)
            except Exception as exc:  # show it; the viewer keeps the preview
                with self._lock:
                    if gen == self._generation:
                        self._set_progress(None, f"re-run failed: {type(exc).__name__}: {exc}")
            finally:
                with self._cv:
                    self._running = False
                    self._cv.notify_all()

    def _sequence_run(self, gen: int, config: PipelineConfig) -> None:
        t0 = time.perf_counter()
        cancelled = lambda: self._generation != gen  # noqa: E731
        last = [-100.0]

        def progress(_stage: str, done: int, total: int) -> None:
            pct = 100.0 * done / total
            if pct - last[0] >= 2.0:
                last[0] = pct
                with self._lock:
                    if not cancelled():
                        text = f"re-running the sequence: {pct:.0f}% (frame {done}/{total})"
                        self._set_progress(pct * (0.3 if fits else 0.95), text)

        with self._lock:
            joints2d = self._joints2d(config)
        js = source_joint_set(self.scene, config).name
        fits = config.fit_smpl and js in FITTABLE_JOINT_SETS
        key = cache_key(self.scene, config, self.model)
        res = run_stages(
            self.scene, config, joints2d, restored=self._restored,
            rows_per_frame=self._rows_for(config),
            key=key, cancelled=cancelled, progress=progress,
        )  # fmt: skip
        with self._lock:
            if res is None or cancelled():
                return
            self.pending = False  # the tracks are final: no more per-frame previews
            self._patched.clear()
            fits = fits and res.num_tracks > 0
            if fits:
                self._show(res, full=True)
                self._set_progress(30.0, "fitting SMPL bodies…")
        if fits:
            done, latest = threading.Event(), LatestProgress()
            watch = threading.Thread(target=self._watch_fit, args=(gen, done, latest), daemon=True)
            watch.start()
            try:
                res = fit_bodies(res, config, self.model, progress=latest)
            finally:
                done.set()
                watch.join()
        with self._lock:
            if cancelled():
                return
            self.base = res
            self._show(res, full=True)
            msg = (
                f"re-run done in {time.perf_counter() - t0:.1f} s: {res.num_tracks} tracks, "
                f"{len(res.person_frame)} person-frames"
            )
            if self._save_pending and self.run_config == config:
                msg += "; " + self._save_results()
            self._set_progress(None, msg)

    def _watch_fit(self, gen: int, done: threading.Event, latest: LatestProgress) -> None:
        while not done.wait(0.25):
            p = latest.value
            with self._lock:
                if p is not None and gen == self._generation:
                    desc, n, total = p
                    self._set_progress(30.0 + 70.0 * n / total, f"{desc}: {n}/{total}")

    def _save_results(self) -> str:
        """Save ``self.base`` (the run config's complete results) as the default results."""
        self._save_pending = False
        root = self.scene.root
        path = self.host.writes.cache_file(root, default_results_path(self.scene))
        save_results(self.base, path)
        self.run_results = self.base
        return f"results saved to `{shown_path(path, root)}`"

    def _set_progress(self, percent: float | None, text: str) -> None:
        g = self.gui
        if percent is not None:
            g.progress.value = float(np.clip(percent, 0.0, 100.0))
        g.progress.visible = percent is not None
        g.status.content = text

    def _show_changes(self) -> None:
        lines = self.diff_lines()
        if lines:
            text = "**Changed from the run config:**\n\n" + "\n".join(f"- {s}" for s in lines)
        else:
            text = "_Same as the run config._"
        self.gui.changes.content = text

    # ------------------------------------------------------------------ export

    def _export(self, path: Path) -> None:
        g = self.gui
        t0 = time.perf_counter()
        try:
            g.export_progress.value = 0.0
            g.export_progress.visible = True
            g.export_status.content = "waiting for the re-run…"
            with self._cv:  # export complete results, not a preview
                self._cv.wait_for(lambda: self._job is None and not self._running)
                results = self.base
            g.export_status.content = f"exporting to `{path}`…"
            done, latest = threading.Event(), LatestProgress()
            watch = threading.Thread(target=self._watch_export, args=(done, latest), daemon=True)
            watch.start()
            try:
                # rerun (~0.3 s to import) loads on the first export, not at every start
                from mvviz.export.rrd import export_rrd

                export_rrd(self.scene, results, self.model, path, progress=latest)
            finally:
                done.set()
                watch.join()
            mb = path.stat().st_size / 1e6
            took = time.perf_counter() - t0
            g.export_status.content = f"wrote `{path}` ({mb:.1f} MB) in {took:.0f} s"
        except Exception as exc:
            g.export_status.content = f"export failed: {type(exc).__name__}: {exc}"
        finally:
            g.export_progress.visible = False
            g.export.disabled = False

    def _watch_export(self, done: threading.Event, latest: LatestProgress) -> None:
        g = self.gui
        while not done.wait(0.25):
            p = latest.value
            if p is not None:
                _, n, total = p
                g.export_progress.value = 100.0 * n / total
                g.export_status.content = f"exporting: {100 * n / total:.0f}% ({n}/{total} frames)"


def make_pipeline_panel(host: PanelHost) -> PipelinePanel:
    """The "Pipeline" folder in ``host``'s GUI (``host.model`` None: the shipped body
    model, loaded when first needed)."""
    return PipelinePanel(host)
