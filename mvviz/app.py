"""The viewer: one viser server, a :class:`ViewerState`, one ``make_*_panel`` per panel.

The viewer reads a scene and its :class:`~pipeline.results.store.PipelineResults` and never
reaches into a stage. A frame change computes :func:`~mvviz.scene.geometry.frame_geometry`
and assigns it to existing scene handles; renders run on one worker thread through a
"latest wins" slot, so scrubbing draws only the newest requested frame.

Every panel (:mod:`mvviz.panels`) is built by its ``make_<name>_panel(host)`` against the
panel contract, :class:`~mvviz.panels.contract.PanelHost`, which :class:`ViewerApp`
implements (state, ``set_results``, ``show_data``, ``jump_to``, ``focus``, ``redraw``,
``subscribe``, ``stopped``, ...); the app keeps every panel it built in
:attr:`ViewerApp.panels` and :meth:`ViewerApp.stop` stops them all.
"""

from __future__ import annotations

import statistics
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import TYPE_CHECKING, TypeVar

import cv2
import numpy as np
import viser

from mvviz.analysis.failures import Failure
from mvviz.analysis.filter_runs import FilterRun
from mvviz.panels.contract import Panel, StateCallback
from mvviz.panels.diagnose_panel import make_diagnose_panel
from mvviz.panels.export_panel import make_export_panel
from mvviz.panels.failure_panel import make_failure_panel
from mvviz.panels.filter_panel import make_filter_panel
from mvviz.panels.icons import use_one_icon_zip
from mvviz.panels.pipeline_panel import make_pipeline_panel
from mvviz.panels.view_panels import (
    make_camera_panel,
    make_layers_panel,
    make_selection_panel,
    make_timeline_panel,
)
from mvviz.safe_paths import WritePolicy
from mvviz.scene.geometry import LayerToggles, ViewerData, frame_geometry, prepare, to_display
from mvviz.scene.images import (
    BodyOutlines,
    FrameStore,
    blank_frame,
    draw_overlay,
    image_overlay,
    video_frame,
)
from mvviz.scene.layers import make_scene_layers
from mvviz.state import ViewerState
from mvviz.workers import LatestWins, PageAcks, StalledClients
from pipeline.core.files import scene_cache_dir
from pipeline.data.calibration_views import CALIBRATION_VIEWS
from pipeline.results.store import PipelineResults

FirstTab = tuple[str, str, Callable[["ViewerApp"], Panel]]
"""(label, icon, build): a tab shown before the viewer's own (see :class:`ViewerApp`)."""

if TYPE_CHECKING:
    from pipeline.body.arrays import BodyModelData
    from pipeline.body.model import BodyModel

STATS_INTERVAL_S = 1.0  # the render-time line updates at most this often
P = TypeVar("P", bound=Panel)

# --------------------------------------------------------------------------- rendering


