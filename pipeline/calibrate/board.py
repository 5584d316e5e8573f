"""The calibration board: its geometry, how it is written down, and its detection in an image.

A board is a ChArUco board (squares with ArUco markers in the white ones, corners named
by id) or a plain checkerboard (every inner corner seen, or none). Geometry in
millimetres on the board plane: corner ``i`` at ``object_points[i] = (x, y, 0)``.

Specs (the ``--board`` option):

* ``charuco:COLSxROWS:SQUARE_M:MARKER_M:DICT[:inverted]``, e.g.
  ``charuco:4x5:0.054:0.0405:DICT_4X4_1000:inverted`` (squares, metres, OpenCV dictionary;
  ``inverted``: white markers on black);
* ``checkerboard:COLSxROWS:SQUARE_M``: COLS x ROWS *squares* (so (COLS-1) x (ROWS-1) inner
  corners), square side in metres;
* a Caliscope ``charuco.toml`` (``columns``, ``rows``, ``dictionary``, ``aruco_scale``,
  ``square_size_override_cm``, ``inverted``).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from pipeline.core.files import SceneFormatError, load_toml
from pipeline.core.units import MM_PER_M

KINDS = ("charuco", "checkerboard")
MIN_CORNERS = 4
"""Corners a view of the board needs to count (a pose from fewer is poorly conditioned)."""


@dataclass(frozen=True)
class Board:
    """A calibration board.

    Attributes:
        kind: ``"charuco"`` or ``"checkerboard"``.
        columns, rows: squares across and down.
        square_mm: side of a square, mm.
        marker_mm: side of a ChArUco marker, mm (0 for a checkerboard).
        dictionary: OpenCV ArUco dictionary name, e.g. ``"DICT_4X4_1000"`` ("" for a
            checkerboard).
        inverted: white markers on black (the image is inverted before detection).
    """

    kind: str
    columns: int
    rows: int
    square_mm: float
    marker_mm: float = 0.0
    dictionary: str = ""
    inverted: bool = False

    @property
    def num_corners(self) -> int:
        return (self.columns - 1) * (self.rows - 1)

    @property
    def object_points(self) -> np.ndarray:
        """(num_corners, 3) inner corners on the board plane, mm, row by row (OpenCV's ids)."""
        i, j = np.meshgrid(np.arange(1, self.columns), np.arange(1, self.rows))
        xy = np.stack([i.ravel(), j.ravel()], axis=1) * self.square_mm
        return np.concatenate([xy, np.zeros((len(xy), 1))], axis=1)

    def opencv_board(self):
        """OpenCV's ``CharucoBoard`` (metres as OpenCV's own units do not matter here)."""
        d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        return cv2.aruco.CharucoBoard(
            (self.columns, self.rows), self.square_mm / MM_PER_M, self.marker_mm / MM_PER_M, d
        )


SPEC_HELP = (
    "charuco:COLSxROWS:SQUARE_M:MARKER_M:DICT[:inverted], checkerboard:COLSxROWS:SQUARE_M, "
    "or a Caliscope charuco.toml"
)


def _size(text: str, source: str) -> tuple[int, int]:
    try:
        cols, rows = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise SceneFormatError(source, "size", f"expected COLSxROWS, got {text!r}") from None
    if cols < 2 or rows < 2 or cols * rows < 6:
        raise SceneFormatError(source, "size", f"expected at least 2x3 squares, got {text!r}")
    return cols, rows


def _metres(text, source: str, field: str) -> float:
    try:
        value = float(text)
    except (TypeError, ValueError):
        raise SceneFormatError(
            source, field, f"expected a length in metres, got {text!r}"
        ) from None
    if not np.isfinite(value) or value <= 0 or value > 10:
        raise SceneFormatError(source, field, f"expected a length in metres (0-10], got {text!r}")
    return value


def _dictionary(name, source: str, field: str) -> str:
    if not isinstance(name, str) or not name.startswith("DICT_") or not hasattr(cv2.aruco, name):
        raise SceneFormatError(
            source,
            field,
            f"expected an OpenCV ArUco dictionary such as DICT_4X4_1000, got {name!r}",
        )
    return name


def parse_board(spec: str | os.PathLike) -> Board:
    """A :class:`Board` from a spec or a Caliscope ``charuco.toml`` (see the module docstring)."""
    text = str(spec)
    if text.endswith(".toml") or Path(text).is_file():
        return read_caliscope_board(text)
    parts = text.split(":")
    kind = parts[0].lower()
    if kind == "checkerboard" and len(parts) == 3:
        cols, rows = _size(parts[1], text)
        return Board("checkerboard", cols, rows, _metres(parts[2], text, "square") * MM_PER_M)
    if kind == "charuco" and len(parts) in (5, 6):
        cols, rows = _size(parts[1], text)
        square = _metres(parts[2], text, "square") * MM_PER_M
        marker = _metres(parts[3], text, "marker") * MM_PER_M
        if marker >= square:
            raise SceneFormatError(text, "marker", "expected a marker smaller than the square")
        inverted = len(parts) == 6
        if inverted and parts[5].lower() != "inverted":
            raise SceneFormatError(text, "inverted", f"expected 'inverted', got {parts[5]!r}")
        return Board("charuco", cols, rows, square, marker, _dictionary(parts[4], text, "dict"),
                     inverted)  # fmt: skip
    raise SceneFormatError(text, "board", f"expected {SPEC_HELP}")


def read_caliscope_board(path: str | os.PathLike) -> Board:
    """A Caliscope ``charuco.toml``: ``columns``, ``rows``, ``dictionary``, ``aruco_scale``
    (marker / square), ``square_size_override_cm``, ``inverted``."""
    path = Path(path)
    data = load_toml(path)
    for key in ("columns", "rows", "dictionary", "square_size_override_cm"):
        if key not in data:
            raise SceneFormatError(path, key, "missing")
    cols, rows = _size(f"{data['columns']}x{data['rows']}", str(path))
    square = _metres(data["square_size_override_cm"], str(path), "square_size_override_cm") * 10
    scale = data.get("aruco_scale", 0.75)
    if not isinstance(scale, (int, float)) or not 0 < scale < 1:
        raise SceneFormatError(path, "aruco_scale", f"expected a number in (0, 1), got {scale!r}")
    inverted = data.get("inverted", False)
    if not isinstance(inverted, bool):
        raise SceneFormatError(path, "inverted", f"expected true/false, got {inverted!r}")
    return Board("charuco", cols, rows, square, square * scale,
                 _dictionary(data["dictionary"], str(path), "dictionary"), inverted)  # fmt: skip


def board_detector(board: Board):
    """A function ``grey image -> (corner_ids (N,), pixels (N, 2))`` for ``board``; N is 0
    when the board is not seen (fewer than :data:`MIN_CORNERS` corners)."""
    if board.kind == "charuco":
        detector = cv2.aruco.CharucoDetector(board.opencv_board())

        def detect(grey: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            corners, ids, _, _ = detector.detectBoard(255 - grey if board.inverted else grey)
            if ids is None or len(ids) < MIN_CORNERS:
                return np.zeros(0, np.int64), np.zeros((0, 2))
            return ids.ravel().astype(np.int64), corners.reshape(-1, 2).astype(float)

        return detect
    pattern = (board.columns - 1, board.rows - 1)
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_MAX_ITER, 30, 1e-3)

    def detect_checkerboard(grey: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
        found, corners = cv2.findChessboardCorners(grey, pattern, flags=flags)
        if not found:
            return np.zeros(0, np.int64), np.zeros((0, 2))
        corners = cv2.cornerSubPix(grey, corners, (5, 5), (-1, -1), criteria)
        return np.arange(board.num_corners), corners.reshape(-1, 2).astype(float)

    return detect_checkerboard
