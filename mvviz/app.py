"""The viewer: one viser server, a :class:`ViewerState`, one ``make_*_panel`` per panel.

The viewer reads a scene and its :class:`~pipeline.results.PipelineResults` and never
reaches into a stage. A frame change computes :func:`~mvviz.scene.geometry.frame_geometry`
and assigns it to existing scene handles; renders run on one worker thread through a
"latest wins" slot, so scrubbing draws only the newest requested frame.

Each ``make_*_panel(server, state, on_change)`` builds one panel and returns a dataclass
of its handles; its callbacks update the state and call ``on_change(reason)``.

Hooks for other panels (filter tuning, failure review, export):
:meth:`ViewerApp.jump_to` (frame, track, joint, view), :meth:`ViewerApp.focus` (point
the clients' cameras), :meth:`ViewerApp.set_results` (show re-run results),
:attr:`ViewerApp.state_changed` (callbacks ``(state, reason)`` after each render), and
``app.server.gui`` for their own GUI.
"""

from __future__ import annotations

import dataclasses
import statistics
import threading
import time
from collections import deque
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import cv2
import numpy as np
import viser

from mvviz.panels.export_panel import make_export_panel
from mvviz.panels.failure_panel import make_failure_panel
from mvviz.panels.filter_panel import make_filter_panel
from mvviz.panels.pipeline_panel import make_pipeline_panel
from mvviz.scene.geometry import (
    FRUSTUM_WIDTHS,
    MESH_DETAILS,
    MESH_STYLES,
    LayerToggles,
    frame_geometry,
    prepare,
)
from mvviz.scene.images import FrameStore, blank_frame, draw_overlay, image_overlay
from mvviz.scene.layers import SceneLayers
from mvviz.state import PANEL_WIDTHS, ViewerState
from mvviz.workers import LatestWins
from pipeline.body_model import BodyModel
from pipeline.results import PipelineResults

SPEEDS = ("0.25x", "0.5x", "1x", "2x", "4x")
STEP_BACK, STEP_FORWARD = "◀ −1", "+1 ▶"
PANEL_JPEG_QUALITY = 65
STATS_INTERVAL_S = 1.0  # the render-time line updates at most this often

def selection_info(state: ViewerState) -> str:
    """Markdown about the selected track and joint in the current frame."""
    data, sel, f = state.data, state.selection, state.frame
    if sel.track is None or not 0 <= sel.track < data.num_tracks:
        return "_No track selected: click a filtered joint or pick one above._"
    k, j, res = sel.track, sel.joint, data.results
    name = data.joint_set.names[j] if 0 <= j < data.joint_set.num_joints else "?"
    raw, filt = res.track_raw[k, f, j], data.filtered[k, f, j]

    def xyz(p: np.ndarray) -> str:
        return "—" if not np.isfinite(p).all() else ", ".join(f"{v:.0f}" for v in p)

    lines = [f"**track {k} · {name}** · frame {f}", f"raw (mm): {xyz(raw)}  "]
    lines.append(f"filtered (mm): {xyz(filt)}  ")
    if np.isfinite(raw).all() and np.isfinite(filt).all():
        lines.append(f"|filtered − raw| = {np.linalg.norm(filt - raw):.0f} mm  ")
    m = res.track_mahalanobis[k, f, j]
    if np.isfinite(m):
        lines.append(f"Mahalanobis {m:.2f}  ")
    q = data.track_person[k, f]
    if q >= 0:
        views = []
        for v, cam in enumerate(data.scene.rig.names):
            e = res.person_reproj[q, j, v]
            if not np.isfinite(e):
                continue
            mark = "used" if res.person_used[q, j, v] else "**outlier**"
            views.append(f"{cam}: {e:.1f} px {mark}")
        lines.append("reprojection: " + ("; ".join(views) if views else "no views"))
    return "\n".join(lines)


# --------------------------------------------------------------------------- panels

OnChange = Callable[[str], None]


