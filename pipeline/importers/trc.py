"""TRC marker files (OpenSim's and Pose2Sim's 3D output): read, write, map to our joints.

A TRC file is tab-separated text::

    PathFileType  4  (X/Y/Z)  <file name>
    DataRate  CameraRate  NumFrames  NumMarkers  Units  OrigDataRate  OrigDataStartFrame  ...
    60        60          100        21          m      60            0                   ...
    Frame#  Time  RHip  <2 empty>  RKnee  ...            (one name per marker, 3 columns each)
            X1  Y1  Z1  X2  Y2  Z2 ...
    <optional empty line>
    1  0.0167  x  y  z  x  y  z ...        (one row per frame; an empty cell = missing)

Units and axes: :class:`TrcData` keeps the file's own units (``m``, ``cm`` or ``mm``) and
axes. OpenSim, and so Pose2Sim, writes **Y up**: our world (millimetres, z up) is
``1000 * trc[..., [2, 0, 1]]`` for a file in metres (:func:`trc_to_world_mm`; checked on
Pose2Sim's balancing trial by reprojection into its calibration). Marker names are
Pose2Sim's (``RHip``, ``LBigToe``, ``Neck``...); :data:`POSE2SIM_MARKERS` maps them onto
our joint sets (:mod:`pipeline.data.joint_sets`) and :func:`trc_to_joint_set` builds
``(num_frames, num_joints, 3)`` world-mm arrays in a joint set's order.

Every malformed input raises :class:`~pipeline.core.files.SceneFormatError` naming the file
and the header field or data cell.
"""

from __future__ import annotations

import math
import os
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.core.files import SceneFormatError, atomic_write, read_text_lines
from pipeline.data.joint_sets import JointSet, get_joint_set
from pipeline.data.references import ReferenceTrack, check_name

# How many millimetres one file unit is.
UNIT_MM: dict[str, float] = {"mm": 1.0, "cm": 10.0, "m": 1000.0}
HEADER_KEYS = (
    "DataRate",
    "CameraRate",
    "NumFrames",
    "NumMarkers",
    "Units",
    "OrigDataRate",
    "OrigDataStartFrame",
    "OrigNumFrames",
)
_REQUIRED_KEYS = ("DataRate", "NumFrames", "NumMarkers", "Units")


@dataclass(frozen=True, eq=False)
class TrcData:
    """One TRC file, F frames of M markers, in the file's own units and axes.

    Attributes:
        path: where it was read from.
        marker_names: (M,) marker names as in the file (e.g. Pose2Sim's ``"RHip"``).
        frame_numbers: (F,) int, the ``Frame#`` column.
        times: (F,) seconds, the ``Time`` column.
        points: (F, M, 3) float, file units and axes (OpenSim: Y up); NaN where a cell
            is empty (or ``nan``).
        units: ``"m"``, ``"cm"`` or ``"mm"``.
        data_rate: frames per second (the ``DataRate`` header field).
    """

    path: Path
    marker_names: tuple[str, ...]
    frame_numbers: np.ndarray
    times: np.ndarray
    points: np.ndarray
    units: str
    data_rate: float

    @property
    def num_frames(self) -> int:
        return int(self.points.shape[0])

    @property
    def num_markers(self) -> int:
        return len(self.marker_names)


# --------------------------------------------------------------------------- reading


def _number(path: Path, field: str, text: str, *, integer: bool = False) -> float:
    try:
        value = float(text)
    except ValueError:
        kind = "an integer" if integer else "a number"
        raise SceneFormatError(path, field, f"expected {kind}, got {text!r}") from None
    if integer and not (math.isfinite(value) and value == round(value)):
        raise SceneFormatError(path, field, f"expected an integer, got {text!r}")
    return value


def _split(line: str) -> list[str]:
    return [c.strip() for c in line.rstrip("\r\n").split("\t")]


def _header(path: Path, lines: list[str]) -> tuple[float, int, int, str]:
    """1. Header fields, a line of keys and a line of values: (DataRate, NumFrames,
    NumMarkers, Units)."""
    keys, values = _split(lines[1]), _split(lines[2])
    for k in _REQUIRED_KEYS:
        if k not in keys:
            raise SceneFormatError(path, k, f"missing from the header line ({keys})")
    header = dict(zip(keys, values, strict=False))
    for k in _REQUIRED_KEYS:
        if header.get(k, "") == "":
            raise SceneFormatError(path, k, "no value on the header's value line")
    rate = _number(path, "DataRate", header["DataRate"])
    if not (math.isfinite(rate) and rate > 0):
        raise SceneFormatError(path, "DataRate", f"expected a positive rate, got {rate}")
    num_frames = int(_number(path, "NumFrames", header["NumFrames"], integer=True))
    num_markers = int(_number(path, "NumMarkers", header["NumMarkers"], integer=True))
    units = header["Units"]
    if units not in UNIT_MM:
        raise SceneFormatError(path, "Units", f"expected one of {sorted(UNIT_MM)}, got {units!r}")
    return rate, num_frames, num_markers, units


