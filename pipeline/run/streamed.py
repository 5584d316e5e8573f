"""The stages of a long run written into its results directory as they go.

:func:`pipeline.run.chunked.run_stages_chunked` bounds the per-frame stages' memory
but still returns every result column in RAM: at 31 cameras x 20 people ~0.3 MB a frame
(the detections' 2D joints copied once any is flipped, the person columns, the tracks and
the filter's arrays), ~3 GB for 10,000 frames. :func:`stream_stages` writes the same
arrays, bit for bit (tested), straight into the ``.npy`` files of a results directory
(:mod:`pipeline.results.array_dir`):

* per-frame columns (person-frames, affinity edges) appended chunk by chunk
  (:class:`pipeline.core.npy_stream.NpyRowAppender`);
* the detections' 2D joints copied into a mapped file in slices, the flipped rows
  written over as the frames come, pages released after each chunk;
* tracking on the person-frames' frame and joints (all that stays in RAM: ~8 KB a
  frame at 20 people), then the Kalman filter and smoother over blocks of tracks
  (:func:`pipeline.run.frames.filter_tracks`; every joint trajectory is independent), each
  block's outputs written to mapped files and released.

An input mapped from a file (a scene whose detections are a directory of ``.npy``,
:mod:`pipeline.data.scene`) has its pages released after each chunk too, so a run's resident
memory does not grow with what it has read.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from pipeline.config import PipelineConfig
from pipeline.core.files import atomic_directory
from pipeline.core.npy_stream import NpyRowAppender, open_npy_for_writing, release_pages
from pipeline.core.progress import Progress, StageBar
from pipeline.data.scene import Scene
from pipeline.results.array_dir import write_meta
from pipeline.results.store import (
    EDGE_FIELDS,
    PERSON_FIELDS,
    DetectionLabels,
    FrameColumns,
    FrameResult,
    PipelineResults,
    cache_key,
    empty_columns,
    filter_arrays,
    fit_arrays,
    join_columns,
    load_results,
    pack_frame,
    results_meta,
)
from pipeline.run.bodies import fit_bodies
from pipeline.run.frames import (
    FRAMES_STAGE,
    filter_tracks,
    frame_rows,
    person_evidence,
    proportions_of_tracks,
    restored_joints,
    run_frame,
    select_2d,
    source_joint_set,
    tracks_of_people,
)

if TYPE_CHECKING:
    from pipeline.body.arrays import BodyModelData
    from pipeline.body.model import BodyModel

# frames whose columns are held before they are written (at 31 x 20 a frame's columns are
# ~110 KB: ~7 MB a chunk)
STREAMED_CHUNK_FRAMES = 64
# Frames x joints x tracks per block of the Kalman filter: it holds ~25 arrays of
# (frames, tracks x joints, 3) float64 while it runs, ~80 MB a block at this size.
FILTER_BLOCK_STEPS = 1 << 17
_COPY_BYTES = 64 << 20  # rows copied per slice into a mapped file


def _copy_rows(dst: np.ndarray, src: np.ndarray) -> None:
    """``dst[:] = src`` for (N, ...) arrays in slices, releasing both maps' pages."""
    step = max(1, _COPY_BYTES // max(dst[:1].nbytes, 1))
    for i in range(0, len(dst), step):
        dst[i : i + step] = src[i : i + step]
        release_pages(dst)
        release_pages(src)


class _FrameSink:
    """Where :func:`stream_stages` puts each frame: the detection labels (in RAM, ~9 bytes
    a row), the detections' 2D joints (a mapped file), the person (Q) and edge (E)
    columns (appended to ``NAME.npy`` files of ``out`` every chunk) and what tracking
    needs of the person-frames."""

    def __init__(self, out: Path, joints2d_all: np.ndarray, num_views: int, keep_edges: bool):
        N, J = joints2d_all.shape[:2]
        self.out, self.source, self.V, self.J = out, joints2d_all, num_views, J
        self.joints2d = open_npy_for_writing(out / "det_joints2d.npy", np.float64, (N, J, 3))
        _copy_rows(self.joints2d, joints2d_all)  # flipped rows are written over as they come
        self.labels = DetectionLabels(self.joints2d, writable=True)
        empty = empty_columns(num_views, J)
        names = PERSON_FIELDS + (EDGE_FIELDS if keep_edges else ())
        self.files = {}
        for n in names:
            col = getattr(empty, n)
            self.files[n] = NpyRowAppender(out / f"{n}.npy", col.dtype, col.shape[1:])
        self.no_edges = {} if keep_edges else {n: getattr(empty, n) for n in EDGE_FIELDS}
        self.pending: list[FrameColumns] = []
        self.frames: list[np.ndarray] = []  # (Q,) person_frame, per chunk
        self.joints: list[np.ndarray] = []  # (Q, J, 3) person_joints, per chunk

    def add(self, fr: FrameResult) -> None:
        """One frame's results (as :class:`pipeline.results.store.DetectionLabels` and
        :func:`pipeline.results.store.pack_frame` take them)."""
        self.labels.add(fr)
        cols = pack_frame(fr, self.V, self.J)
        self.pending.append(dataclasses.replace(cols, **self.no_edges))

    def flush(self) -> None:
        """The pending frames' columns to the files; the maps' pages released."""
        cols = join_columns(self.pending, self.V, self.J)
        for name, fh in self.files.items():
            fh.append(getattr(cols, name))
        self.frames.append(cols.person_frame)
        self.joints.append(cols.person_joints)
        self.pending = []
        release_pages(self.joints2d)
        release_pages(self.source)

    def abandon(self) -> None:
        """Close the files as they are (a failed or cancelled run: the caller discards
        the directory)."""
        for fh in self.files.values():
            fh.discard()

    def close(self) -> list[str]:
        """Every file complete; the names of the arrays written."""
        for fh in self.files.values():
            fh.close()
        for name, a in self.no_edges.items():
            np.save(self.out / f"{name}.npy", a, allow_pickle=False)
        self.joints2d.flush()
        np.save(self.out / "det_person.npy", self.labels.person, allow_pickle=False)
        np.save(self.out / "det_flipped.npy", self.labels.flipped, allow_pickle=False)
        return ["det_joints2d", "det_person", "det_flipped", *self.files, *self.no_edges]


def stream_stages(
    scene: Scene,
    config: PipelineConfig,
    joints2d_all: np.ndarray,
    out: str | os.PathLike,
    *,
    restored: np.ndarray | None,
    key: str = "",
    rows_per_frame: list[np.ndarray] | None = None,
    chunk_frames: int = STREAMED_CHUNK_FRAMES,
    keep_edges: bool = True,
    cancelled: Callable[[], bool] | None = None,
    progress: Progress = True,
) -> tuple[dict, list[str]] | None:
    """The stages of :func:`pipeline.run.chunked.run_stages_chunked` (association,
    triangulation, tracking, filtering; no SMPL fit), their arrays written as ``.npy``
    files into directory ``out`` (existing, empty: the caller's temporary directory).

    Args:
        joints2d_all: (N, J, 3) the 2D joints of every detection row (``select_2d``); may
            be memory-mapped (its pages are released after each chunk).
        chunk_frames: frames whose columns are appended to the files at once.
        keep_edges: False leaves the affinity edges (the E arrays) empty.
        cancelled: checked before each frame; once true the run returns None (the files
            in ``out`` are then incomplete: the caller discards the directory).

    Returns:
        (meta, array names) for :func:`pipeline.results.array_dir.write_meta`, or None if
        cancelled.
    """
    if chunk_frames < 1:
        raise ValueError(f"chunk_frames must be >= 1, got {chunk_frames}")
    out = Path(out)
    rows = frame_rows(scene, config) if rows_per_frame is None else rows_per_frame
    V, F = len(scene.rig), scene.num_frames
    sink = _FrameSink(out, joints2d_all, V, keep_edges)
    try:
        with StageBar(FRAMES_STAGE, F, progress, unit="frame") as bar:
            for f in range(F):
                if cancelled is not None and cancelled():
                    return None
                sink.add(run_frame(scene, f, config, joints2d_all, rows=rows[f]))
                if len(sink.pending) == chunk_frames:
                    sink.flush()
                bar.update()
        if cancelled is not None and cancelled():
            return None
        sink.flush()
        names = sink.close()
    finally:
        sink.abandon()  # after close(), nothing is left open; else the files are let go
    if restored is not None:
        np.save(out / "det_restored.npy", np.ascontiguousarray(restored), allow_pickle=False)
        names.append("det_restored")
    js = source_joint_set(scene, config)
    person_frame, person_joints = np.concatenate(sink.frames), np.concatenate(sink.joints)
    evidence = person_evidence(
        scene, config, sink.joints2d,
        np.load(out / "person_members.npy", mmap_mode="r"),
        np.load(out / "person_used.npy", mmap_mode="r"),
    )  # fmt: skip
    del sink
    names += _stream_tracks(out, person_frame, person_joints, F, config, js, evidence)
    meta = results_meta(
        config, joint_set=js.name, num_frames=F, num_views=V, cache_key=key, body_model=None
    )
    return meta, names


def _stream_tracks(
    out: Path, person_frame, person_joints, num_frames, config, js, evidence
) -> list[str]:
    """Tracking, the proportion check, then the filter over blocks of tracks, into
    ``out``: the ``person_track`` and ``track_*`` files' names."""
    tracks = tracks_of_people(person_frame, person_joints, num_frames, config, js)
    tracks, resolved, contradicted = proportions_of_tracks(
        tracks, person_frame, person_joints, num_frames, config, js, evidence
    )
    np.save(out / "person_track.npy", tracks.track_of, allow_pickle=False)
    np.save(out / "track_raw.npy", tracks.joints, allow_pickle=False)
    np.save(out / "track_resolved.npy", resolved, allow_pickle=False)
    np.save(out / "track_contradicted.npy", contradicted, allow_pickle=False)
    K, F, J = tracks.joints.shape[:3]
    block = max(1, FILTER_BLOCK_STEPS // max(F * J, 1))
    files: dict[str, np.ndarray] = {}
    for k0 in range(0, K, block):
        k1 = min(K, k0 + block)
        filtered = filter_tracks(
            tracks.joints[k0:k1], tracks.last_frame[k0:k1], config, skip=contradicted[k0:k1]
        )
        for name, a in filter_arrays(filtered).items():  # each (k, F, J[, 3])
            if name not in files:
                files[name] = open_npy_for_writing(out / f"{name}.npy", a.dtype, (K, *a.shape[1:]))
            files[name][k0:k1] = a
            release_pages(files[name])
        del filtered
    if not files:  # no tracks: the filter of none gives the arrays' dtypes and shapes
        filtered = filter_tracks(tracks.joints, tracks.last_frame, config, skip=contradicted)
        for name, a in filter_arrays(filtered).items():
            np.save(out / f"{name}.npy", a, allow_pickle=False)
            files[name] = a
    for a in files.values():
        if isinstance(a, np.memmap):
            a.flush()
    return ["person_track", "track_raw", "track_resolved", "track_contradicted", *files]


class _Cancelled(Exception):
    """Raised inside the temporary directory's block so the directory is discarded."""


def run_stages_streamed(
    scene: Scene,
    config: PipelineConfig,
    joints2d_all: np.ndarray,
    path: str | os.PathLike,
    *,
    restored: np.ndarray | None,
    key: str = "",
    chunk_frames: int = STREAMED_CHUNK_FRAMES,
    keep_edges: bool = True,
    cancelled: Callable[[], bool] | None = None,
    progress: Progress = True,
) -> PipelineResults | None:
    """:func:`stream_stages` into results directory ``path``, replaced atomically (a
    failed or cancelled run leaves the previous results), then opened lazily
    (:func:`pipeline.results.store.load_results`). Returns None if cancelled."""
    try:
        with atomic_directory(path, overwrite=True) as tmp:
            got = stream_stages(
                scene, config, joints2d_all, tmp, restored=restored, key=key,
                chunk_frames=chunk_frames, keep_edges=keep_edges, cancelled=cancelled,
                progress=progress,
            )  # fmt: skip
            if got is None:
                raise _Cancelled
            write_meta(tmp, *got)
    except _Cancelled:
        return None
    return load_results(path)


def run_pipeline_to_directory(
    scene: Scene,
    config: PipelineConfig,
    model: BodyModel | BodyModelData,
    path: str | os.PathLike,
    *,
    progress: Progress = True,
) -> PipelineResults:
    """``save_results(run_pipeline(scene, config, model), path)`` for a results directory
    ``path`` (the same files, tested) without the results ever whole in memory: the
    stages streamed (:func:`stream_stages`), then the SMPL fits of the mapped smoothed
    tracks added, all in one temporary directory that replaces ``path`` when complete.
    Returns the results opened lazily."""
    restored = restored_joints(scene, model)
    joints2d = select_2d(scene, config, restored)
    key = cache_key(scene, config, model)
    with atomic_directory(path, overwrite=True) as tmp:
        got = stream_stages(scene, config, joints2d, tmp, restored=restored, key=key,
                            progress=progress)  # fmt: skip
        assert got is not None  # nothing cancels it
        meta, names = got
        write_meta(tmp, meta, names)
        fitted = fit_bodies(load_results(tmp), config, model, progress=progress)
        fits = fit_arrays(fitted)
        if fits:
            for name, a in fits.items():
                np.save(tmp / f"{name}.npy", np.ascontiguousarray(a), allow_pickle=False)
            meta["body_model"] = str(fitted.smpl.model.source)
            write_meta(tmp, meta, names + list(fits))
        del fitted  # its maps of the temporary directory's files
    return load_results(path, model=model)
