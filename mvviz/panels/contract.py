"""The panel contract: what a panel may use of the viewer (:class:`PanelHost`) and what
the viewer calls on every panel (:class:`Panel`).

A panel module offers ``make_<name>_panel(host) -> <Name>Panel``: the controller, whose
``gui`` is a ``<Name>Handles`` dataclass of its viser handles. A panel reads the state
from ``host.state`` and changes what is shown only through the host (``set_results``,
``show_data``, ``jump_to``, ``redraw``), never by writing ``host.state.data``; it follows
the viewer with ``host.subscribe``. :class:`mvviz.app.ViewerApp` implements the host; the
panel tests use a small fake (``tests/mvviz/panels/test_contract.py``), which is the proof
that this contract is all a panel needs. Panels that need another panel's work go
through the host too (``complete_results``, ``filter_runs``).
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Protocol

import numpy as np
import viser

from mvviz.analysis.failures import Failure
from mvviz.analysis.filter_runs import FilterRun
from mvviz.safe_paths import WritePolicy
from mvviz.scene.geometry import ViewerData
from mvviz.scene.images import FrameStore
from mvviz.state import ViewerState
from pipeline.results.store import PipelineResults

if TYPE_CHECKING:
    from pipeline.body.arrays import BodyModelData
    from pipeline.body.model import BodyModel

# ``callback(state, reason)`` after each render: ``state`` a snapshot of what was drawn,
# ``reason`` the comma-joined reasons of the redraw ("frame", "results", "layers", ...).
StateCallback = Callable[[ViewerState, str], None]


class Panel(Protocol):
    """What the viewer calls on every panel it built."""

    def stop(self) -> None:
        """End the panel's threads (idempotent); the viewer calls it once at its stop,
        before the server stops. GUI writes after it are not needed."""
        ...


class PanelHost(Protocol):
    """What a panel may use of the viewer. Every member is documented by what it does;
    nothing here hands out the app itself."""

    @property
    def server(self) -> viser.ViserServer:
        """The viser server: ``server.gui`` for the panel's handles, ``server.scene`` for
        the scene nodes a panel draws itself (under its own path)."""
        ...

    @property
    def state(self) -> ViewerState:
        """What the viewer shows now (frame, selection, layers, data): one object for the
        viewer's life. Read it; change the data only with :meth:`set_results` /
        :meth:`show_data`."""
        ...

    @property
    def model(self) -> BodyModel | BodyModelData | None:
        """The run's body model (None: the shipped one)."""
        ...

    @property
    def frames(self) -> FrameStore | None:
        """The decoded camera frames (None: no videos)."""
        ...

    @property
    def writes(self) -> WritePolicy:
        """Where a panel writes what a browser asks for (typed names: inside
        ``writes.export_dir``; fixed names: under the scene folder, through
        ``writes.scene_file``), and whether it may at all (``writes.read_only``)."""
        ...

    @property
    def stopped(self) -> threading.Event:
        """Set when the viewer stops: workers end, GUI writes are skipped."""
        ...

    @property
    def rendering(self) -> bool:
        """True while the viewer renders a frame (a background job may wait for it to
        end, so it does not hold the GIL against a frame change)."""
        ...

    def subscribe(self, callback: StateCallback) -> Callable[[], None]:
        """Call ``callback(state, reason)`` after each render (on the render thread: keep
        it short); returns the function that unsubscribes it."""
        ...

    def set_results(self, results: PipelineResults) -> None:
        """Show new results of the same scene: the scene layers are rebuilt for the new
        tracks; subscribers then see the reason "results"."""
        ...

    def show_data(self, data: ViewerData) -> None:
        """Show ``data`` on the existing scene nodes (same scene, joint set, tracks and
        fits as the shown data: a preview of other results) and redraw."""
        ...

    def jump_to(
        self,
        frame: int | None = None,
        track: int | None = None,
        joint: int | str | None = None,
        view: int | str | None = None,
    ) -> None:
        """Show ``frame``, select ``track`` / ``joint``, show ``view`` in the camera panel
        (None: unchanged; a negative track clears the selection)."""
        ...

    def focus(self, target: np.ndarray, offset: np.ndarray | None = None) -> None:
        """Point every client's camera at ``target`` (3,) world metres."""
        ...

    def mark_failures(self, failures: Sequence[Failure], criteria: Sequence[str]) -> None:
        """Draw ``failures`` (the entries of every criterion in ``criteria``, for the
        shown data) on the timeline, one lane per criterion."""
        ...

    def redraw(self, reason: str = "redraw") -> None:
        """Draw the state again; ``reason`` reaches the subscribers ("playing" starts or
        pauses playback instead of drawing)."""
        ...

    def wait_idle(self, timeout: float = 10.0) -> bool:
        """Block until the viewer has drawn every requested frame (tests, scripts)."""
        ...

    def complete_results(self) -> PipelineResults:
        """The newest complete results (every stage): the Pipeline panel's once a re-run
        in progress lands (blocks until then), else the shown results. What exports
        write, never a preview."""
        ...

    def filter_runs(self) -> tuple[FilterRun, FilterRun | None] | None:
        """Filter A and B of the Filter A/B panel (B None while it re-filters); None
        without that panel."""
        ...
