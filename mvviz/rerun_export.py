"""Export a scene and its pipeline results as a rerun recording (``.rrd``).

Every rerun call of the project lives in this module: rerun's API changes between
versions (this is written against rerun-sdk 0.41). Open a file with ``rerun run.rrd``.

Units: the recording's world is in METRES, z up (the pipeline's millimetres are divided
by 1000 on the way in); plots keep millimetres. Image coordinates follow rerun's
convention, origin at the top-left CORNER of the top-left pixel: an OpenCV pixel
``(u, v)`` (origin at that pixel's centre) is drawn at ``s * (u + 0.5, v + 0.5)`` for an
image downscaled by ``s``, and the pinhole's intrinsics are shifted and scaled to match.

Entity layout (static context is logged once; each frame sets the time and logs under
paths that mirror the data)::

    world                                      ViewCoordinates RIGHT_HAND_Z_UP and the
                                               AnnotationContext (static, see ClassLayout)
    world/cameras/<camera>                     Transform3D (camera pose) + Pinhole, static
    world/cameras/<camera>/image               EncodedImage (JPEG), per frame
    world/cameras/<camera>/detections          Points2D: the 2D joints that fed the stages
    world/skeletons/{raw,filtered}/<track>     Points3D with keypoint ids
    world/skeletons/gt/<person>                Points3D, SMPL-24
    world/rays/<track>, world/rays/untracked   LineStrips3D: camera centre -> used 2D joint's
                                               ray, up to the triangulated joint's depth
    world/meshes/gt/<person>                   Mesh3D: faces static, vertex positions per frame
    world/meshes/<name>                        any extra MeshSequence (the hook for SMPL fits)
    plots/joints/<track>/<joint>/{raw,filtered}/{x,y,z}   Scalars, mm
    plots/metrics/mahalanobis/<track>          mean Mahalanobis distance over joints
    plots/metrics/{people,tracks,gt_people}    counts per frame

Timelines: ``frame`` (sequence = scene frame index) and ``time`` (seconds, frame / fps).
An entity that is absent in a frame after being present is cleared in that frame.
"""

from __future__ import annotations

import colorsys
import os
import tempfile
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import rerun as rr
import rerun.blueprint as rrb
import torch
from rerun.chunk import RrdReader
from tqdm import tqdm

from pipeline.body_model import BodyModel
from pipeline.cameras import Camera
from pipeline.joint_sets import SMPL24, JointSet, get_joint_set
from pipeline.results import PipelineResults
from pipeline.scene import Scene
from pipeline.video_crop import CalibratedFrames

APP_ID = "mvviz"
MM_TO_M = 1e-3
DEFAULT_PLOT_JOINTS = ("pelvis", "left_wrist", "right_wrist")
# A joint some sets lack, as alternatives tried in order; a tuple of several names is
# their mean (COCO-17 has no pelvis: the mid-point of the hips stands in).
JOINT_ALIASES: dict[str, tuple[tuple[str, ...], ...]] = {
    "pelvis": (("pelvis",), ("mid_hip",), ("left_hip", "right_hip")),
    "neck": (("neck",), ("left_shoulder", "right_shoulder")),
}

GREY_UNASSIGNED = (110, 110, 110)
GREY_UNTRACKED = (210, 210, 210)
GT_COLOR = (120, 225, 140)
AXIS_COLORS = ((230, 80, 80), (80, 200, 90), (80, 130, 235))


# --------------------------------------------------------------------------- data


@dataclass(frozen=True, eq=False)
class MeshSequence:
    """A mesh over time, logged at ``world/meshes/<name>`` (e.g. the SMPL fits of a track).

    Attributes:
        frames: (T,) int scene frame of each row.
        vertices: (T, num_vertices, 3) world METRES.
        faces: (num_faces, 3) int vertex indices.
        color: RGB 0-255.
    """

    frames: np.ndarray
    vertices: np.ndarray
    faces: np.ndarray
    color: tuple[int, int, int] = GT_COLOR

    def __post_init__(self) -> None:
        f, v = np.asarray(self.frames), np.asarray(self.vertices)
        if f.ndim != 1 or v.ndim != 3 or v.shape[0] != f.shape[0] or v.shape[2] != 3:
            raise ValueError(
                f"MeshSequence: expected frames (T,) and vertices (T, V, 3), "
                f"got {f.shape} and {v.shape}"
            )
        if np.asarray(self.faces).ndim != 2 or np.asarray(self.faces).shape[1] != 3:
            raise ValueError(f"MeshSequence: expected faces (F, 3), got {np.shape(self.faces)}")


