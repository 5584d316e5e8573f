"""Calibrate a rig from footage of a board: detection, intrinsics, extrinsics, world frame.

INPUTS: one video or image folder per camera, a :class:`~pipeline.calibrate.board.Board`,
optionally a sync table (``timestamps.csv``), known intrinsics (a
:class:`~pipeline.data.cameras.CameraRig`) and a floor frame.
OUTPUTS: a :class:`Calibration`: the calibrated cameras as a ``CameraRig`` (world mm) and
a report per camera (frames with the board, views used for the intrinsics, the RMS errors,
or why it could not be calibrated). :func:`write_calibration` writes ``cameras.json``, a
Pose2Sim ``Calib.toml``, the report page and ``calibration.npz`` (what the calibration
saw, for the viewer: :mod:`pipeline.data.calibration_views`).

A camera that cannot be calibrated (the board seen in too few frames, or never together
with a calibrated camera) is reported with the reason and the counts; the others still
calibrate. No board at all, or no two cameras sharing a view of it, is an error.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from pipeline.calibrate.board import MIN_CORNERS, Board, board_detector
from pipeline.calibrate.extrinsics import (
    View,
    board_pose,
    bundle_adjust,
    initial_poses,
)
from pipeline.calibrate.footage import camera_name, grey_frames, read_sync
from pipeline.calibrate.intrinsics import MIN_VIEWS, Intrinsics, calibrate_intrinsics
from pipeline.calibrate.report import REPORT_HTML, write_report
from pipeline.calibrate.world import floor_transform
from pipeline.core.files import SceneFormatError
from pipeline.core.progress import Progress, StageBar
from pipeline.data.calibration_views import (
    CALIBRATION_VIEWS,
    CalibrationViews,
    CameraFigures,
    save_calibration_views,
)
from pipeline.data.cameras import CameraRig, make_camera, save_cameras
from pipeline.importers.calibration import write_pose2sim_calibration

MAX_OFFSET_FRAMES = 2.0
"""Bound of a camera's estimated time offset, in frames."""
THUMB_SIDE = 640
"""Long side of the frames kept for the viewer, px."""


@dataclass(frozen=True)
class CameraReport:
    """What the calibration found for one camera.

    Attributes:
        name: the camera's name; image_size: (width, height).
        frames: frames of its footage; board_frames: frames where it sees the board.
        intrinsic_views: views used for its intrinsics (0 when given).
        intrinsic_rms, ba_rms: RMS reprojection error, px (NaN when not computed).
        sync_offset_frames: when its frames were taken against the sync (or the frame
            index), in frames, relative to the first calibrated camera: -0.8 = 0.8 of a
            frame earlier than the sync table says (NaN when not calibrated).
        sync_offset_s: the same in seconds (NaN without a sync table's frame times).
        problem: why it was not calibrated (None when it was).
    """

    name: str
    image_size: tuple[int, int]
    frames: int
    board_frames: int
    intrinsic_views: int = 0
    intrinsic_rms: float = float("nan")
    ba_rms: float = float("nan")
    sync_offset_frames: float = float("nan")
    sync_offset_s: float = float("nan")
    problem: str | None = None


@dataclass(frozen=True)
class Calibration:
    """A calibration's result.

    Attributes:
        rig: the calibrated cameras (world mm, see :mod:`pipeline.calibrate.world`).
        reports: one per camera given, in order.
        views: every view of the board (camera = position in ``reports``).
        residuals: per view, (N, 2) bundle-adjustment reprojection error, px (empty for
            views of uncalibrated cameras).
        T_world_board: synchronised frame -> (4, 4) the board's pose in the world, mm.
        seconds: step name -> seconds taken.
        board: the board.
        world: "camera:<name>" (the first calibrated camera's frame) or "floor:<frame>".
        footage: per camera, its video or folder as given.
        thumbnails: (camera, frame) -> a grey JPEG of each view's frame, its long side
            :data:`THUMB_SIDE` px at most.
    """

    rig: CameraRig
    reports: tuple[CameraReport, ...]
    views: tuple[View, ...]
    residuals: tuple[np.ndarray, ...]
    T_world_board: dict[int, np.ndarray]
    seconds: dict[str, float] = field(default_factory=dict)
    board: Board | None = None
    world: str = ""
    footage: tuple[str, ...] = ()
    thumbnails: dict[tuple[int, int], bytes] = field(default_factory=dict)


