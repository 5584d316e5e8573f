"""Export a scene and its pipeline results as a rerun recording (``.rrd``), and read one back.

The entity layout, timelines and units are those of :mod:`mvviz.export.rerun` (documented there
once); this module writes them to a file atomically, fast: the camera images are read,
resized and JPEG-encoded on one thread per camera ahead of the logging loop, and the GT
meshes, fitted bodies and time series go out as columns (``send_columns``). Open a file with
``rerun run.rrd``.
"""

from __future__ import annotations

import os
import queue
import tempfile
import threading
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from datetime import timedelta
from pathlib import Path

import numpy as np
import rerun as rr
import torch
from rerun.chunk import RrdReader

from mvviz.export.rerun import (  # noqa: F401  (re-exported: the names this module always had)
    APP_ID,
    DEFAULT_PLOT_JOINTS,
    MESH_CHUNK_FRAMES,
    MM_TO_M,
    ClassLayout,
    MeshSequence,
    SceneLogger,
    annotation_context,
    check_inputs,
    decimate_mesh,
    encode_jpeg,
    make_blueprint,
    ray_segments,
    resolve_plot_joint,
    scaled_intrinsics,
    select_frames,
    track_color,
)
from mvviz.export.rerun.sources import FrameSource, scene_frame_sources  # noqa: F401  (re-exported)
from pipeline.body.arrays import BodyModelData
from pipeline.body.model import BodyModel, torch_body_model
from pipeline.core.progress import Progress, track
from pipeline.data.scene import Scene
from pipeline.results.store import PipelineResults
from pipeline.stages.retime import picture_frame

PREFETCH_FRAMES = 16  # images read ahead per camera


def export_batcher() -> rr.ChunkBatcherConfig:
    """How the export's recording cuts its rows into chunks: when the export flushes (every
    :data:`MESH_CHUNK_FRAMES` frames and after each mesh chunk) or an entity's rows reach
    rerun's 2 MB, never on rerun's 200 ms clock. Rerun keeps a little of every chunk it
    writes until the recording closes, and on its clock the chunks depended on how fast
    the export ran, not on the data: with it the export's memory grew ~33 KB a frame of a
    16-camera, 10-person scene (+25 MB from 250 to 1,000 frames before any mesh was sent);
    flushed by the export, the same stays flat. Fewer, larger chunks load faster too."""
    return rr.ChunkBatcherConfig(flush_tick=timedelta(hours=1))


# --------------------------------------------------------------------------- reading back


@dataclass(frozen=True)
class RrdSummary:
    """What a recording holds, read back from the file.

    Attributes:
        rows: entity path -> number of rows logged (static and temporal).
        components: entity path -> component names, e.g. ``"Pinhole:image_from_camera"``.
        static_entities: entity paths with static data.
        frames: sorted distinct values of the ``frame`` timeline.
    """

    rows: dict[str, int]
    components: dict[str, set[str]]
    static_entities: frozenset[str]
    frames: np.ndarray

    @property
    def entities(self) -> list[str]:
        return sorted(self.rows)


def read_rrd_summary(path: str | os.PathLike) -> RrdSummary:
    """Read a ``.rrd`` back (its first recording store; blueprints are separate stores)."""
    rows: dict[str, int] = {}
    components: dict[str, set[str]] = {}
    static: set[str] = set()
    frames: list[np.ndarray] = []
    for chunk in RrdReader(str(path)).stream():
        ent = str(chunk.entity_path)
        rows[ent] = rows.get(ent, 0) + int(chunk.num_rows)
        batch = chunk.to_record_batch()
        names = set(batch.schema.names)
        components.setdefault(ent, set()).update(n for n in names if ":" in n)
        if chunk.is_static:
            static.add(ent)
        elif "frame" in names:
            # a copy: a zero-copy view would keep the chunk's whole decoded buffer (its
            # meshes too) alive, ~2 MB a frame of a 20-person dome's recording
            frames.append(np.unique(batch.column("frame").to_numpy(zero_copy_only=False)))
    all_frames = np.unique(np.concatenate(frames)) if frames else np.zeros(0, np.int64)
    return RrdSummary(rows, components, frozenset(static), all_frames.astype(np.int64))