@dataclass
class TimelinePanel:
    folder: viser.GuiFolderHandle
    slider: viser.GuiSliderHandle
    play: viser.GuiButtonHandle
    step: viser.GuiButtonGroupHandle  # STEP_BACK / STEP_FORWARD
    speed: viser.GuiDropdownHandle
    loop: viser.GuiCheckboxHandle
    label: viser.GuiMarkdownHandle
    stats: viser.GuiMarkdownHandle


def make_timeline_panel(
    server: viser.ViserServer, state: ViewerState, on_change: OnChange
) -> TimelinePanel:
    n = state.data.num_frames
    with server.gui.add_folder("Timeline") as folder:
        slider = server.gui.add_slider("Frame", min=0, max=max(n - 1, 0), step=1, initial_value=0)
        label = server.gui.add_markdown(frame_label(state, 0))
        play = server.gui.add_button("Play", icon=viser.Icon.PLAYER_PLAY)
        step = server.gui.add_button_group("Step", (STEP_BACK, STEP_FORWARD))
        speed = server.gui.add_dropdown("Speed", SPEEDS, initial_value="1x")
        loop = server.gui.add_checkbox("Loop", initial_value=state.loop)
        stats = server.gui.add_markdown("")
    panel = TimelinePanel(folder, slider, play, step, speed, loop, label, stats)

    @slider.on_update
    def _(_) -> None:
        state.frame = int(slider.value)
        on_change("frame")

    @play.on_click
    def _(_) -> None:
        state.playing = not state.playing
        on_change("playing")

    @step.on_click
    def _(event) -> None:
        delta = -1 if event.target.value == STEP_BACK else 1
        slider.value = int(np.clip(int(slider.value) + delta, 0, n - 1))

    @speed.on_update
    def _(_) -> None:
        state.speed = float(speed.value.rstrip("x"))

    @loop.on_update
    def _(_) -> None:
        state.loop = bool(loop.value)

    return panel


def frame_label(state: ViewerState, frame: int) -> str:
    n, fps = state.data.num_frames, state.scene.fps
    return f"frame **{frame}** / {n - 1} · {frame / fps:.2f} s"


@dataclass
class LayersPanel:
    folder: viser.GuiFolderHandle
    toggles: dict[str, viser.GuiCheckboxHandle]
    trail_window: viser.GuiSliderHandle
    frustum_width: viser.GuiDropdownHandle
    mesh_style: viser.GuiDropdownHandle
    mesh_detail: viser.GuiDropdownHandle


LAYER_LABELS = {
    "grid": "Grid",
    "cameras": "Cameras",
    "camera_labels": "Camera labels",
    "frustum_images": "Video on frustums",
    "detections2d": "2D detections",
    "rays": "Rays",
    "rays_selected_only": "Rays: selected track only",
    "raw": "Raw 3D skeletons",
    "filtered": "Filtered skeletons",
    "offset_filtered": "Filtered side by side (+1 m x)",
    "gt": "Ground-truth skeletons",
    "trails": "Trails (selected joint)",
    "meshes": "Ground-truth meshes",
    "fit_meshes": "Fitted SMPL meshes",
    "meshes_selected_only": "Meshes: selected track only",
}

# The page shows this itself when its WebGL renderer is a software one (SwiftShader,
# llvmpipe: what viser's client warns about too), through an <img> error handler that
# asks a throw-away WebGL context for its renderer: the server cannot know.
SOFTWARE_NOTICE_HTML = """<div class="mvviz-software-gl" style="display:none;font-size:0.8em;
color:#9a3412;background:#fff7ed;border:1px solid #fdba74;border-radius:4px;padding:4px 6px;
margin:2px 0">⚠ <b>Software WebGL</b> (<span class="mvviz-gl-renderer"></span>): bodies are
slow to draw here. Keep meshes <i>decimated</i>, try <i>wireframe</i> or <i>selected track
only</i>, or turn hardware acceleration on in the browser.</div><img alt="" src="data:,"
style="display:none" onerror="(function(img){try{var gl=document.createElement('canvas')
.getContext('webgl');var ext=gl&&gl.getExtension('WEBGL_debug_renderer_info');var r=ext?
gl.getParameter(ext.UNMASKED_RENDERER_WEBGL):'';if(/swiftshader|llvmpipe|softpipe|software/i
.test(r)){var box=img.previousElementSibling;box.style.display='block';box.querySelector(
'.mvviz-gl-renderer').textContent=r;}var lose=gl&&gl.getExtension('WEBGL_lose_context');
if(lose){lose.loseContext();}}catch(e){}})(this)">"""