def detect_views(
    footage: list[str | os.PathLike],
    board: Board,
    *,
    sync: np.ndarray | None = None,
    thumbnails: dict[tuple[int, int], bytes] | None = None,
    progress: Progress = False,
) -> tuple[list[View], list[tuple[int, int]], list[int]]:
    """Every view of the board: (views, per camera image size (W, H), per camera frame count).
    With ``sync`` ((num_sync, num_cameras), a :class:`~pipeline.calibrate.footage.SyncTable`'s
    ``frames``) a view's frame is its sync row; else the frame index. ``thumbnails`` gets
    each view's frame as a small JPEG (see :func:`thumbnail`)."""
    detect = board_detector(board)
    views: list[View] = []
    sizes, counts = [], []
    with StageBar("detect the board", len(footage), progress, unit="camera") as bar:
        for c, path in enumerate(footage):
            frame_of = None
            if sync is not None:
                frame_of = {int(f): s for s, f in enumerate(sync[:, c]) if f >= 0}
            n, size = 0, None
            for n, grey in enumerate(grey_frames(path), start=1):
                size = (grey.shape[1], grey.shape[0])
                frame = n - 1 if frame_of is None else frame_of.get(n - 1)
                if frame is None:
                    continue
                ids, pixels = detect(grey)
                if len(ids):
                    views.append(View(camera=c, frame=frame, ids=ids, pixels=pixels))
                    if thumbnails is not None:
                        thumbnails[(c, frame)] = thumbnail(grey)
            if frame_of is not None and n != len(frame_of):
                raise SceneFormatError(
                    path, None, f"{n} frames, but the sync table lists {len(frame_of)} for it"
                )
            sizes.append(size)
            counts.append(n)
            bar.update()
    return views, sizes, counts


def thumb_scale(size: tuple[int, int]) -> float:
    """Thumbnail pixels per image pixel for an image of ``size`` (W, H)."""
    return min(1.0, THUMB_SIDE / max(size))


def thumbnail(grey: np.ndarray) -> bytes:
    """``grey`` (H, W) shrunk to :func:`thumb_scale`, as JPEG bytes."""
    h, w = grey.shape
    s = thumb_scale((w, h))
    small = grey if s == 1.0 else cv2.resize(
        grey, (round(w * s), round(h * s)), interpolation=cv2.INTER_AREA
    )  # fmt: skip
    ok, data = cv2.imencode(".jpg", small, [cv2.IMWRITE_JPEG_QUALITY, 80])
    return data.tobytes() if ok else b""


def _given_intrinsics(given: CameraRig, names: list[str], sizes, source: str) -> list[Intrinsics]:
    """The given rig's intrinsics per camera: by name, else by position."""
    if all(n in given.names for n in names):
        cams = [given[given.index_of(n)] for n in names]
    elif len(given) == len(names):
        cams = list(given)
    else:
        raise SceneFormatError(
            source, "cameras",
            f"expected the cameras {names} (or {len(names)} cameras), got {given.names}",
        )  # fmt: skip
    for cam, name, size in zip(cams, names, sizes, strict=True):
        if (cam.width, cam.height) != tuple(size):
            raise SceneFormatError(
                source, f"{cam.name}.size",
                f"camera {name}'s footage is {size[0]}x{size[1]}, the intrinsics are for "
                f"{cam.width}x{cam.height}",
            )  # fmt: skip
    return [Intrinsics(K=c.K, dist=c.dist, rms=float("nan"), views=()) for c in cams]


def _fit_intrinsics(board, views, sizes, names, given, reports, progress) -> dict[int, Intrinsics]:
    """Camera index -> intrinsics, for the cameras that have them; ``reports`` gets the
    problem of the others."""
    out: dict[int, Intrinsics] = {}
    with StageBar("intrinsics", len(names), progress, unit="camera") as bar:
        for c in range(len(names)):
            mine = [v for v in views if v.camera == c]
            if given is not None:
                out[c] = given[c]
            elif len(mine) < MIN_VIEWS:
                reports[c]["problem"] = (
                    f"the board (>= {MIN_CORNERS} corners) is seen in {len(mine)} of "
                    f"{reports[c]['frames']} frames; the intrinsics need {MIN_VIEWS}"
                )
            else:
                try:
                    out[c] = calibrate_intrinsics(
                        board, [v.ids for v in mine], [v.pixels for v in mine], sizes[c]
                    )
                except ValueError as exc:
                    reports[c]["problem"] = str(exc)
            if c in out:
                reports[c]["intrinsic_views"] = len(out[c].views)
                reports[c]["intrinsic_rms"] = out[c].rms
            bar.update()
    return out


