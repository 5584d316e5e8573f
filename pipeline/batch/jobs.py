"""The work of ``mvviz batch`` as pure functions over a loaded scene (no Ray here).

A scene runs as: :func:`scene_inputs` (the 2D source of every detection row), then
:func:`run_chunk` for each frame chunk (association and triangulation, the per-frame
stages: chunks are independent), then :func:`join_chunks` (tracking, Kalman filtering
and the SMPL fit over the whole sequence). The three together compute exactly what
:func:`pipeline.run.pipeline.run_pipeline` computes: the same functions on the same inputs
in the same order, only the frames of a chunk elsewhere. Units: mm, px, frames.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from pipeline.body.arrays import BodyModelData
from pipeline.config import PipelineConfig
from pipeline.data.scene import Scene
from pipeline.evaluation.evaluate import (
    evaluate,
    ground_truth_slots,
    gt_per_frame,
    stage_metrics,
    to_smpl_slots,
)
from pipeline.results.store import RESULTS_VERSION, FrameResult, PipelineResults
from pipeline.run.frames import frame_rows, restored_joints, run_frame, select_2d
from pipeline.run.pipeline import fit_bodies, pack_run

if TYPE_CHECKING:  # torch: the driver never imports it, the workers' stages do
    from pipeline.body.model import BodyModel

WORST_PER_SCENE = 5  # worst moments kept per scene
WORST_GAP_FRAMES = 10  # two worst moments of a scene are at least this far apart


@dataclass(frozen=True)
class SceneJob:
    """One scene under one configuration: what to run and where its results go.

    ``setting``: the sweep assignments of this job (``("kalman.q=50", ...)``, empty
    without a sweep); ``set_args``: every ``--set`` that made ``config`` (the viewer
    command repeats them, so ``mvviz view`` finds the same cache key)."""

    scene_dir: Path
    config: PipelineConfig
    results_path: Path
    key: str
    setting: tuple[str, ...] = ()
    set_args: tuple[str, ...] = ()
    config_file: Path | None = None

    @property
    def label(self) -> str:
        name = self.scene_dir.name
        return f"{name} [{', '.join(self.setting)}]" if self.setting else name


@dataclass(frozen=True, eq=False)
class SceneInputs:
    """What every chunk of a scene reads besides the scene: N detection rows, J joints."""

    joints2d: np.ndarray  # (N, J, 3) the configured 2D source (x px, y px, confidence)
    restored: np.ndarray | None  # (N, 24, 3) SMPL joints restored from monocular output


def chunk_bounds(num_frames: int, chunk_frames: int) -> list[tuple[int, int]]:
    """``[(start, stop), ...]`` covering ``range(num_frames)`` in chunks of at most
    ``chunk_frames`` frames, as even as possible (0 or less: one chunk)."""
    if num_frames <= 0:
        return [(0, 0)]
    n = 1 if chunk_frames <= 0 else math.ceil(num_frames / chunk_frames)
    edges = np.linspace(0, num_frames, n + 1).round().astype(int)
    return [(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:], strict=True)]


def scene_inputs(
    scene: Scene, config: PipelineConfig, model: BodyModel | BodyModelData
) -> SceneInputs:
    """The restoration and source selection of :func:`pipeline.run.pipeline.run_pipeline`."""
    restored = restored_joints(scene, model)
    return SceneInputs(joints2d=select_2d(scene, config, restored), restored=restored)


def run_chunk(
    scene: Scene, config: PipelineConfig, inputs: SceneInputs, start: int, stop: int
) -> list[FrameResult]:
    """Association and triangulation of frames ``start..stop-1`` (as
    :func:`pipeline.run.frames.run_frames` does them, frame by frame)."""
    rows = frame_rows(scene)
    return [run_frame(scene, f, config, inputs.joints2d, rows=rows[f]) for f in range(start, stop)]


def join_chunks(
    scene: Scene,
    config: PipelineConfig,
    model: BodyModel | BodyModelData,
    inputs: SceneInputs,
    chunks: Sequence[list[FrameResult]],
    key: str,
) -> PipelineResults:
    """The sequence stages over the chunks' frames, in frame order, and the SMPL fit."""
    frames = [fr for chunk in chunks for fr in chunk]
    if [fr.frame for fr in frames] != list(range(scene.num_frames)):
        raise ValueError(f"{scene.root}: the chunks do not cover frames 0..{scene.num_frames - 1}")
    packed = pack_run(scene, frames, config, inputs.joints2d, restored=inputs.restored, key=key)
    return fit_bodies(packed, config, model, progress=False)


def stored_key(path: str | os.PathLike) -> str | None:
    """The cache key a results file was written with (None: no file, not a results
    file of this version): reads only its ``meta`` entry."""
    try:
        with np.load(path, allow_pickle=False) as z:
            meta = json.loads(str(z["meta"]))
    except (OSError, KeyError, ValueError):
        return None
    return meta.get("cache_key") if meta.get("version") == RESULTS_VERSION else None


