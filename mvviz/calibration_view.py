"""The calibration view: what ``mvviz calibrate`` saw, in the browser.

``mvviz view OUT`` (or ``python app.py OUT``) on a calibration folder opens it: the
cameras as frusta, the board at each pose the calibration found (coloured by time; a
click on one selects its frame), the reprojection error of each camera over the frames
(a chart), and the selected view: that camera's frame with its corners as detected
(green rings) and as reprojected by the bundle adjustment (red crosses). Per camera, the
figures of ``calibration_report.html``: frames with the board, RMS error, estimated time
offset, and why a camera was not calibrated. A camera clicked in the 3D view or picked
in the list shows its view of the selected frame; "worst view" jumps to the view with the
largest error.

It reads ``OUT/calibration.npz`` and ``OUT/cameras.json``
(:mod:`pipeline.data.calibration_views`, :mod:`pipeline.data.cameras`) and nothing of the
calibration step. World in mm in the files, metres in the 3D view.
"""

from __future__ import annotations

import threading
from pathlib import Path

import cv2
import numpy as np
import viser
import viser.uplot

from mvviz.scene.geometry import MM, camera_geometry
from pipeline.core.files import SceneFormatError
from pipeline.data.calibration_views import (
    CALIBRATION_VIEWS,
    CalibrationViews,
    load_calibration_views,
)
from pipeline.data.cameras import CameraRig, load_cameras

ROOT = "/calibration"
PANEL_WIDTH = 480
IMAGE_WIDTH = 456
EMBEDDED_IMAGE_WIDTH = 320  # the scene viewer's panel is 340 px wide
# camera colours (RGB), in order
PALETTE = np.array([
    [31, 119, 180], [255, 127, 14], [44, 160, 44], [214, 39, 40], [148, 103, 189],
    [140, 86, 75], [227, 119, 194], [127, 127, 127], [188, 189, 34], [23, 190, 207],
])  # fmt: skip
SELECTED = (255, 140, 0)
SUSPECT_RMS_PX = 1.0  # a camera's RMS error above it is flagged
DETECTED_BGR = (60, 220, 60)
REPROJECTED_BGR = (40, 40, 255)


def load_calibration_folder(folder: str | Path) -> tuple[CalibrationViews, CameraRig]:
    """The saved views and the calibrated cameras of a ``mvviz calibrate`` output."""
    folder = Path(folder)
    views = load_calibration_views(folder / CALIBRATION_VIEWS)
    rig = load_cameras(folder / "cameras.json")
    missing = [c.name for c in views.cameras if c.calibrated and c.name not in rig.names]
    if missing:
        raise SceneFormatError(
            folder / "cameras.json", None,
            f"the calibration's cameras {missing} are not in it (written by another run?)",
        )  # fmt: skip
    return views, rig


def time_colours(n: int) -> np.ndarray:
    """(n, 3) uint8: dark blue (first) through green to yellow (last), viridis-like."""
    stops = np.array([[68, 1, 84], [59, 82, 139], [33, 145, 140], [94, 201, 98], [253, 231, 37]])
    x = np.linspace(0, 1, max(n, 1))[:n] * (len(stops) - 1)
    i = np.minimum(x.astype(int), len(stops) - 2)
    w = (x - i)[:, None]
    return ((1 - w) * stops[i] + w * stops[i + 1]).round().astype(np.uint8)


def board_outline(views: CalibrationViews) -> np.ndarray:
    """(4, 3) the board's outer corners in board coordinates, mm (squares included)."""
    b = views.board
    w, h = b["columns"] * b["square_mm"], b["rows"] * b["square_mm"]
    return np.array([[0, 0, 0], [w, 0, 0], [w, h, 0], [0, h, 0]], float)


def board_grid(views: CalibrationViews) -> np.ndarray:
    """(S, 2, 3) the board's square edges in board coordinates, mm."""
    b = views.board
    s, c, r = b["square_mm"], b["columns"], b["rows"]
    segs = [[[i * s, 0, 0], [i * s, r * s, 0]] for i in range(c + 1)]
    segs += [[[0, j * s, 0], [c * s, j * s, 0]] for j in range(r + 1)]
    return np.array(segs, float)


