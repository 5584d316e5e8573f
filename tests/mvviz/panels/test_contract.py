"""The panel contract is enough: every panel module builds and works on a fake host (a
real viser server on a free port, the viewer state, and a record of what the panel
asked for), with no :class:`~mvviz.app.ViewerApp`."""

from __future__ import annotations

import dataclasses
import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest
import viser

from mvviz.analysis.failures import Failure
from mvviz.analysis.filter_runs import FilterRun
from mvviz.analysis.timeline_strip import playhead_html
from mvviz.panels.contract import PanelHost, StateCallback
from mvviz.panels.export_panel import LAST, make_export_panel
from mvviz.panels.failure_panel import make_failure_panel
from mvviz.panels.filter_panel import make_filter_panel
from mvviz.panels.pipeline_panel import make_pipeline_panel
from mvviz.panels.view_panels import (
    make_camera_panel,
    make_layers_panel,
    make_selection_panel,
    make_timeline_panel,
)
from mvviz.safe_paths import WritePolicy
from mvviz.scene.geometry import ViewerData, prepare
from mvviz.state import ViewerState
from pipeline.config import load_config
from pipeline.results.store import PipelineResults
from tests.mvviz.conftest import free_port

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")


class FakeHost:
    """A :class:`PanelHost` without the app. Subscribers are called on one worker thread
    (as the app calls them on its render thread); ``calls`` records every request."""

    def __init__(self, state: ViewerState, writes: WritePolicy | None = None) -> None:
        self.server = viser.ViserServer(host="127.0.0.1", port=free_port(), verbose=False)
        self.state = state
        self.model = None
        self.frames = None
        self.writes = writes or WritePolicy(Path("/nonexistent"), "a fake host writes nothing")
        self.stopped = threading.Event()
        self.rendering = False
        self.calls: list[tuple[str, object]] = []
        self._subscribers: list[StateCallback] = []
        self._notifier = ThreadPoolExecutor(1, thread_name_prefix="fake-host")

    def subscribe(self, callback: StateCallback) -> Callable[[], None]:
        self._subscribers.append(callback)
        return lambda: self._subscribers.remove(callback) if callback in self._subscribers else None

    def set_results(self, results: PipelineResults) -> None:
        self.calls.append(("set_results", results))
        old = self.state.data
        self.state.data = prepare(old.scene, results, None, bodies=old.bodies)
        self.redraw("results")

    def show_data(self, data: ViewerData) -> None:
        self.calls.append(("show_data", data))
        self.state.data = data
        self.redraw()

    def jump_to(self, frame=None, track=None, joint=None, view=None) -> None:
        self.calls.append(("jump_to", (frame, track, joint, view)))
        if frame is not None:
            self.state.frame = int(frame)
        self.redraw("frame")

    def focus(self, target: np.ndarray, offset: np.ndarray | None = None) -> None:
        self.calls.append(("focus", np.asarray(target)))

    def mark_failures(self, failures, criteria) -> None:
        self.calls.append(("mark_failures", (tuple(failures), tuple(criteria))))

    def redraw(self, reason: str = "redraw") -> None:
        self.calls.append(("redraw", reason))
        st = self.state.snapshot()
        self._notifier.submit(lambda: [cb(st, reason) for cb in list(self._subscribers)])

    def wait_idle(self, timeout: float = 10.0) -> bool:
        self._notifier.submit(lambda: None).result(timeout)
        return True

    def complete_results(self) -> PipelineResults:
        return self.state.results

    def filter_runs(self) -> tuple[FilterRun, FilterRun | None] | None:
        return None

    def asked(self, what: str) -> list[object]:
        return [arg for name, arg in self.calls if name == what]

    def stop(self) -> None:
        self.stopped.set()
        self._notifier.shutdown(wait=True)
        self.server.stop()


@pytest.fixture
def host(viewer_scene, tmp_path):
    """A fake host of the tiny scene, its root in a temporary directory (panels that
    save write there)."""
    scene, results, model = viewer_scene
    scene = dataclasses.replace(scene, root=tmp_path)
    h = FakeHost(ViewerState.create(scene, results, model), WritePolicy(tmp_path / "exports"))
    yield h
    h.stop()


def test_the_fake_is_a_panel_host(host):
    _: PanelHost = host  # what a type checker checks; here: every member is present
    for name in ("server", "state", "model", "frames", "writes", "stopped", "rendering"):
        assert hasattr(host, name)
    for name in PanelHost.__dict__:
        if not name.startswith("_"):
            assert hasattr(host, name), name


