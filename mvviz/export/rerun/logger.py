"""SceneLogger: one scene and its results into a recording, static context, frames
and columns, with the layout of :mod:`mvviz.export.rerun`."""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence

import numpy as np
import rerun as rr
import torch

from mvviz.export.heap import release_free_heap
from mvviz.export.rerun.frames import (
    _FrameLogger,
    _group,
    _log_cameras,
    _log_detections,
    _log_gt,
    _log_rays,
    _log_skeletons,
    _points3d,
    _send_mesh_column,
    encode_jpeg,
)
from mvviz.export.rerun.layout import (
    BODY_STAGES,
    DEFAULT_PLOT_JOINTS,
    GT_COLOR,
    MM_TO_M,
    ClassLayout,
    MeshSequence,
    _pool_sizes,
    annotation_context,
    body_color,
    check_inputs,
    make_blueprint,
    resolve_plot_joint,
    scaled_intrinsics,
)
from mvviz.export.rerun.meshes import display_mesh, skin_subset
from mvviz.export.rerun.series import _log_plots
from pipeline.body.model import BodyModel, torch_body_model
from pipeline.core.npy_stream import mapped_arrays, release_pages
from pipeline.data.joint_sets import get_joint_set
from pipeline.data.scene import Scene
from pipeline.fit.types import SmplFit
from pipeline.results.store import PipelineResults
from pipeline.run.frames import row_frames

SKIN_BATCH = 128  # meshes skinned per torch call
MESH_CHUNK_FRAMES = 64
"""Frames of mesh vertices sent per ``send_columns`` call: 20 people x ~1,700 kept
vertices x 12 bytes x 64 frames is ~26 MB, whatever the scene's length."""


PLOT_CHUNK_FRAMES = 1024
"""Frames of the time series sent per piece: a piece's columns wait in rerun's queue
until it is drained, and every piece cuts a chunk per series (each with an entry in
the file's index), so pieces are longer than the meshes'."""


def _chunks(values: np.ndarray, size: int) -> list[np.ndarray]:
    """``values`` cut in consecutive pieces of ``size`` (0: one piece)."""
    size = len(values) if size <= 0 else int(size)
    return [values[a : a + size] for a in range(0, len(values), max(size, 1))]


ImageLike = bytes | np.ndarray  # JPEG bytes, or a BGR uint8 image (h, w, 3)