def make_layers_panel(
    server: viser.ViserServer, state: ViewerState, on_change: OnChange
) -> LayersPanel:
    toggles = {}
    # what this scene and run cannot show: off, and disabled below
    missing = [
        name
        for name, absent in (
            ("gt", state.data.gt_points is None),
            ("meshes", state.data.bodies is None),
            ("fit_meshes", state.data.fit_bodies is None),
        )
        if absent
    ]
    for name in missing:
        setattr(state.layers, name, False)
    with server.gui.add_folder("Layers") as folder:
        for name, label in LAYER_LABELS.items():
            cb = server.gui.add_checkbox(label, initial_value=getattr(state.layers, name))
            toggles[name] = cb

            def bind(name: str = name, cb: viser.GuiCheckboxHandle = cb) -> None:
                @cb.on_update
                def _(_) -> None:
                    setattr(state.layers, name, bool(cb.value))
                    on_change("layers")

            bind()
        for ref in state.scene.references:  # one checkbox per reference track
            cb = server.gui.add_checkbox(
                f"Reference: {ref}", initial_value=ref not in state.layers.references_off
            )
            toggles[f"reference:{ref}"] = cb

            def bind_ref(ref: str = ref, cb: viser.GuiCheckboxHandle = cb) -> None:
                @cb.on_update
                def _(_) -> None:
                    off = state.layers.references_off - {ref}
                    state.layers.references_off = off if cb.value else off | {ref}
                    on_change("layers")

            bind_ref()
        window = server.gui.add_slider(
            "Trail ± frames", min=0, max=100, step=1, initial_value=state.layers.trail_window
        )
        widths = tuple(f"{w} px" for w in FRUSTUM_WIDTHS)
        frustum_width = server.gui.add_dropdown(
            "Frustum video", widths, initial_value=f"{state.layers.frustum_image_width} px"
        )
        mesh_style = server.gui.add_dropdown(
            "Mesh style", MESH_STYLES, initial_value=state.layers.mesh_style,
            hint="translucent / wireframe bodies show the skeletons inside",
        )  # fmt: skip
        mesh_detail = server.gui.add_dropdown(
            "Mesh detail", MESH_DETAILS, initial_value=state.layers.mesh_detail,
            hint="decimated: ~1/6 of the faces, for the display only (exports are full)",
        )  # fmt: skip

    @mesh_style.on_update
    def _(_) -> None:
        state.layers.mesh_style = str(mesh_style.value)
        on_change("layers")

    @mesh_detail.on_update
    def _(_) -> None:
        state.layers.mesh_detail = str(mesh_detail.value)
        on_change("layers")

    @frustum_width.on_update
    def _(_) -> None:
        state.layers.frustum_image_width = int(frustum_width.value.split()[0])
        on_change("layers")

    @window.on_update
    def _(_) -> None:
        state.layers.trail_window = int(window.value)
        on_change("layers")

    for name in missing:
        toggles[name].disabled = True
    return LayersPanel(folder, toggles, window, frustum_width, mesh_style, mesh_detail)


@dataclass
class SelectionPanel:
    folder: viser.GuiFolderHandle
    track: viser.GuiDropdownHandle
    joint: viser.GuiDropdownHandle
    info: viser.GuiMarkdownHandle


NO_TRACK = "none"