def count_entities(path: str | os.PathLike) -> dict[str, int]:
    """Entity path -> rows logged, of the recording at ``path`` (private ``/__*`` ones left out)."""
    return {k: v for k, v in read_rrd_summary(path).rows.items() if not k.startswith("/__")}


# --------------------------------------------------------------------------- images


class _Prefetcher:
    """One thread per camera reading, resizing and JPEG-encoding ``frames`` in order,
    up to PREFETCH_FRAMES ahead (OpenCV releases the GIL: this overlaps the logging)."""

    def __init__(
        self, sources: Mapping[str, FrameSource], frames, cam_size, quality, offsets=None
    ) -> None:
        self._queues = {name: queue.Queue(PREFETCH_FRAMES) for name in sources}
        self._stop = threading.Event()
        # A camera re-timed by sync.offsets shows the picture its used rows were recorded in.
        picture = {
            name: [picture_frame(offsets or {}, name, f) for f in frames] for name in sources
        }
        self._threads = [
            threading.Thread(
                target=self._read,
                args=(src, picture[name], cam_size[name], quality, self._queues[name]),
                name=f"rrd-images-{name}", daemon=True,
            )
            for name, src in sources.items()
        ]  # fmt: skip
        for t in self._threads:
            t.start()

    def _read(self, src, frames, size, quality, q) -> None:
        w, h, _ = size
        for f in frames:
            try:
                img = src.read(f)
                item = None if img is None else encode_jpeg(img, w, h, quality=quality)
            except Exception as exc:  # re-raised on the logging thread
                item = exc
            while not self._stop.is_set():
                try:
                    q.put(item, timeout=0.1)
                    break
                except queue.Full:
                    continue
            if self._stop.is_set() or isinstance(item, Exception):
                return

    def next(self) -> dict[str, bytes | None]:
        out = {}
        for name, q in self._queues.items():
            item = q.get()
            if isinstance(item, Exception):
                raise item
            out[name] = item
        return out

    def close(self) -> None:
        self._stop.set()
        for t in self._threads:
            t.join(timeout=5)


# --------------------------------------------------------------------------- export


