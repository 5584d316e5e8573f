"""Log a scene and its pipeline results into a rerun recording: yours, a file, or live.

The one place of the project's rerun entity layout, used by ``mvviz export-rrd``
(:func:`mvviz.rerun_export.export_rrd`), by the viewer's live mode (``python app.py
--rerun``, :mod:`mvviz.rerun_live`) and by scripts and notebooks::

    import rerun as rr
    from mvviz.rerun import log_scene

    rr.init("my_app", spawn=True)              # or rr.save(...), rr.serve_grpc(), ...
    log_scene(scene, results, frames=range(0, 100))   # into the global recording
    log_scene(scene, results, recording=my_rec, body_model=model, images=False)

Every rerun call of the project lives here and in the two modules above: rerun's API
changes between versions (this is written against rerun-sdk 0.41).

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
    world/skeletons/filter_b/<track>           Points3D: filter B of the viewer (live only)
    world/skeletons/gt/<person>                Points3D, SMPL-24
    world/rays/<track>, world/rays/untracked   LineStrips3D: camera centre -> used 2D joint's
                                               ray, up to the triangulated joint's depth
    world/meshes/gt/<person>                   Mesh3D: faces static, vertex positions per frame
    world/bodies/{smpl,smpl_vae}/<track>       Mesh3D: the fitted SMPL body (step I, and
                                               corrected by the VAE prior), decimated as
                                               the GT meshes; faces static, vertices per
                                               frame; track colour (step I darker)
    world/meshes/<name>                        any extra MeshSequence (e.g. a fit of yours)
    plots/joints/<track>/<joint>/<stage>/{x,y,z}   Scalars, mm; stage raw / filtered
    plots/metrics/mahalanobis<branch>/<track>  mean Mahalanobis distance over joints
    plots/metrics/{people,tracks,gt_people}<branch>   counts per frame

Branches: the first results logged have stages ``raw`` / ``filtered`` and no branch
suffix. In the live viewer every re-run of the Pipeline panel adds a branch ``_run<n>``
(stages ``raw_run<n>``, ``filtered_run<n>``, ``mahalanobis_run<n>``, ...) and every
filter B change a branch ``_b<n>`` (``filtered_b<n>``, ``mahalanobis_b<n>``), so before
and after, A and B are lines of the same time-series views.

Timelines: ``frame`` (sequence = scene frame index) and ``time`` (seconds, frame / fps).
An entity that is absent in a frame after being present is cleared in that frame.
"""

from __future__ import annotations

import colorsys
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np
import rerun as rr
import rerun.blueprint as rrb
import torch

from pipeline.body_model import BodyModel, axis_angle_to_matrix, rigid_chain
from pipeline.cameras import Camera
from pipeline.joint_sets import SMPL24, JointSet, get_joint_set
from pipeline.results import PipelineResults
from pipeline.scene import Scene
from pipeline.smpl_fit import SmplFit

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
BODY_STAGES = ("smpl", "smpl_vae")  # PipelineResults fields holding SmplFit bodies
AXIS_COLORS = ((230, 80, 80), (80, 200, 90), (80, 130, 235))


# --------------------------------------------------------------------------- data


@dataclass(frozen=True, eq=False)
class MeshSequence:
    """A mesh over time, logged at ``world/meshes/<name>`` (e.g. a body fit of your own).

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


def display_mesh(body_model: BodyModel, cell_mm: float | None) -> tuple[np.ndarray, np.ndarray]:
    """``(keep, faces)`` of ``body_model``'s mesh decimated by :func:`decimate_mesh` at
    ``cell_mm`` (None: every vertex): kept vertex indices, uint32 faces into them."""
    faces = body_model.faces.cpu().numpy()
    keep = np.arange(body_model.num_vertices)
    if cell_mm:
        keep, faces = decimate_mesh(
            body_model.v_template.cpu().numpy(),
            faces,
            body_model.weights.cpu().numpy(),
            cell_mm * MM_TO_M,
        )
    return keep, faces.astype(np.uint32)


def body_color(stage: str, track: int) -> tuple[int, int, int]:
    """A fitted body's colour: its track's; step I's (``smpl``) the darker shade."""
    return track_color(track, raw=stage != "smpl_vae")