def make_selection_panel(
    server: viser.ViserServer, state: ViewerState, on_change: OnChange
) -> SelectionPanel:
    data, sel = state.data, state.selection
    tracks = (NO_TRACK,) + tuple(str(k) for k in range(data.num_tracks))
    joints = data.joint_set.names or ("-",)
    with server.gui.add_folder("Selection") as folder:
        track = server.gui.add_dropdown(
            "Track", tracks, initial_value=NO_TRACK if sel.track is None else str(sel.track)
        )
        joint = server.gui.add_dropdown("Joint", joints, initial_value=joints[sel.joint])
        info = server.gui.add_markdown(selection_info(state))

    def update(_) -> None:
        t = None if track.value == NO_TRACK else int(track.value)
        j = joint.options.index(joint.value)
        state.selection = dataclasses.replace(state.selection, track=t, joint=j)
        on_change("selection")

    track.on_update(update)
    joint.on_update(update)
    return SelectionPanel(folder, track, joint, info)


@dataclass
class CameraPanel:
    panel: viser.PanelHandle
    camera: viser.GuiDropdownHandle
    image: viser.GuiImageHandle
    width: viser.GuiDropdownHandle
    legend: viser.GuiMarkdownHandle
    # shown by the page itself in software WebGL; in this panel, which is always in view
    software_notice: viser.GuiHtmlHandle


# What the camera panel's lines are (mvviz.scene.images.draw_overlay).
CAMERA_LEGEND = (
    "<small>**thick** lines, dots: 2D detections, coloured by the person they were "
    "associated to (**grey**: unassigned) · **thin**, rings: the filtered 3D result "
    "reprojected · **thin dark**, crosses: ground truth</small>"
)


def make_camera_panel(
    server: viser.ViserServer, state: ViewerState, on_change: OnChange
) -> CameraPanel:
    names = tuple(state.scene.rig.names)
    cam = state.scene.rig[state.camera]
    w = state.panel_image_width
    panel = server.gui.add_panel()
    with panel.add_tab("Camera", viser.Icon.CAMERA):
        camera = server.gui.add_dropdown("Camera", names, initial_value=names[state.camera])
        image = server.gui.add_image(
            blank_frame(w, round(cam.height * w / cam.width)),
            format="jpeg",
            jpeg_quality=PANEL_JPEG_QUALITY,
        )
        widths = tuple(f"{w} px" for w in PANEL_WIDTHS)
        legend = server.gui.add_markdown(CAMERA_LEGEND)
        width = server.gui.add_dropdown("Image width", widths, initial_value=f"{w} px")
        software_notice = server.gui.add_html(SOFTWARE_NOTICE_HTML)
    panel.dock_left()
    panel.set_width(400)

    @camera.on_update
    def _(_) -> None:
        state.camera = names.index(camera.value)
        state.selection = dataclasses.replace(state.selection, view=state.camera)
        on_change("camera")

    @width.on_update
    def _(_) -> None:
        state.panel_image_width = int(width.value.split()[0])
        on_change("camera")

    return CameraPanel(panel, camera, image, width, legend, software_notice)


# --------------------------------------------------------------------------- rendering


