"""The Dataset panel: the scenes of a ``mvviz batch`` report, sorted by a metric, worst
first; a click opens a scene at its worst moment.

The panel reads the report (``batch_report.json``, :mod:`pipeline.batch.report`). A
click on the scene already shown jumps there through the host; another scene is handed
to ``open_scene(row, moment)``, which the command line supplies (loading a different
scene replaces the viewer, which is not a panel's to do).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import viser

from mvviz.panels.contract import PanelHost
from pipeline.batch.report import METRICS

OpenScene = Callable[[dict, dict | None], None]
"""``open_scene(row, moment)``: show the report row's scene at ``moment`` (a worst
moment ``{"frame", "track", ...}``, or None)."""


@dataclass
class DatasetHandles:
    folder: viser.GuiFolderHandle
    sort_by: viser.GuiDropdownHandle
    summary: viser.GuiMarkdownHandle
    scenes: viser.GuiFolderHandle
    buttons: list[viser.GuiButtonHandle] = field(default_factory=list)  # in shown order


def sort_rows(rows: list[dict], metric: str) -> list[dict]:
    """``rows`` worst first by ``metric`` (the highest error, the lowest PCK); rows
    without the figure, then failed rows, last, each group in the report's order."""
    higher_better = METRICS[metric][1]

    def key(r: dict):
        v = (r.get("summary") or {}).get(metric)
        if v is None:
            return (1 if r.get("summary") else 2, 0.0)
        return (0, v if higher_better else -v)

    return sorted(rows, key=key)


def _fmt(v) -> str:
    return "–" if v is None else (f"{v:.3f}" if abs(v) < 1 and v != 0 else f"{v:.1f}")


class DatasetPanel:
    """The panel's controller: :meth:`sort` and :meth:`open` are what its widgets do."""

    def __init__(
        self,
        host: PanelHost,
        report: dict,
        *,
        current: str | None,
        open_scene: OpenScene,
        sort_by: str | None = None,
    ) -> None:
        """``current``: the results file of the shown scene (a report row's ``results``)."""
        self.host, self.report, self.current, self._open_scene = host, report, current, open_scene
        self.rows: list[dict] = list(report["rows"])
        present = [
            m
            for m in METRICS
            if any((r.get("summary") or {}).get(m) is not None for r in self.rows)
        ]
        self.metrics = present or ["mpjpe_mm"]
        metric = sort_by if sort_by in self.metrics else report["worst_scenes"]["metric"]
        metric = metric if metric in self.metrics else self.metrics[0]
        gui = host.server.gui
        titles = [METRICS[m][0] for m in self.metrics]
        with gui.add_folder("Dataset", expand_by_default=True) as folder:
            sort = gui.add_dropdown(
                "Sort by (worst first)", titles, initial_value=METRICS[metric][0]
            )
            summary = gui.add_markdown("")
            with gui.add_folder("Scenes", expand_by_default=True) as scenes:
                pass
        self.gui = DatasetHandles(folder=folder, sort_by=sort, summary=summary, scenes=scenes)
        self.metric = metric
        sort.on_update(lambda _e: self.sort(self.metrics[titles.index(sort.value)]))
        self.sort(metric)

    def sort(self, metric: str) -> list[str]:
        """Order the scene buttons by ``metric``, worst first; returns their labels."""
        self.metric = metric
        self.rows = sort_rows(self.rows, metric)
        for b in self.gui.buttons:
            b.remove()
        self.gui.buttons = []
        gui = self.host.server.gui
        with self.gui.scenes:
            for r in self.rows:
                s = r.get("summary")
                shown = r["results"] == self.current
                text = f"{'▶ ' if shown else ''}{r['label']} · {_fmt((s or {}).get(metric))}"
                if s is None:
                    text = f"{r['label']} · failed"
                b = gui.add_button(text, disabled=s is None, hint=r.get("error") or r["scene"])
                b.on_click(lambda _e, label=r["label"]: self.open(label))
                self.gui.buttons.append(b)
        c = self.report.get("counts", {})
        self.gui.summary.content = (
            f"{len(self.rows)} runs ({c.get('failed', 0)} failed), by "
            f"**{METRICS[metric][0]}**; a click opens the scene at its worst moment."
        )
        return [r["label"] for r in self.rows]

    def open(self, label: str) -> dict | None:
        """Show the scene ``label`` at its worst moment; returns that moment."""
        row = next(r for r in self.rows if r["label"] == label)
        worst = (row.get("summary") or {}).get("worst") or []
        moment = worst[0] if worst else None
        if row["results"] == self.current:
            if moment is not None:
                self.host.jump_to(frame=moment["frame"], track=moment["track"])
        else:
            self._open_scene(row, moment)
        return moment

    def stop(self) -> None:
        """Nothing runs in the background."""


def make_dataset_panel(
    host: PanelHost,
    report: dict,
    *,
    current: str | None,
    open_scene: OpenScene,
    sort_by: str | None = None,
) -> DatasetPanel:
    return DatasetPanel(host, report, current=current, open_scene=open_scene, sort_by=sort_by)
