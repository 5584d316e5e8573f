"""A fitted SMPL track as a BVH file (Blender, MotionBuilder, most animation tools).

One skeleton per file: the body model's 24 joints (names from the model), offsets from
the track's fitted betas, metres, **Y up** (BVH's and Blender's importer's default
axes), the skeleton of :mod:`pipeline.exports.skeleton`. Channels: the root
``Xposition Yposition Zposition Zrotation Xrotation Yrotation``, every other joint
``Zrotation Xrotation Yrotation`` (the CMU files' order; ``R = Rz @ Rx @ Ry``,
intrinsic, degrees). Leaf joints end in an ``End Site`` a bone's length beyond them.

All of the scene's frames are written (frame i = scene frame i, ``Frame Time`` =
1 / fps); where the fit has no body (a gap in the track, or before it starts and after
it ends), the pose of the last fitted frame is held (the first one before the track
starts): BVH has no way to say "absent". The notes returned say which frames.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from pipeline.core.files import atomic_write
from pipeline.exports.common import gap_note
from pipeline.exports.skeleton import TrackSkeleton, end_site_offsets, track_skeleton
from pipeline.fit.types import SmplFit

ROOT_CHANNELS = ("Xposition", "Yposition", "Zposition", "Zrotation", "Xrotation", "Yrotation")
JOINT_CHANNELS = ("Zrotation", "Xrotation", "Yrotation")
EULER_ORDER = "ZXY"  # scipy: upper case = intrinsic, R = Rz @ Rx @ Ry


def _fmt(v: float) -> str:
    return f"{v:.6f}"


def bvh_text(skel: TrackSkeleton, end_sites: dict[int, np.ndarray], *, fps: float) -> str:
    """The BVH file of one :class:`TrackSkeleton` (see the module docstring)."""
    J = len(skel.parents)
    children: dict[int, list[int]] = {j: [] for j in range(J)}
    for j in range(1, J):
        children[int(skel.parents[j])].append(j)
    lines: list[str] = ["HIERARCHY"]

    def emit(j: int, depth: int) -> None:
        pad = "  " * depth
        head = "ROOT" if skel.parents[j] < 0 else "JOINT"
        chans = ROOT_CHANNELS if skel.parents[j] < 0 else JOINT_CHANNELS
        lines.append(f"{pad}{head} {skel.names[j]}")
        lines.append(f"{pad}{{")
        lines.append(f"{pad}  OFFSET {' '.join(_fmt(v) for v in skel.offsets[j])}")
        lines.append(f"{pad}  CHANNELS {len(chans)} {' '.join(chans)}")
        for c in children[j]:
            emit(c, depth + 1)
        if not children[j]:
            lines.append(f"{pad}  End Site")
            lines.append(f"{pad}  {{")
            lines.append(f"{pad}    OFFSET {' '.join(_fmt(v) for v in end_sites[j])}")
            lines.append(f"{pad}  }}")
        lines.append(f"{pad}}}")

    order: list[int] = []

    def visit(j: int) -> None:
        order.append(j)
        for c in children[j]:
            visit(c)

    emit(0, 0)
    visit(0)
    F = skel.num_frames
    euler = Rotation.from_matrix(skel.local_rotations[:, order].reshape(-1, 3, 3))
    angles = euler.as_euler(EULER_ORDER, degrees=True).reshape(F, J * 3)
    values = np.concatenate([skel.root_position, angles], axis=1)  # root first in `order`
    lines += ["MOTION", f"Frames: {F}", f"Frame Time: {1.0 / fps:.8f}"]
    lines += [" ".join(_fmt(v) for v in row) for row in values]
    return "\n".join(lines) + "\n"


def write_bvh_track(path: str | os.PathLike, fit: SmplFit, k: int, *, fps: float) -> list[str]:
    """Write track ``k`` of ``fit`` as a BVH file, atomically; returns notes (held
    frames)."""
    if not fps > 0:
        raise ValueError(f"fps must be > 0, got {fps}")
    skel = track_skeleton(fit, k)
    text = bvh_text(skel, end_site_offsets(fit, skel), fps=fps)
    with atomic_write(Path(path), "w") as fh:
        fh.write(text)
    note = gap_note(skel.present, "the last fitted pose is held (BVH has no 'absent')")
    return [f"track {k}: {note}"] if note else []