class SceneLogger:
    """Logs one scene and its results into a recording: static context, frames, columns.

    Built once per results (the class layout, detection groups and GT mesh vertices are
    precomputed here); :func:`log_scene`, the export and the live viewer call its methods.

    Args:
        recording: where to log (None: rerun's global recording, as ``rr.log`` does).
        body_model: skins the GT meshes (None or ``meshes=False``: no GT meshes).
        bodies: log the fitted SMPL bodies of ``results.smpl`` / ``results.smpl_vae`` at
            ``world/bodies/<stage>/<track>`` (each fit skins with its own body model).
        image_width: width of the logged images, px (never more than the camera's); the
            pinholes match it. ``images=False``: pinholes at the camera's resolution.
        mesh_cell_mm: the GT meshes are decimated with :func:`decimate_mesh` at this cell
            size (25 mm keeps ~1/4 of the vertices); None keeps them all. The fitted
            bodies are decimated the same way.
        extra_meshes: name -> :class:`MeshSequence`, logged at ``world/meshes/<name>``.
        plot_joints: joints plotted per track (aliases such as ``pelvis`` resolve per set).
        sparse: frames come in any order (a viewer's visits): a frame clears every entity
            logged before that it lacks, not only those of the previous frame.
        pause: called before each per-frame log call (the live viewer yields there).
    """

    def __init__(
        self,
        scene: Scene,
        results: PipelineResults,
        recording: rr.RecordingStream | None = None,
        *,
        body_model: BodyModel | None = None,
        images: bool = True,
        image_width: int = 480,
        jpeg_quality: int = 80,
        meshes: bool = True,
        bodies: bool = True,
        mesh_cell_mm: float | None = 25.0,
        extra_meshes: Mapping[str, MeshSequence] | None = None,
        plot_joints: Sequence[str] = DEFAULT_PLOT_JOINTS,
        sparse: bool = False,
        pause: Callable[[], None] | None = None,
    ) -> None:
        check_inputs(scene, results)
        self.scene, self.results, self.body_model = scene, results, body_model
        self.rec = recording if recording is not None else rr.get_global_data_recording()
        if self.rec is None:
            raise ValueError("no recording: pass recording= or call rr.init(...) first")
        self.images, self.jpeg_quality = images, jpeg_quality
        self.joint_set = get_joint_set(results.joint_set)
        self.plot_idx = {name: resolve_plot_joint(self.joint_set, name) for name in plot_joints}
        det, gt = scene.detections, scene.gt
        n_unassigned, n_untracked = _pool_sizes(results, row_frames(scene, results.config),
                                                det.view)  # fmt: skip
        self.layout = ClassLayout(
            num_tracks=results.num_tracks,
            gt_people=tuple(int(p) for p in np.unique(gt.person_id)) if gt is not None else (),
            num_unassigned=n_unassigned,
            num_untracked=n_untracked,
        )
        widths = {c.name: (min(image_width, c.width) if images else c.width) for c in scene.rig}
        self.cam_size = {}  # camera name -> (width, height, s) of its pinhole and images
        for cam in scene.rig:
            _, w, h, s = scaled_intrinsics(cam, widths[cam.name])
            self.cam_size[cam.name] = (w, h, s)
        self._widths = widths
        self.rows_by_frame = _group(row_frames(scene, results.config))  # as the stages used
        self.person_by_frame = _group(results.person_frame)
        self.gt_by_frame = _group(gt.frame) if gt is not None else {}
        self.extra = dict(extra_meshes or {})
        self._extra_rows = {
            name: {int(f): i for i, f in enumerate(np.asarray(seq.frames))}
            for name, seq in self.extra.items()
        }
        self.mesh_faces = self.mesh_keep = None
        has_smpl = gt is not None and all(
            a is not None for a in (gt.smpl_pose, gt.smpl_betas, gt.transl)
        )
        if meshes and body_model is not None and has_smpl:
            self.mesh_keep, self.mesh_faces = display_mesh(body_model, mesh_cell_mm)
        self._mesh_vertices: np.ndarray | None = None
        # the fitted bodies: stage -> SmplFit, and (keep, faces) of its display mesh
        self.fits: dict[str, SmplFit] = {}
        self.body_meshes: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        for stage in BODY_STAGES if bodies else ():
            fit = getattr(results, stage, None)
            if fit is not None and fit.present.any():
                self.fits[stage] = fit
                self.body_meshes[stage] = display_mesh(torch_body_model(fit.model), mesh_cell_mm)
        self._frames = _FrameLogger(self.rec, sparse=sparse, pause=pause)
        # the memory-mapped arrays under the scene and its results (a results directory,
        # a detections directory): what a drain hands back (see drain)
        self._mapped = mapped_arrays(scene, results)

    @property
    def has_meshes(self) -> bool:
        return self.mesh_faces is not None

    # ------------------------------------------------------------------ static

    def log_static(self, *, blueprint: bool = False) -> None:
        """View coordinates, annotation context, cameras, mesh faces (and the blueprint)."""
        rec, scene = self.rec, self.scene
        if blueprint:
            rec.send_blueprint(make_blueprint(scene.rig.names), make_active=False)
        rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        rec.log("world", annotation_context(self.layout, self.joint_set), static=True)
        _log_cameras(rec, scene, self._widths)
        if self.has_meshes:
            for p in self.layout.gt_people:
                rec.log(
                    f"world/meshes/gt/{p}",
                    rr.Mesh3D.from_fields(triangle_indices=self.mesh_faces, albedo_factor=GT_COLOR),
                    static=True,
                )
        for stage, fit in self.fits.items():
            faces = self.body_meshes[stage][1]
            for k in np.flatnonzero(fit.present.any(1)):
                rec.log(
                    f"world/bodies/{stage}/{k}",
                    rr.Mesh3D.from_fields(
                        triangle_indices=faces, albedo_factor=body_color(stage, int(k))
                    ),
                    static=True,
                )
        for name, seq in self.extra.items():
            rec.log(
                f"world/meshes/{name}",
                rr.Mesh3D.from_fields(
                    triangle_indices=np.asarray(seq.faces, np.uint32), albedo_factor=seq.color
                ),
                static=True,
            )

    # ------------------------------------------------------------------ frames

    def gt_mesh_vertices(self, rows: np.ndarray) -> np.ndarray | None:
        """(len(rows), V', 3) float32 world METRES: the decimated mesh of each GT row of
        ``rows``, skinned in batches (None without meshes). Only the rows asked for: a
        long scene's every GT mesh would not fit in memory (10,000 frames x 20 people x
        ~1,700 kept vertices is ~4 GB)."""
        if not self.has_meshes:
            return None
        gt, keep = self.scene.gt, self.mesh_keep
        rows = np.asarray(rows, np.int64)
        out = np.empty((len(rows), len(keep), 3), np.float32)
        with torch.no_grad():
            for a in range(0, len(rows), SKIN_BATCH):
                r = rows[a : a + SKIN_BATCH]
                v = skin_subset(self.body_model, gt.smpl_pose[r], gt.smpl_betas[r], keep)
                out[a : a + len(r)] = v + gt.transl[r, None, :] * MM_TO_M
        return out

    def body_vertices(self, stage: str, tracks: np.ndarray, frames: np.ndarray) -> np.ndarray:
        """(N, V', 3) float32 world METRES: the display mesh of the ``stage`` fit of
        ``tracks[i]`` at ``frames[i]`` (present person-frames), skinned in batches."""
        fit, (keep, _) = self.fits[stage], self.body_meshes[stage]
        out = np.empty((len(tracks), len(keep), 3), np.float32)
        model = torch_body_model(fit.model)  # a loaded run's fit holds the numpy arrays
        with torch.no_grad():
            for a in range(0, len(out), SKIN_BATCH):
                k, f = tracks[a : a + SKIN_BATCH], frames[a : a + SKIN_BATCH]
                scales = None if fit.bone_scales is None else fit.bone_scales[k]
                v = skin_subset(model, fit.pose_rotvecs[k, f], fit.betas[k], keep, scales)
                out[a : a + len(k)] = v + fit.transl[k, f][:, None, :] * MM_TO_M
        return out

    def set_time(self, frame: int) -> None:
        self.rec.set_time("frame", sequence=int(frame))
        self.rec.set_time("time", duration=int(frame) / self.scene.fps)

    def log_frame(
        self,
        frame: int,
        *,
        images: Mapping[str, ImageLike | None] | None = None,
        gt_meshes: bool = True,
        bodies: bool = True,
        filter_b: np.ndarray | None = None,
    ) -> None:
        """Set the time to ``frame`` and log its per-frame entities.

        Args:
            images: camera name -> JPEG bytes already at the pinhole's size, or a BGR
                image (resized and encoded here); cameras left out log no image.
            gt_meshes: log the GT meshes' vertices (the export sends them as columns).
            bodies: log the fitted bodies' vertices (the export sends them as columns).
            filter_b: (K, F, J, 3) mm, a second filter's tracks, logged at
                ``world/skeletons/filter_b/<track>``.
        """
        f, logger, res, layout = int(frame), self._frames, self.results, self.layout
        self.set_time(f)
        for name, img in (images or {}).items():
            if img is None:
                continue
            if not isinstance(img, bytes | bytearray | memoryview):
                w, h, _ = self.cam_size[name]
                img = encode_jpeg(img, w, h, quality=self.jpeg_quality)
            logger.log(
                f"world/cameras/{name}/image",
                rr.EncodedImage(contents=bytes(img), media_type="image/jpeg"),
            )
        _log_detections(logger, self.scene, res, layout, self.cam_size, self.rows_by_frame.get(f))
        _log_skeletons(logger, res, layout, res.track_filtered, f)
        if filter_b is not None:
            for k in range(res.num_tracks):
                pts = _points3d(filter_b[k, f], layout.filtered(k), 0.016)
                if pts is not None:
                    logger.log(f"world/skeletons/filter_b/{k}", pts)
        _log_rays(logger, self.scene, res, self.person_by_frame.get(f))
        gt = self.scene.gt
        if gt is not None and f in self.gt_by_frame:
            rows = self.gt_by_frame[f]
            _log_gt(logger, gt, layout, rows, self.gt_mesh_vertices(rows) if gt_meshes else None)
        for stage, fit in self.fits.items() if bodies else ():
            ks = np.flatnonzero(fit.present[:, f])
            if ks.size:
                verts = self.body_vertices(stage, ks, np.full(ks.size, f))
                for k, v in zip(ks, verts, strict=True):
                    logger.log(
                        f"world/bodies/{stage}/{k}", rr.Mesh3D.from_fields(vertex_positions=v)
                    )
        for name, seq in self.extra.items():
            i = self._extra_rows[name].get(f)
            if i is not None:
                logger.log(
                    f"world/meshes/{name}",
                    rr.Mesh3D.from_fields(vertex_positions=np.asarray(seq.vertices[i])),
                )
        logger.end_frame()

    # ------------------------------------------------------------------ columns

    def send_gt_meshes(self, frame_ids: np.ndarray, chunk_frames: int = MESH_CHUNK_FRAMES) -> None:
        """Every GT mesh's vertices over ``frame_ids`` as columns per person
        (``send_columns``), ``chunk_frames`` frames at a time (0: all at once), each
        chunk skinned just before it is sent: the export's memory stays that of one
        chunk however long the scene. From the person's first frame on, a
        frame where it is absent gets an empty mesh."""
        gt = self.scene.gt
        if not self.has_meshes:
            return
        frame_ids = np.asarray(frame_ids, np.int64)
        fps = self.scene.fps
        for p in self.layout.gt_people:
            mine = np.flatnonzero(gt.person_id == p)
            row_at = np.full(self.scene.num_frames, -1, np.int64)
            row_at[gt.frame[mine]] = mine
            present = row_at[frame_ids] >= 0
            if not present.any():
                continue
            fr = frame_ids[int(np.argmax(present)) :]  # from the first frame with the person
            for chunk in _chunks(fr, chunk_frames):
                rows = row_at[chunk]
                lengths = np.where(rows >= 0, len(self.mesh_keep), 0)
                verts = self.gt_mesh_vertices(rows[rows >= 0])
                _send_mesh_column(self.rec, f"world/meshes/gt/{p}", chunk, verts, lengths, fps)
                self.drain(chunk_frames)

    def send_bodies(self, frame_ids: np.ndarray, chunk_frames: int = MESH_CHUNK_FRAMES) -> None:
        """Every fitted body's vertices over ``frame_ids`` as columns per (stage, track),
        chunk by chunk, as :meth:`send_gt_meshes`."""
        frame_ids = np.asarray(frame_ids, np.int64)
        for stage, fit in self.fits.items():
            n = len(self.body_meshes[stage][0])
            present = fit.present[:, frame_ids]  # (K, F')
            first = np.where(present.any(1), np.argmax(present, 1), len(frame_ids))
            for chunk_at in _chunks(np.arange(len(frame_ids)), chunk_frames):
                lo, hi = int(chunk_at[0]), int(chunk_at[-1]) + 1
                started = np.flatnonzero(first < hi)  # empty meshes where a track pauses
                if started.size == 0:
                    continue
                ks, cols = np.nonzero(present[:, lo:hi])
                verts = self.body_vertices(stage, ks, frame_ids[lo + cols])
                for k in started:
                    start = max(lo, int(first[k]))  # from the track's first fitted frame
                    lengths = np.where(present[k, start:hi], n, 0)
                    _send_mesh_column(self.rec, f"world/bodies/{stage}/{k}",
                                      frame_ids[start:hi], verts[ks == k], lengths,
                                      self.scene.fps)  # fmt: skip
                self.drain(chunk_frames)

    def drain(self, chunk_frames: int) -> None:
        """Wait until what was sent is written: rerun queues what it is given faster
        than its writer compresses and writes it, so without this a whole scene's meshes
        wait in memory (measured: ~150 KB a frame of the sample kept until the end)."""
        if chunk_frames > 0:
            self.rec.flush()
            release_free_heap()  # the chunk's freed buffers leave the heap (mvviz.export.heap)
            # and the pages of the mapped results read so far leave the resident set: the
            # kernel could reclaim them, but they would show as ~90 KB a frame of
            # resident memory on a 16-camera dome (bench_export_memory's file pages)
            for arr in self._mapped:
                release_pages(arr)

    def send_plots(
        self,
        frame_ids: np.ndarray | None = None,
        *,
        branch: str = "",
        filtered: np.ndarray | None = None,
        mahalanobis: np.ndarray | None = None,
        chunk_frames: int = PLOT_CHUNK_FRAMES,
    ) -> None:
        """The time series (see the module docstring) as columns, ``chunk_frames`` frames
        at a time (0: all at once), drained after each piece: what waits to be written is
        one piece's, however long the scene. A ``branch`` with ``filtered`` (K, F, J, 3) mm
        and ``mahalanobis`` (K, F, J) is a second filter (its raw input and counts are the
        results' own and are left out)."""
        frame_ids = np.arange(self.scene.num_frames) if frame_ids is None else frame_ids
        other_filter = filtered is not None
        for i, piece in enumerate(_chunks(np.asarray(frame_ids, np.int64), chunk_frames)):
            _log_plots(
                self.rec, self.scene, self.results, piece, self.plot_idx,
                self.person_by_frame, self.gt_by_frame, branch=branch, filtered=filtered,
                mahalanobis=mahalanobis, raw=not other_filter, counts=not other_filter,
                styles=i == 0,
            )  # fmt: skip
            self.drain(chunk_frames)
