"""Results out, in the formats users' next tools read (``mvviz export``, the viewer's
Export folder).

=========== ======================================== ====================================
format      what                                     module
=========== ======================================== ====================================
``trc``     a stage's joints as markers, m, Y up     :mod:`pipeline.exports.markers`
``c3d``     the same, binary, mm, z up               :mod:`pipeline.exports.markers`
``bvh``     a fitted track's skeleton and motion     :mod:`pipeline.exports.bvh`
``smpl-npz`` a fitted track's SMPL parameters, AMASS :mod:`pipeline.exports.smpl_npz`
``glb``     every fitted track, skinned and animated :mod:`pipeline.exports.gltf`
=========== ======================================== ====================================

:func:`export_results` is the one entry point: it picks the stage (refusing one the run
does not have, with the stages it has), the tracks, the file names, and calls the
writer. Every writer writes atomically (:func:`pipeline.core.files.atomic_write`).
"""

from __future__ import annotations

import os
from pathlib import Path

from pipeline.exports.common import (
    BODY_STAGES,
    STAGES,
    ExportedFile,
    ExportError,
    available_stages,
    default_stage,
    per_track_paths,
    select_tracks,
    stage_fit,
    stage_points,
)
from pipeline.results.store import PipelineResults

FORMATS = ("trc", "c3d", "bvh", "smpl-npz", "glb")
EXTENSIONS = {"trc": ".trc", "c3d": ".c3d", "bvh": ".bvh", "smpl-npz": ".npz", "glb": ".glb"}
BODY_FORMATS = ("bvh", "smpl-npz", "glb")
"""Formats of fitted bodies: they need an SMPL stage."""

__all__ = [
    "BODY_FORMATS", "EXTENSIONS", "BODY_STAGES", "FORMATS", "STAGES", "ExportError",
    "ExportedFile", "available_stages", "default_stage", "export_results", "stages_for",
]  # fmt: skip


def stages_for(results: PipelineResults, fmt: str) -> tuple[str, ...]:
    """The stages of this run that ``fmt`` can write."""
    have = available_stages(results)
    return tuple(s for s in have if s in BODY_STAGES) if fmt in BODY_FORMATS else have


def export_results(
    results: PipelineResults,
    fmt: str,
    path: str | os.PathLike,
    *,
    fps: float,
    stage: str | None = None,
    track: int | str = "all",
    per_track: bool = False,
) -> list[ExportedFile]:
    """Write ``stage`` (default: the run's last, :func:`default_stage`) of ``results`` as
    ``fmt`` to ``path``.

    Tracks: ``"all"`` (every track with a frame in the stage) or one id. TRC and C3D
    put several tracks in one file with prefixed marker names, or with ``per_track``
    one file each; BVH and smpl-npz hold one body per file, so several tracks always
    give ``STEM_track<k>SUFFIX`` files beside ``path``; glb holds every track in one
    file. Raises :class:`ExportError` for a stage, track or format the run cannot give.
    """
    if fmt not in FORMATS:
        raise ExportError(f"unknown format {fmt!r}: expected one of {', '.join(FORMATS)}")
    if not fps > 0:
        raise ExportError(f"fps must be > 0, got {fps}")
    bodies = fmt in BODY_FORMATS
    stage = stage or default_stage(results, bodies=bodies)
    path = Path(path)
    if fmt in ("trc", "c3d"):
        from pipeline.exports.markers import write_c3d_tracks, write_trc_tracks

        points = stage_points(results, stage)
        present = (points == points).all(-1).any(-1)  # (K, F): a finite joint
        tracks = select_tracks(present, track)
        write = write_trc_tracks if fmt == "trc" else write_c3d_tracks
        groups = [[k] for k in tracks] if per_track else [tracks]
        paths = per_track_paths(path, tracks) if per_track else [path]
        out = []
        for p, group in zip(paths, groups, strict=True):
            write(p, points, results.joint_set, group, fps=fps)
            gaps = int((~present[group]).sum())
            note = (f"{gaps} track-frames without a pose: empty cells" if fmt == "trc"
                    else f"{gaps} track-frames without a pose: residual -1")  # fmt: skip
            out.append(ExportedFile(p, tuple(group), (note,) if gaps else ()))
        return out

    fit = stage_fit(results, stage, fmt=fmt)
    tracks = select_tracks(fit.present, track)
    if fmt == "glb":
        from pipeline.exports.gltf import write_glb

        notes = write_glb(path, fit, tracks, fps=fps)
        return [ExportedFile(path, tuple(tracks), tuple(notes))]
    if fmt == "bvh":
        from pipeline.exports.bvh import write_bvh_track as write_one
    else:
        from pipeline.exports.smpl_npz import write_smpl_npz_track as write_one
    out = []
    for p, k in zip(per_track_paths(path, tracks), tracks, strict=True):
        notes = write_one(p, fit, k, fps=fps)
        out.append(ExportedFile(p, (k,), tuple(notes)))
    return out