# --------------------------------------------------------------------------- summary


def _finite(x: float | None) -> float | None:
    """JSON-safe: NaN and inf become None."""
    return float(x) if x is not None and np.isfinite(x) else None


def summarize(scene: Scene, results: PipelineResults) -> dict:
    """The figures of one scene's run for the dataset report: the configured filter's
    MPJPE / PCK@160 / PCP / acceleration error (where there is ground truth), the raw
    and SMPL rows' MPJPE, association precision / recall and ID switches, mean
    reprojection error per camera, and the worst moments (:func:`worst_moments`)."""
    ev = evaluate(scene, results)
    stage = "rts" if results.config.kalman.smoother else "kalman"
    row = ev.stages.get(stage, {})
    views = scene.rig.names
    out = {
        "num_frames": results.num_frames,
        "num_tracks": results.num_tracks,
        "has_gt": scene.gt is not None,
        "stage": stage,
        "mpjpe_mm": _finite(row.get("mpjpe")),
        "pck160": _finite(row.get("pck")),
        "pcp": _finite(row.get("pcp")),
        "accel_mm": _finite(row.get("accel")),
        "raw_mpjpe_mm": _finite(ev.stages.get("raw", {}).get("mpjpe")),
        "smpl_mpjpe_mm": _finite(ev.stages.get("smpl", {}).get("mpjpe")),
        "assoc_precision": _finite(ev.association.get("precision")),
        "assoc_recall": _finite(ev.association.get("recall")),
        "id_switches": ev.association.get("id_switches"),
        "reprojection_px": {
            v: _finite(x) for v, x in zip(views, ev.reprojection_view_mean, strict=True)
        },
        "reprojection_mean_px": _finite(
            float(np.nanmean(ev.reprojection_view_mean))
            if np.isfinite(ev.reprojection_view_mean).any()
            else None
        ),
    }
    out["worst"] = worst_moments(scene, results)
    return out


def _pick_worst(frame_value: np.ndarray, count: int, gap: int) -> list[int]:
    """Frames of the ``count`` largest finite values, at least ``gap`` frames apart."""
    order = [
        f
        for f in np.argsort(-np.nan_to_num(frame_value, nan=-np.inf))
        if np.isfinite(frame_value[f])
    ]
    picked: list[int] = []
    for f in order:
        if all(abs(f - p) >= gap for p in picked):
            picked.append(int(f))
        if len(picked) == count:
            break
    return picked


def _finite_mean(x: np.ndarray) -> np.ndarray:
    """(..., k) -> (...) the mean of each row's finite values, NaN where it has none
    (np.nanmean warns "Mean of empty slice" for every person-frame nobody matched)."""
    ok = np.isfinite(x)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(ok, x, 0.0).sum(-1) / ok.sum(-1)


def worst_moments(
    scene: Scene, results: PipelineResults, *, count: int = WORST_PER_SCENE
) -> list[dict]:
    """The scene's worst frames: with ground truth, by the largest per-person MPJPE of
    the filtered tracks (mm, the person's matched track named); without, by the largest
    per-person mean reprojection error of the raw triangulation (px). Each:
    ``{"frame", "track", "metric", "value"}``, worst first."""
    F = results.num_frames
    if scene.gt is not None:
        gt_slots, _ = ground_truth_slots(scene.gt, results.joint_set)
        gt_dense, _ = gt_per_frame(scene.gt, gt_slots, F)
        measured = np.isfinite(results.track_raw).all(-1, keepdims=True)
        tracks = np.where(measured, results.track_filtered, np.nan)
        _, match = stage_metrics(to_smpl_slots(tracks, results.joint_set), gt_dense)
        err = _finite_mean(np.linalg.norm(match.pred - match.gt, axis=-1))
        frames, who, metric = match.frame, match.pred_index, "mpjpe_mm"
    else:
        reproj = np.where(results.person_used, results.person_reproj, np.nan)
        err = _finite_mean(reproj.reshape(len(reproj), -1))
        frames, who, metric = results.person_frame, results.person_track, "reprojection_px"
    per_frame = np.full(F, np.nan)
    best_row = np.full(F, -1)
    for i in np.flatnonzero(np.isfinite(err)):
        f = frames[i]
        if not err[i] <= per_frame[f]:  # NaN-safe max
            per_frame[f], best_row[f] = err[i], i
    return [
        {
            "frame": f,
            "track": int(who[best_row[f]]),
            "metric": metric,
            "value": float(per_frame[f]),
        }
        for f in _pick_worst(per_frame, count, WORST_GAP_FRAMES)
    ]
