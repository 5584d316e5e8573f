"""The "Failures" panel: the worst problems of one criterion as buttons, and frame notes.

A criterion dropdown (:data:`mvviz.analysis.failures.CRITERIA`, those the scene and run support)
picks what to rank; the top :data:`MAX_ENTRIES` of :func:`~mvviz.analysis.failures.find_failures`
(one entry per problem and span of frames) become buttons labelled with the span and the
track (``"1. f 140–172 · track 2"``), each with its whole text on a wrapping line below
(joint, camera, measure, frames). An overview line counts the entries of every
criterion, and the summary those of each kind in the one shown; every criterion's
entries go to the timeline's strip (``host.mark_failures``). A click calls
``host.jump_to`` (timeline, track, joint, and the camera panel on a camera that sees the
person: :func:`~mvviz.analysis.failures.seeing_view`) and, with "Look at it" on,
``host.focus`` on the joint or the person. Lists are computed on a worker thread,
cached per results and criterion, and recomputed when the host shows new results.

Notes: a text box and "Flag this frame" add a :class:`~mvviz.analysis.failures.Note` for the
current frame, saved at once to ``SCENE/.mvviz/notes.json``; each note is a button that
jumps to its frame and selects it for "Delete selected note". The file is read again
before each change, so notes another viewer saved survive; an unreadable notes file is
reported in the panel and never overwritten (flagging works again once it is fixed).
A read-only viewer shows the notes, disables flagging and deleting, and refuses both.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field

import numpy as np
import viser

from mvviz.analysis.failures import (
    Failure,
    Note,
    all_failures,
    available_criteria,
    kind_counts,
    load_notes,
    nearest_pose,
    new_note,
    notes_path,
    rank,
    save_notes,
    seeing_view,
)
from mvviz.analysis.failures.protocol import protocol_summary
from mvviz.panels.contract import PanelHost
from mvviz.safe_paths import shown_path
from mvviz.scene.geometry import MM, ViewerData
from mvviz.state import ViewerState
from mvviz.workers import LatestWins, yielding_to
from pipeline.core.files import SceneFormatError

MAX_ENTRIES = 15
SELECTED_COLOR = "orange"
NOTE_LABEL_CHARS = 36
CRITERION_LABELS = {
    "reprojection": "Reprojection error (px)",
    "mpjpe": "MPJPE vs ground truth (mm)",
    "association": "Association conflicts",
    "id": "Identity: births, deaths, switches",
    "kalman": "Kalman Mahalanobis",
    "proportions": "Bones: re-solved, contradicted joints",
    "smpl": "SMPL residual, joint limits",
    "labels": "Label check",
    "protocol": "Shelf / Campus PCP: wrong limbs",
}
CRITERION_SHORT = {
    "reprojection": "reproj.",
    "mpjpe": "MPJPE",
    "association": "assoc.",
    "id": "ID",
    "kalman": "Kalman",
    "proportions": "bones",
    "smpl": "SMPL",
    "labels": "labels",
    "protocol": "PCP",
}
CRITERION_HELP = {
    "reprojection": "reprojection errors of used views at least 2× that joint's usual error "
    "in that camera (the run's median); ranked by the ratio",
    "mpjpe": "MPJPE of the filtered track vs its matched ground truth at least 2× the run's "
    "median; people or tracks left unmatched, one entry per span",
    "association": "detections close to two people, people seen by < 2 views, track gaps, "
    "confident unassigned detections (enabled cameras only)",
    "id": "track births after frame 0, deaths before the last frame, ID switches vs GT",
    "kalman": "Mahalanobis distance of the measurement above 3, per track and span",
    "proportions": "joints whose bones were more than 25 % off their track's median length: "
    "re-solved from the views that fit, or kept but not filtered (contradicted)",
    "smpl": "fit residuals at least 2× that joint's usual residual (ranked by the ratio), "
    "joint rotations outside their limits (÷ 10°) and frames where the prior's correction "
    "backed off (step I's pose kept)",
    "labels": "keypoint labels that look wrong (left/right, joint order, one camera "
    "mirrored), per scene, track or camera; measured ÷ threshold",
    "protocol": "limbs the Shelf / Campus protocol counts wrong on the filtered tracks, "
    "against the truth stored in the scene; ranked by error ÷ the limit (half the limb)",
}


@dataclass
class FailureHandles:
    """The folder's handles. ``note_buttons`` grows as notes are added (unused ones are
    hidden)."""

    folder: viser.GuiFolderHandle
    criterion: viser.GuiDropdownHandle
    look: viser.GuiCheckboxHandle
    summary: viser.GuiMarkdownHandle
    entries: list[viser.GuiButtonHandle]
    details: list[viser.GuiMarkdownHandle]  # the whole text of each entry, wrapping
    overview: viser.GuiMarkdownHandle  # entries per criterion
    notes_folder: viser.GuiFolderHandle
    note_text: viser.GuiTextHandle
    flag: viser.GuiButtonHandle
    delete: viser.GuiButtonHandle
    notes_info: viser.GuiMarkdownHandle
    note_buttons: list[viser.GuiButtonHandle] = field(default_factory=list)


def make_failure_handles(server: viser.ViserServer, criteria: tuple[str, ...]) -> FailureHandles:
    """The "Failures" folder: criterion, :data:`MAX_ENTRIES` hidden entry buttons, notes."""
    gui = server.gui
    labels = tuple(CRITERION_LABELS[c] for c in criteria)
    with gui.add_folder("Failures") as folder:
        criterion = gui.add_dropdown("Criterion", labels, initial_value=labels[0])
        look = gui.add_checkbox(
            "Look at it", True, hint="a click also points the 3D view at the failing joint"
        )
        overview = gui.add_markdown("")
        summary = gui.add_markdown("")
        entries, details = [], []
        for _ in range(MAX_ENTRIES):
            entries.append(gui.add_button("-", visible=False))
            details.append(gui.add_markdown("", visible=False))
        with gui.add_folder("Notes") as notes_folder:
            note_text = gui.add_text("Note", "", hint="what is wrong in this frame")
            flag = gui.add_button("Flag this frame", icon=viser.Icon.FLAG)
            delete = gui.add_button("Delete selected note", icon=viser.Icon.TRASH, disabled=True)
            notes_info = gui.add_markdown("")
    return FailureHandles(
        folder, criterion, look, summary, entries, details, overview, notes_folder, note_text,
        flag, delete, notes_info,
    )  # fmt: skip


def criterion_of(label: str) -> str:
    """Dropdown label -> criterion name."""
    return next(c for c, lab in CRITERION_LABELS.items() if lab == label)


def note_label(note: Note) -> str:
    text = note.text.strip().replace("\n", " ") or "(no text)"
    if len(text) > NOTE_LABEL_CHARS:
        text = text[: NOTE_LABEL_CHARS - 1] + "…"
    return f"f {note.frame} · {text}"


def entry_details(failure: Failure) -> str:
    """The entry's whole text after its button's span (markdown-safe)."""
    text = failure.text[len(failure.span) :].lstrip(" ·")
    return text.replace("*", "\\*").replace("_", "\\_")


def failure_point(data: ViewerData, failure: Failure) -> np.ndarray | None:
    """(3,) world metres to look at for ``failure``: its joint of the filtered track
    (raw if the filter has none), else the track's centre, else (the track is missing
    in that frame) the centre of its nearest known pose; None without a track."""
    k, f, j = failure.track, failure.frame, failure.joint
    if k is None or not 0 <= k < data.num_tracks:
        return None
    for points in (data.filtered[k, f], data.results.track_raw[k, f]):  # (J, 3) mm
        ok = np.isfinite(points).all(1)
        if j is not None and ok[j]:
            return points[j] * MM
        if j is None and ok.any():
            return points[ok].mean(0) * MM
    pose = nearest_pose(data.results, k, f)
    return None if pose is None else pose.mean(0) * MM


class FailurePanel:
    """The "Failures" panel at work.

    ``failures`` are the entries shown (at most :data:`MAX_ENTRIES`), ``found`` how many
    the criterion found, ``kinds`` those per kind; ``notes`` the scene's notes in frame order,
    ``notes_error`` why the notes file could not be read (nothing is saved over it).
    """

    def __init__(self, host: PanelHost) -> None:
        self.host = host
        self._lock = threading.RLock()
        self._data: ViewerData = host.state.data
        self._cache: dict[tuple[int, str], list[Failure]] = {}
        self.criteria = available_criteria(self._data.scene, self._data.results)
        self.gui = make_failure_handles(host.server, self.criteria)
        self.failures: list[Failure] = []
        self.found = 0
        self.counts: dict[str, int] = {}  # entries per criterion, for the overview
        self.kinds: dict[str, int] = {}
        self.selected_failure: int | None = None
        self.scene_root = self._data.scene.root
        self.notes_file = notes_path(self.scene_root)
        self.notes: list[Note] = []
        self.notes_error: str | None = None
        self.selected_note: int | None = None
        self.message = ""
        self._load_notes()
        self._bind()
        self._worker = LatestWins(self._refresh, name="mvviz-failures")
        self._unsubscribe = host.subscribe(self._on_state_changed)
        self._worker.request()

    # ------------------------------------------------------------------ public

    @property
    def criterion(self) -> str:
        return criterion_of(self.gui.criterion.value)

    def set_criterion(self, criterion: str) -> None:
        """Show ``criterion``'s list (one of :attr:`criteria`)."""
        self.gui.criterion.value = CRITERION_LABELS[criterion]
        self._worker.request()

    def click(self, index: int) -> Failure:
        """What a click on entry ``index`` does: jump to it and mark it."""
        with self._lock:
            failure = self.failures[index]
            self._mark(self.gui.entries, index, self.selected_failure)
            self.selected_failure = index
        view = seeing_view(self._data.scene, self._data.results, failure)
        self.host.jump_to(failure.frame, failure.track, failure.joint, view)
        target = failure_point(self._data, failure)
        if self.gui.look.value and target is not None:
            self.host.focus(target)
        return failure

    def flag(self, text: str | None = None, frame: int | None = None) -> Note:
        """Add a note for ``frame`` (default: the current one) with ``text`` (default:
        the text box), save the notes file at once and clear the text box.

        The file is read again first, so notes another viewer saved are kept; an
        unreadable file raises :class:`SceneFormatError` and is left as it is; a
        read-only viewer raises :class:`~mvviz.safe_paths.WriteRefused`."""
        self._writable_notes_file()
        note = new_note(
            self.host.state.frame if frame is None else frame,
            self.gui.note_text.value if text is None else text,
        )
        with self._lock:
            notes = self._reload_for_write()
            notes = sorted([*notes, note], key=lambda n: (n.frame, n.created))
            save_notes(self.notes_file, notes)
            self.notes = notes
            self.selected_note = notes.index(note)
            self.message = f"saved to `{shown_path(self.notes_file, self.scene_root)}`"
            self._show_notes()
        self.gui.note_text.value = ""
        return note

    def select_note(self, index: int) -> Note:
        """Select note ``index`` and jump to its frame."""
        with self._lock:
            note = self.notes[index]
            self.selected_note = index
            self._show_notes()
        self.host.jump_to(frame=note.frame)
        return note

    def delete_selected(self) -> Note | None:
        """Delete the selected note and save (None when no note is selected, or when
        the file no longer has it)."""
        with self._lock:
            i = self.selected_note
            if i is None or not 0 <= i < len(self.notes):
                return None
            note = self.notes[i]
            self._writable_notes_file()
            notes = self._reload_for_write()
            self.selected_note = None
            if note in notes:
                notes.remove(note)
                save_notes(self.notes_file, notes)
                self.message = f"deleted the note on frame {note.frame}"
            else:
                note, self.message = None, "that note was already gone from the file"
            self.notes = notes
            self._show_notes()
        return note

    def refresh(self) -> None:
        """Recompute the list (in the background; :meth:`wait_idle` waits for it)."""
        self._worker.request()

    def wait_idle(self, timeout: float = 30.0) -> bool:
        return self._worker.wait_idle(timeout)

    def stop(self) -> None:
        """Stop following the host and end the worker (the host calls it at its stop)."""
        self._unsubscribe()
        self._worker.stop()

    def remove(self) -> None:
        """Stop and take the folder off the GUI."""
        self.stop()
        self.gui.folder.remove()

    # ------------------------------------------------------------------ internals

    def _bind(self) -> None:
        g = self.gui

        @g.criterion.on_update
        def _(_) -> None:
            self._worker.request()

        for i, button in enumerate(g.entries):

            def bind(i: int = i, button: viser.GuiButtonHandle = button) -> None:
                @button.on_click
                def _(_) -> None:
                    if i < len(self.failures):
                        self.click(i)

            bind()

        @g.flag.on_click
        def _(_) -> None:
            try:
                self.flag()
            except (OSError, ValueError) as exc:
                with self._lock:
                    self.message = f"**not saved:** {exc}"
                    self._show_notes()

        @g.delete.on_click
        def _(_) -> None:
            try:
                self.delete_selected()
            except (OSError, ValueError) as exc:
                with self._lock:
                    self.message = f"**not saved:** {exc}"
                    self._show_notes()

    def _on_state_changed(self, st: ViewerState, reason: str) -> None:
        """After each render: new results (a re-run, an applied filter) -> new lists."""
        if st.data is not self._data and st.data is self.host.state.data:
            self._worker.request()

    def _refresh(self) -> None:
        data = self.host.state.data
        with self._lock:
            if data is not self._data:  # new results: new lists, maybe other criteria
                self._data, self._cache = data, {}
                criteria = available_criteria(data.scene, data.results)
                if criteria != self.criteria:
                    self.criteria = criteria
                    current = self.criterion
                    labels = tuple(CRITERION_LABELS[c] for c in criteria)
                    self.gui.criterion.options = labels
                    if current in criteria:
                        self.gui.criterion.value = CRITERION_LABELS[current]
        criterion = self.criterion
        t0 = time.perf_counter()
        with yielding_to(lambda: self.host.rendering):  # frame changes go first
            found = self._all(data, criterion)
        ms = (time.perf_counter() - t0) * 1e3
        with self._lock:
            if data is not self._data or criterion != self.criterion:
                self._worker.request()  # changed meanwhile: show the newer one
                return
            self.failures, self.found = rank(found, MAX_ENTRIES), len(found)
            self.kinds = kind_counts(found)
            self.selected_failure = None
            self._show_failures(criterion, ms)
        with yielding_to(lambda: self.host.rendering):
            every = {c: self._all(data, c) for c in self.criteria}  # the others, once
        with self._lock:
            if data is self._data:
                self.counts = {c: len(found) for c, found in every.items()}
                self._show_overview()
                marks = [f for found in every.values() for f in found]
                self.host.mark_failures(marks, self.criteria)  # on the timeline

    def _all(self, data: ViewerData, criterion: str) -> list[Failure]:
        """Every entry of ``criterion`` for ``data`` (cached)."""
        key = (id(data), criterion)
        if key not in self._cache:
            self._cache[key] = all_failures(data.scene, data.results, criterion=criterion)
        return self._cache[key]

    def _show_overview(self) -> None:
        parts = [
            f"{CRITERION_SHORT[c]} **{n}**" if n else f"{CRITERION_SHORT[c]} 0"
            for c, n in self.counts.items()
        ]
        self.gui.overview.content = "<small>Problems: " + " · ".join(parts) + "</small>"

    def _show_failures(self, criterion: str, ms: float) -> None:
        g = self.gui
        for i, (button, details) in enumerate(zip(g.entries, g.details, strict=True)):
            if i < len(self.failures):
                f = self.failures[i]
                button.label = f"{i + 1}. {f.head}"
                button.color = None
                button.visible = True
                details.content = f"<small>{entry_details(f)}</small>"
                details.visible = True
            else:
                button.visible = False
                details.visible = False
        if not self.failures:
            head = "**No problems** for this criterion."
        else:
            more = f" of {self.found}" if self.found > len(self.failures) else ""
            head = f"**{len(self.failures)}{more}** worst, worst first (click to go there)"
            head += "\n\n" + " · ".join(f"{k} **{n}**" for k, n in self.kinds.items())
        if criterion == "protocol" and self._data is not None:
            head += "\n\n" + protocol_summary(self._data.scene, self._data.results)
        g.summary.content = f"{head}\n\n<small>{CRITERION_HELP[criterion]} · {ms:.0f} ms</small>"

    @staticmethod
    def _mark(buttons: list[viser.GuiButtonHandle], new: int | None, old: int | None) -> None:
        if old is not None and old < len(buttons) and old != new:
            buttons[old].color = None
        if new is not None:
            buttons[new].color = SELECTED_COLOR

    def _writable_notes_file(self) -> None:
        """Raise :class:`~mvviz.safe_paths.WriteRefused` when the notes may not be written
        (a read-only viewer, or a symlink leading the file out of the scene)."""
        self.host.writes.cache_file(self.scene_root, self.notes_file)

    def _reload_for_write(self) -> list[Note]:
        """The notes on disk now (call with the lock held); raises if unreadable."""
        try:
            notes = load_notes(self.notes_file)
        except SceneFormatError as exc:
            self.notes_error = str(exc)
            self._show_notes()
            raise
        self.notes_error = None
        return sorted(notes, key=lambda n: (n.frame, n.created))

    def _load_notes(self) -> None:
        try:
            self.notes = sorted(load_notes(self.notes_file), key=lambda n: (n.frame, n.created))
            self.notes_error = None
        except SceneFormatError as exc:
            self.notes, self.notes_error = [], str(exc)
        self._show_notes()

    def _show_notes(self) -> None:
        """Relabel the note buttons (adding more when needed), status line, enable state."""
        g = self.gui
        while len(g.note_buttons) < len(self.notes):
            with g.notes_folder:
                button = self.host.server.gui.add_button("-", icon=viser.Icon.NOTE)
            i = len(g.note_buttons)
            g.note_buttons.append(button)

            def bind(i: int = i, button: viser.GuiButtonHandle = button) -> None:
                @button.on_click
                def _(_) -> None:
                    if i < len(self.notes):
                        self.select_note(i)

            bind()
        for i, button in enumerate(g.note_buttons):
            if i < len(self.notes):
                button.label = note_label(self.notes[i])
                button.color = SELECTED_COLOR if i == self.selected_note else None
                button.visible = True
            else:
                button.visible = False
        read_only = self.host.writes.read_only is not None
        g.flag.disabled = read_only
        g.delete.disabled = self.selected_note is None or self.notes_error is not None or read_only
        if self.notes_error is not None:
            g.notes_info.content = (
                f"**Notes file unreadable**, left as it is: fix or move it, then flag "
                f"again.\n\n"
                f"<small>{self.notes_error}</small>"
            )
            return
        n = len(self.notes)
        count = f"{n} note{'s' if n != 1 else ''}" if n else "No notes yet"
        msg = f" · {self.message}" if self.message else ""
        g.notes_info.content = f"<small>{count}{msg}</small>"


def make_failure_panel(host: PanelHost) -> FailurePanel:
    """The "Failures" folder in ``host``'s GUI, following its results."""
    return FailurePanel(host)
