"""What a calibration saw, for looking at it later: ``OUT/calibration.npz``.

``mvviz calibrate`` writes it beside ``cameras.json`` (atomically); the viewer's
calibration view (``mvviz view OUT``) reads it and nothing else of the calibration step.
It holds, per camera, the figures of the calibration; per view of the board (one camera,
one frame), its corners as detected and as reprojected by the bundle adjustment, and a
small grey JPEG of the frame; per frame, the board's pose in the world. World in mm,
images in pixels of the camera's full image (the thumbnails are smaller: each camera's
``thumb_scale``).

Arrays (V views, M corners over all views, F frames with a board pose, C cameras):
``view_camera`` (V,), ``view_frame`` (V,), ``view_start`` (V + 1,) (view v's corners are
rows ``view_start[v]:view_start[v + 1]``), ``corner_id`` (M,), ``detected`` (M, 2),
``reprojected`` (M, 2) (NaN for views of cameras that were not calibrated),
``pose_frame`` (F,), ``T_world_board`` (F, 4, 4), ``object_points`` (num_corners, 3) mm,
``thumbs`` (total bytes,) uint8 with ``thumb_start`` (V + 1,) (an empty slice: no
thumbnail), and ``meta``: a JSON string (cameras, board, world).
"""

from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from pipeline.core.files import SceneFormatError, load_npz, save_npz_atomic

CALIBRATION_VIEWS = "calibration.npz"
FORMAT = "mvviz-calibration-views"
VERSION = 1
ARRAYS = ("object_points", "view_camera", "view_frame", "view_start", "corner_id", "detected",
          "reprojected", "pose_frame", "T_world_board", "thumbs", "thumb_start")  # fmt: skip


@dataclass(frozen=True)
class CameraFigures:
    """One camera's figures (see :class:`pipeline.calibrate.calibrate.CameraReport`).

    Attributes:
        name; image_size: (width, height) px; frames: frames of its footage;
        board_frames: frames with the board; calibrated: whether it has a pose;
        ba_rms: bundle-adjustment RMS, px (NaN when not calibrated);
        sync_offset_frames, sync_offset_s: its estimated time offset (NaN: unknown);
        problem: why it was not calibrated ("" when it was); footage: its video or
        folder, as given; thumb_scale: its thumbnails' pixels per image pixel.
    """

    name: str
    image_size: tuple[int, int]
    frames: int
    board_frames: int
    calibrated: bool
    ba_rms: float
    sync_offset_frames: float
    sync_offset_s: float
    problem: str
    footage: str
    thumb_scale: float


@dataclass(frozen=True, eq=False)
class CalibrationViews:
    """The contents of ``calibration.npz`` (see the module docstring)."""

    cameras: tuple[CameraFigures, ...]
    board: dict  # kind, columns, rows, square_mm
    world: str  # "camera:<name>" (the first camera's frame) or "floor:<frame>"
    object_points: np.ndarray
    view_camera: np.ndarray
    view_frame: np.ndarray
    view_start: np.ndarray
    corner_id: np.ndarray
    detected: np.ndarray
    reprojected: np.ndarray
    pose_frame: np.ndarray
    T_world_board: np.ndarray
    thumbs: np.ndarray
    thumb_start: np.ndarray

    @property
    def num_views(self) -> int:
        return len(self.view_camera)

    @property
    def z_up(self) -> bool:
        """Whether the world is the floor frame (z up); else a camera's (y down)."""
        return self.world.startswith("floor:")

    def corners(self, view: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """View ``view``'s corner ids (N,), detected (N, 2) and reprojected (N, 2) px."""
        s = slice(self.view_start[view], self.view_start[view + 1])
        return self.corner_id[s], self.detected[s], self.reprojected[s]

    def view_rms(self) -> np.ndarray:
        """(V,) each view's RMS reprojection error, px (NaN: not adjusted)."""
        err2 = np.sum((self.reprojected - self.detected) ** 2, axis=1)
        counts = np.diff(self.view_start)
        rows = np.repeat(np.arange(self.num_views), counts)
        sums = np.bincount(rows, weights=err2, minlength=self.num_views)
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.sqrt(sums / counts)

    def find_view(self, camera: int, frame: int) -> int | None:
        """The view of ``camera`` at ``frame``, or None."""
        hit = np.flatnonzero((self.view_camera == camera) & (self.view_frame == frame))
        return int(hit[0]) if len(hit) else None

    def thumbnail(self, view: int) -> bytes | None:
        """View ``view``'s frame as JPEG bytes (grey, ``thumb_scale`` of the image)."""
        a, b = self.thumb_start[view], self.thumb_start[view + 1]
        return None if a == b else self.thumbs[a:b].tobytes()

    def board_pose(self, frame: int) -> np.ndarray | None:
        """(4, 4) ``T_world_board`` (mm) at ``frame``, or None."""
        hit = np.flatnonzero(self.pose_frame == frame)
        return self.T_world_board[hit[0]] if len(hit) else None


def save_calibration_views(views: CalibrationViews, path: str | os.PathLike) -> None:
    """Write ``views`` to ``path`` atomically."""
    meta = {
        "format": FORMAT,
        "version": VERSION,
        "cameras": [asdict(c) | {"image_size": list(c.image_size)} for c in views.cameras],
        "board": views.board,
        "world": views.world,
    }
    arrays = {k: getattr(views, k) for k in ARRAYS}
    text = json.dumps(meta, allow_nan=True)
    save_npz_atomic(path, meta=np.array(text), **arrays)


def load_calibration_views(path: str | os.PathLike) -> CalibrationViews:
    """Read a ``calibration.npz``; a missing, foreign or inconsistent file is a
    :class:`SceneFormatError` naming it."""
    path = Path(path)
    z = load_npz(path)
    try:
        meta = json.loads(str(z["meta"]))
    except (KeyError, ValueError):
        raise SceneFormatError(path, "meta", "expected mvviz calibrate's calibration.npz") from None
    if meta.get("format") != FORMAT or meta.get("version") != VERSION:
        raise SceneFormatError(
            path, "meta.format", f"expected {FORMAT} version {VERSION}, got "
            f"{meta.get('format')!r} version {meta.get('version')!r}",
        )  # fmt: skip
    need = ARRAYS
    missing = [k for k in need if k not in z]
    if missing:
        raise SceneFormatError(path, missing[0], "missing")
    cameras = tuple(
        CameraFigures(**(c | {"image_size": tuple(c["image_size"])})) for c in meta["cameras"]
    )
    v, m = len(z["view_camera"]), len(z["corner_id"])
    shapes_ok = (
        len(z["view_frame"]) == v and z["view_start"].shape == (v + 1,)
        and z["view_start"][-1] == m and z["detected"].shape == (m, 2)
        and z["reprojected"].shape == (m, 2) and z["thumb_start"].shape == (v + 1,)
        and z["T_world_board"].shape == (len(z["pose_frame"]), 4, 4)
        and (v == 0 or 0 <= z["view_camera"].min() <= z["view_camera"].max() < len(cameras))
    )  # fmt: skip
    if not shapes_ok:
        raise SceneFormatError(path, None, "the views' arrays do not agree in length")
    return CalibrationViews(
        cameras=cameras, board=meta["board"], world=meta["world"], **{k: z[k] for k in need},
    )  # fmt: skip