def view_window(
    points: np.ndarray, image_size: tuple[int, int], *, zoom: bool
) -> tuple[float, float, float]:
    """(x0, y0, w) of the image region to show, in image pixels, of the image's aspect:
    the whole image, or with ``zoom`` the corners ``points`` (N, 2) with a margin."""
    iw, ih = image_size
    pts = points[np.all(np.isfinite(points), axis=1)]
    if not zoom or not len(pts):
        return 0.0, 0.0, float(iw)
    lo, hi = pts.min(0), pts.max(0)
    aspect = iw / ih
    w = float(np.clip(max(2.0 * (hi - lo)[0], 2.0 * (hi - lo)[1] * aspect, iw / 5), 1, iw))
    h = w / aspect
    cx, cy = (lo + hi) / 2
    x0 = float(np.clip(cx - w / 2, 0, iw - w))
    y0 = float(np.clip(cy - h / 2, 0, ih - h))
    return x0, y0, w


def draw_view(
    views: CalibrationViews, camera: int, frame: int, *, width: int = IMAGE_WIDTH,
    zoom: bool = True,
) -> tuple[np.ndarray, str]:  # fmt: skip
    """(H, W, 3) RGB picture of ``camera``'s view of the board at ``frame`` (its frame,
    the corners as detected and as reprojected; with ``zoom`` the region of the board)
    and a line saying what it shows."""
    cam = views.cameras[camera]
    iw, ih = cam.image_size
    height = max(1, round(ih * width / iw))
    k = views.find_view(camera, frame)
    det = rep = np.zeros((0, 2))
    if k is not None:
        _, det, rep = views.corners(k)
    x0, y0, w = view_window(np.concatenate([det, rep]), (iw, ih), zoom=zoom)
    s = width / w  # output pixels per image pixel
    jpeg = None if k is None else views.thumbnail(k)
    if jpeg:
        grey = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_GRAYSCALE)
        ts = cam.thumb_scale
        # pixel centres: image u = (thumbnail t + 0.5) / ts - 0.5; output o = (u - x0) s
        M = np.array([[s / ts, 0, (0.5 / ts - 0.5 - x0) * s],
                      [0, s / ts, (0.5 / ts - 0.5 - y0) * s]])  # fmt: skip
        image = cv2.warpAffine(grey, M, (width, height), flags=cv2.INTER_LINEAR)
        image = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    else:
        image = np.full((height, width, 3), 40, np.uint8)
    if k is None:
        cv2.putText(image, f"{cam.name} does not see the board in frame {frame}",
                    (10, height // 2), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (220, 220, 220), 1,
                    cv2.LINE_AA)  # fmt: skip
        return cv2.cvtColor(image, cv2.COLOR_BGR2RGB), f"**{cam.name}**, frame {frame}: no board"
    origin = np.array([x0, y0])
    ring = max(4, round(1.5 * s))
    for d, r in zip((det - origin) * s, (rep - origin) * s, strict=True):
        dp = tuple(np.round(d).astype(int))
        cv2.circle(image, dp, ring, DETECTED_BGR, 1, cv2.LINE_AA)
        if np.all(np.isfinite(r)):
            rp = tuple(np.round(r).astype(int))
            cv2.line(image, dp, rp, REPROJECTED_BGR, 1, cv2.LINE_AA)
            cv2.drawMarker(image, rp, REPROJECTED_BGR, cv2.MARKER_CROSS, 2 * ring, 1, cv2.LINE_AA)
    err = np.linalg.norm(rep - det, axis=1)
    where = "" if w >= iw else f" (zoomed x{iw / w:.1f})"
    if np.isfinite(err).any():
        line = (f"**{cam.name}**, frame {frame}: {len(det)} corners, RMS "
                f"{np.sqrt(np.nanmean(err**2)):.2f} px, max {np.nanmax(err):.2f} px"
                f"{where}")  # fmt: skip
    else:
        line = f"**{cam.name}**, frame {frame}: {len(det)} corners (camera not calibrated){where}"
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB), line


def camera_table(views: CalibrationViews) -> str:
    """The per-camera figures as a markdown table, then why a camera was not calibrated."""
    rows = ["| camera | board | RMS px | time offset | |", "|---|---:|---:|---:|---|"]
    for c in views.cameras:
        rms = f"{c.ba_rms:.2f}" if np.isfinite(c.ba_rms) else "-"
        off = "-"
        if np.isfinite(c.sync_offset_frames):
            off = f"{round(c.sync_offset_frames, 2) + 0.0:+.2f} fr"  # + 0.0: no "-0.00"
            if np.isfinite(c.sync_offset_s):
                off += f" ({round(1000 * c.sync_offset_s) + 0.0:+.0f} ms)"
        notes = []
        if c.problem:
            notes.append("not calibrated")
        if abs(c.sync_offset_frames) >= 0.5:
            notes.append("check the sync")
        if c.ba_rms > SUSPECT_RMS_PX:
            notes.append("large error: check its intrinsics and views")
        note = "; ".join(notes)
        rows.append(f"| {c.name} | {c.board_frames}/{c.frames} | {rms} | {off} | {note} |")
    problems = [f"- **{c.name}** not calibrated: {c.problem}" for c in views.cameras if c.problem]
    return "\n".join(rows + ([""] + problems if problems else []))


