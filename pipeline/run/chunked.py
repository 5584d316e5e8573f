"""The per-frame and sequence stages of a long run in bounded memory.

:func:`pipeline.run.pipeline.run_stages` keeps every frame's
:class:`pipeline.results.store.FrameResult` until the sequence stages and the packing have run, and
a frame result holds its association's (n, n) affinity and ray-distance matrices: at 31 cameras x 20
people
(~460 detection rows a frame) 3.65 MB a frame, 36 GB for 10,000 frames.
:func:`run_stages_chunked` gives the same :class:`~pipeline.results.store.PipelineResults`
(tested equal) but packs each frame into its result columns as soon as it is done
(:func:`pipeline.results.store.pack_frame`), joins a chunk's columns into one array per field
every ``chunk_frames`` frames (no per-frame Python objects survive the chunk) and runs
tracking and filtering on the person columns (:func:`pipeline.run.frames.sequence_of_people`).

What still grows with the frames is what the results hold: per person-frame columns
(~0.1 MB a frame at 31 x 20) and the affinity edges :func:`~pipeline.results.store.pack_frame`
keeps (each person's own pairs and the compatible ones: at 31 x 20 ~23,300 a frame,
16 bytes each, 1.15 MB a frame of peak in all; every finite pair, ~110,000 of 32 bytes,
was 3.7 MB a frame: ``bench/bench_memory.py --dome``).
``keep_edges=False`` leaves the edges out (empty E arrays): the viewer re-runs the frame
on screen (:func:`pipeline.run.frames.run_frame`) when it needs them.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from pipeline.config import PipelineConfig
from pipeline.core.progress import Progress, StageBar
from pipeline.data.scene import Scene
from pipeline.results.store import (
    DetectionLabels,
    FrameColumns,
    PipelineResults,
    assemble_results,
    join_columns,
    pack_frame,
)
from pipeline.run.frames import (
    FRAMES_STAGE,
    frame_rows,
    person_evidence,
    run_frame,
    sequence_of_people,
    source_joint_set,
)

PACKED_CHUNK_FRAMES = 256  # frames packed into columns before they are joined


def _without_edges(c: FrameColumns) -> FrameColumns:
    none_i, none_f = np.zeros(0, np.int32), np.zeros(0, np.float32)
    return FrameColumns(
        c.person_frame, c.person_joints, c.person_reproj, c.person_used, c.person_members,
        c.person_linkage, none_i, none_i, none_f, none_f,
    )  # fmt: skip


def run_stages_chunked(
    scene: Scene,
    config: PipelineConfig,
    joints2d_all: np.ndarray,
    *,
    restored: np.ndarray | None,
    key: str = "",
    rows_per_frame: list[np.ndarray] | None = None,
    chunk_frames: int = PACKED_CHUNK_FRAMES,
    keep_edges: bool = True,
    cancelled: Callable[[], bool] | None = None,
    progress: Progress = True,
) -> PipelineResults | None:
    """:func:`pipeline.run.pipeline.run_stages` (association, triangulation, tracking,
    filtering, packed; no SMPL fit) without keeping the frames' results.

    Args:
        joints2d_all: (N, J, 3) the 2D joints of every detection row (``select_2d``).
        chunk_frames: frames whose columns are joined into one array per field at once.
        keep_edges: False leaves the affinity edges (the E arrays) empty.
        cancelled: checked before each frame; once true the run returns None.
    """
    if chunk_frames < 1:
        raise ValueError(f"chunk_frames must be >= 1, got {chunk_frames}")
    rows = frame_rows(scene, config) if rows_per_frame is None else rows_per_frame
    V, J = len(scene.rig), joints2d_all.shape[1]
    labels = DetectionLabels(joints2d_all)
    chunks: list[FrameColumns] = []
    pending: list[FrameColumns] = []
    with StageBar(FRAMES_STAGE, scene.num_frames, progress, unit="frame") as bar:
        for f in range(scene.num_frames):
            if cancelled is not None and cancelled():
                return None
            fr = run_frame(scene, f, config, joints2d_all, rows=rows[f])
            labels.add(fr)
            cols = pack_frame(fr, V, J)
            pending.append(cols if keep_edges else _without_edges(cols))
            del fr  # the (n, n) matrices go now, not at the end of the run
            if len(pending) == chunk_frames:
                chunks.append(join_columns(pending, V, J))
                pending = []
            bar.update()
    if cancelled is not None and cancelled():
        return None
    cols = join_columns(chunks + [join_columns(pending, V, J)], V, J)
    del chunks, pending
    js = source_joint_set(scene, config)
    evidence = person_evidence(
        scene, config, labels.joints2d, cols.person_members, cols.person_used
    )
    seq = sequence_of_people(
        cols.person_frame, cols.person_joints, scene.num_frames, config, js, evidence
    )
    return assemble_results(
        labels, cols, seq, config=config, joint_set=js.name, num_frames=scene.num_frames,
        num_views=V, restored=restored, cache_key=key,
    )  # fmt: skip
