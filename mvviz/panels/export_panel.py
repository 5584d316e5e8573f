"""The "Export" panel: the run in the formats other tools read, as ``mvviz export``.

Format (trc, c3d, bvh, smpl-npz, glb), stage (the run's stages that format can hold;
"last" = the run's last, as the command's default), track (all or one id), one file
per track for trc/c3d, and the file name: a name inside the export folder
(``host.writes.export_dir``), refused in the status line if it leads out of it or names
an existing file while "Overwrite" is off (:mod:`mvviz.safe_paths`). "Export" writes on
a background thread through :func:`pipeline.exports.export_results`, from the newest
complete results (a re-run of the Pipeline panel in progress is waited for), into a
hidden staging folder, then moves each file into place (so the per-track files are
checked too), and the status line lists the files written and the writers' notes (held
poses, gaps). The choices follow the results: after a re-run the stage and track lists
are rebuilt. A read-only viewer shows the button disabled and refuses the export.
"""

from __future__ import annotations

import dataclasses
import os
import shutil
import tempfile
import threading
from dataclasses import dataclass
from pathlib import Path

import viser

from mvviz.panels.contract import PanelHost
from mvviz.safe_paths import WriteRefused, resolve_inside
from pipeline.exports import EXTENSIONS, FORMATS, ExportedFile, export_results, stages_for
from pipeline.results.store import PipelineResults

LAST = "last"
ALL = "all"


@dataclass
class ExportHandles:
    folder: viser.GuiFolderHandle
    format: viser.GuiDropdownHandle
    stage: viser.GuiDropdownHandle
    track: viser.GuiDropdownHandle
    per_track: viser.GuiCheckboxHandle
    path: viser.GuiTextHandle
    overwrite: viser.GuiCheckboxHandle
    export: viser.GuiButtonHandle
    status: viser.GuiMarkdownHandle


def stage_options(results: PipelineResults, fmt: str) -> tuple[str, ...]:
    return (LAST, *stages_for(results, fmt))


def track_options(results: PipelineResults) -> tuple[str, ...]:
    return (ALL, *(str(k) for k in range(results.num_tracks)))


def default_name(scene_name: str, fmt: str, stage: str) -> str:
    """The suggested file name in the export folder."""
    tag = "" if stage == LAST else f"_{stage}"
    return f"{scene_name}{tag}{EXTENSIONS[fmt]}"


def make_export_handles(
    server: viser.ViserServer, results: PipelineResults, name: str, out_dir: Path
) -> ExportHandles:
    with server.gui.add_folder("Export", expand_by_default=False) as folder:
        fmt = server.gui.add_dropdown(
            "Format", FORMATS, initial_value="glb",
            hint="trc/c3d: joints as markers; bvh: skeleton; smpl-npz: AMASS-style; "
            "glb: every body, skinned and animated",
        )  # fmt: skip
        stage = server.gui.add_dropdown(
            "Stage", stage_options(results, "glb"), initial_value=LAST,
            hint="last: the run's last stage (bodies: smpl_vae, else smpl)",
        )  # fmt: skip
        track = server.gui.add_dropdown("Track", track_options(results), initial_value=ALL)
        per_track = server.gui.add_checkbox(
            "One file per track", initial_value=False,
            hint="trc/c3d; bvh and smpl-npz always write one file per track",
        )  # fmt: skip
        out = server.gui.add_text(
            "Export path", initial_value=name, hint=f"a file name inside {out_dir}"
        )
        overwrite = server.gui.add_checkbox(
            "Overwrite", initial_value=False, hint="replace files of the same name"
        )
        export = server.gui.add_button("Export", icon=viser.Icon.FILE_EXPORT)
        status = server.gui.add_markdown(f"<small>into `{out_dir}`</small>")
    return ExportHandles(folder, fmt, stage, track, per_track, out, overwrite, export, status)


