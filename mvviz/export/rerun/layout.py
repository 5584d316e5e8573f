"""The entity layout's data and static context: constants, colours, the class ids of
the annotation context, the blueprint, frame selection and input checks (see
:mod:`mvviz.export.rerun`)."""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from pipeline.core.palette import track_rgb
from pipeline.data.cameras import Camera
from pipeline.data.joint_sets import SMPL24, JointSet
from pipeline.data.scene import Scene
from pipeline.results.store import (
    BODY_STAGES,  # noqa: F401  (re-exported)
    PipelineResults,
)

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
RAW_SHADE = 0.6  # a raw track's colour: its filtered colour this much darker


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
    """The track's colour, as the viewer draws it (:func:`pipeline.core.palette.track_rgb`);
    ``raw`` is a darker shade of it."""
    rgb = track_rgb(track)
    return tuple(int(c * RAW_SHADE) for c in rgb) if raw else rgb


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


def body_color(stage: str, track: int) -> tuple[int, int, int]:
    """A fitted body's colour: its track's; step I's (``smpl``) the darker shade."""
    return track_color(track, raw=stage != "smpl_vae")


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
