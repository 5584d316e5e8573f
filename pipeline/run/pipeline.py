"""The whole run, composed: restoration, the per-frame stages (association and
triangulation), the sequence stages (tracking and filtering), then the SMPL fits.

This package is the one place where stages are composed: :mod:`pipeline.run.frames`
holds the per-frame and sequence steps, :mod:`pipeline.run.chunked` packs frames as
they are done, :mod:`pipeline.run.streamed` writes a long scene's columns to disk as it
goes, and this module chains them into :func:`run_pipeline` and :func:`run_or_load`.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from pipeline.body.arrays import BodyModelData
from pipeline.config import PipelineConfig
from pipeline.core.files import CACHE_DIR, SceneFormatError
from pipeline.core.progress import Progress
from pipeline.data.scene import Scene
from pipeline.results.store import (
    FrameResult,
    PipelineResults,
    cache_key,
    default_results_path,
    is_npz_path,
    load_results,
    pack,
    results_path_in,
    save_results,
)
from pipeline.run.bodies import fit_bodies
from pipeline.run.chunked import run_stages_chunked
from pipeline.run.frames import restored_joints, run_sequence, select_2d, source_joint_set
from pipeline.run.streamed import run_pipeline_to_directory

if TYPE_CHECKING:
    from pipeline.body.model import BodyModel


def pack_run(
    scene: Scene,
    frames: list[FrameResult],
    config: PipelineConfig,
    joints2d_all: np.ndarray,
    *,
    restored: np.ndarray | None,
    key: str = "",
) -> PipelineResults:
    """The sequence stages (tracking, filtering) over ``frames``, packed."""
    js = source_joint_set(scene, config)
    seq = run_sequence(frames, scene.num_frames, config, js, scene)
    return pack(
        frames, seq, config=config, joint_set=js.name, num_frames=scene.num_frames,
        num_views=len(scene.rig), restored=restored,
        joints2d_all=joints2d_all, cache_key=key,
    )  # fmt: skip


def run_stages(
    scene: Scene,
    config: PipelineConfig,
    joints2d_all: np.ndarray,
    *,
    restored: np.ndarray | None,
    key: str = "",
    rows_per_frame: list[np.ndarray] | None = None,
    cancelled: Callable[[], bool] | None = None,
    progress: Progress = True,
) -> PipelineResults | None:
    """The stages after restoration: association and triangulation of every frame, then
    tracking and filtering, packed (no SMPL fit). Returns None once ``cancelled()`` is
    true (checked between frames and after them).

    Runs :func:`pipeline.run.chunked.run_stages_chunked`: each frame is packed into
    its columns as it is done, so the frames' (n, n) association matrices do not pile
    up (dome:31 x 20, 100 frames: peak 1,129 MB when every FrameResult was kept until
    the packing; same arrays as ``pack_run(run_frames(...))``, tested)."""
    return run_stages_chunked(
        scene, config, joints2d_all, restored=restored, key=key,
        rows_per_frame=rows_per_frame, cancelled=cancelled, progress=progress,
    )  # fmt: skip


def run_pipeline(
    scene: Scene,
    config: PipelineConfig,
    model: BodyModel | BodyModelData,
    *,
    progress: Progress = True,
) -> PipelineResults:
    """All stages, from a loaded scene to :class:`PipelineResults`."""
    restored = restored_joints(scene, model)
    joints2d = select_2d(scene, config, restored)
    key = cache_key(scene, config, model)
    packed = run_stages(scene, config, joints2d, restored=restored, key=key, progress=progress)
    assert packed is not None  # nothing cancels it
    return fit_bodies(packed, config, model, progress=progress)


def run_or_load(
    scene: Scene,
    config: PipelineConfig,
    model: BodyModel | BodyModelData,
    *,
    out: str | os.PathLike | None = None,
    progress: Progress = True,
    force: bool = False,
) -> tuple[PipelineResults, bool]:
    """Load cached results if their key matches, else run and save. Returns (results, cached)."""
    path = Path(out) if out else default_results_path(scene)
    key = cache_key(scene, config, model)
    # a scene folder that cannot be written keeps its results elsewhere; those it holds
    # (computed before it was made read-only) are read all the same
    found = [path]
    if not out:
        found = list(dict.fromkeys([path, results_path_in(scene, scene.root / CACHE_DIR)]))
    for have in found if not force else ():
        if not have.exists():
            continue
        try:
            res = load_results(have, model=model)
            if res.cache_key == key:
                return res, True
        except SceneFormatError:
            pass  # stale or foreign file: recompute and replace it
    if not is_npz_path(path):
        # a directory: the stages write into it as they go, nothing whole in memory
        return run_pipeline_to_directory(scene, config, model, path, progress=progress), False
    res = run_pipeline(scene, config, model, progress=progress)
    save_results(res, path)
    return res, False