class ExportPanel:
    """The panel's GUI and its background export (one at a time)."""

    def __init__(self, host: PanelHost) -> None:
        self.host = host
        self.scene = host.state.scene
        self.out_dir = host.writes.export_dir
        name = default_name(self.scene.name, "glb", LAST)
        self.gui = make_export_handles(host.server, host.state.results, name, self.out_dir)
        if host.writes.read_only is not None:
            self.gui.export.disabled = True
            self.gui.status.content = f"<small>{host.writes.read_only}</small>"
        self._thread: threading.Thread | None = None
        self._lock = threading.Lock()
        self.last_files: list[ExportedFile] = []
        self.gui.format.on_update(lambda _: self._choices_changed())
        self.gui.stage.on_update(lambda _: self._suggest_path())
        self.gui.export.on_click(lambda _: self.export())
        self._unsubscribe = host.subscribe(self._on_state_changed)

    # ------------------------------------------------------------------ choices

    def _results(self) -> PipelineResults:
        """The newest complete results: the Pipeline panel's once its re-run lands."""
        return self.host.complete_results()

    def _set_options(self, handle: viser.GuiDropdownHandle, options: tuple[str, ...]) -> None:
        if tuple(handle.options) != options:
            value = handle.value
            handle.options = options
            handle.value = value if value in options else options[0]

    def _choices_changed(self) -> None:
        results = self.host.state.results
        self._set_options(self.gui.stage, stage_options(results, self.gui.format.value))
        self._set_options(self.gui.track, track_options(results))
        self._suggest_path()

    def _suggest_path(self) -> None:
        """Keep the name's extension (and stage tag) in step while it is one we made."""
        g = self.gui
        current = Path(g.path.value)
        if current.parent == Path(".") and current.name.startswith(self.scene.name):
            name = default_name(self.scene.name, g.format.value, g.stage.value)
            if name != g.path.value:  # no message for an unchanged value
                g.path.value = name

    def _on_state_changed(self, state, reason: str) -> None:
        if "results" in reason.split(","):
            self._choices_changed()

    # ------------------------------------------------------------------ export

    def export(
        self, *, fmt: str | None = None, stage: str | None = None, track: str | None = None,
        path: str | Path | None = None, per_track: bool | None = None,
        overwrite: bool | None = None,
    ) -> threading.Thread | None:  # fmt: skip
        """Export with the GUI's choices (or these; ``path`` a name inside the export
        folder), on a background thread (returned); None, and the reason in the status
        line, when the viewer is read-only or the name is refused."""
        g = self.gui
        with self._lock:
            if self._thread is not None and self._thread.is_alive():
                return self._thread
            overwrite = g.overwrite.value if overwrite is None else overwrite
            try:
                target = self.host.writes.export_file(
                    g.path.value if path is None else path, overwrite=overwrite
                )
            except WriteRefused as exc:
                self.last_files = []
                g.status.content = f"export refused: {exc}"
                return None
            job = {
                "fmt": fmt or g.format.value,
                "stage": stage or g.stage.value,
                "track": track or g.track.value,
                "path": target,
                "per_track": g.per_track.value if per_track is None else per_track,
                "overwrite": overwrite,
            }
            g.export.disabled = True
            self._thread = threading.Thread(
                target=self._export, kwargs=job, name="mvviz-export", daemon=True
            )
            self._thread.start()
            return self._thread

    def stop(self) -> None:
        """Stop following the host; an export in progress finishes on its own thread."""
        self._unsubscribe()

    def wait(self, timeout: float = 60.0) -> bool:
        """Block until no export runs (for tests and scripts)."""
        t = self._thread
        if t is not None:
            t.join(timeout)
            return not t.is_alive()
        return True

    def _export(
        self, *, fmt: str, stage: str, track: str, path: Path, per_track: bool, overwrite: bool
    ) -> None:
        g = self.gui
        try:
            g.status.content = "waiting for the re-run…"
            results = self._results()
            g.status.content = f"exporting {fmt} to `{path}`…"
            files = self._write_staged(path, overwrite, lambda staged: export_results(
                results, fmt, staged, fps=self.scene.fps,
                stage=None if stage == LAST else stage, track=track, per_track=per_track,
            ))  # fmt: skip
            self.last_files = files
            lines = [
                f"- `{f.path.name}` ({f.path.stat().st_size / 1e3:.0f} KB, tracks "
                f"{', '.join(map(str, f.tracks))})" for f in files
            ]  # fmt: skip
            notes = [f"- {n}" for f in files for n in f.notes]
            text = f"**wrote {len(files)} file(s)** in `{path.parent}`:\n\n" + "\n".join(lines)
            if notes:
                text += "\n\n**notes:**\n\n" + "\n".join(notes)
            g.status.content = text
        except Exception as exc:  # shown where the user looks: the panel
            self.last_files = []
            refused = isinstance(exc, WriteRefused)  # a file of the same name appeared
            g.status.content = f"export {'refused' if refused else 'failed'}: {exc}"
        finally:
            g.export.disabled = False

    def _write_staged(self, path: Path, overwrite: bool, write) -> list[ExportedFile]:
        """``write(staged_path)``'s files, written in a hidden folder beside ``path``
        (inside the export folder) and then moved into place, each checked by
        :func:`resolve_inside` first: nothing is moved if one of them is refused."""
        path.parent.mkdir(parents=True, exist_ok=True)
        staging = Path(tempfile.mkdtemp(prefix=".export-", dir=path.parent))
        try:
            files = write(staging / path.name)
            where = path.parent.relative_to(Path(self.out_dir).resolve())
            moves = [
                (f, resolve_inside(self.out_dir, where / f.path.name, overwrite=overwrite))
                for f in files
            ]
            for f, dest in moves:
                os.replace(f.path, dest)
            return [dataclasses.replace(f, path=dest) for f, dest in moves]
        finally:
            shutil.rmtree(staging, ignore_errors=True)


def make_export_panel(host: PanelHost) -> ExportPanel:
    """The "Export" folder in ``host``'s GUI."""
    return ExportPanel(host)