def resize(image: np.ndarray, width: int, height: int) -> np.ndarray:
    """``image`` resized to (width, height): halved by 2x2 means (OpenCV's fast integer
    INTER_AREA) while more than twice too wide, then bilinear; ~5x faster than one
    INTER_AREA at a fractional scale, with as little aliasing."""
    while image.shape[1] >= 2 * width and image.shape[0] >= 2 * height:
        image = cv2.resize(image, None, fx=0.5, fy=0.5, interpolation=cv2.INTER_AREA)
    if image.shape[1] != width or image.shape[0] != height:
        image = cv2.resize(image, (width, height), interpolation=cv2.INTER_LINEAR)
    return image


def skin_subset(
    body_model: BodyModel, pose: np.ndarray, betas: np.ndarray, keep: np.ndarray
) -> np.ndarray:
    """Linear blend skinning of the vertices ``keep`` only (the model's forward skins all).

    Args:
        pose: (B, 72) axis-angle; betas: (B, <=num_betas); keep: (V',) vertex indices.
    Returns:
        (B, V', 3) float32 posed vertices, metres, without translation.
    """
    bm = body_model
    if bm.has_posedirs:  # pose blend shapes need every vertex: the model's own path
        return bm(torch.as_tensor(pose, dtype=torch.float32), betas).vertices.numpy()[:, keep]
    pose = torch.as_tensor(pose, dtype=bm.v_template.dtype).reshape(len(pose), -1, 3)
    b = torch.zeros(len(pose), bm.num_betas, dtype=pose.dtype)
    given = torch.as_tensor(betas, dtype=pose.dtype).reshape(len(pose), -1)[:, : bm.num_betas]
    b[:, : given.shape[1]] = given
    idx = torch.as_tensor(keep)
    # 1. shape blend shapes of the kept vertices
    v_shaped = bm.v_template[idx] + torch.einsum("vcb,nb->nvc", bm.shapedirs[idx], b)
    rest = bm.rest_joints(b)
    # 2. forward kinematics; joint transforms relative to the rest pose
    posed, T = rigid_chain(axis_angle_to_matrix(pose), rest, bm.parents, bm.levels)
    rel_t = posed - (T[..., :3, :3] @ rest[..., None])[..., 0]  # (B, J, 3)
    # 3. blend per-vertex transforms by the skinning weights
    w = bm.weights[idx]
    Rv = torch.einsum("vj,njab->nvab", w, T[..., :3, :3])
    return ((Rv @ v_shaped[..., None])[..., 0] + w @ rel_t).numpy().astype(np.float32)