@dataclass(frozen=True)
class ClassLayout:
    """Class ids of the annotation context: a class is a colour plus a skeleton.

    Rerun joins keypoints of the same class id within one entity, so every skeleton that
    can share an entity with another gets its own id: the detections of one view and
    frame that belong to no track take ids from the ``unassigned`` / ``untracked`` pools.

    Ids, in order: filtered tracks [0, K), raw tracks [K, 2K), GT people, then the pools.
    """

    num_tracks: int
    gt_people: tuple[int, ...]
    num_unassigned: int
    num_untracked: int
    _gt_index: dict[int, int] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "_gt_index", {p: i for i, p in enumerate(self.gt_people)})
        if self.num_classes > 65535:
            raise ValueError(f"too many classes for rerun's u16 class ids ({self.num_classes})")

    def filtered(self, track: int) -> int:
        return track

    def raw(self, track: int) -> int:
        return self.num_tracks + track

    def gt(self, person_id: int) -> int:
        return 2 * self.num_tracks + self._gt_index[person_id]

    def unassigned(self, i: int) -> int:
        return 2 * self.num_tracks + len(self.gt_people) + i

    def untracked(self, i: int) -> int:
        return self.unassigned(self.num_unassigned) + i

    @property
    def num_classes(self) -> int:
        return self.untracked(self.num_untracked)


def track_color(track: int, *, raw: bool = False) -> tuple[int, int, int]:
    """A distinct RGB colour per track (golden-ratio hues); ``raw`` is a darker shade."""
    hue = (0.07 + 0.618034 * track) % 1.0
    r, g, b = colorsys.hsv_to_rgb(hue, 0.55 if raw else 0.8, 0.6 if raw else 0.95)
    return int(255 * r), int(255 * g), int(255 * b)


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
            frames.append(np.asarray(batch.column("frame").to_numpy(zero_copy_only=False)))
    all_frames = np.unique(np.concatenate(frames)) if frames else np.zeros(0, np.int64)
    return RrdSummary(rows, components, frozenset(static), all_frames.astype(np.int64))


def count_entities(path: str | os.PathLike) -> dict[str, int]:
    """Entity path -> rows logged, of the recording at ``path`` (private ``/__*`` ones left out)."""
    return {k: v for k, v in read_rrd_summary(path).rows.items() if not k.startswith("/__")}


# --------------------------------------------------------------------------- helpers


def resolve_plot_joint(joint_set: JointSet, name: str) -> np.ndarray:
    """Indices of the joints whose mean is joint ``name`` (aliases in JOINT_ALIASES)."""
    for names in JOINT_ALIASES.get(name, ((name,),)):
        if all(n in joint_set.index for n in names):
            return np.array([joint_set.index[n] for n in names])
    raise ValueError(
        f"joint {name!r} is not in joint set {joint_set.name} "
        f"(expected one of {list(joint_set.names)} or {sorted(JOINT_ALIASES)})"
    )


def select_frames(frames: slice | range | Iterable[int] | None, num_frames: int) -> np.ndarray:
    """Sorted unique frame indices in [0, num_frames); a slice/range may run past the end."""
    if frames is None:
        return np.arange(num_frames)
    if isinstance(frames, slice):
        return np.arange(num_frames)[frames]
    out = np.unique(np.asarray(list(frames), dtype=np.int64))
    inside = (out >= 0) & (out < num_frames)
    if isinstance(frames, range):
        return out[inside]
    bad = out[~inside]
    if bad.size:
        raise ValueError(f"frames {bad[:5].tolist()} are outside [0, {num_frames})")
    return out