class CalibrationView:
    """The calibration's scene nodes and GUI on a viser server (see the module docstring).

    ``camera`` and ``frame`` say which view is shown; :meth:`select` changes them.
    ``embedded``: a tab of the scene viewer (the GUI goes where the caller opened it; the
    scene's own cameras and up direction stay; the boards are drawn when asked)."""

    def __init__(
        self, server: viser.ViserServer, views: CalibrationViews, rig: CameraRig,
        *, embedded: bool = False,
    ) -> None:  # fmt: skip
        self.server, self.views, self.rig = server, views, rig
        self.embedded = embedded
        self._lock = threading.RLock()
        self._showing = False  # set while _show moves the widgets: their callbacks wait
        self.rms = views.view_rms()
        frames = np.unique(views.view_frame)
        self.frames = frames if len(frames) else np.zeros(1, np.int64)
        seen = [c for c in range(len(views.cameras)) if (views.view_camera == c).any()]
        self.camera = seen[0] if seen else 0
        self.frame = int(self.frames[0])
        self._add_scene()
        self._add_gui()
        self.select(self.camera, self._best_frame(self.camera))

    # ------------------------------------------------------------------ building

    def _add_scene(self) -> None:
        views, scene = self.views, self.server.scene
        self.group = scene.add_frame(ROOT, show_axes=False, visible=not self.embedded)
        if not self.embedded:
            scene.set_up_direction("+z" if views.z_up else "-y")
            scene.add_frame(f"{ROOT}/world", axes_length=0.15, axes_radius=0.004)
        self.frusta: dict[int, viser.CameraFrustumHandle] = {}
        for c, figures in enumerate(views.cameras):
            if self.embedded or not figures.calibrated or figures.name not in self.rig.names:
                continue
            g = camera_geometry(self.rig[self.rig.index_of(figures.name)], plane_depth=0.2)
            base = f"{ROOT}/cameras/{figures.name}"
            scene.add_frame(base, show_axes=False, wxyz=g.wxyz, position=g.position)
            frustum = scene.add_camera_frustum(
                f"{base}/frustum", fov=g.fov, aspect=g.aspect, scale=g.frustum_scale,
                color=tuple(int(v) for v in PALETTE[c % len(PALETTE)]), thickness=2.0,
                thickness_units="screen",
            )  # fmt: skip
            frustum.on_click(lambda _e, c=c: self.select(camera=c))
            self.frusta[c] = frustum
            scene.add_label(f"{base}/label", figures.name, position=(0.0, 0.0, 0.0))
        # every board pose: a translucent quad coloured by time (click: its frame) and
        # its squares as lines
        outline, grid = board_outline(views) * MM, board_grid(views) * MM
        colours = time_colours(len(views.pose_frame))
        segments, segment_colours = [], []
        for i, (frame, T) in enumerate(zip(views.pose_frame, views.T_world_board, strict=True)):
            R, t = T[:3, :3], T[:3, 3] * MM
            quad = scene.add_mesh_simple(
                f"{ROOT}/boards/{int(frame)}", outline @ R.T + t,
                np.array([[0, 1, 2], [0, 2, 3]]), color=tuple(int(v) for v in colours[i]),
                opacity=0.35, side="double",
            )  # fmt: skip
            quad.on_click(lambda _e, f=int(frame): self.select(frame=f))
            segments.append(grid @ R.T + t)
            segment_colours.append(np.broadcast_to(colours[i], (len(grid), 2, 3)))
        if segments:
            scene.add_line_segments(
                f"{ROOT}/board_lines", np.concatenate(segments).astype(np.float32),
                np.concatenate(segment_colours), thickness=1.0, thickness_units="screen",
            )  # fmt: skip
        self.selected_board = scene.add_line_segments(
            f"{ROOT}/selected_board", grid.astype(np.float32), SELECTED, thickness=3.0,
            thickness_units="screen", visible=False,
        )  # fmt: skip
        if not self.embedded:
            self._frame_camera_view()

    def _frame_camera_view(self) -> None:
        """Start the page's camera behind the cameras, looking at the boards."""
        views = self.views
        if not len(views.T_world_board) or not self.rig.names:
            return
        target = np.median(views.T_world_board[:, :3, 3], axis=0) * MM
        centres = np.array([c.center for c in self.rig]) * MM
        away = centres.mean(0) - target
        up = np.array([0, 0, 1.0]) if views.z_up else np.array([0, -1.0, 0])
        dist = max(1.5, 2.2 * np.linalg.norm(away))
        pos = target + away / max(np.linalg.norm(away), 1e-6) * dist + 0.5 * dist * up
        self.server.initial_camera.position = tuple(pos)
        self.server.initial_camera.look_at = tuple(target)
        self.server.initial_camera.up = tuple(up)

    def _add_gui(self) -> None:
        views, gui = self.views, self.server.gui
        if not self.embedded:
            gui.configure_theme(control_width="large", show_share_button=False)
            gui.main_panel.dock_right()
            gui.main_panel.set_width(PANEL_WIDTH)
        calibrated = sum(c.calibrated for c in views.cameras)
        world = (f"the board on the floor in frame {views.world.split(':', 1)[1]} (z up)"
                 if views.z_up else f"{views.world.split(':', 1)[1]}'s frame")  # fmt: skip
        gui.add_markdown(
            f"**Calibration**: {calibrated} of {len(views.cameras)} cameras, "
            f"{len(views.pose_frame)} board poses, {views.num_views} views; world: {world}"
        )
        self.table = gui.add_markdown(camera_table(views))
        if self.embedded:
            self.show_boards = gui.add_checkbox("Board poses in 3D", False)
            self.show_boards.on_update(
                lambda _e: setattr(self.group, "visible", self.show_boards.value)
            )
        self.chart = self._add_chart()
        names = [c.name for c in views.cameras]
        self.camera_choice = gui.add_dropdown("Camera", names, initial_value=names[self.camera])
        self.camera_choice.on_update(lambda _e: self.select(camera=names.index(
            self.camera_choice.value)))  # fmt: skip
        lo, hi = int(self.frames.min()), int(self.frames.max())
        self.frame_slider = gui.add_slider("Frame", lo, max(hi, lo + 1), 1, self.frame)
        self.frame_slider.on_update(lambda _e: self.select(frame=int(self.frame_slider.value)))
        buttons = gui.add_button_group("Views", ["◀ previous", "next ▶", "worst view"])
        buttons.on_click(lambda e: self._step(e.target.value))
        self.zoom = gui.add_checkbox("Zoom to the board", True)
        self.zoom.on_update(lambda _e: self.select())
        self.frame_line = gui.add_markdown("")
        self.view_line = gui.add_markdown("")
        self.image = gui.add_image(np.zeros((2, 2, 3), np.uint8), label="view",
                                   format="jpeg", jpeg_quality=85)  # fmt: skip
        gui.add_markdown(
            "<small>green rings: corners as detected; red crosses: as reprojected by the "
            "bundle adjustment (the line between them is the error)</small>"
        )

    def _add_chart(self) -> viser.GuiUplotHandle:
        """Each camera's per-view RMS error over the frames (px); the selected view as a
        black ring (a chart series of its own)."""
        views = self.views
        x = np.arange(int(self.frames.min()), int(self.frames.max()) + 1, dtype=float)
        ys, series = [], [viser.uplot.Series(label="frame")]
        for c, figures in enumerate(views.cameras):
            y = np.full(len(x), np.nan)
            mine = np.flatnonzero(views.view_camera == c)
            y[views.view_frame[mine] - int(x[0])] = self.rms[mine]
            ys.append(y)
            colour = "#" + "".join(f"{int(v):02x}" for v in PALETTE[c % len(PALETTE)])
            # points only: viser sends NaN, which uPlot would join across (not a gap)
            series.append(viser.uplot.Series(
                label=figures.name, stroke=colour, width=0,
                points={"show": True, "size": 6, "fill": colour, "stroke": colour},
            ))  # fmt: skip
        self._chart_x = x
        top = float(np.nanmax(self.rms)) if np.isfinite(self.rms).any() else 1.0
        self._chart_top = max(1.0, top * 1.05)
        ys.append(self._marker())
        series.append(viser.uplot.Series(
            label="selected view", stroke="#000000", width=0,
            points={"show": True, "size": 11, "stroke": "#000000", "fill": "#ffffff00"},
        ))  # fmt: skip
        return self.server.gui.add_uplot(
            data=(x, *ys), series=tuple(series), title="reprojection error per view, px",
            scales={"x": {"time": False}, "y": {"range": [0, self._chart_top]}},
            aspect=2.2,
        )  # fmt: skip

    def _marker(self) -> np.ndarray:
        """The selected view's error at its frame (a ring on the chart), NaN elsewhere."""
        y = np.full(len(self._chart_x), np.nan)
        i = int(self.frame - self._chart_x[0])
        k = self.views.find_view(self.camera, self.frame)
        if 0 <= i < len(y) and k is not None:
            y[i] = self.rms[k]
        return y

    # ------------------------------------------------------------------ selection

    def _best_frame(self, camera: int) -> int:
        """The frame of ``camera``'s view nearest the current frame (or the current)."""
        mine = self.views.view_frame[self.views.view_camera == camera]
        if not len(mine):
            return self.frame
        return int(mine[np.argmin(np.abs(mine - self.frame))])

    def _step(self, what: str) -> None:
        views = self.views
        mine = np.sort(views.view_frame[views.view_camera == self.camera])
        if what == "worst view":
            k = int(np.nanargmax(np.where(np.isfinite(self.rms), self.rms, -1)))
            self.select(int(views.view_camera[k]), int(views.view_frame[k]))
        elif len(mine):
            later, earlier = mine[mine > self.frame], mine[mine < self.frame]
            if what.startswith("next") and len(later):
                self.select(frame=int(later[0]))
            elif what.startswith("◀") and len(earlier):
                self.select(frame=int(earlier[-1]))

    def select(self, camera: int | None = None, frame: int | None = None) -> None:
        """Show ``camera``'s view of the board at ``frame`` (either kept when None)."""
        with self._lock:
            if self._showing:  # a widget _show moved calls back: already shown
                return
            if camera is not None:
                self.camera = int(camera)
            if frame is not None:
                self.frame = int(frame)
            self._showing = True
            try:
                self._show()
            finally:
                self._showing = False

    def _show(self) -> None:
        views, c, f = self.views, self.camera, self.frame
        width = EMBEDDED_IMAGE_WIDTH if self.embedded else IMAGE_WIDTH
        image, line = draw_view(views, c, f, zoom=self.zoom.value, width=width)
        if self.camera_choice.value != views.cameras[c].name:
            self.camera_choice.value = views.cameras[c].name
        if int(self.frame_slider.value) != f:
            self.frame_slider.value = f
        for k, frustum in self.frusta.items():
            frustum.thickness = 5.0 if k == c else 2.0
        with self.server.atomic():
            self.image.image = image
            self.view_line.content = line
            T = views.board_pose(f)
            self.selected_board.visible = T is not None
            if T is not None:
                grid = board_grid(views) * MM @ T[:3, :3].T + T[:3, 3] * MM
                self.selected_board.points = grid.astype(np.float32)
            seen = np.flatnonzero(views.view_frame == f)
            parts = [f"{views.cameras[views.view_camera[k]].name} "
                     f"({'-' if not np.isfinite(self.rms[k]) else f'{self.rms[k]:.2f} px'})"
                     for k in seen]  # fmt: skip
            seen_by = f"the board is seen by {', '.join(parts)}" if parts else "no board"
            self.frame_line.content = f"Frame {f}: {seen_by}"
            data = list(self.chart.data)
            data[-1] = self._marker()
            self.chart.data = tuple(data)

    def stop(self) -> None:
        """Nothing runs on its own: selection happens in the server's callbacks."""


def make_calibration_panel(host) -> CalibrationView | None:
    """The scene viewer's Calibration tab (a :class:`~mvviz.panels.contract.PanelHost`
    ``host``), when the scene folder has its calibration's ``calibration.npz``; a line
    saying why when it cannot be read."""
    path = host.state.scene.root / CALIBRATION_VIEWS
    try:
        views = load_calibration_views(path)
    except SceneFormatError as exc:
        host.server.gui.add_markdown(f"The calibration cannot be shown: {exc}")
        return None
    return CalibrationView(host.server, views, host.state.scene.rig, embedded=True)


class CalibrationApp:
    """A viser server showing one calibration folder (``mvviz view OUT``)."""

    frames = None  # no videos decoded: the views' frames are in calibration.npz
    rerun_live = None

    def __init__(self, folder: str | Path, server: viser.ViserServer) -> None:
        views, rig = load_calibration_folder(folder)
        self.server = server
        self.view = CalibrationView(server, views, rig)

    @property
    def url(self) -> str:
        host = self.server.get_host()
        host = "127.0.0.1" if host in ("0.0.0.0", "") else host
        return f"http://{host}:{self.server.get_port()}"

    def stop(self) -> None:
        self.view.stop()
        self.server.stop()