class ViewerApp:
    """The running viewer: server, scene layers, panels, render worker, playback."""

    def __init__(
        self,
        state: ViewerState,
        *,
        host: str = "127.0.0.1",
        port: int = 8080,
        frames: FrameStore | None = None,
        model: BodyModel | None = None,
        verbose: bool = False,
    ) -> None:
        self.state = state
        self.model = model  # the body model of the run (None: the shipped one)
        self.frames = frames
        self.state_changed: list[Callable[[ViewerState, str], None]] = []
        self.frame_times_ms: deque[float] = deque(maxlen=500)
        self._reasons: set[str] = set()
        self._reasons_lock = threading.Lock()
        self._stopped = threading.Event()
        self._play_wake = threading.Event()
        self._applied_layers: LayerToggles | None = None
        self.last_render_ms: dict[str, float] = {}
        self.render_errors: list[str] = []
        self._render_lock = threading.Lock()

        server = self.server = viser.ViserServer(host=host, port=port, verbose=verbose)
        server.gui.configure_theme(control_width="medium", show_share_button=False)
        # Dock both panels so the 3D canvas is the free space between them, and the
        # initial camera's look-at point lands in the middle of what is visible.
        server.gui.main_panel.dock_right()
        server.gui.main_panel.set_width(340)
        server.scene.set_up_direction("+z")
        self._set_initial_camera()
        self.layers = SceneLayers(server, state.data, on_joint_click=self._on_joint_click)
        # The timeline stays on top whatever tab is open (scrubbing while looking at a
        # failure, a filter or a layer is the point); below it one tab per panel.
        self.timeline = make_timeline_panel(server, state, self._on_change)
        self.tabs = tabs = server.gui.add_tab_group()
        with tabs.add_tab("Layers", viser.Icon.STACK_2):
            self.layers_panel = make_layers_panel(server, state, self._on_change)
        with tabs.add_tab("Selection", viser.Icon.POINTER):
            self.selection_panel = make_selection_panel(server, state, self._on_change)
        self.camera_panel = make_camera_panel(server, state, self._on_change)
        with tabs.add_tab("Pipeline", viser.Icon.ADJUSTMENTS):
            self.pipeline_panel = make_pipeline_panel(self, model=self.model)
        with tabs.add_tab("Filter A/B", viser.Icon.CHART_LINE):
            self.filter_panel = make_filter_panel(self)
        with tabs.add_tab("Failures", viser.Icon.ALERT_TRIANGLE):
            self.failure_panel = make_failure_panel(self)
        with tabs.add_tab("Export", viser.Icon.DOWNLOAD):
            self.export_panel = make_export_panel(self)
        for folder in (self.pipeline_panel.gui.folder, self.export_panel.gui.folder):
            folder.expand_by_default = True  # alone in its tab: open
        self._image_pool = ThreadPoolExecutor(1, thread_name_prefix="mvviz-images")
        self.last_image_cpu_ms = 0.0  # CPU time of the last frame's image job
        self._stats_shown_t = -np.inf
        self._renderer = LatestWins(self._render)
        self._player = threading.Thread(target=self._play_loop, name="mvviz-play", daemon=True)
        self._player.start()
        if frames is not None:
            frames.on_camera_ready.append(lambda _cam: self._on_change("video"))
        self._on_change("init")

    # ------------------------------------------------------------------ public hooks

    @property
    def url(self) -> str:
        host = self.server.get_host()
        host = "127.0.0.1" if host in ("0.0.0.0", "") else host
        return f"http://{host}:{self.server.get_port()}"

    def set_frame(self, frame: int) -> None:
        """Go to ``frame`` (moves the slider, which redraws)."""
        n = self.state.data.num_frames
        self.timeline.slider.value = int(np.clip(frame, 0, n - 1))

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
        sel = self.selection_panel
        if track is not None:
            sel.track.value = str(int(track)) if track >= 0 else NO_TRACK
        if joint is not None:
            names = self.state.data.joint_set.names
            sel.joint.value = joint if isinstance(joint, str) else names[int(joint)]
        if view is not None:
            names = self.state.scene.rig.names
            self.camera_panel.camera.value = view if isinstance(view, str) else names[int(view)]
        if frame is not None:
            self.set_frame(frame)

    def focus(self, target: np.ndarray, offset: np.ndarray | None = None) -> None:
        """Point every connected client's camera at ``target`` (world metres) from
        ``target + offset`` (default: 2.5 m away, from behind-left and above)."""
        target = np.asarray(target, float)
        offset = np.array([-1.4, -1.9, 1.0]) if offset is None else np.asarray(offset, float)
        for client in self.server.get_clients().values():
            client.camera.position = target + offset  # moves look_at along with it
            client.camera.look_at = target

    def redraw(self) -> None:
        self._on_change("redraw")

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
            self.layers = SceneLayers(self.server, data, on_joint_click=self._on_joint_click)
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
        sel = self.selection_panel
        sel.track.options = (NO_TRACK,) + tuple(str(k) for k in range(data.num_tracks))
        sel.joint.options = data.joint_set.names
        self._on_change("results")

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
        self._stopped.set()
        self._play_wake.set()
        self._renderer.stop()
        self._image_pool.shutdown(wait=True)
        self._player.join(timeout=5)
        self.server.stop()

    # ------------------------------------------------------------------ internals

    def _set_initial_camera(self) -> None:
        """Look at the action from behind and above the first camera (so its video faces
        the viewer), turned a little so that frustum does not hide the people."""
        data = self.state.data
        c = data.center.copy()
        c[2] = 0.9
        d = data.cameras[0].position[:2] - c[:2] if data.cameras else np.array([-1.0, -1.0])
        d = d / max(np.linalg.norm(d), 1e-6)
        a = np.deg2rad(30.0)
        d = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]) @ d
        r = max(3.5, 2.0 * data.spread + 1.5)
        pos = np.array([c[0] + d[0] * r, c[1] + d[1] * r, c[2] + 0.55 * r])
        self.server.initial_camera.position = tuple(pos)
        self.server.initial_camera.look_at = tuple(c)
        self.server.initial_camera.up = (0.0, 0.0, 1.0)
        self.server.initial_camera.fov = np.deg2rad(50.0)

    def _on_joint_click(self, track: int, joint: int) -> None:
        if 0 <= joint < self.state.data.joint_set.num_joints:
            self.jump_to(track=track, joint=joint)

    def _on_change(self, reason: str) -> None:
        with self._reasons_lock:
            self._reasons.add(reason)
        if reason == "playing":
            self._play_wake.set()
            self.timeline.play.label = "Pause" if self.state.playing else "Play"
            self.timeline.play.icon = (
                viser.Icon.PLAYER_PAUSE if self.state.playing else viser.Icon.PLAYER_PLAY
            )
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
    ) -> tuple[dict[str, tuple[object, np.ndarray | None]], np.ndarray]:
        """The frustums' images (camera name -> (key, image or None)) and the camera
        panel's picture with its overlay, for ``st``'s frame. Runs on the image thread."""
        t0 = time.thread_time()
        f, lay, data = st.frame, st.layers, st.data
        images: dict[str, tuple[object, np.ndarray | None]] = {}
        fw = lay.frustum_image_width
        for cam in data.cameras:
            img = None
            if lay.frustum_images and lay.cameras and self.frames is not None:
                img = self.frames.small(cam.name, f, fw)
            images[cam.name] = ((f, fw) if img is not None else None, img)
        camera = st.scene.rig[st.camera]
        w = st.panel_image_width
        h = max(1, round(camera.height * w / camera.width))
        base = self.frames.frame(camera.name, f) if self.frames is not None else None
        if base is None:
            base = blank_frame(w, h)
        elif base.shape[1] != w:  # overlays are drawn after resizing: crisp at any width
            # bilinear up to 2x down (~7x faster than INTER_AREA here, little aliasing)
            interp = cv2.INTER_AREA if base.shape[1] > 2 * w else cv2.INTER_LINEAR
            base = cv2.resize(base, (w, h), interpolation=interp)
        panel_image = draw_overlay(base, image_overlay(data, st.camera, f, lay))
        self.last_image_cpu_ms = (time.thread_time() - t0) * 1e3
        return images, panel_image

    def _render_locked(self) -> None:
        t0 = time.perf_counter()
        with self._reasons_lock:
            reasons, self._reasons = self._reasons, set()
        st = self.state.snapshot()
        f, lay = st.frame, st.layers
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
            self.timeline.label.content = frame_label(st, f)
            self.selection_panel.info.content = selection_info(st)
            t2 = time.perf_counter()
            images, panel_image = images_job.result()
            t3 = time.perf_counter()
            self.layers.set_frustum_images(images)
            self.camera_panel.image.image = panel_image
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
            self.timeline.stats.content = (
                f"<small>server render {ms:.0f} ms (median {s['median_ms']:.0f}, "
                f"p95 {s['p95_ms']:.0f})</small>"
            )
        reason = ",".join(sorted(reasons)) or "redraw"
        for cb in list(self.state_changed):
            try:
                cb(st, reason)
            except Exception as exc:
                print(f"mvviz view: state_changed callback failed: {exc}")

    def _play_loop(self) -> None:
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
            if delay > 0:
                time.sleep(delay)
            else:
                next_t = time.perf_counter()  # fell behind: frames get skipped, not queued
            f = st.frame + 1
            if f >= st.data.num_frames:
                if not st.loop:
                    st.playing = False
                    self._on_change("playing")
                    continue
                f = 0
            self.set_frame(f)