def scaled_intrinsics(cam: Camera, width: int) -> tuple[np.ndarray, int, int, float]:
    """Rerun pinhole of ``cam`` for an image ``width`` pixels wide.

    Returns ``(K, width, height, s)`` with ``s = width / cam.width`` and ``K`` in rerun's
    corner-origin pixels: ``K = diag(s, s, 1) @ (cam.K shifted by half a pixel)``.
    """
    s = width / cam.width
    height = max(1, round(cam.height * s))
    K = np.array(cam.K, float)
    K[0, 2] += 0.5
    K[1, 2] += 0.5
    return np.diag([s, s, 1.0]) @ K, int(width), int(height), s


class FrameSource:
    """Frames of one camera (BGR uint8) from its video or image folder; reading in
    increasing frame order is cheapest (a video is decoded forward, seeking on jumps).
    ``place`` puts each frame on the calibrated image, as the viewer shows it."""

    def __init__(self, video=None, image_dir=None, place: CalibratedFrames | None = None) -> None:
        self.video, self.image_dir, self._place = video, image_dir, place
        self._cap = cv2.VideoCapture(str(video)) if video is not None else None
        self._next = 0

    def read(self, frame: int) -> np.ndarray | None:
        img = self._read(frame)
        return img if img is None or self._place is None else self._place(img)

    def _read(self, frame: int) -> np.ndarray | None:
        if self._cap is not None:
            if frame < self._next or frame - self._next > 50:
                self._cap.set(cv2.CAP_PROP_POS_FRAMES, frame)
                self._next = frame
            while self._next < frame:
                self._cap.grab()
                self._next += 1
            ok, img = self._cap.read()
            self._next += 1
            return img if ok else None
        if self.image_dir is not None:
            for ext in (".jpg", ".png", ".jpeg"):
                p = self.image_dir / f"{frame:06d}{ext}"
                if p.is_file():
                    return cv2.imread(str(p), cv2.IMREAD_COLOR)
        return None

    def close(self) -> None:
        if self._cap is not None:
            self._cap.release()


def decimate_mesh(
    rest_vertices: np.ndarray, faces: np.ndarray, weights: np.ndarray, cell: float
) -> tuple[np.ndarray, np.ndarray]:
    """Vertex clustering that keeps skinning exact: a subset of the mesh's own vertices.

    Vertices are grouped by (grid cell of size ``cell`` in the rest pose, dominant
    skinning joint), so parts that touch at rest but move apart (arm and torso) never
    merge; each group keeps the vertex nearest its mean, faces are re-indexed and the
    collapsed ones dropped. Posing the kept vertices equals decimating the posed mesh.

    Args:
        rest_vertices: (num_vertices, 3) rest pose, in the unit of ``cell``.
        faces: (num_faces, 3); weights: (num_vertices, num_joints) skinning weights.
    Returns:
        keep: (num_kept,) indices of the kept vertices; faces: (num_kept_faces, 3) into them.
    """
    rest = np.asarray(rest_vertices, float)
    key = np.column_stack([np.floor(rest / cell).astype(np.int64), np.argmax(weights, 1)])
    _, group = np.unique(key, axis=0, return_inverse=True)
    group = group.ravel()
    n = int(group.max()) + 1
    mean = np.zeros((n, 3))
    np.add.at(mean, group, rest)
    mean /= np.bincount(group, minlength=n)[:, None]
    dist = np.linalg.norm(rest - mean[group], axis=1)
    order = np.lexsort((dist, group))  # by group, nearest to the mean first
    keep = order[np.unique(group[order], return_index=True)[1]]
    f = group[np.asarray(faces)]
    f = f[(f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])]
    _, first = np.unique(np.sort(f, 1), axis=0, return_index=True)
    return keep, f[np.sort(first)]


