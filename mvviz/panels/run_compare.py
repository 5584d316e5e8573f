"""The Pipeline panel's whole-run A/B: "Compare with the saved config".

A is the current run (the panel's newest complete results: every stage, the whole
sequence, what the viewer shows); B is the saved config (``SCENE/mvviz_config.json``,
else the defaults), run over the whole sequence on a background thread with a progress
bar, or read from the scene's cache when that configuration was run before
(:func:`pipeline.diagnose.compare_runs.run_cached`, the same files ``mvviz compare``
uses). Then :func:`~pipeline.diagnose.compare_runs.compare_runs` gives:

- a table of the figures that differ (A, B, B - A), and how many are equal;
- the worst moments, one button each (frames, track, distance): a click shows that
  frame with A's track selected (``host.jump_to``);
- run B's people drawn with A's, as thin magenta skeletons under
  ``/world/skeletons/compare_b`` (B's tracks are its own, so the Filter A/B overlay,
  which re-filters A's tracks, cannot carry them; this one follows the frame and the
  "side by side" offset of A's filtered skeletons).

Units: mm in the results, metres in the scene.
"""

from __future__ import annotations

import math
import threading
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
import viser

from mvviz.panels.contract import PanelHost
from mvviz.scene.geometry import MM, OFFSET_FILTERED_M, bone_segments
from pipeline.config import CONFIG_FILE, PipelineConfig, load_config
from pipeline.diagnose.compare_runs import (
    MATCH_GATE_MM,
    Difference,
    RunComparison,
    compare_runs,
    run_cached,
)
from pipeline.results.store import PipelineResults

if TYPE_CHECKING:
    from pipeline.body.arrays import BodyModelData
    from pipeline.body.model import BodyModel

B_ROOT = "/world/skeletons/compare_b"
B_COLOR = (230, 40, 200)  # magenta: no track colour of the palette, and not filter B's
B_BONE_WIDTH_M = 0.012  # thinner than A's filtered bones (0.022 m): A shows through
MOMENTS = 8  # buttons: the largest moved spans first, then people only one run has


def saved_config(scene_root) -> tuple[PipelineConfig, str]:
    """The saved config and where it came from (the file, or "the defaults")."""
    path = scene_root / CONFIG_FILE
    if path.is_file():
        return load_config(path), f"`{CONFIG_FILE}`"
    return PipelineConfig(), f"the defaults (no `{CONFIG_FILE}`)"


def _num(x: float) -> str:
    """A table cell: 3 decimals below 1, 3 digits below 10, else 1 decimal; led by an
    en space, which markdown keeps (viser's tables have no cell padding)."""
    if not math.isfinite(x):
        return "\u2002–"
    text = f"{x:.3f}" if abs(x) < 1 else f"{x:.3g}" if abs(x) < 10 else f"{x:.1f}"
    return "\u2002" + text


def figures_table(cmp: RunComparison) -> str:
    """Markdown: the figures that differ, A | B | B − A; then how many are equal."""
    lines = ["| figure | A | B | B − A |", "|---|---:|---:|---:|"]
    equal = 0
    for name, a, b in cmp.rows:
        same = (a == b) or (not math.isfinite(a) and not math.isfinite(b))
        if same:
            equal += 1
            continue
        lines.append(f"| {name} | {_num(a)} | {_num(b)} | {_num(b - a)} |")
    if len(lines) == 2:
        return f"_All {equal} figures equal._"
    return "\n".join(lines) + f"\n\n_{equal} other figures equal._"


def moment_label(d: Difference) -> str:
    """A button's text for one difference."""
    span = f"f {d.start}" if d.start == d.stop else f"f {d.start}–{d.stop}"
    if d.kind == "moved":
        return f"{span} · track {d.track_a} · {d.peak_mm:.0f} mm"
    who = f"track {d.track_a}" if d.track_a >= 0 else f"B track {d.track_b}"
    return f"{span} · {who} · {d.kind}"


@dataclass
class CompareHandles:
    folder: viser.GuiFolderHandle
    button: viser.GuiButtonHandle
    progress: viser.GuiProgressBarHandle
    status: viser.GuiMarkdownHandle
    table: viser.GuiMarkdownHandle
    show_b: viser.GuiCheckboxHandle
    moments: list[viser.GuiButtonHandle] = field(default_factory=list)


def make_compare_handles(server: viser.ViserServer) -> CompareHandles:
    with server.gui.add_folder("Compare runs (A/B)", expand_by_default=False) as folder:
        button = server.gui.add_button(
            "Compare with the saved config", icon=viser.Icon.ARROWS_DIFF,
            hint="A = this run, B = the saved config, both over the whole sequence",
        )  # fmt: skip
        progress = server.gui.add_progress_bar(0.0, visible=False, animated=True)
        status = server.gui.add_markdown("")
        show_b = server.gui.add_checkbox("Show run B", True, hint="B's skeletons, magenta")
        table = server.gui.add_markdown("")  # the moment buttons follow it
    return CompareHandles(folder, button, progress, status, table, show_b)


