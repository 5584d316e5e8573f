"""The "Diagnose" panel: what is wrong with the capture (``mvviz diagnose``), in the viewer.

"Run diagnose" runs :func:`pipeline.diagnose.report.diagnose` on the shown scene and
results on a worker thread (progress bar; "Cancel" stops it between steps and between
cameras), then each camera's residual against the joints the other cameras triangulate
(:func:`pipeline.diagnose.calibration.camera_residual`, suspects left out of the others'
references as the calibration check does). It shows a table over the cameras (sync
offset and confidence, calibration verdict, a step in time), the floor and up verdict,
the commands that apply the fixes, and for the chosen camera: its sync residual curve over
candidate shifts, its residual over time with a step marked (buttons jump to the step
and to the worst frame) and its residual vector field over its image. New results make
the findings stale (they say so) until the next run.

Units: frames, pixels, millimetres, degrees, as the diagnoses give them.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass

import numpy as np
import viser

from mvviz.analysis.diagnose_plots import (
    residual_field_image,
    residual_series_image,
    sync_curve_image,
)
from mvviz.panels.contract import PanelHost
from mvviz.scene.images import video_frame
from mvviz.workers import LatestWins
from pipeline.data.scene import Scene
from pipeline.diagnose.calibration import CameraResidual, camera_residual
from pipeline.diagnose.report import Diagnosis, diagnose
from pipeline.results.store import PipelineResults
from pipeline.stages.retime import offsets_setting

GO_STEP, GO_WORST = "moved at", "worst frame"
FIELD_WIDTH = 400  # px of the vector field's picture (the panel's width)
NOT_RUN = "_Not run yet: **Run diagnose** checks sync, calibration and the floor (~10-30 s)._"


@dataclass(frozen=True, eq=False)
class DiagnoseFindings:
    """One run of the panel: the diagnosis, each camera's residual (for its field and its
    time series), what it was run on, and how long it took."""

    diagnosis: Diagnosis
    residuals: dict[str, CameraResidual]
    results: PipelineResults
    seconds: float

    def series(self, camera: str) -> np.ndarray:
        """(F,) median residual per frame of ``camera``, px (NaN: nobody seen)."""
        return self.residuals[camera].series(self.results.num_frames)


def camera_residuals(
    scene: Scene, results: PipelineResults, diagnosis: Diagnosis, *, cancelled=None, progress=None
) -> dict[str, CameraResidual] | None:
    """Each camera against the others' joints, the suspects left out of the others'
    references, on the run the calibration was judged on (``results`` re-timed by the
    confident sync offsets, :mod:`pipeline.diagnose.in_sync`); None if ``cancelled()``
    between cameras."""
    results = diagnosis.calibration_run or results
    bad = frozenset(
        scene.rig.index_of(n) for n, f in diagnosis.calibration.items() if f.suspect
    )  # fmt: skip
    out = {}
    for v, cam in enumerate(scene.rig):
        if cancelled is not None and cancelled():
            return None
        if progress is not None:
            progress(v, len(scene.rig))
        out[cam.name] = camera_residual(scene, results, v, bad - {v})
    return out


def summary_markdown(d: Diagnosis) -> str:
    """One row per camera (sync offset and confidence, calibration residual that does
    not average out, a step in time), then a line per suspect camera."""
    lines = ["| camera | sync (frames) | conf. | calib. (px) | moved at |", "|---|---|---|---|---|"]
    notes = []
    for name, e in d.sync.items():
        c = d.calibration.get(name)
        sync = f"{e.offset_frames:+.2f}"
        sync = f"**{sync} {'late' if e.offset_frames > 0 else 'early'}**" if e.offset else sync
        if not e.trusted:
            sync += " (cannot tell)"
        calib, moved = "—", "—"
        if c is not None:
            calib = f"**{c.systematic_px:.1f} suspect**" if c.suspect else f"{c.systematic_px:.1f}"
            if c.out_of_sync:
                calib += " (in time)"
            moved = "—" if c.step is None else f"**{c.step.frame}**"
            if c.suspect:
                notes.append(
                    f"Camera **{name}** disagrees with the others ({c.systematic_px:.1f} px "
                    f"that does not average out, others {c.others_systematic_px:.1f}): the "
                    f"bundle adjustment moves it {c.rotation_error_deg:.2f}° / "
                    f"{c.translation_error_mm:.0f} mm (residual {c.residual_px:.1f} → "
                    f"{c.residual_after_px:.1f} px)."
                )
            if c.step is not None:
                notes.append(
                    f"Camera **{name}**'s residual steps at frame {c.step.frame} "
                    f"({c.step.before_px:.1f} → {c.step.after_px:.1f} px): moved then?"
                )
        lines.append(f"| {name} | {sync} | {e.confidence:.2f} | {calib} | {moved} |")
    for name, c in d.calibration.items():
        if c.out_of_sync:
            notes.append(
                f"Camera **{name}** is out of sync, not miscalibrated: "
                f"{c.systematic_as_recorded_px:.1f} px as recorded, "
                f"{c.systematic_px:.1f} px with its 2D re-timed by "
                f"{c.retimed_by_frames:+.2f} frames."
            )
    if d.retimed:
        offs = ", ".join(f"{k} {v:+.2f}" for k, v in d.retimed.items())
        notes.append(f"_Calibration judged with the offsets found applied ({offs})._")
    return "\n".join(lines) + ("\n\n" + "\n\n".join(notes) if notes else "")


def floor_markdown(d: Diagnosis) -> str:
    f = d.floor
    if f is None:
        return "**Floor and up**: cannot tell (no track with shoulders and ankles)."
    state = "ok" if f.ok else "**not z-up with the floor at 0**"
    up = ", ".join(f"{x:.3f}" for x in f.up)
    return (
        f"**Floor and up** ({f.method}, {f.points} samples): up ({up}), "
        f"{f.angle_to_z_deg:.1f}° from +z, floor at {f.height_mm:.0f} mm: {state}"
    )


def fix_commands(scene: Scene, d: Diagnosis, applied: dict[str, float] | None = None) -> str:
    """The commands that apply what was found (the viewer does not rewrite a scene);
    ``applied``: the offsets the diagnosed run re-timed with already (they add up)."""
    root = str(scene.root)
    cmds = []
    late = {n: e.offset_frames for n, e in d.sync.items() if e.offset}
    if late:
        cmds.append(f"mvviz run {root} --set sync.offsets={offsets_setting(late, applied)}")
    if any(f.refined is not None for f in d.calibration.values()):
        cmds.append(f"mvviz diagnose {root} --write-cameras {root}/cameras_refined.json")
    if d.floor is not None and not d.floor.ok:
        cmds.append(f"mvviz diagnose {root} --fix-floor {root}_z_up")
    if not cmds:
        return "**Fixes**: nothing to fix."
    return "**Fixes** (run in a terminal):\n\n```\n" + "\n".join(cmds) + "\n```"


@dataclass
class DiagnoseHandles:
    folder: viser.GuiFolderHandle
    run: viser.GuiButtonHandle
    cancel: viser.GuiButtonHandle
    progress: viser.GuiProgressBarHandle
    status: viser.GuiMarkdownHandle
    summary: viser.GuiMarkdownHandle
    floor: viser.GuiMarkdownHandle
    commands: viser.GuiMarkdownHandle
    camera: viser.GuiDropdownHandle
    sync_plot: viser.GuiImageHandle
    series_plot: viser.GuiImageHandle
    go: viser.GuiButtonGroupHandle  # GO_STEP / GO_WORST
    field: viser.GuiImageHandle


def make_diagnose_handles(
    server: viser.ViserServer, camera_names: list[str], camera: str
) -> DiagnoseHandles:
    blank = np.full((8, 8, 3), 255, np.uint8)
    with server.gui.add_folder("Diagnose the capture") as folder:
        run = server.gui.add_button("Run diagnose", icon=viser.Icon.STETHOSCOPE)
        cancel = server.gui.add_button("Cancel", disabled=True)
        progress = server.gui.add_progress_bar(0.0, visible=False, animated=True)
        status = server.gui.add_markdown(NOT_RUN)
        summary = server.gui.add_markdown("")
        floor = server.gui.add_markdown("")
        commands = server.gui.add_markdown("")
        camera_list = tuple(camera_names)
        camera = server.gui.add_dropdown("Camera", camera_list, initial_value=camera, disabled=True)
        sync_plot = server.gui.add_image(blank, format="png", visible=False)
        series_plot = server.gui.add_image(blank, format="png", visible=False)
        go = server.gui.add_button_group("Go to", (GO_STEP, GO_WORST), visible=False)
        field = server.gui.add_image(blank, format="jpeg", jpeg_quality=80, visible=False)
    return DiagnoseHandles(
        folder, run, cancel, progress, status, summary, floor, commands, camera, sync_plot,
        series_plot, go, field,
    )  # fmt: skip


class DiagnosePanel:
    """Runs the diagnoses off the GUI thread (latest wins; a newer run or Cancel stops
    one between steps) and shows them. ``findings``: the last complete run (None before);
    ``stale``: the viewer shows other results since."""

    def __init__(self, host: PanelHost) -> None:
        self.host = host
        self.camera = host.state.scene.rig.names[host.state.camera]
        self.gui = make_diagnose_handles(host.server, host.state.scene.rig.names, self.camera)
        self.findings: DiagnoseFindings | None = None
        self.stale = False
        self._generation = 0  # bumped by run, cancel and stop
        self._requested = 0  # the generation the worker's next run is for
        self._lock = threading.Lock()
        self._worker = LatestWins(self._work, name="mvviz-diagnose", halted=host.stopped.is_set)
        self._unsubscribe = host.subscribe(self._on_state)
        self._bind()

    # ------------------------------------------------------------------ actions

    def run(self) -> None:
        """Start a diagnosis of the shown results (a running one is dropped)."""
        with self._lock:
            self._generation += 1
            self._requested = self._generation
        self._set_progress(0.0, "starting…")
        self.gui.cancel.disabled = False
        self._worker.request()

    def cancel(self) -> None:
        """Stop the running diagnosis at its next step (the last findings stay shown)."""
        with self._lock:
            self._generation += 1
        kept = " (the earlier findings stay shown)" if self.findings else ""
        self._set_progress(None, "cancelled" + kept)
        self.gui.cancel.disabled = True

    def wait(self, timeout: float = 120.0) -> bool:
        """Block until no diagnosis runs (tests, scripts)."""
        return self._worker.wait_idle(timeout)

    def show_camera(self, camera: str) -> None:
        """Draw ``camera``'s curve, time series and field (the dropdown does this)."""
        self.camera = camera
        if self.gui.camera.value != camera:
            self.gui.camera.value = camera  # its callback lands here again
            return
        self._draw_camera()

    def go_to(self, what: str) -> int | None:
        """Jump to the chosen camera's step (``GO_STEP``) or worst frame (``GO_WORST``),
        showing that camera; the frame, or None if there is none."""
        if self.findings is None:
            return None
        frame = None
        if what == GO_STEP:
            c = self.findings.diagnosis.calibration.get(self.camera)
            frame = None if c is None or c.step is None else c.step.frame
        else:
            s = self.findings.series(self.camera)
            frame = int(np.nanargmax(s)) if np.isfinite(s).any() else None
        if frame is not None:
            self.host.jump_to(frame=frame, view=self.camera)
        return frame

    def stop(self) -> None:
        with self._lock:
            self._generation += 1
        self._unsubscribe()
        self._worker.stop()

    # ------------------------------------------------------------------ worker

    def _work(self) -> None:
        with self._lock:
            gen = self._requested
        cancelled = lambda: self._generation != gen or self.host.stopped.is_set()  # noqa: E731
        scene, results = self.host.state.scene, self.host.state.results
        t0 = time.perf_counter()

        def step(name: str, done: int, total: int) -> None:
            if not cancelled():
                self._set_progress(80.0 * done / max(total, 1), f"diagnosing: {name}…")

        found = diagnose(scene, results, progress=step, cancelled=cancelled)
        if found is None:
            return

        def camera_step(done: int, total: int) -> None:
            if not cancelled():
                self._set_progress(80.0 + 20.0 * done / total, "residual fields…")

        residuals = camera_residuals(
            scene, results, found, cancelled=cancelled, progress=camera_step
        )  # fmt: skip
        if residuals is None or cancelled():
            return
        self.findings = DiagnoseFindings(found, residuals, results, time.perf_counter() - t0)
        self.stale = results is not self.host.state.results
        self._show_findings()

    # ------------------------------------------------------------------ drawing

    def _show_findings(self) -> None:
        f, g = self.findings, self.gui
        assert f is not None
        d = f.diagnosis
        g.summary.content = summary_markdown(d)
        g.floor.content = floor_markdown(d)
        applied = f.results.config.sync.by_camera()
        g.commands.content = fix_commands(self.host.state.scene, d, applied)
        self._set_progress(None, self._status())
        g.cancel.disabled = True
        g.camera.disabled = False
        worst = self._worst_camera(d)
        if worst is not None:
            self.camera = worst
        for h in (g.sync_plot, g.series_plot, g.go, g.field):
            h.visible = True
        self.show_camera(self.camera)

    def _status(self) -> str:
        f = self.findings
        if f is None:
            return NOT_RUN
        text = f"Diagnosed in {f.seconds:.1f} s ({f.results.num_frames} frames)."
        if self.stale:
            text += " **Stale**: the viewer shows other results now; run again."
        return text

    @staticmethod
    def _worst_camera(d: Diagnosis) -> str | None:
        """The camera to show first: a suspect, else the most out of sync, else None."""
        suspects = [n for n, c in d.calibration.items() if c.suspect]
        if suspects:
            return suspects[0]
        late = [(abs(e.offset_frames), n) for n, e in d.sync.items() if e.offset]
        return max(late)[1] if late else None

    def _draw_camera(self) -> None:
        f, g, name = self.findings, self.gui, self.camera
        if f is None:
            return
        d = f.diagnosis
        if name in d.sync:
            g.sync_plot.image = sync_curve_image(d.sync[name])
        c = d.calibration.get(name)
        g.series_plot.image = residual_series_image(name, f.series(name), c and c.step)
        g.go.disabled = False
        scene = self.host.state.scene
        cam = scene.rig[scene.rig.index_of(name)]
        base = None
        if self.host.frames is not None:
            st = self.host.state
            base = self.host.frames.frame(name, video_frame(st.data, name, st.frame))
        g.field.image, _ = residual_field_image(
            f.residuals[name], cam, width=FIELD_WIDTH, base=base
        )

    def _set_progress(self, percent: float | None, text: str) -> None:
        if self.host.stopped.is_set():
            return
        g = self.gui
        if percent is not None:
            g.progress.value = float(np.clip(percent, 0.0, 100.0))
        g.progress.visible = percent is not None
        g.status.content = text

    def _on_state(self, state, reason: str) -> None:
        if "results" in reason and self.findings is not None and not self.stale:
            self.stale = state.results is not self.findings.results
            if self.stale:
                self.gui.status.content = self._status()

    def _bind(self) -> None:
        g = self.gui

        @g.run.on_click
        def _(_) -> None:
            self.run()

        @g.cancel.on_click
        def _(_) -> None:
            self.cancel()

        @g.camera.on_update
        def _(_) -> None:
            self.camera = str(g.camera.value)
            self._draw_camera()

        @g.go.on_click
        def _(event) -> None:
            self.go_to(event.target.value)


def make_diagnose_panel(host: PanelHost) -> DiagnosePanel:
    """The "Diagnose the capture" folder (its own tab)."""
    return DiagnosePanel(host)
