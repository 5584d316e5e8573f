"""The viewer's own panels: the timeline, the layer toggles, the selection and the
camera image panel, each ``make_<name>_panel(host) -> <Name>Panel`` over the panel
contract (:mod:`mvviz.panels.contract`) like every other panel.

Their callbacks change the state (frame, layers, selection, camera) and call
``host.redraw(reason)``; the app calls the controllers' ``show_*`` methods while it
renders (inside one ``server.atomic()``) and :meth:`SelectionPanel.select`,
:meth:`CameraPanel.show_view`, :meth:`TimelinePanel.set_frame` for ``jump_to``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import viser

from mvviz.analysis.failures import Failure, seeing_view
from mvviz.analysis.joint_views import joint_views, joint_views_markdown
from mvviz.analysis.timeline_strip import (
    draw_failure_strip,
    legend_html,
    next_failure,
    playhead_html,
)
from mvviz.panels.contract import PanelHost
from mvviz.panels.failure_panel import CRITERION_SHORT
from mvviz.scene.geometry import FRUSTUM_WIDTHS, MESH_DETAILS, MESH_STYLES
from mvviz.scene.images import BodyOutlines, blank_frame, bodies_text
from mvviz.state import PANEL_WIDTHS, ViewerState
from pipeline.evaluation.evaluate import fit_distance_frames

SPEEDS = ("0.25x", "0.5x", "1x", "2x", "4x")
STEP_BACK, STEP_FORWARD = "◀ −1", "+1 ▶"
PREV_FAILURE, NEXT_FAILURE = "◀ failure", "failure ▶"
FINDING_FAILURES = '<div style="font-size:0.75em">finding failures…</div>'
PANEL_JPEG_QUALITY = 65
NO_TRACK = "none"


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
    fits = fit_distance_markdown(res, k)  # the track's bodies, before the joint's views
    if fits:
        lines += ["", fits]
    lines.append("")  # each view's part in this joint, and why a view was left out
    lines.append(joint_views_markdown(joint_views(data, k, j, f)))
    return "\n".join(lines)


FIT_LABELS = {"smpl": "step I", "smpl_vae": "SMPL + VAE", "floor": "floor"}


def fit_distance_markdown(results, track: int) -> str:
    """The track's body fits against their input (median over its frames), next to the
    floor of constant bone lengths; empty without fits."""
    if results.smpl is None and results.smpl_vae is None:
        return ""
    medians = {}
    for name, v in fit_distance_frames(results, track).items():
        v = v[np.isfinite(v)]
        if v.size:
            medians[name] = float(np.median(v))
    if not medians:
        return ""
    order = [n for n in ("smpl", "smpl_vae", "floor") if n in medians]
    parts = [f"{FIT_LABELS[n]} {medians[n]:.1f}" for n in order]
    text = "body fit vs its input (mm, median over the track): " + " · ".join(parts)
    if "floor" in medians:
        text += (
            "  \n_floor: the best skeleton of constant bone lengths, how far the input "
            "itself is from rigid_"
        )
    return text


def frame_label(state: ViewerState, frame: int) -> str:
    n, fps = state.data.num_frames, state.scene.fps
    return f"frame **{frame}** / {n - 1} · {frame / fps:.2f} s"


# --------------------------------------------------------------------------- timeline


@dataclass
class TimelineHandles:
    folder: viser.GuiFolderHandle
    slider: viser.GuiSliderHandle
    playhead: viser.GuiHtmlHandle  # the current frame, over the failure strip
    strip: viser.GuiImageHandle  # frame ticks and the failure marks (draw_failure_strip)
    legend: viser.GuiHtmlHandle  # the strip's colours, entries per criterion
    jump: viser.GuiButtonGroupHandle  # PREV_FAILURE / NEXT_FAILURE
    play: viser.GuiButtonHandle
    step: viser.GuiButtonGroupHandle  # STEP_BACK / STEP_FORWARD
    speed: viser.GuiDropdownHandle
    loop: viser.GuiCheckboxHandle
    label: viser.GuiMarkdownHandle
    stats: viser.GuiMarkdownHandle


class TimelinePanel:
    """Frame slider; under it, as wide as the panel, the playhead and the failure strip
    (frame ticks, a mark per failure span in its criterion's colour) with its legend and
    previous / next failure buttons; play / step / speed / loop, the frame label and the
    render time. ``failures`` are the marks drawn (:meth:`show_failures`)."""

    def __init__(self, host: PanelHost) -> None:
        self.host = host
        self.gui = make_timeline_handles(host.server, host.state)
        self.failures: tuple[Failure, ...] = ()
        self.criteria: tuple[str, ...] = ()
        self._playhead_frame = 0
        self._strip_frames = host.state.data.num_frames
        self._bind()

    def set_frame(self, frame: int) -> None:
        """Go to ``frame`` (moves the slider, whose callback redraws)."""
        n = self.host.state.data.num_frames
        self.gui.slider.value = int(np.clip(frame, 0, n - 1))

    def show_frame(self, state: ViewerState) -> None:
        self.gui.label.content = frame_label(state, state.frame)
        n = state.data.num_frames
        if (state.frame, n) != (self._playhead_frame, self._strip_frames):
            self.gui.playhead.content = playhead_html(n, state.frame)
            self._playhead_frame = state.frame
            if n != self._strip_frames:  # other results of another length: marks redrawn
                self._strip_frames = n
                self.show_failures(self.failures, self.criteria)

    def show_failures(self, failures: Sequence[Failure], criteria: Sequence[str]) -> None:
        """Draw ``failures`` on the strip, one lane per criterion of ``criteria``."""
        self.failures, self.criteria = tuple(failures), tuple(criteria)
        n = self.host.state.data.num_frames
        self.gui.strip.image = draw_failure_strip(n, self.failures, criteria=self.criteria)
        counts = {c: sum(f.criterion == c for f in self.failures) for c in self.criteria}
        self.gui.legend.content = legend_html(counts, CRITERION_SHORT)  # the Failures tab's names

    def jump_to_failure(self, direction: int) -> Failure | None:
        """Go to the start of the next (``direction`` > 0) or previous failure span after
        the current frame, select its track and joint and show a camera that sees it."""
        failure = next_failure(self.failures, self.host.state.frame, direction)
        if failure is None:
            return None
        data = self.host.state.data
        at_start = dataclasses.replace(failure, frame=failure.first)
        view = None
        if failure.track is None or 0 <= failure.track < data.num_tracks:
            view = seeing_view(data.scene, data.results, at_start)
        track = failure.track if failure.track is not None else None
        self.host.jump_to(failure.first, track, failure.joint, view)
        return failure

    def show_playing(self, playing: bool) -> None:
        self.gui.play.label = "Pause" if playing else "Play"
        self.gui.play.icon = viser.Icon.PLAYER_PAUSE if playing else viser.Icon.PLAYER_PLAY

    def show_stats(self, text: str) -> None:
        self.gui.stats.content = text

    def stop(self) -> None:
        pass  # no threads

    def _bind(self) -> None:
        g, host, state = self.gui, self.host, self.host.state

        @g.slider.on_update
        def _(_) -> None:
            state.frame = int(g.slider.value)
            host.redraw("frame")

        @g.play.on_click
        def _(_) -> None:
            state.playing = not state.playing
            host.redraw("playing")

        @g.step.on_click
        def _(event) -> None:
            delta = -1 if event.target.value == STEP_BACK else 1
            self.set_frame(int(g.slider.value) + delta)

        @g.jump.on_click
        def _(event) -> None:
            self.jump_to_failure(-1 if event.target.value == PREV_FAILURE else 1)

        @g.speed.on_update
        def _(_) -> None:
            state.speed = float(g.speed.value.rstrip("x"))

        @g.loop.on_update
        def _(_) -> None:
            state.loop = bool(g.loop.value)


def make_timeline_handles(server: viser.ViserServer, state: ViewerState) -> TimelineHandles:
    n = state.data.num_frames
    with server.gui.add_folder("Timeline") as folder:
        slider = server.gui.add_slider("Frame", min=0, max=max(n - 1, 0), step=1, initial_value=0)
        playhead = server.gui.add_html(playhead_html(n, 0))
        strip = server.gui.add_image(draw_failure_strip(n, (), criteria=()), format="png")
        legend = server.gui.add_html(FINDING_FAILURES)
        jump = server.gui.add_button_group("Go to", (PREV_FAILURE, NEXT_FAILURE))
        label = server.gui.add_markdown(frame_label(state, 0))
        play = server.gui.add_button("Play", icon=viser.Icon.PLAYER_PLAY)
        step = server.gui.add_button_group("Step", (STEP_BACK, STEP_FORWARD))
        speed = server.gui.add_dropdown("Speed", SPEEDS, initial_value="1x")
        loop = server.gui.add_checkbox("Loop", initial_value=state.loop)
        stats = server.gui.add_markdown("")
    return TimelineHandles(
        folder, slider, playhead, strip, legend, jump, play, step, speed, loop, label, stats
    )


def make_timeline_panel(host: PanelHost) -> TimelinePanel:
    """The "Timeline" folder (above the tabs)."""
    return TimelinePanel(host)


# --------------------------------------------------------------------------- layers


@dataclass
class LayersHandles:
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
    "detections2d_panel_camera_only": "2D detections: panel camera only",
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
    "bodies_on_images": "Fitted bodies on the camera image",
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


class LayersPanel:
    """One checkbox per layer (those the scene and run cannot show: off and disabled),
    trails, frustum video width, mesh style and detail."""

    def __init__(self, host: PanelHost) -> None:
        self.host = host
        state = host.state
        missing = [
            name
            for name, absent in (
                ("gt", state.data.gt_points is None),
                ("meshes", state.data.bodies is None),
                ("fit_meshes", state.data.fit_bodies is None),
                ("bodies_on_images", state.data.fit_bodies is None),
            )
            if absent
        ]
        for name in missing:
            setattr(state.layers, name, False)
        self.gui = make_layers_handles(host.server, state)
        self._bind()
        for name in missing:
            self.gui.toggles[name].disabled = True

    def stop(self) -> None:
        pass  # no threads

    def _bind(self) -> None:
        g, host, lay = self.gui, self.host, self.host.state.layers

        def bind(name: str, cb: viser.GuiCheckboxHandle) -> None:
            @cb.on_update
            def _(_) -> None:
                if name.startswith("reference:"):
                    ref = name.split(":", 1)[1]
                    off = lay.references_off - {ref}
                    lay.references_off = off if cb.value else off | {ref}
                else:
                    setattr(lay, name, bool(cb.value))
                host.redraw("layers")

        for name, cb in g.toggles.items():
            bind(name, cb)

        @g.mesh_style.on_update
        def _(_) -> None:
            lay.mesh_style = str(g.mesh_style.value)
            host.redraw("layers")

        @g.mesh_detail.on_update
        def _(_) -> None:
            lay.mesh_detail = str(g.mesh_detail.value)
            host.redraw("layers")

        @g.frustum_width.on_update
        def _(_) -> None:
            lay.frustum_image_width = int(g.frustum_width.value.split()[0])
            host.redraw("layers")

        @g.trail_window.on_update
        def _(_) -> None:
            lay.trail_window = int(g.trail_window.value)
            host.redraw("layers")


def make_layers_handles(server: viser.ViserServer, state: ViewerState) -> LayersHandles:
    lay = state.layers
    with server.gui.add_folder("Layers") as folder:
        toggles = {
            name: server.gui.add_checkbox(label, initial_value=getattr(lay, name))
            for name, label in LAYER_LABELS.items()
        }
        for ref in state.scene.references:  # one checkbox per reference track
            toggles[f"reference:{ref}"] = server.gui.add_checkbox(
                f"Reference: {ref}", initial_value=ref not in lay.references_off
            )
        window = server.gui.add_slider(
            "Trail ± frames", min=0, max=100, step=1, initial_value=lay.trail_window
        )
        widths = tuple(f"{w} px" for w in sorted({*FRUSTUM_WIDTHS, lay.frustum_image_width}))
        frustum_width = server.gui.add_dropdown(
            "Frustum video", widths, initial_value=f"{lay.frustum_image_width} px"
        )
        mesh_style = server.gui.add_dropdown(
            "Mesh style", MESH_STYLES, initial_value=lay.mesh_style,
            hint="translucent / wireframe bodies show the skeletons inside",
        )  # fmt: skip
        mesh_detail = server.gui.add_dropdown(
            "Mesh detail", MESH_DETAILS, initial_value=lay.mesh_detail,
            hint="decimated: ~1/6 of the faces, for the display only (exports are full)",
        )  # fmt: skip
    return LayersHandles(folder, toggles, window, frustum_width, mesh_style, mesh_detail)


def make_layers_panel(host: PanelHost) -> LayersPanel:
    """The "Layers" folder."""
    return LayersPanel(host)


# --------------------------------------------------------------------------- selection


@dataclass
class SelectionHandles:
    folder: viser.GuiFolderHandle
    track: viser.GuiDropdownHandle
    joint: viser.GuiDropdownHandle
    info: viser.GuiMarkdownHandle


class SelectionPanel:
    """Track and joint dropdowns and what is known about the selected joint."""

    def __init__(self, host: PanelHost) -> None:
        self.host = host
        self.gui = make_selection_handles(host.server, host.state)
        self.gui.track.on_update(self._update)
        self.gui.joint.on_update(self._update)

    def select(self, track: int | None = None, joint: int | str | None = None) -> None:
        """Select ``track`` (negative: none) and ``joint`` (index or name); None keeps."""
        g = self.gui
        if track is not None:
            g.track.value = str(int(track)) if track >= 0 else NO_TRACK
        if joint is not None:
            names = self.host.state.data.joint_set.names
            g.joint.value = joint if isinstance(joint, str) else names[int(joint)]

    def set_choices(self, num_tracks: int, joint_names: tuple[str, ...]) -> None:
        """The dropdowns' options for new results."""
        self.gui.track.options = (NO_TRACK,) + tuple(str(k) for k in range(num_tracks))
        self.gui.joint.options = joint_names

    def show(self, state: ViewerState) -> None:
        self.gui.info.content = selection_info(state)

    def stop(self) -> None:
        pass  # no threads

    def _update(self, _) -> None:
        g, state = self.gui, self.host.state
        t = None if g.track.value == NO_TRACK else int(g.track.value)
        j = g.joint.options.index(g.joint.value)
        state.selection = dataclasses.replace(state.selection, track=t, joint=j)
        self.host.redraw("selection")


def make_selection_handles(server: viser.ViserServer, state: ViewerState) -> SelectionHandles:
    data, sel = state.data, state.selection
    tracks = (NO_TRACK,) + tuple(str(k) for k in range(data.num_tracks))
    joints = data.joint_set.names or ("-",)
    with server.gui.add_folder("Selection") as folder:
        track = server.gui.add_dropdown(
            "Track", tracks, initial_value=NO_TRACK if sel.track is None else str(sel.track)
        )
        joint = server.gui.add_dropdown("Joint", joints, initial_value=joints[sel.joint])
        info = server.gui.add_markdown(selection_info(state))
    return SelectionHandles(folder, track, joint, info)


def make_selection_panel(host: PanelHost) -> SelectionPanel:
    """The "Selection" folder."""
    return SelectionPanel(host)


# --------------------------------------------------------------------------- camera


@dataclass
class CameraHandles:
    panel: viser.PanelHandle
    camera: viser.GuiDropdownHandle
    image: viser.GuiImageHandle
    width: viser.GuiDropdownHandle
    legend: viser.GuiMarkdownHandle
    bodies: viser.GuiHtmlHandle  # each track's fitted body vs its 2D, when they are drawn
    # shown by the page itself in software WebGL; in this panel, which is always in view
    software_notice: viser.GuiHtmlHandle


# What the camera panel's lines are (mvviz.scene.images.draw_overlay).
CAMERA_LEGEND = (
    "<small>**thick** lines, dots: 2D detections, coloured by the person they were "
    "associated to (**grey**: unassigned) · **thin**, rings: the filtered 3D result "
    "reprojected · **thin dark**, crosses: ground truth · **filled outlines**: the fitted "
    'bodies (layer "Fitted bodies on the camera image")</small>'
)


class CameraPanel:
    """The left-docked panel: one camera's picture with the 2D overlays, its legend."""

    def __init__(self, host: PanelHost) -> None:
        self.host = host
        self.gui = make_camera_handles(host.server, host.state)
        self._bind()

    def show_view(self, view: int | str) -> None:
        """Show camera ``view`` (index or name)."""
        names = self.host.state.scene.rig.names
        self.gui.camera.value = view if isinstance(view, str) else names[int(view)]

    def show_image(self, image: np.ndarray) -> None:
        self.gui.image.image = image

    def show_bodies(self, bodies: BodyOutlines | None) -> None:
        """Each track's fitted body vs its 2D, for the bodies drawn on the picture."""
        text = bodies_text(bodies)
        if text != self.gui.bodies.content:  # not re-sent on every frame
            self.gui.bodies.content = text

    def stop(self) -> None:
        pass  # no threads

    def _bind(self) -> None:
        g, host, state = self.gui, self.host, self.host.state
        names = tuple(state.scene.rig.names)

        @g.camera.on_update
        def _(_) -> None:
            state.camera = names.index(g.camera.value)
            state.selection = dataclasses.replace(state.selection, view=state.camera)
            host.redraw("camera")

        @g.width.on_update
        def _(_) -> None:
            state.panel_image_width = int(g.width.value.split()[0])
            host.redraw("camera")


def make_camera_handles(server: viser.ViserServer, state: ViewerState) -> CameraHandles:
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
        bodies = server.gui.add_html("")
        legend = server.gui.add_markdown(CAMERA_LEGEND)
        width = server.gui.add_dropdown("Image width", widths, initial_value=f"{w} px")
        software_notice = server.gui.add_html(SOFTWARE_NOTICE_HTML)
    panel.dock_left()
    panel.set_width(400)
    return CameraHandles(panel, camera, image, width, legend, bodies, software_notice)


def make_camera_panel(host: PanelHost) -> CameraPanel:
    """The camera image panel, docked left."""
    return CameraPanel(host)
