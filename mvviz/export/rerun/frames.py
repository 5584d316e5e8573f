"""Per-frame entities: images, 2D detections, skeletons, rays, GT skeletons and
meshes, and the logger that clears what a frame lacks (see :mod:`mvviz.export.rerun`)."""

from __future__ import annotations

from collections.abc import Callable

import cv2
import numpy as np
import rerun as rr

from mvviz.export.rerun.layout import (
    GREY_UNTRACKED,
    MM_TO_M,
    ray_segments,
    scaled_intrinsics,
    track_color,
)
from pipeline.data.scene import Scene


def resize(image: np.ndarray, width: int, height: int) -> np.ndarray:
    """``image`` resized to (width, height): halved by 2x2 means (OpenCV's fast integer
    INTER_AREA) while more than twice too wide, then bilinear; ~5x faster than one
    INTER_AREA at a fractional scale, with as little aliasing."""
    while image.shape[1] >= 2 * width and image.shape[0] >= 2 * height:
        image = cv2.resize(image, None, fx=0.5, fy=0.5, interpolation=cv2.INTER_AREA)
    if image.shape[1] != width or image.shape[0] != height:
        image = cv2.resize(image, (width, height), interpolation=cv2.INTER_LINEAR)
    return image


def encode_jpeg(image_bgr: np.ndarray, width: int, height: int, *, quality: int = 80) -> bytes:
    """Resize a BGR image to (width, height) and JPEG-encode it."""
    image_bgr = resize(image_bgr, width, height)
    ok, buf = cv2.imencode(".jpg", image_bgr, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise RuntimeError("JPEG encoding failed")
    return buf.tobytes()


class _FrameLogger:
    """Logs per-frame entities and clears those absent from this frame: logged in the
    previous frame (frames in order, as the export) or ever (``sparse``: the frames a
    viewer visits, in any order). ``pause()`` runs before each log call (the live mode
    waits there while the viewer renders)."""

    def __init__(
        self,
        rec: rr.RecordingStream,
        *,
        sparse: bool = False,
        pause: Callable[[], None] | None = None,
    ) -> None:
        self.rec, self.sparse, self.pause = rec, sparse, pause
        self._prev: set[str] = set()
        self._now: set[str] = set()

    def log(self, path: str, entity) -> None:
        if self.pause is not None:
            self.pause()
        self.rec.log(path, entity)
        self._now.add(path)

    def end_frame(self) -> None:
        for path in sorted(self._prev - self._now):
            self.rec.log(path, rr.Clear(recursive=False))
        self._prev = self._prev | self._now if self.sparse else self._now
        self._now = set()


def _log_cameras(rec: rr.RecordingStream, scene: Scene, widths: dict[str, int]) -> dict:
    """Static camera poses and pinholes; returns camera name -> (width, height, s)."""
    out = {}
    for cam in scene.rig:
        K, w, h, s = scaled_intrinsics(cam, widths[cam.name])
        path = f"world/cameras/{cam.name}"
        T = cam.T_world_camera
        rec.log(
            path,
            rr.Transform3D(translation=T[:3, 3] * MM_TO_M, mat3x3=T[:3, :3]),
            rr.Pinhole(image_from_camera=K, resolution=[w, h], camera_xyz=rr.ViewCoordinates.RDF),
            static=True,
        )
        out[cam.name] = (w, h, s)
    return out


def _group(values: np.ndarray) -> dict[int, np.ndarray]:
    """Value -> indices where ``values`` equals it."""
    order = np.argsort(values, kind="stable")
    keys, starts = np.unique(values[order], return_index=True)
    return {int(k): idx for k, idx in zip(keys, np.split(order, starts[1:]), strict=True)}


def _log_detections(logger, scene, results, layout, cam_size, rows) -> None:
    """Per camera: the 2D joints of this frame, coloured by track (pools for the rest)."""
    if rows is None:
        rows = np.zeros(0, int)
    views = scene.detections.view[rows]
    J = results.det_joints2d.shape[1]
    for v, cam in enumerate(scene.rig):
        _, _, s = cam_size[cam.name]
        pos, kid, cid = [], [], []
        n_un = n_ut = 0
        for r in rows[views == v]:
            q = results.det_person[r]
            k = results.person_track[q] if q >= 0 else -1
            if k >= 0:
                c = layout.filtered(int(k))
            elif q >= 0:
                c, n_ut = layout.untracked(n_ut), n_ut + 1
            else:
                c, n_un = layout.unassigned(n_un), n_un + 1
            kp = results.det_joints2d[r]
            ok = (kp[:, 2] > 0) & np.isfinite(kp[:, :2]).all(1)
            pos.append(s * (kp[ok, :2] + 0.5))
            kid.append(np.arange(J)[ok])
            cid.append(np.full(int(ok.sum()), c))
        if pos:
            logger.log(
                f"world/cameras/{cam.name}/detections",
                rr.Points2D(
                    np.concatenate(pos),
                    keypoint_ids=np.concatenate(kid),
                    class_ids=np.concatenate(cid),
                    radii=rr.Radius.ui_points(3.0),
                ),
            )


def _points3d(joints_mm: np.ndarray, class_id: int, radius: float) -> rr.Points3D | None:
    ok = np.isfinite(joints_mm).all(1)
    if not ok.any():
        return None
    return rr.Points3D(
        joints_mm[ok] * MM_TO_M,
        keypoint_ids=np.flatnonzero(ok),
        class_ids=class_id,
        radii=radius,
    )


def _log_skeletons(logger, results, layout, filtered, f: int) -> None:
    for k in range(results.num_tracks):
        raw = _points3d(results.track_raw[k, f], layout.raw(k), 0.012)
        if raw is not None:
            logger.log(f"world/skeletons/raw/{k}", raw)
        filt = _points3d(filtered[k, f], layout.filtered(k), 0.02)
        if filt is not None:
            logger.log(f"world/skeletons/filtered/{k}", filt)


def _log_rays(logger, scene, results, people) -> None:
    """For each person of the frame: a segment per (used joint, view)."""
    if people is None:
        return
    by_track: dict[str, list[np.ndarray]] = {}
    for q in people:
        k = int(results.person_track[q])
        key = str(k) if k >= 0 else "untracked"
        X = results.person_joints[q]
        for v, cam in enumerate(scene.rig):
            r = results.person_members[q, v]
            if r < 0:
                continue
            js = np.flatnonzero(results.person_used[q, :, v] & np.isfinite(X).all(1))
            js = js[np.isfinite(results.det_joints2d[r, js, :2]).all(1)]
            if js.size == 0:
                continue
            start, end = ray_segments(cam, results.det_joints2d[r, js, :2], X[js])
            by_track.setdefault(key, []).append(np.stack([start, end], 1) * MM_TO_M)
    for key, segs in by_track.items():
        color = GREY_UNTRACKED if key == "untracked" else track_color(int(key))
        logger.log(
            f"world/rays/{key}",
            rr.LineStrips3D(np.concatenate(segs), colors=[(*color, 110)], radii=0.002),
        )


def _log_gt(logger, gt, layout, rows: np.ndarray, mesh_vertices: np.ndarray | None) -> None:
    """GT skeletons and, given ``mesh_vertices`` ((len(rows), V', 3) m, one mesh per row
    of ``rows``), GT meshes."""
    for n, i in enumerate(rows):
        p = int(gt.person_id[i])
        pts = _points3d(gt.joints3d[i], layout.gt(p), 0.015)
        if pts is not None:
            logger.log(f"world/skeletons/gt/{p}", pts)
        if mesh_vertices is not None:
            logger.log(
                f"world/meshes/gt/{p}", rr.Mesh3D.from_fields(vertex_positions=mesh_vertices[n])
            )


def _send_mesh_column(rec, path: str, frames, vertices, lengths, fps: float) -> None:
    """Mesh vertex positions over ``frames`` as one column: ``vertices`` (N, V, 3) m are
    the rows of the frames with ``lengths`` V (the others, 0, get an empty mesh)."""
    frames = np.asarray(frames)
    rec.send_columns(
        path,
        indexes=[
            rr.TimeColumn("frame", sequence=frames),
            rr.TimeColumn("time", duration=frames / fps),
        ],
        columns=rr.Mesh3D.columns(vertex_positions=vertices.reshape(-1, 3)).partition(lengths),
    )