def encode_jpeg(image_bgr: np.ndarray, width: int, height: int, *, quality: int = 80) -> bytes:
    """Resize a BGR image to (width, height) and JPEG-encode it."""
    if image_bgr.shape[1] != width or image_bgr.shape[0] != height:
        image_bgr = cv2.resize(image_bgr, (width, height), interpolation=cv2.INTER_AREA)
    ok, buf = cv2.imencode(".jpg", image_bgr, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise RuntimeError("JPEG encoding failed")
    return buf.tobytes()


def ray_segments(
    cam: Camera, pixels: np.ndarray, points: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Rays from ``cam``'s centre through distorted ``pixels`` (n, 2), each up to the depth
    along the ray of its triangulated point ``points`` (n, 3), world mm.

    Returns (n, 3) start and (n, 3) end points, world mm; the gap between ``end`` and
    ``points`` is the ray's miss distance.
    """
    d = cam.pixels_to_rays(pixels)  # (n, 3) unit, world
    c = cam.center
    depth = np.clip(np.einsum("nc,nc->n", points - c, d), 0.0, None)
    end = c + d * depth[:, None]
    return np.broadcast_to(c, end.shape), end


def check_inputs(scene: Scene, results: PipelineResults) -> None:
    """The results must belong to the scene: same views, frames and detection rows."""
    K, F = results.track_raw.shape[:2]
    problems = []
    if results.num_views != len(scene.rig):
        problems.append(f"{results.num_views} views, scene has {len(scene.rig)} cameras")
    if results.num_frames != scene.num_frames or F != scene.num_frames:
        problems.append(f"{results.num_frames} frames, scene has {scene.num_frames}")
    if results.det_joints2d.shape[0] != len(scene.detections):
        problems.append(
            f"{results.det_joints2d.shape[0]} detection rows, scene has {len(scene.detections)}"
        )
    for name in ("track_forward", "track_smoothed"):
        if getattr(results, name).shape != results.track_raw.shape:
            problems.append(f"{name} shape {getattr(results, name).shape} != track_raw's")
    if problems:
        raise ValueError("results do not match the scene: " + "; ".join(problems))


def _pool_sizes(results: PipelineResults, frame: np.ndarray, view: np.ndarray) -> tuple[int, int]:
    """Most detections of one (frame, view) that are unassigned / in an untracked person."""
    person = results.det_person
    tracked = np.zeros(person.shape, bool)
    tracked[person >= 0] = results.person_track[person[person >= 0]] >= 0
    out = []
    for mask in (person < 0, (person >= 0) & ~tracked):
        if not mask.any():
            out.append(0)
            continue
        _, counts = np.unique(np.stack([frame[mask], view[mask]], 1), axis=0, return_counts=True)
        out.append(int(counts.max()))
    return out[0], out[1]


class _FrameLogger:
    """Logs per-frame entities and clears those logged last frame but not this one."""

    def __init__(self, rec: rr.RecordingStream) -> None:
        self.rec = rec
        self._prev: set[str] = set()
        self._now: set[str] = set()

    def log(self, path: str, entity) -> None:
        self.rec.log(path, entity)
        self._now.add(path)

    def end_frame(self) -> None:
        for path in sorted(self._prev - self._now):
            self.rec.log(path, rr.Clear(recursive=False))
        self._prev, self._now = self._now, set()


# --------------------------------------------------------------------------- static context


def make_blueprint(camera_names: Sequence[str]) -> rrb.Blueprint:
    """3D view big on the left; camera views in a grid above tabs of plots on the right.

    The camera views also show the filtered 3D skeletons projected through the pinhole
    (undistorted), next to the 2D detections on the (distorted) image.
    """
    cams = [
        rrb.Spatial2DView(
            origin=f"world/cameras/{name}",
            contents=["$origin/**", "/world/skeletons/filtered/**"],
            name=str(name),
        )
        for name in camera_names
    ]
    plots = rrb.Tabs(
        rrb.TimeSeriesView(origin="plots/joints", name="joints (mm)"),
        rrb.TimeSeriesView(origin="plots/metrics", name="metrics"),
    )
    right = rrb.Vertical(rrb.Grid(*cams, name="cameras"), plots, row_shares=[3, 2])
    return rrb.Blueprint(
        rrb.Horizontal(rrb.Spatial3DView(origin="world", name="3D"), right, column_shares=[3, 2]),
        collapse_panels=False,
    )


def _class(cid: int, label: str, color, joint_set: JointSet) -> rr.ClassDescription:
    return rr.ClassDescription(
        info=rr.AnnotationInfo(id=cid, label=label, color=color),
        keypoint_annotations=[
            rr.AnnotationInfo(id=j, label=n) for j, n in enumerate(joint_set.names)
        ],
        keypoint_connections=list(joint_set.bones),
    )


def annotation_context(layout: ClassLayout, joint_set: JointSet) -> rr.AnnotationContext:
    """Every class of ``layout``: tracks and pools use ``joint_set``, GT people SMPL-24."""
    classes = []
    for k in range(layout.num_tracks):
        classes.append(_class(layout.filtered(k), f"track {k}", track_color(k), joint_set))
        classes.append(_class(layout.raw(k), f"track {k} raw", track_color(k, raw=True), joint_set))
    for p in layout.gt_people:
        classes.append(_class(layout.gt(p), f"gt person {p}", GT_COLOR, SMPL24))
    for i in range(layout.num_unassigned):
        classes.append(_class(layout.unassigned(i), "unassigned", GREY_UNASSIGNED, joint_set))
    for i in range(layout.num_untracked):
        classes.append(_class(layout.untracked(i), "untracked", GREY_UNTRACKED, joint_set))
    return rr.AnnotationContext(classes)


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


# --------------------------------------------------------------------------- export


def export_rrd(
    scene: Scene,
    results: PipelineResults,
    body_model: BodyModel | None,
    path: str | os.PathLike,
    *,
    frames: slice | range | Iterable[int] | None = None,
    images: bool = True,
    image_width: int = 480,
    jpeg_quality: int = 80,
    meshes: bool = True,
    mesh_cell_mm: float | None = 25.0,
    extra_meshes: Mapping[str, MeshSequence] | None = None,
    plot_joints: Sequence[str] = DEFAULT_PLOT_JOINTS,
    progress: bool = True,
) -> Path:
    """Write ``scene`` and its ``results`` to the recording ``path``, atomically.

    The file is written beside ``path`` under a temporary name and renamed when complete
    (missing parent directories are created); on any error the temporary file is removed
    and ``path`` is left as it was.

    Args:
        body_model: skins the GT meshes (``None`` or ``meshes=False``: no GT meshes).
        mesh_cell_mm: GT meshes are decimated with :func:`decimate_mesh` at this cell size
            (25 mm keeps ~1/4 of the open model's vertices); ``None`` keeps them all.
            Vertex positions dominate the file size: 12 bytes per vertex per frame.
        frames: the scene frames to log (default all), e.g. ``range(100, 150)``.
        images: log each camera's video frame, downscaled to ``image_width`` pixels (never
            upscaled) and JPEG-encoded; without images the pinholes keep the camera's
            full resolution.
        extra_meshes: name -> MeshSequence, logged at ``world/meshes/<name>``.
        plot_joints: joints plotted per track (aliases such as ``pelvis`` resolve per set).
    Returns:
        ``path``.
    """
    path = Path(path)
    check_inputs(scene, results)
    frame_ids = select_frames(frames, scene.num_frames)
    joint_set = get_joint_set(results.joint_set)
    plot_idx = {name: resolve_plot_joint(joint_set, name) for name in plot_joints}
    det = scene.detections
    gt = scene.gt
    n_unassigned, n_untracked = _pool_sizes(results, det.frame, det.view)
    layout = ClassLayout(
        num_tracks=results.num_tracks,
        gt_people=tuple(int(p) for p in np.unique(gt.person_id)) if gt is not None else (),
        num_unassigned=n_unassigned,
        num_untracked=n_untracked,
    )

    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    os.close(fd)
    tmp = Path(tmp_name)
    rec = rr.RecordingStream(APP_ID)
    sources: dict[str, FrameSource] = {}
    # rerun encodes and writes on its own threads; torch's intra-op threads spinning
    # beside them made skinning ~10x slower on a 2-core machine. Restored below.
    torch_threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        rec.set_log_time_enabled(False)
        rec.save(tmp, default_blueprint=make_blueprint(scene.rig.names))
        rec.send_recording_name(scene.name)
        rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        rec.log("world", annotation_context(layout, joint_set), static=True)

        widths = {c.name: (min(image_width, c.width) if images else c.width) for c in scene.rig}
        cam_size = _log_cameras(rec, scene, widths)
        if images:
            crops = scene.meta.get("video_crop") or {}  # what each video does not show
            for cam in scene.rig:
                if cam.name in scene.videos or cam.name in scene.image_dirs:
                    size, crop = (cam.width, cam.height), crops.get(cam.name)
                    sources[cam.name] = FrameSource(
                        scene.videos.get(cam.name),
                        scene.image_dirs.get(cam.name),
                        CalibratedFrames(cam.name, size, crop=crop),
                    )
        faces = keep = None
        has_smpl = gt is not None and all(
            a is not None for a in (gt.smpl_pose, gt.smpl_betas, gt.transl)
        )
        if meshes and body_model is not None and has_smpl:
            faces = body_model.faces.cpu().numpy()
            keep = np.arange(body_model.num_vertices)
            if mesh_cell_mm:
                keep, faces = decimate_mesh(
                    body_model.v_template.cpu().numpy(),
                    faces,
                    body_model.weights.cpu().numpy(),
                    mesh_cell_mm * MM_TO_M,
                )
            faces = faces.astype(np.uint32)
            for p in layout.gt_people:
                rec.log(
                    f"world/meshes/gt/{p}",
                    rr.Mesh3D.from_fields(triangle_indices=faces, albedo_factor=GT_COLOR),
                    static=True,
                )
        extra = dict(extra_meshes or {})
        extra_rows = {}
        for name, seq in extra.items():
            rec.log(
                f"world/meshes/{name}",
                rr.Mesh3D.from_fields(
                    triangle_indices=np.asarray(seq.faces, np.uint32), albedo_factor=seq.color
                ),
                static=True,
            )
            extra_rows[name] = {int(f): i for i, f in enumerate(np.asarray(seq.frames))}

        rows_by_frame = _group(det.frame)
        person_by_frame = _group(results.person_frame)
        gt_by_frame = _group(gt.frame) if gt is not None else {}
        filtered = results.track_filtered
        logger = _FrameLogger(rec)
        for f in tqdm(frame_ids, desc="export rrd", unit="frame", disable=not progress):
            f = int(f)
            rec.set_time("frame", sequence=f)
            rec.set_time("time", duration=f / scene.fps)
            for name, src in sources.items():
                img = src.read(f)
                if img is not None:
                    w, h, _ = cam_size[name]
                    jpeg = encode_jpeg(img, w, h, quality=jpeg_quality)
                    logger.log(
                        f"world/cameras/{name}/image",
                        rr.EncodedImage(contents=jpeg, media_type="image/jpeg"),
                    )
            _log_detections(logger, scene, results, layout, cam_size, rows_by_frame.get(f))
            _log_skeletons(logger, results, layout, filtered, f)
            _log_rays(logger, scene, results, person_by_frame.get(f))
            if gt is not None and f in gt_by_frame:
                _log_gt(logger, gt, layout, gt_by_frame[f], body_model, keep)
            for name, seq in extra.items():
                i = extra_rows[name].get(f)
                if i is not None:
                    logger.log(
                        f"world/meshes/{name}",
                        rr.Mesh3D.from_fields(vertex_positions=np.asarray(seq.vertices[i])),
                    )
            logger.end_frame()

        _log_plots(rec, scene, results, frame_ids, plot_idx, person_by_frame, gt_by_frame)
        rec.flush()
        rec.disconnect()  # closes the file and writes its footer
        with open(tmp, "rb+") as fh:
            os.fsync(fh.fileno())
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp makes 0600; give the usual file mode
        os.replace(tmp, path)
    except BaseException:
        try:
            rec.disconnect()
        finally:
            tmp.unlink(missing_ok=True)
        raise
    finally:
        torch.set_num_threads(torch_threads)
        for src in sources.values():
            src.close()
    return path


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


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


def _log_gt(logger, gt, layout, rows: np.ndarray, body_model, keep: np.ndarray | None) -> None:
    """GT skeletons and, when ``keep`` (mesh vertices to log) is given, GT meshes."""
    for i in rows:
        p = int(gt.person_id[i])
        pts = _points3d(gt.joints3d[i], layout.gt(p), 0.015)
        if pts is not None:
            logger.log(f"world/skeletons/gt/{p}", pts)
    if keep is None:
        return
    with torch.no_grad():
        out = body_model(
            torch.as_tensor(gt.smpl_pose[rows], dtype=torch.float32),
            torch.as_tensor(gt.smpl_betas[rows], dtype=torch.float32),
        )
    verts = out.vertices.numpy()[:, keep] + gt.transl[rows, None, :] * MM_TO_M  # (P, V', 3) m
    for i, v in zip(rows, verts, strict=True):
        logger.log(
            f"world/meshes/gt/{int(gt.person_id[i])}",
            rr.Mesh3D.from_fields(vertex_positions=v.astype(np.float32)),
        )


def _send_series(rec, path: str, frames: np.ndarray, values: np.ndarray, fps: float) -> None:
    ok = np.isfinite(values)
    if not ok.any():
        return
    fr = frames[ok]
    rec.send_columns(
        path,
        indexes=[rr.TimeColumn("frame", sequence=fr), rr.TimeColumn("time", duration=fr / fps)],
        columns=rr.Scalars.columns(scalars=values[ok].astype(np.float64)),
    )


def _log_plots(rec, scene, results, frame_ids, plot_idx, person_by_frame, gt_by_frame) -> None:
    """Joint coordinates per track, Mahalanobis distances and counts, as columns."""
    fps = scene.fps
    filtered = results.track_filtered
    for k in range(results.num_tracks):
        for name, idx in plot_idx.items():
            for stage, arr, width in (("raw", results.track_raw, 1.0), ("filtered", filtered, 2.0)):
                xyz = arr[k][frame_ids][:, idx].mean(1)  # (F, 3) mm
                for a, axis in enumerate("xyz"):
                    path = f"plots/joints/{k}/{name}/{stage}/{axis}"
                    color = AXIS_COLORS[a] if stage == "filtered" else _dim(AXIS_COLORS[a])
                    rec.log(
                        path,
                        rr.SeriesLines(
                            colors=[color], widths=[width], names=[f"{k} {name} {stage} {axis}"]
                        ),
                        static=True,
                    )
                    _send_series(rec, path, frame_ids, xyz[:, a], fps)
        maha = results.track_mahalanobis[k][frame_ids]  # (F, J)
        with np.errstate(invalid="ignore"):
            finite = np.isfinite(maha)
            mean = np.where(
                finite.any(1), np.nansum(np.where(finite, maha, 0), 1) / finite.sum(1), np.nan
            )
        path = f"plots/metrics/mahalanobis/{k}"
        rec.log(path, rr.SeriesLines(colors=[track_color(k)], names=[f"track {k}"]), static=True)
        _send_series(rec, path, frame_ids, mean, fps)

    counts = {
        "people": np.array([len(person_by_frame.get(int(f), ())) for f in frame_ids], float),
        "tracks": np.isfinite(filtered[:, frame_ids]).all(-1).any(-1).sum(0).astype(float),
    }
    if scene.gt is not None:
        counts["gt_people"] = np.array([len(gt_by_frame.get(int(f), ())) for f in frame_ids], float)
    for name, values in counts.items():
        rec.log(f"plots/metrics/{name}", rr.SeriesLines(names=[name]), static=True)
        _send_series(rec, f"plots/metrics/{name}", frame_ids, values, fps)


def _dim(color: tuple[int, int, int]) -> tuple[int, int, int]:
    return tuple(int(0.55 * c + 0.45 * 128) for c in color)
