"""``python app.py --batch DIR``: the viewer on a ``mvviz batch`` report's scenes.

One scene is shown at a time, with the Dataset tab (:mod:`mvviz.panels.dataset_panel`)
listing every scene of ``DIR/batch_report.json``. Opening another scene replaces the
whole viewer: the shown one stops (its server too) and the next is built on a new server
on the same port, which the open pages reconnect to by themselves; every panel then
works on the new scene exactly as ``mvviz view SCENE`` builds it, with nothing of the
last scene left in any panel.
"""

from __future__ import annotations

import argparse
import threading
import traceback
from pathlib import Path

import viser

from mvviz.cli.view import serve_until_interrupted, start, stop
from mvviz.panels.dataset_panel import DatasetPanel, make_dataset_panel
from pipeline.batch.report import load_report
from pipeline.core.files import SceneFormatError


def scene_args(args: argparse.Namespace, row: dict, moment: dict | None) -> argparse.Namespace:
    """``mvviz view``'s options for a report row: its scene, results file, config and
    overrides (so the cache key matches and the results are read, not recomputed)."""
    ns = argparse.Namespace(**vars(args))
    ns.scene = Path(row["scene"])
    ns.out = Path(row["results"])
    ns.config = Path(row["config_file"]) if row.get("config_file") else None
    ns.set = list(row.get("set_args") or [])
    ns.frame = moment["frame"] if moment else None
    ns.track = moment["track"] if moment and moment.get("track", -1) >= 0 else None
    ns.force, ns.batch, ns.rerun = False, None, False
    return ns


class BatchViewer:
    """The shown scene's viewer and its Dataset panel; :meth:`request` switches scenes."""

    def __init__(self, args: argparse.Namespace, report: dict, *, progress: bool = True) -> None:
        self.args, self.report, self.progress = args, report, progress
        self.app = None
        self.panel: DatasetPanel | None = None
        self.sort_by: str | None = None
        self.shown: dict | None = None
        self._lock = threading.Lock()
        self.switched = threading.Event()  # set after each completed switch (tests)

    def open(self, row: dict, moment: dict | None) -> None:
        """Build the viewer for ``row`` at ``moment`` (the previous one stopped first)."""
        with self._lock:
            if self.app is not None:
                self.sort_by = self.panel.metric if self.panel else self.sort_by
                stop(self.app)
                self.app = self.panel = None

            def dataset_panel(app) -> DatasetPanel:
                self.panel = make_dataset_panel(
                    app, self.report, current=row["results"], open_scene=self.request,
                    sort_by=self.sort_by,
                )  # fmt: skip
                return self.panel

            # The Dataset tab first, so that the page, which reconnects to every new
            # scene's viewer, opens on the list the user was going through.
            self.app = start(
                scene_args(self.args, row, moment), progress=self.progress,
                first_tab=("Dataset", viser.Icon.DATABASE, dataset_panel),
            )  # fmt: skip
            self.shown = row
        self.switched.set()

    def request(self, row: dict, moment: dict | None) -> None:
        """Open ``row`` from a GUI callback: on a thread of its own, since the switch
        stops the server whose callback thread asks for it."""
        self.switched.clear()
        threading.Thread(target=self._switch, args=(row, moment), daemon=True).start()

    def _switch(self, row: dict, moment: dict | None) -> None:
        previous = self.shown
        try:
            self.open(row, moment)
        except Exception:
            traceback.print_exc()
            print(f"could not open {row['label']}; back to {previous['label']}")
            if previous is not None and self.app is None:
                self.open(previous, None)

    def stop(self) -> None:
        with self._lock:
            if self.app is not None:
                stop(self.app)
                self.app = None


def first_row(report: dict) -> dict:
    """The scene to show first: the worst one, else the first with results."""
    rows = [r for r in report["rows"] if r.get("summary")]
    if not rows:
        raise SceneFormatError("--batch", "rows", "no scene of the report has results")
    worst = report["worst_scenes"]["labels"]
    return next((r for r in rows if worst and r["label"] == worst[0]), rows[0])


def start_batch(args: argparse.Namespace, *, progress: bool = True) -> BatchViewer:
    report = load_report(args.batch)
    viewer = BatchViewer(args, report, progress=progress)
    row = first_row(report)
    worst = row["summary"].get("worst") or []
    viewer.open(row, worst[0] if worst else None)
    return viewer


def run_batch(args: argparse.Namespace) -> int:
    viewer = start_batch(args)
    return serve_until_interrupted(viewer.stop)
