"""Calibration footage: the frames of each camera, and which frames were taken together.

A camera's footage is a video file or a folder of images (sorted by name). Frames of
different cameras are matched by index, or by a Caliscope-style ``timestamps.csv``
(``sync_index, cam_id, frame_index, frame_time``): the frames sharing a ``sync_index``
were taken together. A camera's rows, in ``frame_index`` order, are its frames in order
(a table may count frames from an earlier start of the recording than the footage kept).
Its ``frame_time`` (seconds), when present, is when each camera's frame was stamped: the
bundle adjustment starts the cameras' time offsets from it.
"""

from __future__ import annotations

import csv
import os
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from pipeline.core.files import SceneFormatError

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")


def camera_name(path: str | os.PathLike) -> str:
    """A camera's name from its footage: the file's stem or the folder's name."""
    path = Path(path)
    return path.name if path.is_dir() else path.stem


def image_files(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)


def grey_frames(path: str | os.PathLike) -> Iterator[np.ndarray]:
    """The frames of one camera, grey (H, W) uint8, in order. A video that does not open or
    a folder without images is a :class:`SceneFormatError`."""
    path = Path(path)
    if not path.exists():
        raise SceneFormatError(path, None, "file not found")
    if path.is_dir():
        files = image_files(path)
        if not files:
            raise SceneFormatError(path, None, f"expected images ({', '.join(IMAGE_SUFFIXES)})")
        for f in files:
            image = cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)
            if image is None:
                raise SceneFormatError(f, None, "not a readable image")
            yield image
        return
    capture = cv2.VideoCapture(str(path))
    try:
        ok, frame = capture.read()
        if not capture.isOpened() or not ok:
            raise SceneFormatError(path, None, "not a video OpenCV can read (no frame decoded)")
        while ok:
            yield frame if frame.ndim == 2 else cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)
            ok, frame = capture.read()
    finally:
        capture.release()


@dataclass(frozen=True)
class SyncTable:
    """A sync table read from a ``timestamps.csv``.

    Attributes:
        frames: (num_sync, num_cameras) position of each camera's frame in its footage at
            each sync index (-1: no frame), rows in sync-index order.
        times: (num_sync, num_cameras) each frame's ``frame_time``, seconds (NaN: no
            frame), or None when the table has no ``frame_time`` column.
    """

    frames: np.ndarray
    times: np.ndarray | None


def read_sync(path: str | os.PathLike, num_cameras: int) -> SyncTable:
    """A ``timestamps.csv`` -> its :class:`SyncTable`; ``cam_id`` is the camera's position
    in the order the footage was given."""
    path = Path(path)
    if not path.is_file():
        raise SceneFormatError(path, None, "file not found")
    rows: dict[int, np.ndarray] = {}
    stamps: dict[int, np.ndarray] = {}
    with path.open(newline="", encoding="utf-8") as fh:
        reader = csv.DictReader(fh)
        need = {"sync_index", "cam_id", "frame_index"}
        if reader.fieldnames is None or not need <= set(reader.fieldnames):
            raise SceneFormatError(path, "header", f"expected the columns {sorted(need)}")
        timed = "frame_time" in reader.fieldnames
        for line, row in enumerate(reader, start=2):
            try:
                sync, cam, frame = (int(row[k]) for k in ("sync_index", "cam_id", "frame_index"))
            except (TypeError, ValueError):
                raise SceneFormatError(path, f"line {line}", "expected integers") from None
            if not 0 <= cam < num_cameras:
                raise SceneFormatError(
                    path, f"line {line}.cam_id",
                    f"expected 0..{num_cameras - 1} (one per camera given), got {cam}",
                )  # fmt: skip
            rows.setdefault(sync, np.full(num_cameras, -1, np.int64))[cam] = frame
            if timed:
                try:
                    stamp = float(row["frame_time"])
                except (TypeError, ValueError):
                    raise SceneFormatError(
                        path, f"line {line}.frame_time", "expected seconds"
                    ) from None
                if not np.isfinite(stamp):
                    raise SceneFormatError(path, f"line {line}.frame_time", "expected seconds")
                stamps.setdefault(sync, np.full(num_cameras, np.nan))[cam] = stamp
    if not rows:
        raise SceneFormatError(path, None, "no rows")
    table = np.stack([rows[k] for k in sorted(rows)])
    for c in range(num_cameras):  # frame_index -> position among the camera's frames
        have = table[:, c] >= 0
        if not have.any():
            raise SceneFormatError(path, "cam_id", f"no rows for camera {c}")
        order = np.unique(table[have, c])
        if len(order) != have.sum():
            raise SceneFormatError(
                path, "frame_index", f"camera {c} has a frame at two sync indices"
            )
        table[have, c] = np.searchsorted(order, table[have, c])
    times = np.stack([stamps[k] for k in sorted(rows)]) if timed else None
    return SyncTable(frames=table, times=times)