class ViewerApp:
    """The running viewer: server, scene layers, panels, render worker, playback.

    Implements :class:`~mvviz.panels.contract.PanelHost` for the panels it builds.
    """

    def __init__(
        self,
        state: ViewerState,
        *,
        host: str = "127.0.0.1",
        port: int = 8080,
        frames: FrameStore | None = None,
        model: BodyModel | BodyModelData | None = None,
        verbose: bool = False,
        server: viser.ViserServer | None = None,
        first_tab: FirstTab | None = None,
        writes: WritePolicy | None = None,
    ) -> None:
        """``server``: an already running server to build on (``host``, ``port`` and
        ``verbose`` then unused; ``mvviz view`` starts it before the heavy imports).
        ``first_tab``: (label, icon, build) of a panel shown before the standard tabs,
        open when the page loads (viser opens a tab group at its first tab and has no
        way to select another): the Dataset panel of ``app.py --batch``.
        ``writes``: where the panels write and whether they may (default: into
        ``SCENE/.mvviz/export``, read-only unless the server is bound to loopback)."""
        self.state = state
        self.model = model  # the body model of the run (None: the shipped one)
        self.frames = frames
        self.frame_times_ms: deque[float] = deque(maxlen=500)
        self.panels: list[Panel] = []  # every panel built, in order: stop() stops them
        self._subscribers: list[StateCallback] = []
        self._reasons: set[str] = set()
        self._reasons_lock = threading.Lock()
        self._stopped = threading.Event()
        self._play_wake = threading.Event()
        # video frames playback has advanced (skipped ones included): how far it got,
        # which the frame number alone cannot tell once it loops
        self.frames_played = 0
        self._applied_layers: LayerToggles | None = None
        self.last_render_ms: dict[str, float] = {}
        self.render_errors: list[str] = []
        self._render_lock = threading.Lock()

        if server is None:
            server = viser.ViserServer(host=host, port=port, verbose=verbose)
        self.server = server
        self.writes = writes or WritePolicy.for_host(
            server.get_host(), scene_cache_dir(state.scene.root) / "export"
        )
        server.gui.configure_theme(control_width="medium", show_share_button=False)
        # Dock both panels so the 3D canvas is the free space between them, and the
        # initial camera's look-at point lands in the middle of what is visible.
        server.gui.main_panel.dock_right()
        server.gui.main_panel.set_width(340)
        server.scene.set_up_direction("+z")
        self._set_initial_camera()
        use_one_icon_zip()  # the panels' icons: ~0.35 s of CPU less at every start
        self.layers = make_scene_layers(server, state.data, on_joint_click=self._on_joint_click)
        self._build_panels(first_tab)
        self._image_pool = ThreadPoolExecutor(1, thread_name_prefix="mvviz-images")
        self.last_image_cpu_ms = 0.0  # CPU time of the last frame's image job
        self._stats_shown_t = -np.inf
        self._renderer = LatestWins(self._render)
        self._acks = PageAcks(server)  # playback waits for the pages (drops, never lags)
        self._stalls = StalledClients(server)  # a client that stopped reading is let go
        self._player = threading.Thread(target=self._play_loop, name="mvviz-play", daemon=True)
        self._player.start()
        if frames is not None:
            frames.on_camera_ready.append(lambda _cam: self._on_change("video"))
        self._on_change("init")

    def _build_panels(self, first_tab: FirstTab | None = None) -> None:
        """The timeline on top whatever tab is open (scrubbing while looking at a
        failure, a filter or a layer is the point); below it one tab per panel; the
        camera panel docked left."""
        self.read_only_line: viser.GuiMarkdownHandle | None = None
        if self.writes.read_only is not None:  # why the save and export buttons are off
            line = f"<small>**{self.writes.read_only}**</small>"
            self.read_only_line = self.server.gui.add_markdown(line)
        self.timeline = self._add(make_timeline_panel(self))
        self.tabs = tabs = self.server.gui.add_tab_group()
        if first_tab is not None:
            label, icon, build = first_tab
            with tabs.add_tab(label, icon):
                self._add(build(self))
        with tabs.add_tab("Layers", viser.Icon.STACK_2):
            self.layers_panel = self._add(make_layers_panel(self))
        with tabs.add_tab("Selection", viser.Icon.POINTER):
            self.selection_panel = self._add(make_selection_panel(self))
        self.camera_panel = self._add(make_camera_panel(self))
        with tabs.add_tab("Pipeline", viser.Icon.ADJUSTMENTS):
            self.pipeline_panel = self._add(make_pipeline_panel(self))
        with tabs.add_tab("Filter A/B", viser.Icon.CHART_LINE):
            self.filter_panel = self._add(make_filter_panel(self))
        with tabs.add_tab("Failures", viser.Icon.ALERT_TRIANGLE):
            self.failure_panel = self._add(make_failure_panel(self))
        with tabs.add_tab("Export", viser.Icon.DOWNLOAD):
            self.export_panel = self._add(make_export_panel(self))
        with tabs.add_tab("Diagnose", viser.Icon.STETHOSCOPE):
            self.diagnose_panel = self._add(make_diagnose_panel(self))
        self.calibration_panel = None
        if (self.state.scene.root / CALIBRATION_VIEWS).is_file():  # a mvviz calibrate folder
            from mvviz.calibration_view import make_calibration_panel

            with tabs.add_tab("Calibration", viser.Icon.CAMERA):
                self.calibration_panel = make_calibration_panel(self)
            if self.calibration_panel is not None:
                self._add(self.calibration_panel)
        for panel in (self.pipeline_panel, self.export_panel, self.diagnose_panel):
            folder = panel.gui.folder
            folder.expand_by_default = True  # alone in its tab: open

    def _add(self, panel: P) -> P:
        """Keep ``panel`` for :meth:`stop`."""
        self.panels.append(panel)
        return panel

    # ------------------------------------------------------------------ the panel host

    @property
    def url(self) -> str:
        host = self.server.get_host()
        host = "127.0.0.1" if host in ("0.0.0.0", "") else host
        return f"http://{host}:{self.server.get_port()}"

    @property
    def stopped(self) -> threading.Event:
        """Set by :meth:`stop`: panel workers end, GUI writes are skipped."""
        return self._stopped

    @property
    def rendering(self) -> bool:
        """A frame is being rendered (the render lock is held)."""
        return self._render_lock.locked()

    def subscribe(self, callback: StateCallback) -> Callable[[], None]:
        """Call ``callback(state, reason)`` after each render; returns the unsubscriber."""
        self._subscribers.append(callback)

        def unsubscribe() -> None:
            if callback in self._subscribers:
                self._subscribers.remove(callback)

        return unsubscribe

    def set_frame(self, frame: int) -> None:
        """Go to ``frame`` (moves the slider, which redraws)."""
        self.timeline.set_frame(frame)

    def jump_to(
        self,
        frame: int | None = None,
        track: int | None = None,
        joint: int | str | None = None,
        view: int | str | None = None,
    ) -> None:
        """Show ``frame``, select ``track``/``joint``, show ``view`` in the image panel.

        The entry point for panels that list problems (failure review, filter tuning).
        """
        self.selection_panel.select(track, joint)
        if view is not None:
            self.camera_panel.show_view(view)
        if frame is not None:
            self.set_frame(frame)

    def focus(self, target: np.ndarray, offset: np.ndarray | None = None) -> None:
        """Point every connected client's camera at ``target`` (world metres) from
        ``target + offset`` (default: 2.5 m away, from behind-left and above)."""
        target = to_display(self.state.data.T_display_world, target)
        offset = np.array([-1.4, -1.9, 1.0]) if offset is None else np.asarray(offset, float)
        for client in self.server.get_clients().values():
            client.camera.position = target + offset  # moves look_at along with it
            client.camera.look_at = target

    def mark_failures(self, failures: Sequence[Failure], criteria: Sequence[str]) -> None:
        """Draw ``failures`` on the timeline's strip (the Failures panel calls it)."""
        self.timeline.show_failures(failures, criteria)

    def redraw(self, reason: str = "redraw") -> None:
        self._on_change(reason)

    def show_data(self, data: ViewerData) -> None:
        """Show ``data`` (same scene, joint set, tracks, fits) on the existing nodes."""
        self.state.data = data
        self.redraw()

    def set_results(self, results: PipelineResults) -> None:
        """Show new results of the same scene (e.g. re-run with other parameters): the
        scene layers are rebuilt for the new tracks, the selection is kept where valid."""
        old = self.state.data
        data = prepare(old.scene, results, None, bodies=old.bodies)
        with self._render_lock, self.server.atomic():
            skinned = {
                h.name for h in (*self.layers.meshes.values(), *self.layers.fit_meshes.values())
            }
            self.layers.remove()
            self.state.data = data
            self.layers = make_scene_layers(self.server, data, on_joint_click=self._on_joint_click)
            self.layers.set_visibility(self.state.layers)  # shown meshes: in this batch
            self._applied_layers = None
            # viser 1.1.1's client blanks the page ("Cannot read properties of null
            # (reading 'remove')") when a skinned mesh is removed and nothing of that name
            # is added in the same batch; fewer tracks or no fits remove some. Leave an
            # empty node in each one's place.
            kept = {
                h.name for h in (*self.layers.meshes.values(), *self.layers.fit_meshes.values())
            }
            for name in sorted(skinned - kept):
                self.server.scene.add_frame(name, show_axes=False, visible=False)
        self.selection_panel.set_choices(data.num_tracks, data.joint_set.names)
        self._on_change("results")

    def complete_results(self) -> PipelineResults:
        """The Pipeline panel's newest complete results (waits for a re-run to land)."""
        panel = getattr(self, "pipeline_panel", None)
        return self.state.results if panel is None else panel.complete_results()

    def filter_runs(self) -> tuple[FilterRun, FilterRun | None] | None:
        """Filter A and B of the Filter A/B panel (None before it is built)."""
        panel = getattr(self, "filter_panel", None)
        return None if panel is None else (panel.run_a, panel.run_b)

    def wait_idle(self, timeout: float = 10.0) -> bool:
        return self._renderer.wait_idle(timeout)

    def frame_time_stats(self) -> dict[str, float]:
        """Server-side render time per frame change, milliseconds."""
        t = list(self.frame_times_ms)
        if not t:
            return {"count": 0, "median_ms": float("nan"), "p95_ms": float("nan")}
        return {
            "count": len(t),
            "median_ms": statistics.median(t),
            "p95_ms": float(np.percentile(t, 95)),
        }

    def stop(self) -> None:
        """Stop playback, every panel, the render and image threads, then the server."""
        self._stopped.set()
        self._play_wake.set()
        for panel in reversed(self.panels):
            panel.stop()
        self._renderer.stop()
        self._image_pool.shutdown(wait=True)
        self._player.join(timeout=5)
        self._acks.stop()
        self._stalls.stop()
        self.server.stop()

    # ------------------------------------------------------------------ internals

    def _set_initial_camera(self) -> None:
        """Look at the action from behind and above the first camera (so its video faces
        the viewer), turned a little so that frustum does not hide the people."""
        data = self.state.data
        c = data.center.copy()
        if np.allclose(data.T_display_world, np.eye(4)):
            c[2] = 0.9  # chest height over a z-up world's floor
        d = data.cameras[0].position[:2] - c[:2] if data.cameras else np.array([-1.0, -1.0])
        d = d / max(np.linalg.norm(d), 1e-6)
        a = np.deg2rad(30.0)
        d = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]) @ d
        # a room-sized rig is seen from >= 3.5 m; a desk-sized one from nearer
        r = max(min(3.5, 2.5 * data.camera_distance), 2.0 * data.spread + 1.5)
        pos = np.array([c[0] + d[0] * r, c[1] + d[1] * r, c[2] + 0.55 * r])
        self.server.initial_camera.position = tuple(pos)
        self.server.initial_camera.look_at = tuple(c)
        self.server.initial_camera.up = (0.0, 0.0, 1.0)
        self.server.initial_camera.fov = np.deg2rad(50.0)
        for client in self.server.get_clients().values():  # a page opened while loading
            client.camera.up_direction = (0.0, 0.0, 1.0)
            client.camera.position = tuple(pos)  # moves look_at along with it
            client.camera.look_at = tuple(c)

    def _on_joint_click(self, track: int, joint: int) -> None:
        if 0 <= joint < self.state.data.joint_set.num_joints:
            self.jump_to(track=track, joint=joint)

    def _on_change(self, reason: str) -> None:
        with self._reasons_lock:
            self._reasons.add(reason)
        if reason == "playing":
            self._play_wake.set()
            self.timeline.show_playing(self.state.playing)
            return
        self._renderer.request()

    def _render(self) -> None:
        with self._render_lock:
            try:
                self._render_locked()
            except Exception as exc:
                self.render_errors.append(f"{type(exc).__name__}: {exc}")
                raise

    def _frame_images(
        self, st: ViewerState
    ) -> tuple[dict[str, tuple[object, np.ndarray | None]], np.ndarray, BodyOutlines | None]:
        """The frustums' images (camera name -> (key, image or None)), the camera panel's
        picture with its overlay and the bodies drawn on it, for ``st``'s frame. Runs on
        the image thread."""
        t0 = time.thread_time()
        f, lay, data = st.frame, st.layers, st.data
        images: dict[str, tuple[object, np.ndarray | None]] = {}
        fw = lay.frustum_image_width
        for cam in data.cameras:
            img, vf = None, video_frame(data, cam.name, f)  # a re-timed camera's own frame
            if lay.frustum_images and lay.cameras and self.frames is not None:
                img = self.frames.small(cam.name, vf, fw)
            images[cam.name] = ((vf, fw) if img is not None else None, img)
        camera = st.scene.rig[st.camera]
        w = st.panel_image_width
        h = max(1, round(camera.height * w / camera.width))
        vf = video_frame(data, camera.name, f)
        base = self.frames.frame(camera.name, vf) if self.frames is not None else None
        if base is None:
            base = blank_frame(w, h)
        elif base.shape[1] != w:  # overlays are drawn after resizing: crisp at any width
            # bilinear up to 2x down (~7x faster than INTER_AREA here, little aliasing)
            interp = cv2.INTER_AREA if base.shape[1] > 2 * w else cv2.INTER_LINEAR
            base = cv2.resize(base, (w, h), interpolation=interp)
        overlay = image_overlay(data, st.camera, f, lay)
        panel_image = draw_overlay(base, overlay)
        self.last_image_cpu_ms = (time.thread_time() - t0) * 1e3
        return images, panel_image, overlay.bodies

    def _render_locked(self) -> None:
        t0 = time.perf_counter()
        with self._reasons_lock:
            reasons, self._reasons = self._reasons, set()
        st = self.state.snapshot()
        lay = st.layers
        # Decoding, resizing and drawing the images (OpenCV, which releases the GIL) run
        # on a second thread while this one computes and assigns the geometry.
        images_job = self._image_pool.submit(self._frame_images, st)
        geom = frame_geometry(st)
        t1 = time.perf_counter()
        with self.server.atomic():
            if lay != self._applied_layers:
                self.layers.set_visibility(lay)
                self._applied_layers = lay
            self.layers.apply(geom, st.selection)
            self.layers.highlight_camera(st.scene.rig.names[st.camera])
            self.timeline.show_frame(st)
            self.selection_panel.show(st)
            t2 = time.perf_counter()
            images, panel_image, bodies = images_job.result()
            t3 = time.perf_counter()
            self.layers.set_frustum_images(images)
            self.camera_panel.show_image(panel_image)
            self.camera_panel.show_bodies(bodies)
        self.server.flush()
        t4 = time.perf_counter()
        ms = (t4 - t0) * 1e3
        self.frame_times_ms.append(ms)
        self.last_render_ms = {
            "geometry": (t1 - t0) * 1e3,
            "assign": (t2 - t1) * 1e3,
            "wait for images": (t3 - t2) * 1e3,
            "send images": (t4 - t3) * 1e3,
        }
        if t4 - self._stats_shown_t >= STATS_INTERVAL_S:  # a figure to read, not to flicker
            self._stats_shown_t = t4
            s = self.frame_time_stats()
            self.timeline.show_stats(
                f"<small>server render {ms:.0f} ms (median {s['median_ms']:.0f}, "
                f"p95 {s['p95_ms']:.0f})</small>"
            )
        reason = ",".join(sorted(reasons)) or "redraw"
        for cb in list(self._subscribers):
            try:
                cb(st, reason)
            except Exception as exc:
                print(f"mvviz view: state-change callback failed: {exc}")

    def _play_loop(self) -> None:
        """Advance one frame per video frame; after each, wait for the render and for
        the open pages to apply it (:class:`~mvviz.workers.PageAcks`), then skip the
        frames that time passed: a slow page drops frames instead of lagging."""
        next_t = time.perf_counter()
        while not self._stopped.is_set():
            st = self.state
            if not st.playing:
                self._play_wake.wait(0.5)
                self._play_wake.clear()
                next_t = time.perf_counter()
                continue
            period = 1.0 / (st.scene.fps * max(st.speed, 1e-3))
            next_t += period
            delay = next_t - time.perf_counter()
            step = 1
            if delay > 0:
                time.sleep(delay)
            else:  # fell behind (render or page slower than the video): skip
                missed = int(-delay / period)
                step += missed
                next_t += missed * period
            f, n = st.frame + step, st.data.num_frames
            if f >= n:
                if st.loop:
                    f %= n
                elif st.frame < n - 1:
                    f = n - 1  # the last frame is shown, whatever was skipped
                else:
                    st.playing = False
                    self._on_change("playing")
                    continue
            self.frames_played += step
            self.set_frame(f)
            self._renderer.wait_idle(self._acks.timeout_s)
            self._acks.wait()