class RunCompare:
    """The section's GUI, its run of B and B's skeletons (see the module docstring).

    ``current()`` returns A's complete results (it may block until a re-run lands);
    ``model()`` the body model."""

    def __init__(
        self,
        host: PanelHost,
        *,
        current: Callable[[], PipelineResults],
        model: Callable[[], BodyModel | BodyModelData],
    ) -> None:
        self.host = host
        self.scene = host.state.scene
        self._current, self._model = current, model
        self.gui = make_compare_handles(host.server)
        self.comparison: RunComparison | None = None
        self.run_b: PipelineResults | None = None
        self.shown: list[Difference] = []  # the differences behind the buttons
        self._lock = threading.RLock()
        self._thread: threading.Thread | None = None
        self._b_nodes: dict[str, viser.SceneNodeHandle] = {}
        self._drawn: tuple | None = None
        self.gui.button.on_click(lambda _: self.compare())
        self.gui.show_b.on_update(lambda _: self._draw_b(force=True))
        self._unsubscribe = host.subscribe(lambda st, reason: self._draw_b())

    # ------------------------------------------------------------------ public

    def compare(self) -> threading.Thread:
        """Start the comparison on a background thread (one at a time), returned."""
        with self._lock:
            if self._thread is not None and self._thread.is_alive():
                return self._thread
            self.gui.button.disabled = True
            self._thread = threading.Thread(target=self._run, name="mvviz-compare", daemon=True)
            self._thread.start()
            return self._thread

    def jump(self, i: int) -> None:
        """Show difference ``i`` of the buttons: its peak frame, A's track selected."""
        d = self.shown[i]
        self.host.jump_to(frame=d.peak_frame, track=d.track_a if d.track_a >= 0 else None)

    def wait_idle(self, timeout: float = 60.0) -> bool:
        t = self._thread
        if t is not None:
            t.join(timeout)
            return not t.is_alive()
        return True

    def stop(self) -> None:
        self._unsubscribe()

    # ------------------------------------------------------------------ run

    def _run(self) -> None:
        g = self.gui
        t0 = time.perf_counter()
        try:
            g.progress.value, g.progress.visible = 0.0, True
            g.status.content = "waiting for the current run (A)…"
            a = self._current()
            config_b, origin = saved_config(self.scene.root)
            g.status.content = f"running B = {origin} over the whole sequence…"

            def progress(stage: str, done: int, total: int) -> None:
                g.progress.value = 100.0 * done / max(total, 1)
                g.status.content = f"B = {origin}: {stage} {done}/{total}"

            b, reused, _ = run_cached(self.scene, config_b, self._model(), progress=progress)
            cmp = compare_runs(self.scene, a, b)
            with self._lock:
                self.comparison, self.run_b = cmp, b
            how = "cached" if reused else "run"
            changed = ", ".join(f"{k}: {x} → {y}" for k, x, y in cmp.config_changes) or "none"
            g.status.content = (
                f"**A** = this run, **B** = {origin} ({how}; {time.perf_counter() - t0:.0f} s)."
                f" Fields that differ: {changed}"
            )
            g.table.content = figures_table(cmp)
            self._set_moments(cmp.top(MOMENTS // 2))
            self._build_b_nodes()
            self._draw_b(force=True)
        except Exception as exc:  # shown, not raised: the viewer goes on
            g.status.content = f"compare failed: {type(exc).__name__}: {exc}"
        finally:
            g.progress.visible = False
            g.button.disabled = False

    def _set_moments(self, diffs: list[Difference]) -> None:
        server = self.host.server
        for h in self.gui.moments:
            h.remove()
        self.gui.moments = []
        self.shown = diffs
        if not diffs:
            self.gui.table.content += "\n\n_Every person within the threshold in every frame._"
            return
        self.gui.table.content += (
            f"\n\n**Where they differ most** (A's track; only in A/B: nobody within "
            f"{MATCH_GATE_MM:.0f} mm in the other run). Click to go there:"
        )
        with self.gui.folder:
            for i, d in enumerate(diffs):
                h = server.gui.add_button(moment_label(d))
                h.on_click(lambda _, i=i: self.jump(i))
                self.gui.moments.append(h)

    # ------------------------------------------------------------------ B's skeletons

    def _build_b_nodes(self) -> None:
        scene = self.host.server.scene
        with self._lock:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # already removed with the scene: fine
                for h in self._b_nodes.values():
                    h.remove()
            empty = np.zeros((1, 2, 3), np.float32)
            self._b_nodes = {
                "root": scene.add_frame(B_ROOT, show_axes=False, visible=False),
                "bones": scene.add_line_segments(
                    f"{B_ROOT}/bones",
                    empty,
                    B_COLOR,
                    thickness=B_BONE_WIDTH_M,
                    thickness_units="world",
                ),  # fmt: skip
            }
            self._drawn = None

    def _draw_b(self, *, force: bool = False) -> None:
        st = self.host.state
        with self._lock:
            b, nodes = self.run_b, self._b_nodes
            if b is None or not nodes:
                return
            show = bool(self.gui.show_b.value)
            key = (b, st.frame, show, st.layers.offset_filtered)
            if key == self._drawn and not force:
                return
            try:
                nodes["root"].visible = show
                nodes["root"].position = (
                    OFFSET_FILTERED_M if st.layers.offset_filtered else np.zeros(3)
                )
                if show:
                    self._draw_b_bones(b, st.frame)
            except RuntimeError:  # nodes gone with a results change: the next compare redraws
                return
            self._drawn = key

    def _draw_b_bones(self, b: PipelineResults, frame: int) -> None:
        data = self.host.state.data
        line = self._b_nodes["bones"]
        if b.joint_set != data.joint_set.name or not 0 <= frame < b.num_frames:
            line.visible = False  # another 2D source: its joints are not A's skeleton's
            return
        bones = data.joint_set.bones
        pts = b.track_filtered[:, frame] * MM  # (K_b, J, 3) m
        segs = [bone_segments(p, bones) for p in pts if np.isfinite(p).all(-1).any()]
        segs = [s for s in segs if len(s)]
        if segs:
            line.points = np.concatenate(segs).astype(np.float32)
        line.visible = bool(segs)


def make_run_compare(
    host: PanelHost,
    *,
    current: Callable[[], PipelineResults],
    model: Callable[[], BodyModel | BodyModelData],
) -> RunCompare:
    """The section, built in the GUI container open at the call (the Pipeline folder)."""
    return RunCompare(host, current=current, model=model)