def calibrate_cameras(  # long: the steps in order, each a call, with the reports between
    footage: list[str | os.PathLike],
    board: Board,
    *,
    sync: str | os.PathLike | None = None,
    intrinsics: CameraRig | None = None,
    intrinsics_source: str = "--intrinsics",
    floor_frame: int | None = None,
    names: list[str] | None = None,
    sync_offsets: bool = True,
    progress: Progress = False,
) -> Calibration:
    """Calibrate the cameras filmed in ``footage`` (see the module docstring).

    ``sync_offsets``: estimate each camera's time offset against the sync (or the frame
    index) in the bundle adjustment (see :func:`~pipeline.calibrate.extrinsics.bundle_adjust`);
    False holds the cameras as synchronised as given.

    Raises:
        SceneFormatError: unreadable footage or sync table, the board never found, no two
            cameras sharing a view of it, or a floor frame without the board.
    """
    seconds: dict[str, float] = {}
    source = ", ".join(str(p) for p in footage)
    names = names or [camera_name(p) for p in footage]
    if len(set(names)) != len(names):
        raise SceneFormatError(source, None, f"camera names must be unique, got {names}")
    sync_table = None if sync is None else read_sync(sync, len(footage))
    t0 = time.perf_counter()
    thumbs: dict[tuple[int, int], bytes] = {}
    views, sizes, counts = detect_views(
        footage, board, sync=None if sync_table is None else sync_table.frames,
        thumbnails=thumbs, progress=progress,
    )  # fmt: skip
    seconds["detect"] = time.perf_counter() - t0
    reports = [
        {"name": n, "image_size": s, "frames": k,
         "board_frames": len({v.frame for v in views if v.camera == c})}
        for c, (n, s, k) in enumerate(zip(names, sizes, counts, strict=True))
    ]  # fmt: skip
    if not views:
        what = f"{board.kind} {board.columns}x{board.rows}"
        raise SceneFormatError(source, None, f"the board ({what}) is in no frame of any camera")
    given = None
    if intrinsics is not None:
        given = _given_intrinsics(intrinsics, names, sizes, intrinsics_source)
    t0 = time.perf_counter()
    intr = _fit_intrinsics(board, views, sizes, names, given, reports, progress)
    seconds["intrinsics"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    pts = board.object_points
    usable = [v for v in views if v.camera in intr]
    poses = [board_pose(pts[v.ids], v.pixels, intr[v.camera].K, intr[v.camera].dist)
             for v in usable]  # fmt: skip
    cams = sorted(intr)
    if not cams:
        why = "; ".join(f"{r['name']}: {r['problem']}" for r in reports)
        raise SceneFormatError(source, None, f"no camera could be calibrated: {why}")
    T_cam_root, shared = initial_poses(usable, poses, cams)
    for c in cams:
        if c not in T_cam_root:
            counts_c = ", ".join(f"{names[o]} {shared.get((min(c, o), max(c, o)), 0)}"
                                 for o in cams if o != c)  # fmt: skip
            reports[c]["problem"] = (
                f"never sees the board in the same frame as the calibrated cameras "
                f"(shared frames: {counts_c})"
            )
    if len(T_cam_root) < 2:
        raise SceneFormatError(source, None, "no two cameras see the board in the same frame: "
                               + "; ".join(f"{r['name']}: {r.get('problem') or 'alone'}"
                                           for r in reports))  # fmt: skip
    intr_pairs = {c: (intr[c].K, intr[c].dist) for c in T_cam_root}
    times = None if sync_table is None else sync_table.times
    if times is None and sync_table is not None:  # matched, untimed: the sync index
        times = np.repeat(np.arange(len(sync_table.frames), dtype=float)[:, None],
                          len(footage), axis=1)  # fmt: skip
    adjusted = bundle_adjust(
        usable,
        pts,
        intr_pairs,
        T_cam_root,
        poses,
        times=times,
        max_offset_frames=MAX_OFFSET_FRAMES if sync_offsets else None,
    )
    for c, offset in adjusted.time_offsets.items():
        reports[c]["sync_offset_frames"] = offset / adjusted.frame_period
        if sync_table is not None and sync_table.times is not None:
            reports[c]["sync_offset_s"] = offset
    seconds["extrinsics"] = time.perf_counter() - t0
    residuals = [np.zeros((0, 2))] * len(views)
    index = {id(v): k for k, v in enumerate(views)}
    for v, r in zip(usable, adjusted.residuals, strict=True):
        residuals[index[id(v)]] = r
    for c in adjusted.T_camera_root:
        r = np.concatenate([residuals[k] for k, v in enumerate(views) if v.camera == c])
        reports[c]["ba_rms"] = float(np.sqrt(np.mean(np.sum(r**2, axis=1))))
    T_world_root = np.eye(4)
    if floor_frame is not None:
        if floor_frame not in adjusted.T_root_board:
            seen = sorted(adjusted.T_root_board)
            raise SceneFormatError(
                "--floor-frame", None,
                f"no calibrated camera sees the board in frame {floor_frame}; it is seen in "
                f"frames {seen[:20]}{' ...' if len(seen) > 20 else ''}",
            )  # fmt: skip
        centres = np.stack([np.linalg.inv(T)[:3, 3] for T in adjusted.T_camera_root.values()])
        T_world_root = floor_transform(adjusted.T_root_board[floor_frame], centres)
    cameras = []
    for c in sorted(adjusted.T_camera_root):
        T = adjusted.T_camera_root[c] @ np.linalg.inv(T_world_root)
        w, h = sizes[c]
        cameras.append(make_camera(name=names[c], width=w, height=h, K=intr[c].K,
                                   dist=intr[c].dist, R=T[:3, :3], t=T[:3, 3]))  # fmt: skip
    return Calibration(
        rig=CameraRig(tuple(cameras)),
        reports=tuple(CameraReport(**r) for r in reports),
        views=tuple(views),
        residuals=tuple(residuals),
        T_world_board={f: T_world_root @ T for f, T in adjusted.T_root_board.items()},
        seconds=seconds,
        board=board,
        world=f"camera:{names[cams[0]]}" if floor_frame is None else f"floor:{floor_frame}",
        footage=tuple(str(p) for p in footage),
        thumbnails=thumbs,
    )


def calibration_views(calibration: Calibration) -> CalibrationViews:
    """What ``calibration`` saw, for the viewer (:mod:`pipeline.data.calibration_views`)."""
    views, board = calibration.views, calibration.board
    calibrated = set(calibration.rig.names)
    cameras = tuple(
        CameraFigures(
            name=r.name, image_size=tuple(int(v) for v in r.image_size), frames=r.frames,
            board_frames=r.board_frames, calibrated=r.name in calibrated,
            ba_rms=float(r.ba_rms), sync_offset_frames=float(r.sync_offset_frames),
            sync_offset_s=float(r.sync_offset_s), problem=r.problem or "",
            footage=calibration.footage[c] if c < len(calibration.footage) else "",
            thumb_scale=thumb_scale(r.image_size),
        )
        for c, r in enumerate(calibration.reports)
    )  # fmt: skip
    counts = [len(v.ids) for v in views]
    detected = np.concatenate([v.pixels for v in views]) if views else np.zeros((0, 2))
    reprojected = np.concatenate([
        v.pixels + r if len(r) == len(v.ids) else np.full((len(v.ids), 2), np.nan)
        for v, r in zip(views, calibration.residuals, strict=True)
    ]) if views else np.zeros((0, 2))  # fmt: skip
    jpegs = [calibration.thumbnails.get((v.camera, v.frame), b"") for v in views]
    frames = sorted(calibration.T_world_board)
    return CalibrationViews(
        cameras=cameras,
        board={"kind": board.kind, "columns": board.columns, "rows": board.rows,
               "square_mm": board.square_mm},
        world=calibration.world,
        object_points=board.object_points,
        view_camera=np.array([v.camera for v in views], np.int64),
        view_frame=np.array([v.frame for v in views], np.int64),
        view_start=np.concatenate([[0], np.cumsum(counts)]).astype(np.int64),
        corner_id=np.concatenate([v.ids for v in views]).astype(np.int64)
        if views else np.zeros(0, np.int64),
        detected=detected,
        reprojected=reprojected,
        pose_frame=np.array(frames, np.int64),
        T_world_board=np.array([calibration.T_world_board[f] for f in frames]).reshape(-1, 4, 4),
        thumbs=np.frombuffer(b"".join(jpegs), np.uint8),
        thumb_start=np.concatenate([[0], np.cumsum([len(j) for j in jpegs])]).astype(np.int64),
    )  # fmt: skip


def write_calibration(calibration: Calibration, out_dir: str | os.PathLike) -> list[Path]:
    """Write ``cameras.json`` (native), ``Calib.toml`` (Pose2Sim),
    ``calibration_report.html`` and ``calibration.npz`` (:func:`calibration_views`) into
    ``out_dir``, each atomically. Returns their paths."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    save_cameras(calibration.rig, out_dir / "cameras.json")
    toml = write_pose2sim_calibration(calibration.rig, out_dir / "Calib.toml")
    write_report(calibration, out_dir / REPORT_HTML)
    save_calibration_views(calibration_views(calibration), out_dir / CALIBRATION_VIEWS)
    return [out_dir / "cameras.json", toml, out_dir / REPORT_HTML, out_dir / CALIBRATION_VIEWS]