def test_view_panels_change_the_state_and_ask_for_redraws(host):
    makers = (make_timeline_panel, make_layers_panel, make_selection_panel, make_camera_panel)
    panels = [make(host) for make in makers]
    timeline, layers, selection, camera = panels
    timeline.set_frame(7)
    assert host.state.frame == 7 and ("redraw", "frame") in host.calls
    layers.gui.toggles["rays"].value = False
    assert host.state.layers.rays is False and ("redraw", "layers") in host.calls
    selection.select(track=1, joint=0)
    assert host.state.selection.track == 1 and host.state.selection.joint == 0
    camera.show_view(1)
    assert host.state.camera == 1 == host.state.selection.view
    for p in panels:
        p.stop()


def test_timeline_marks_failures_and_jumps_to_them(host):
    timeline = make_timeline_panel(host)
    assert timeline.jump_to_failure(+1) is None  # nothing to go to before they are found
    n = host.state.data.num_frames
    late = Failure("kalman", 2.0, frame=12, track=1, joint=0, view=None, first=10, last=14)
    early = Failure("id", 3.0, frame=4, track=0, joint=None, view=None)
    blank = timeline.gui.strip.image.copy()
    timeline.show_failures([late, early], ("id", "kalman"))
    assert timeline.gui.strip.image.shape[1] == blank.shape[1]
    assert (timeline.gui.strip.image != 255).any(-1).sum() > (blank != 255).any(-1).sum()
    assert "Kalman 1" in timeline.gui.legend.content
    host.state.frame = 0
    assert timeline.jump_to_failure(+1) is early
    assert host.asked("jump_to")[-1][:3] == (4, 0, None)
    assert timeline.jump_to_failure(+1) is late and host.state.frame == 10
    assert timeline.jump_to_failure(+1) is None  # the last one: stays
    assert timeline.jump_to_failure(-1) is early and host.state.frame == 4
    host.state.frame = n - 1
    timeline.show_frame(host.state.snapshot())  # the playhead follows the frame
    assert timeline.gui.playhead.content == playhead_html(n, n - 1)
    timeline.stop()


def test_export_panel_writes_through_the_host(host, tmp_path):
    panel = make_export_panel(host)
    panel.export(fmt="trc", stage="raw", track="0", path="t.trc", per_track=False)
    assert panel.wait(60)
    assert [f.path for f in panel.last_files] == [tmp_path / "exports" / "t.trc"]
    host.set_results(host.state.results)  # new results: the choices are rebuilt
    assert host.wait_idle() and panel.gui.stage.options[0] == LAST
    panel.stop()


def test_failure_panel_jumps_and_focuses_through_the_host(host):
    panel = make_failure_panel(host)
    assert panel.wait_idle(60)
    panel.set_criterion("kalman")
    assert panel.wait_idle(60) and panel.failures
    failure = panel.click(0)
    assert host.asked("jump_to")[-1][:2] == (failure.frame, failure.track)
    marks, criteria = host.asked("mark_failures")[-1]  # every criterion's, for the timeline
    assert criteria == panel.criteria and len(marks) == sum(panel.counts.values())
    note = panel.flag("looks off", frame=3)
    assert panel.notes == [note] and panel.notes_file.is_file()
    panel.stop()


@pytest.mark.slow
def test_filter_panel_applies_b_through_the_host(host):
    panel = make_filter_panel(host)
    assert panel.wait_idle(30)
    panel.scale_q("×4")
    assert panel.wait_idle(30) and panel.b_differs
    path = panel.apply_b()
    (applied,) = host.asked("set_results")
    assert applied.config.kalman == panel.params_b == load_config(path).kalman
    assert host.wait_idle() and panel.wait_idle(30)
    assert panel.run_a.params == panel.params_b  # A follows the results the host shows
    panel.stop()


def test_pipeline_panel_previews_through_the_host(host):
    panel = make_pipeline_panel(host)
    host.state.frame = 5
    panel.gui.cameras[host.state.scene.rig.names[0]].value = False  # re-runs frame 5 now
    assert panel.pending and host.asked("show_data") + host.asked("set_results")
    assert host.state.results.config.disabled_views == (host.state.scene.rig.names[0],)
    panel.stop()  # drops the sequence re-run in progress