def encode_jpeg(image_bgr: np.ndarray, width: int, height: int, *, quality: int = 80) -> bytes:
    """Resize a BGR image to (width, height) and JPEG-encode it."""
    image_bgr = resize(image_bgr, width, height)
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
    """GT skeletons and, given ``mesh_vertices`` (GT row -> (V', 3) m), GT meshes."""
    for i in rows:
        p = int(gt.person_id[i])
        pts = _points3d(gt.joints3d[i], layout.gt(p), 0.015)
        if pts is not None:
            logger.log(f"world/skeletons/gt/{p}", pts)
        if mesh_vertices is not None:
            logger.log(
                f"world/meshes/gt/{p}", rr.Mesh3D.from_fields(vertex_positions=mesh_vertices[i])
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


def _log_plots(
    rec,
    scene,
    results,
    frame_ids,
    plot_idx,
    person_by_frame,
    gt_by_frame,
    *,
    branch: str = "",
    filtered: np.ndarray | None = None,
    mahalanobis: np.ndarray | None = None,
    raw: bool = True,
    counts: bool = True,
) -> None:
    """Joint coordinates per track, Mahalanobis distances and counts, as columns.

    ``branch`` suffixes the stage and metric names (see the module docstring);
    ``filtered`` (K, F, J, 3) mm and ``mahalanobis`` (K, F, J) replace the results' own
    (filter B); without ``raw`` / ``counts`` those series are left out.
    """
    fps = scene.fps
    filtered = results.track_filtered if filtered is None else filtered
    mahalanobis = results.track_mahalanobis if mahalanobis is None else mahalanobis
    stages = (("raw", results.track_raw, 1.0),) if raw else ()
    stages += (("filtered", filtered, 2.0),)
    for k in range(results.num_tracks):
        for name, idx in plot_idx.items():
            for stage, arr, width in stages:
                xyz = arr[k][frame_ids][:, idx].mean(1)  # (F, 3) mm
                for a, axis in enumerate("xyz"):
                    path = f"plots/joints/{k}/{name}/{stage}{branch}/{axis}"
                    color = AXIS_COLORS[a] if stage == "filtered" else _dim(AXIS_COLORS[a])
                    if branch:
                        width = 1.0 if stage == "raw" else 1.5
                    rec.log(
                        path,
                        rr.SeriesLines(
                            colors=[color],
                            widths=[width],
                            names=[f"{k} {name} {stage}{branch} {axis}"],
                        ),
                        static=True,
                    )
                    _send_series(rec, path, frame_ids, xyz[:, a], fps)
        maha = mahalanobis[k][frame_ids]  # (F, J)
        with np.errstate(invalid="ignore"):
            finite = np.isfinite(maha)
            mean = np.where(
                finite.any(1), np.nansum(np.where(finite, maha, 0), 1) / finite.sum(1), np.nan
            )
        path = f"plots/metrics/mahalanobis{branch}/{k}"
        rec.log(
            path, rr.SeriesLines(colors=[track_color(k)], names=[f"track {k}{branch}"]), static=True
        )
        _send_series(rec, path, frame_ids, mean, fps)
    if not counts:
        return
    series = {
        "people": np.array([len(person_by_frame.get(int(f), ())) for f in frame_ids], float),
        "tracks": np.isfinite(filtered[:, frame_ids]).all(-1).any(-1).sum(0).astype(float),
    }
    if scene.gt is not None and not branch:
        series["gt_people"] = np.array([len(gt_by_frame.get(int(f), ())) for f in frame_ids], float)
    for name, values in series.items():
        path = f"plots/metrics/{name}{branch}"
        rec.log(path, rr.SeriesLines(names=[f"{name}{branch}"]), static=True)
        _send_series(rec, path, frame_ids, values, fps)


def _dim(color: tuple[int, int, int]) -> tuple[int, int, int]:
    return tuple(int(0.55 * c + 0.45 * 128) for c in color)


# --------------------------------------------------------------------------- logging a scene


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
        n_unassigned, n_untracked = _pool_sizes(results, det.frame, det.view)
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
        self.rows_by_frame = _group(det.frame)
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
                self.body_meshes[stage] = display_mesh(fit.model, mesh_cell_mm)
        self._frames = _FrameLogger(self.rec, sparse=sparse, pause=pause)

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

    def gt_mesh_vertices(self) -> np.ndarray | None:
        """(num_gt_rows, V', 3) float32 world METRES of every GT row's decimated mesh,
        skinned in batches on first use (None without meshes)."""
        if not self.has_meshes:
            return None
        if self._mesh_vertices is None:
            gt, keep = self.scene.gt, self.mesh_keep
            out = np.empty((len(gt.frame), len(keep), 3), np.float32)
            with torch.no_grad():
                for a in range(0, len(out), 128):
                    b = min(a + 128, len(out))
                    v = skin_subset(self.body_model, gt.smpl_pose[a:b], gt.smpl_betas[a:b], keep)
                    out[a:b] = v + gt.transl[a:b, None, :] * MM_TO_M
            self._mesh_vertices = out
        return self._mesh_vertices

    def body_vertices(self, stage: str, tracks: np.ndarray, frames: np.ndarray) -> np.ndarray:
        """(N, V', 3) float32 world METRES: the display mesh of the ``stage`` fit of
        ``tracks[i]`` at ``frames[i]`` (present person-frames), skinned in batches."""
        fit, (keep, _) = self.fits[stage], self.body_meshes[stage]
        out = np.empty((len(tracks), len(keep), 3), np.float32)
        with torch.no_grad():
            for a in range(0, len(out), 128):
                k, f = tracks[a : a + 128], frames[a : a + 128]
                v = skin_subset(fit.model, fit.pose_rotvecs[k, f], fit.betas[k], keep)
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
            verts = self.gt_mesh_vertices() if gt_meshes else None
            _log_gt(logger, gt, layout, self.gt_by_frame[f], verts)
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

    def send_gt_meshes(self, frame_ids: np.ndarray) -> None:
        """Every GT mesh's vertices over ``frame_ids`` as one column per person
        (``send_columns``); a frame where the person is absent gets an empty mesh."""
        verts = self.gt_mesh_vertices()
        gt = self.scene.gt
        if verts is None:
            return
        fps = self.scene.fps
        for p in self.layout.gt_people:
            row_of = {int(gt.frame[i]): i for i in np.flatnonzero(gt.person_id == p)}
            present = np.array([int(f) in row_of for f in frame_ids])
            if not present.any():
                continue
            # from the first frame with the person: empty partitions where it is absent
            fr = np.asarray(frame_ids)[int(np.argmax(present)) :]
            rows = [row_of[int(f)] for f in fr if int(f) in row_of]
            lengths = np.array([verts.shape[1] if int(f) in row_of else 0 for f in fr])
            _send_mesh_column(self.rec, f"world/meshes/gt/{p}", fr, verts[rows], lengths, fps)

    def send_bodies(self, frame_ids: np.ndarray) -> None:
        """Every fitted body's vertices over ``frame_ids`` as one column per (stage,
        track), as :meth:`send_gt_meshes`."""
        frame_ids = np.asarray(frame_ids, np.int64)
        for stage, fit in self.fits.items():
            present = fit.present[:, frame_ids]  # (K, F')
            ks, cols = np.nonzero(present)
            if ks.size == 0:
                continue
            verts = self.body_vertices(stage, ks, frame_ids[cols])
            n = verts.shape[1]
            for k in np.unique(ks):
                pk = present[k]
                fr = frame_ids[int(np.argmax(pk)) :]
                lengths = np.where(pk[int(np.argmax(pk)) :], n, 0)
                _send_mesh_column(self.rec, f"world/bodies/{stage}/{k}", fr, verts[ks == k],
                                  lengths, self.scene.fps)  # fmt: skip

    def send_plots(
        self,
        frame_ids: np.ndarray | None = None,
        *,
        branch: str = "",
        filtered: np.ndarray | None = None,
        mahalanobis: np.ndarray | None = None,
    ) -> None:
        """The time series (see the module docstring) as columns; a ``branch`` with
        ``filtered`` (K, F, J, 3) mm and ``mahalanobis`` (K, F, J) is a second filter
        (its raw input and counts are the results' own and are left out)."""
        frame_ids = np.arange(self.scene.num_frames) if frame_ids is None else frame_ids
        other_filter = filtered is not None
        _log_plots(
            self.rec, self.scene, self.results, frame_ids, self.plot_idx,
            self.person_by_frame, self.gt_by_frame, branch=branch, filtered=filtered,
            mahalanobis=mahalanobis, raw=not other_filter, counts=not other_filter,
        )  # fmt: skip


def log_scene(
    scene: Scene,
    results: PipelineResults,
    recording: rr.RecordingStream | None = None,
    frames: slice | range | Iterable[int] | None = None,
    *,
    images: Mapping[str, Callable[[int], ImageLike | None]] | bool = False,
    body_model: BodyModel | None = None,
    blueprint: bool = True,
    progress: Callable[[Iterable[int]], Iterable[int]] | None = None,
    **options,
) -> SceneLogger:
    """Log ``scene`` and its ``results`` into ``recording`` (default: the global one of
    ``rr.init``) with the layout of this module: static context, blueprint, the
    ``frames`` (default all; a slice or range may run past the end), GT meshes, fitted
    bodies and time series as columns.

    Args:
        images: camera name -> ``read(frame)`` returning JPEG bytes or a BGR image (e.g.
            :class:`mvviz.rerun_export.FrameSource`), or True to read the scene's videos
            and image folders, or False (default) for no images.
        body_model: skins the GT meshes (``pipeline.body_model.load_body_model()``).
        progress: wraps the frame loop (e.g. ``tqdm``).
        options: of :class:`SceneLogger` (``image_width``, ``mesh_cell_mm``, ...).
    Returns:
        The :class:`SceneLogger`, to log more frames or branches into the same recording.
    """
    readers: Mapping[str, Callable[[int], ImageLike | None]] = {}
    opened = []
    if images is True:
        from mvviz.rerun_export import scene_frame_sources  # noqa: PLC0415  (cv2 video I/O)

        opened = list(scene_frame_sources(scene).values())
        readers = {src.camera: src.read for src in opened}
    elif images:
        readers = images
    logger = SceneLogger(
        scene, results, recording, body_model=body_model, images=bool(readers), **options
    )
    frame_ids = select_frames(frames, scene.num_frames)
    try:
        logger.log_static(blueprint=blueprint)
        loop = progress(frame_ids) if progress is not None else frame_ids
        for f in loop:
            f = int(f)
            logger.log_frame(
                f, images={n: r(f) for n, r in readers.items()}, gt_meshes=False, bodies=False
            )
        logger.send_gt_meshes(frame_ids)
        logger.send_bodies(frame_ids)
        logger.send_plots(frame_ids)
    finally:
        for src in opened:
            src.close()
    return logger