def export_rrd(
    scene: Scene,
    results: PipelineResults,
    body_model: BodyModel | BodyModelData | None,
    path: str | os.PathLike,
    *,
    frames: slice | range | Iterable[int] | None = None,
    images: bool = True,
    image_width: int = 480,
    jpeg_quality: int = 80,
    meshes: bool = True,
    bodies: bool = True,
    mesh_cell_mm: float | None = 25.0,
    extra_meshes: Mapping[str, MeshSequence] | None = None,
    plot_joints: Sequence[str] = DEFAULT_PLOT_JOINTS,
    mesh_chunk_frames: int = MESH_CHUNK_FRAMES,
    progress: Progress = True,
) -> Path:
    """Write ``scene`` and its ``results`` to the recording ``path``, atomically.

    The file is written beside ``path`` under a temporary name and renamed when complete
    (missing parent directories are created); on any error the temporary file is removed
    and ``path`` is left as it was. What is logged is :func:`mvviz.export.rerun.log_scene`'s.

    Args:
        body_model: skins the GT meshes (``None`` or ``meshes=False``: no GT meshes).
        mesh_cell_mm: GT meshes are decimated with :func:`decimate_mesh` at this cell size
            (25 mm keeps ~1/4 of the open model's vertices); ``None`` keeps them all.
            Vertex positions dominate the file size: 12 bytes per vertex per frame.
        bodies: log the fitted SMPL bodies (``results.smpl`` / ``smpl_vae``) at
            ``world/bodies/<stage>/<track>``, decimated at ``mesh_cell_mm`` as well.
        frames: the scene frames to log (default all), e.g. ``range(100, 150)``.
        images: log each camera's video frame, downscaled to ``image_width`` pixels (never
            upscaled) and JPEG-encoded; without images the pinholes keep the camera's
            full resolution.
        extra_meshes: name -> MeshSequence, logged at ``world/meshes/<name>``.
        plot_joints: joints plotted per track (aliases such as ``pelvis`` resolve per set).
        mesh_chunk_frames: frames of GT meshes and bodies skinned and sent at a time: the
            export's memory does not grow with the scene's length (0: all at once).
    Returns:
        ``path``.
    """
    path = Path(path)
    check_inputs(scene, results)
    frame_ids = select_frames(frames, scene.num_frames)
    tmp = _temp_beside(path)
    rec = rr.RecordingStream(APP_ID, batcher_config=export_batcher())
    sources: dict[str, FrameSource] = {}
    prefetch: _Prefetcher | None = None
    # rerun encodes and writes on its own threads; torch's intra-op threads spinning
    # beside them made skinning ~10x slower on a 2-core machine. Restored below.
    torch_threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        logger = SceneLogger(
            scene, results, rec, images=images,
            body_model=None if body_model is None else torch_body_model(body_model),
            image_width=image_width, jpeg_quality=jpeg_quality, meshes=meshes, bodies=bodies,
            mesh_cell_mm=mesh_cell_mm, extra_meshes=extra_meshes, plot_joints=plot_joints,
        )  # fmt: skip
        rec.set_log_time_enabled(False)
        rec.save(tmp, default_blueprint=make_blueprint(scene.rig.names))
        rec.send_recording_name(scene.name)
        logger.log_static()
        if images:
            sources = scene_frame_sources(scene)
            offsets = results.config.sync.by_camera()  # re-timed cameras' pictures
            prefetch = _Prefetcher(sources, frame_ids, logger.cam_size, jpeg_quality, offsets)
        _log_frames(logger, frame_ids, prefetch, progress, mesh_chunk_frames)
        _complete(rec, tmp, path)
    except BaseException:
        try:
            rec.disconnect()
        finally:
            tmp.unlink(missing_ok=True)
        raise
    finally:
        torch.set_num_threads(torch_threads)
        _close_readers(prefetch, sources)
    return path


def _close_readers(prefetch: _Prefetcher | None, sources: Mapping[str, FrameSource]) -> None:
    """Stop the image prefetch threads, then close the video readers they read from."""
    if prefetch is not None:
        prefetch.close()
    for src in sources.values():
        src.close()


def _temp_beside(path: Path) -> Path:
    """A new empty temporary file in ``path``'s directory (created if missing)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    os.close(fd)
    return Path(tmp_name)


def _log_frames(
    logger: SceneLogger,
    frame_ids: np.ndarray,
    prefetch: _Prefetcher | None,
    progress: Progress,
    mesh_chunk_frames: int = MESH_CHUNK_FRAMES,
) -> None:
    """Every frame (with its prefetched images), then the GT meshes, bodies and plots."""
    for i, f in enumerate(track(frame_ids, "export rrd", progress, unit="frame")):
        imgs = prefetch.next() if prefetch is not None else None
        logger.log_frame(int(f), images=imgs, gt_meshes=False, bodies=False)
        if mesh_chunk_frames > 0 and (i + 1) % mesh_chunk_frames == 0:
            logger.drain(mesh_chunk_frames)  # written before more is queued: one chunk's memory
    logger.send_gt_meshes(frame_ids, mesh_chunk_frames)
    logger.send_bodies(frame_ids, mesh_chunk_frames)
    logger.send_plots(frame_ids)


def _complete(rec: rr.RecordingStream, tmp: Path, path: Path) -> None:
    """Close the recording in ``tmp`` and move it to ``path``, synced, in the usual mode."""
    rec.flush()
    rec.disconnect()  # closes the file and writes its footer
    with open(tmp, "rb+") as fh:
        os.fsync(fh.fileno())
    os.chmod(tmp, 0o666 & ~_umask())  # mkstemp makes 0600; give the usual file mode
    os.replace(tmp, path)


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask
