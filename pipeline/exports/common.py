"""What every writer of :mod:`pipeline.exports` shares: stages, tracks, axes, gaps, names.

Units and axes: the results are world millimetres, z up (:mod:`pipeline.data.scene`). The
Y-up formats (TRC, BVH, glTF) take the world there by the rotation of
:func:`pipeline.importers.trc.world_mm_to_trc`: ``(x, y, z)_out = (y, z, x)_world``
(:data:`WORLD_TO_Y_UP`, det +1, so a person's left stays on their left); it is the
inverse of what our TRC and BVH readers apply to Y-up files.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pipeline.fit.types import SmplFit
from pipeline.results.store import BODY_STAGES, STAGES, PipelineResults

WORLD_TO_Y_UP = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
"""(3, 3) rotation from our z-up world to a Y-up file's axes: ``out = M @ world``."""


class ExportError(ValueError):
    """A request the results cannot satisfy (stage absent, track unknown, ...)."""


@dataclass(frozen=True)
class ExportedFile:
    """One file a writer produced, and what the user should know about it."""

    path: Path
    tracks: tuple[int, ...]
    notes: tuple[str, ...] = field(default=())


# --------------------------------------------------------------------------- stages


def available_stages(results: PipelineResults) -> tuple[str, ...]:
    """The stages of :data:`STAGES` this run has (none without tracks)."""
    if results.num_tracks == 0:
        return ()
    out = ["raw", "kalman", "rts"]
    out += [s for s in BODY_STAGES if getattr(results, s) is not None]
    return tuple(out)


def _check_stage(results: PipelineResults, stage: str) -> None:
    if stage not in STAGES:
        raise ExportError(f"unknown stage {stage!r}: expected one of {', '.join(STAGES)}")
    have = available_stages(results)
    if stage not in have:
        if not have:
            raise ExportError("the run has no tracks: nothing to export")
        why = ""
        if stage in BODY_STAGES and results.smpl is None:
            why = (
                " (the run fitted no SMPL bodies: config fit_smpl=false)"
                if not results.config.fit_smpl
                else f" (the run fitted no SMPL bodies to its {results.joint_set!r} tracks)"
            )
        elif stage == "smpl_vae":
            why = " (the run has no VAE pose prior: config use_pose_prior=false)"
        raise ExportError(f"the run has no {stage!r} stage{why}; it has: {', '.join(have)}")


def stage_points(results: PipelineResults, stage: str) -> np.ndarray:
    """(K, F, J, 3) world mm of ``stage`` in the run's joint set (an SMPL stage: the
    fitted body's prediction of those joints); NaN where missing."""
    _check_stage(results, stage)
    if stage in BODY_STAGES:
        return getattr(results, stage).keypoints
    return {"raw": results.track_raw, "kalman": results.track_forward,
            "rts": results.track_smoothed}[stage]  # fmt: skip


def stage_fit(results: PipelineResults, stage: str, *, fmt: str) -> SmplFit:
    """The :class:`SmplFit` of an SMPL stage; other stages are refused for ``fmt``."""
    if stage not in BODY_STAGES and stage in STAGES:
        raise ExportError(
            f"{fmt} holds fitted bodies: --stage must be one of {', '.join(BODY_STAGES)}, "
            f"not {stage!r}"
        )
    _check_stage(results, stage)
    return getattr(results, stage)


def default_stage(results: PipelineResults, *, bodies: bool) -> str:
    """The last stage the run has: of the fits if ``bodies``, else of the joints
    (``rts`` when the config smooths, else ``kalman``)."""
    if bodies:
        for s in reversed(BODY_STAGES):
            if getattr(results, s) is not None:
                return s
        return "smpl"  # absent: the writer's check says so
    return "rts" if results.config.kalman.smoother else "kalman"


# --------------------------------------------------------------------------- tracks


def select_tracks(present: np.ndarray, track: int | str) -> list[int]:
    """Track indices to write: ``"all"`` (tracks with at least one frame) or one id.

    Args:
        present: (K, F) bool, person-frames the stage has.
    """
    K = present.shape[0]
    if str(track) == "all":
        out = [k for k in range(K) if present[k].any()]
        if not out:
            raise ExportError("no track has a frame in this stage: nothing to export")
        return out
    try:
        k = int(track)
    except (TypeError, ValueError):
        raise ExportError(f"--track: expected 'all' or a track id, got {track!r}") from None
    if not 0 <= k < K:
        raise ExportError(f"track {k} does not exist: the run has tracks 0..{K - 1}")
    if not present[k].any():
        raise ExportError(f"track {k} has no frame in this stage")
    return [k]


def per_track_paths(path: str | os.PathLike, tracks: Sequence[int]) -> list[Path]:
    """``PATH`` for one track; ``STEM_track<k>SUFFIX`` beside it for several."""
    path = Path(path)
    if len(tracks) == 1:
        return [path]
    return [path.with_name(f"{path.stem}_track{k}{path.suffix}") for k in tracks]


# --------------------------------------------------------------------------- gaps


def hold_indices(present: np.ndarray) -> np.ndarray:
    """(F,) int: for each frame, the frame whose pose it shows when poses are held:
    itself where present, else the last present frame before it (the first present
    frame before the track starts). ``present`` (F,) bool, not all False."""
    present = np.asarray(present, bool)
    idx = np.where(present, np.arange(len(present)), -1)
    idx = np.maximum.accumulate(idx)
    first = int(np.argmax(present))
    return np.where(idx < 0, first, idx)


def gap_note(present: np.ndarray, what: str = "holds the last pose") -> str | None:
    """A sentence on a track's missing frames, or None if it has all of them."""
    missing = np.flatnonzero(~np.asarray(present, bool))
    if len(missing) == 0:
        return None
    runs = np.split(missing, np.flatnonzero(np.diff(missing) > 1) + 1)
    spans = ", ".join(f"{r[0]}" if len(r) == 1 else f"{r[0]}-{r[-1]}" for r in runs[:6])
    more = f" and {len(runs) - 6} more" if len(runs) > 6 else ""
    return f"{len(missing)} frames without a body (frames {spans}{more}): {what}"
