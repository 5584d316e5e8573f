"""Joints as markers: TRC (OpenSim / Pose2Sim) and C3D (biomechanics' binary format).

Input: ``points`` (K, F, J, 3) world millimetres, z up, NaN where a joint or a
person-frame is missing, in a joint set of :mod:`pipeline.data.joint_sets`.

* TRC: the convention of Pose2Sim's output, which OpenSim reads: metres, **Y up**
  (:func:`pipeline.importers.trc.world_mm_to_trc`), ``DataRate`` = the scene's fps,
  ``Frame#`` = scene frame + 1, ``Time`` = frame / fps; a missing value is an empty cell.
  Marker names are Pose2Sim's for the layouts it knows (``RHip``, ``LBigToe``...:
  the inverse of :data:`pipeline.importers.trc.POSE2SIM_MARKERS`), else our joint names.
* C3D (through the ``c3d`` package, the reader/writer Pose2Sim uses): millimetres in
  our world axes (z up, the usual lab frame of C3D; ``POINT:X_SCREEN = +X``,
  ``Y_SCREEN = +Z`` tell viewers which way is up), float storage, the same marker
  names (C3D labels are 30 characters at most); a missing marker has residual -1.

Several tracks in one file get prefixed names (``track0_RHip``); one file per track
keeps the plain names.
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from pipeline.core.files import atomic_write
from pipeline.data.joint_sets import get_joint_set
from pipeline.importers.trc import POSE2SIM_MARKERS, world_mm_to_trc, write_trc

C3D_LABEL_LEN = 30


def marker_names(joint_set: str) -> list[str]:
    """Marker names of a joint set: Pose2Sim's where it has them, else ours."""
    js = get_joint_set(joint_set)
    ours_to_p2s = {v: k for k, v in POSE2SIM_MARKERS.get(js.name, {}).items()}
    return [ours_to_p2s.get(n, n) for n in js.names]


def _columns(
    points: np.ndarray, joint_set: str, tracks: Sequence[int], *, prefix: bool
) -> tuple[list[str], np.ndarray]:
    """Names (len(tracks) * J,) and points (F, len(tracks) * J, 3) of the chosen tracks."""
    names = marker_names(joint_set)
    if points.ndim != 4 or points.shape[2:] != (len(names), 3):
        raise ValueError(f"points: expected (K, F, {len(names)}, 3), got {points.shape}")
    cols = [f"track{k}_{n}" if prefix else n for k in tracks for n in names]
    pts = np.concatenate([points[k] for k in tracks], axis=1)  # (F, T*J, 3)
    return cols, pts


def write_trc_tracks(
    path: str | os.PathLike,
    points: np.ndarray,
    joint_set: str,
    tracks: Sequence[int],
    *,
    fps: float,
    prefix: bool | None = None,
) -> Path:
    """Write ``tracks`` of ``points`` (K, F, J, 3) world mm into one TRC file (metres,
    Y up), atomically. ``prefix`` (default: more than one track) prefixes the names."""
    prefix = len(tracks) > 1 if prefix is None else prefix
    names, pts = _columns(points, joint_set, tracks, prefix=prefix)
    write_trc(path, names, world_mm_to_trc(pts, y_up=True, units="m"), rate=fps, units="m")
    return Path(path)


def write_c3d_tracks(
    path: str | os.PathLike,
    points: np.ndarray,
    joint_set: str,
    tracks: Sequence[int],
    *,
    fps: float,
    prefix: bool | None = None,
) -> Path:
    """Write ``tracks`` of ``points`` (K, F, J, 3) world mm into one C3D file (mm, z up),
    atomically; a missing marker has residual -1 (and zero coordinates)."""
    import c3d  # its import is only paid by C3D exports

    prefix = len(tracks) > 1 if prefix is None else prefix
    names, pts = _columns(points, joint_set, tracks, prefix=prefix)
    long = [n for n in names if len(n) > C3D_LABEL_LEN]
    if long:
        raise ValueError(f"C3D labels are {C3D_LABEL_LEN} characters at most: {long[:3]}")
    F, M = pts.shape[:2]
    writer = c3d.Writer(point_rate=float(fps), analog_rate=0.0, point_scale=-1.0,
                        point_units="mm  ")  # fmt: skip
    writer.set_point_labels(names)
    writer.set_screen_axis(X="+X", Y="+Z")
    writer.set_start_frame(1)
    valid = np.isfinite(pts).all(-1)  # (F, M)
    no_analog = np.zeros((0, 0), np.float32)
    frames = []
    for f in range(F):
        rec = np.zeros((M, 5), np.float32)  # x, y, z, residual, camera mask
        rec[valid[f], :3] = pts[f, valid[f]]
        rec[~valid[f], 3] = -1.0
        frames.append((rec, no_analog))
    writer.add_frames(frames)
    with atomic_write(path, "wb") as fh, warnings.catch_warnings():
        warnings.filterwarnings("ignore", "No analog data", UserWarning)  # none is written
        writer.write(fh)
    return Path(path)


def read_c3d_points(path: str | os.PathLike) -> tuple[list[str], np.ndarray, float]:
    """(labels, points (F, M, 3) mm with NaN where the residual is negative, rate): the
    ``c3d`` package's reader, for checking what :func:`write_c3d_tracks` wrote."""
    import c3d

    with open(path, "rb") as fh, warnings.catch_warnings():
        warnings.filterwarnings("ignore", "No analog data", UserWarning)  # none is written
        reader = c3d.Reader(fh)
        labels = [str(s).strip() for s in reader.point_labels]
        rate = float(reader.point_rate)
        out = []
        for _, pts, _ in reader.read_frames():
            p = np.asarray(pts[:, :3], float).copy()
            p[pts[:, 3] < 0] = np.nan
            out.append(p)
    return labels, np.stack(out) if out else np.zeros((0, len(labels), 3)), rate