def _marker_names(path: Path, lines: list[str], num_markers: int) -> tuple[str, ...]:
    """2. Marker names (line 4), checked against the coordinate labels (line 5)."""
    name_cells = _split(lines[3])
    if name_cells[:2] != ["Frame#", "Time"]:
        raise SceneFormatError(
            path, "Frame#", f"line 4 should start with 'Frame#', 'Time', got {name_cells[:2]}"
        )
    markers = tuple(c for c in name_cells[2:] if c)
    if len(markers) != num_markers:
        raise SceneFormatError(
            path,
            "NumMarkers",
            f"the header says {num_markers} markers, line 4 names {len(markers)}",
        )
    if len(set(markers)) != len(markers):
        dup = sorted({m for m in markers if markers.count(m) > 1})
        raise SceneFormatError(path, "marker names", f"markers named twice: {dup}")
    labels = [c for c in _split(lines[4]) if c]
    if len(labels) != 3 * num_markers:
        raise SceneFormatError(
            path,
            "coordinate labels",
            f"expected {3 * num_markers} coordinate columns (X1 Y1 Z1 ... for "
            f"{num_markers} markers) on line 5, got {len(labels)}",
        )
    return markers


def _data_rows(
    path: Path, lines: list[str], num_frames: int, markers: tuple[str, ...]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """3. Data rows; empty lines (OpenSim writes one after the labels) are skipped.
    Returns frame numbers (F,), times (F,) s and points (F, 3 * M), NaN where empty."""
    num_markers = len(markers)
    width = 2 + 3 * num_markers
    rows = [(i, line) for i, line in enumerate(lines[5:], start=6) if line.strip()]
    if len(rows) != num_frames:
        raise SceneFormatError(
            path, "NumFrames", f"the header says {num_frames} frames, the file has {len(rows)} rows"
        )
    frames = np.zeros(num_frames, np.int64)
    times = np.zeros(num_frames)
    points = np.full((num_frames, 3 * num_markers), np.nan)
    for r, (lineno, line) in enumerate(rows):
        cells = _split(line)
        while len(cells) > width and cells[-1] == "":
            cells.pop()  # trailing tabs
        if len(cells) > width:
            raise SceneFormatError(
                path,
                f"line {lineno}",
                f"{len(cells)} columns, more than Frame#, Time and 3 x {num_markers} markers",
            )
        if len(cells) < 2 or cells[0] == "" or cells[1] == "":
            raise SceneFormatError(path, f"line {lineno}", "Frame# and Time are required")
        frames[r] = int(_number(path, f"line {lineno} Frame#", cells[0], integer=True))
        times[r] = _number(path, f"line {lineno} Time", cells[1])
        for c, text in enumerate(cells[2:]):
            if text:
                field = f"line {lineno} {markers[c // 3]} {'XYZ'[c % 3]}"
                points[r, c] = _number(path, field, text)
    if np.isinf(points).any():
        r, c = np.argwhere(np.isinf(points))[0]
        raise SceneFormatError(path, f"line {rows[r][0]} {markers[c // 3]}", "infinite value")
    return frames, times, points


def read_trc(path: str | os.PathLike) -> TrcData:
    """Read a TRC file; checks the header against the data (see the module docstring)."""
    path = Path(path)
    lines = read_text_lines(path)
    names = ("PathFileType", "header keys", "header values", "Frame#", "coordinate labels")
    for i, what in enumerate(names):
        if i >= len(lines):
            raise SceneFormatError(path, what, f"missing header line {i + 1} ({what})")
    if _split(lines[0])[0] != "PathFileType":
        raise SceneFormatError(
            path, "PathFileType", f"line 1 should start with 'PathFileType', got {lines[0][:40]!r}"
        )
    rate, num_frames, num_markers, units = _header(path, lines)
    markers = _marker_names(path, lines, num_markers)
    frames, times, points = _data_rows(path, lines, num_frames, markers)
    return TrcData(
        path=path,
        marker_names=markers,
        frame_numbers=frames,
        times=times,
        points=points.reshape(num_frames, num_markers, 3),
        units=units,
        data_rate=float(rate),
    )


# --------------------------------------------------------------------------- writing


def _cell(v: float) -> str:
    return repr(float(v)) if math.isfinite(v) else ""


def write_trc(
    path: str | os.PathLike,
    marker_names: Sequence[str],
    points: np.ndarray,
    *,
    rate: float,
    units: str = "m",
    start_frame: int = 1,
) -> None:
    """Write ``points`` (F, M, 3), in ``units`` and the TRC's axes, as a TRC file, atomically.

    Frame numbers are ``start_frame, start_frame + 1, ...``; times ``i / rate`` seconds
    from 0. NaN is written as an empty cell; floats are written exactly (``repr``).
    """
    path = Path(path)
    pts = np.asarray(points, float)
    names = [str(n) for n in marker_names]
    if pts.ndim != 3 or pts.shape[1:] != (len(names), 3):
        raise ValueError(f"points: expected shape (F, {len(names)}, 3), got {pts.shape}")
    if units not in UNIT_MM:
        raise ValueError(f"units: expected one of {sorted(UNIT_MM)}, got {units!r}")
    if not (math.isfinite(rate) and rate > 0):
        raise ValueError(f"rate: expected a positive number, got {rate}")
    if len(set(names)) != len(names) or any(not n or "\t" in n for n in names):
        raise ValueError(f"marker_names must be unique, non-empty and without tabs: {names}")
    F, M = pts.shape[:2]
    out = [
        f"PathFileType\t4\t(X/Y/Z)\t{path.name}",
        "\t".join(HEADER_KEYS),
        "\t".join(map(str, (_num(rate), _num(rate), F, M, units, _num(rate), start_frame, F))),
        "\t".join(["Frame#", "Time"] + [f"{n}\t\t" for n in names]),
        "\t".join(["", ""] + [f"{a}{k + 1}" for k in range(M) for a in "XYZ"]),
        "",
    ]
    flat = pts.reshape(F, 3 * M)
    for i in range(F):
        cells = [str(start_frame + i), repr(i / rate)] + [_cell(v) for v in flat[i]]
        out.append("\t".join(cells))
    with atomic_write(path, "w") as fh:
        fh.write("\n".join(out) + "\n")


def _num(x: float) -> str:
    return str(int(x)) if float(x).is_integer() else repr(float(x))


# --------------------------------------------------------------------------- axes and joints


def trc_to_world_mm(trc: TrcData, *, y_up: bool = True) -> np.ndarray:
    """(F, M, 3) world millimetres, z up, of a TRC's points.

    ``y_up`` (OpenSim's convention, what Pose2Sim writes): world ``(x, y, z)`` =
    TRC ``(Z, X, Y)``; otherwise the TRC's axes are taken as the world's.
    """
    pts = trc.points[..., [2, 0, 1]] if y_up else trc.points
    return pts * UNIT_MM[trc.units]


def world_mm_to_trc(points_mm: np.ndarray, *, y_up: bool = True, units: str = "m") -> np.ndarray:
    """The inverse of :func:`trc_to_world_mm`: (..., 3) world mm, z up -> TRC axes, ``units``."""
    if units not in UNIT_MM:
        raise ValueError(f"units: expected one of {sorted(UNIT_MM)}, got {units!r}")
    p = np.asarray(points_mm, float)
    return (p[..., [1, 2, 0]] if y_up else p) / UNIT_MM[units]


def _sides(pairs: Mapping[str, str]) -> dict[str, str]:
    """``{"Hip": "hip"}`` -> ``{"RHip": "right_hip", "LHip": "left_hip"}``."""
    return {f"{s[0].upper()}{k}": f"{s}_{v}" for k, v in pairs.items() for s in ("right", "left")}


_LIMBS = _sides(
    {"Shoulder": "shoulder", "Elbow": "elbow", "Wrist": "wrist", "Hip": "hip", "Knee": "knee",
     "Ankle": "ankle"}
)  # fmt: skip
_FACE = {"Nose": "nose"} | _sides({"Eye": "eye", "Ear": "ear"})
_FEET = _sides({"BigToe": "big_toe", "SmallToe": "small_toe", "Heel": "heel"})

# Per joint set of ours: Pose2Sim marker name -> our joint name. Pose2Sim's names are
# those of its skeletons (Pose2Sim/skeletons.py); where one name means different points
# in different skeletons, the entry follows the Pose2Sim skeleton of the same layout:
# BODY_25B's "Neck" is its upper neck (keypoint 17) and "Head" the top of the head
# (18); BODY_25's and COCO-18's "Neck" the mid-shoulder neck (1), BODY_25's "CHip" the
# mid hip (8); HALPE_26's "Head" is the top of the head (17), "Neck" (18), "Hip" (19);
# BlazePose's "RBigToe" is MediaPipe's foot index (32). Markers without a counterpart
# (e.g. COCO-17's neck, which Pose2Sim computes) are left out.
POSE2SIM_MARKERS: dict[str, dict[str, str]] = {
    "body25b": _LIMBS | _FACE | _FEET | {"Neck": "upper_neck", "Head": "head_top"},
    "body25": _LIMBS | _FACE | _FEET | {"Neck": "neck", "CHip": "mid_hip"},
    "halpe26": _LIMBS | _FACE | _FEET | {"Head": "head_top", "Neck": "neck", "Hip": "mid_hip"},
    "coco17": _LIMBS | _FACE,
    "coco18": _LIMBS | _FACE | {"Neck": "neck"},
    "coco23": _LIMBS | _FACE | _FEET,
    "coco_wholebody133": _LIMBS | _FACE | _FEET,
    "h36m17": _LIMBS,
    "blazepose33": _LIMBS
    | _FACE
    | _sides({"EyeInner": "eye_inner", "EyeOuter": "eye_outer", "Mouth": "mouth"})
    | _sides({"Pinky": "pinky", "Index": "index", "Thumb": "thumb", "Heel": "heel"})
    | _sides({"BigToe": "foot_index"}),
}


def trc_to_joint_set(
    trc: TrcData,
    joint_set: str | JointSet,
    *,
    markers: Mapping[str, str] | None = None,
    y_up: bool = True,
) -> np.ndarray:
    """(F, J, 3) world millimetres (z up) in ``joint_set``'s order; NaN for joints the
    TRC lacks (or where its cells are empty).

    ``markers`` (TRC marker name -> joint name) overrides
    ``POSE2SIM_MARKERS[joint_set.name]``. A TRC of which no marker maps is an error.
    """
    try:
        js = joint_set if isinstance(joint_set, JointSet) else get_joint_set(joint_set)
    except ValueError as exc:
        raise SceneFormatError(trc.path, "joint_set", str(exc)) from None
    if markers is None:
        if js.name not in POSE2SIM_MARKERS:
            raise SceneFormatError(
                trc.path,
                "joint_set",
                f"no Pose2Sim marker mapping for {js.name!r}; "
                f"expected one of {sorted(POSE2SIM_MARKERS)}",
            )
        markers = POSE2SIM_MARKERS[js.name]
    world = trc_to_world_mm(trc, y_up=y_up)  # (F, M, 3)
    out = np.full((trc.num_frames, js.num_joints, 3), np.nan)
    used = 0
    for m, name in enumerate(trc.marker_names):
        joint = markers.get(name)
        if joint is None:
            continue
        if joint not in js.index:
            raise SceneFormatError(
                trc.path, "marker_names", f"marker {name!r} maps to {joint!r}, not in {js.name}"
            )
        out[:, js.index[joint]] = world[:, m]
        used += 1
    if used == 0:
        raise SceneFormatError(
            trc.path,
            "marker_names",
            f"none of the markers {list(trc.marker_names)} maps to a {js.name} joint",
        )
    return out


def reference_from_trc(
    path: str | os.PathLike,
    name: str,
    joint_set: str | JointSet,
    *,
    fps: float | None = None,
    y_up: bool = True,
) -> ReferenceTrack:
    """A scene reference track (:mod:`pipeline.data.references`) from a TRC file: its markers
    in ``joint_set`` (world mm, z up), TRC row ``i`` = scene frame ``i``. A TRC rate other
    than the scene's ``fps`` is warned about (the rows are still taken frame for frame)."""
    check_name(name, path)
    trc = read_trc(path)
    joints = trc_to_joint_set(trc, joint_set, y_up=y_up)
    if fps is not None and abs(trc.data_rate - fps) > 1e-6 * fps:
        warnings.warn(
            f"{path}: DataRate {trc.data_rate:g} Hz, the scene {fps:g} fps; "
            "TRC row i is taken as scene frame i",
            stacklevel=2,
        )
    mapped = int(np.isfinite(joints).all(-1).any(0).sum())
    source = (
        f"{Path(path).resolve()} (TRC, {trc.units}, {'Y up' if y_up else 'z up'}, "
        f"{trc.num_frames} frames at {trc.data_rate:g} Hz, {mapped} joints)"
    )
    return ReferenceTrack(name=name, joints=joints, source=source)
