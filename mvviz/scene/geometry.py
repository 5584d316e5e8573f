"""What the viewer draws for a frame: colours, layer options, the per-run viewer data and
pure functions from a frame to its geometry (no viser here; unit-testable).

Units: the pipeline works in world millimetres (z up); the viewer draws in world
**metres** (z up), which is the scale viser's grid and camera controls expect. Every 3D
array this module returns is in metres; 2D arrays stay in pixels.

:func:`prepare` computes a :class:`ViewerData` once per run (indices, camera geometry,
detection rays, body poses); :func:`frame_geometry` a :class:`FrameGeometry` for one
frame, which :class:`mvviz.scene.layers.SceneLayers` assigns to the viser nodes.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Protocol

import numpy as np
import viser.transforms as vtf

from mvviz.scene.bodies import Bodies, GtBodies, fitted_bodies, gt_bodies
from mvviz.scene.lazy_rows import LazyRows, RowBlocks
from pipeline.association.affinity import pinhole_rays
from pipeline.core.palette import TRACK_PALETTE
from pipeline.data.cameras import Camera
from pipeline.data.joint_sets import SMPL24, JointSet, get_joint_set
from pipeline.data.scene import Scene
from pipeline.results.store import PipelineResults
from pipeline.run.frames import frame_rows, group_by_frame

if TYPE_CHECKING:
    from pipeline.body.arrays import BodyModelData
    from pipeline.body.model import BodyModel

MM = 1e-3  # millimetres -> metres

# One colour per track id, shared with the rerun and file exports (pipeline.core.palette).
PALETTE = np.array(TRACK_PALETTE, dtype=np.uint8)
UNASSIGNED = np.array((150, 150, 150), np.uint8)  # detection in no cluster
UNTRACKED = np.array((70, 70, 70), np.uint8)  # clustered person that no track kept
OUTLIER = np.array((230, 20, 20), np.uint8)  # view rejected for a joint
GT_SKELETON = np.array((40, 40, 40), np.uint8)
# Another tool's result (scene.references): a warm mid grey, lighter than the ground
# truth's near-black; an off-white would vanish on viser's white background.
REFERENCE_SKELETON = np.array((150, 146, 132), np.uint8)
GT_MESH = (205, 205, 200)
# The camera panel's camera in 3D: yellow, which no track has.
SELECTED_CAMERA = np.array((235, 190, 0), np.uint8)


def track_color(track: int | np.ndarray) -> np.ndarray:
    """(3,) or (n, 3) uint8 colour of track id(s); -1 gets :data:`UNTRACKED`."""
    t = np.asarray(track)
    out = PALETTE[np.maximum(t, 0) % len(PALETTE)]
    return np.where((t < 0)[..., None], UNTRACKED, out).astype(np.uint8)


def pale(color: np.ndarray, amount: float = 0.5) -> np.ndarray:
    """Blend uint8 colour(s) toward white."""
    c = np.asarray(color, float)
    return (c + (255.0 - c) * amount).astype(np.uint8)


# --------------------------------------------------------------------------- options


@dataclass
class LayerToggles:
    """Which layers are drawn, and their options (one GUI control each)."""

    grid: bool = True
    cameras: bool = True
    camera_labels: bool = True
    frustum_images: bool = True
    detections2d: bool = True
    # the 2D detections on the camera panel's frustum only: 31 frusta's are ~200 KB a
    # frame change, mostly too small to read (on past ALL_FRUSTA_MAX_CAMERAS cameras)
    detections2d_panel_camera_only: bool = False
    rays: bool = True
    rays_selected_only: bool = True  # every ray of every person is a thicket
    raw: bool = True
    filtered: bool = True
    offset_filtered: bool = False
    gt: bool = True
    trails: bool = True
    trail_window: int = 25
    frustum_image_width: int = 128  # px of the video on the frustums (see FRUSTUM_WIDTHS)
    meshes: bool = False  # opaque bodies hide the skeletons inside them
    fit_meshes: bool = False
    meshes_selected_only: bool = False  # the selected track's body (and its GT person's)
    bodies_on_images: bool = False  # fitted bodies reprojected on the camera panel's image
    mesh_style: str = "solid"  # one of MESH_STYLES
    mesh_detail: str = "decimated"  # one of MESH_DETAILS: what the browser skins
    references_off: frozenset[str] = frozenset()  # reference tracks not drawn, by name


@dataclass(frozen=True)
class Selection:
    """The selected track (None: none) and joint (index into the results' joint set),
    and optionally a view (camera index) another panel asked to look at."""

    track: int | None = None
    joint: int = 0
    view: int | None = None


# How the bodies are drawn: "translucent" and "wireframe" show the skeletons inside;
# "decimated" display meshes (mvviz.scene.decimate, ~1/6 of the faces) keep software WebGL
# interactive, "full" is the body model's own mesh (what exports write).
MESH_STYLES = ("solid", "translucent", "wireframe")
MESH_DETAILS = ("decimated", "full")
MESH_OPACITY = 0.45  # of a translucent body


# Frustum video widths offered (px): an image plane is ~100-200 px on screen at the
# default view; 128 px JPEGs (~2 kB each) cost 1/4 of the 320 px ones per frame change.
FRUSTUM_WIDTHS = (128, 320)
FRUSTUM_JPEG_QUALITY = 50

OFFSET_FILTERED_M = np.array([1.0, 0.0, 0.0])
CENTER_FRAMES = 1000  # frames the action's centre and spread are read from
ALL_FRUSTA_MAX_CAMERAS = 8  # more cameras: 2D detections on the panel camera's frustum only
# and the frustums' video this wide (px): 31 frusta's 128 px JPEGs were 62.5 KB a frame
# change (bench/bench_viewer_scale.py), more than half of it
MANY_CAMERAS_FRUSTUM_WIDTH = 80


# --------------------------------------------------------------------------- static data


@dataclass(frozen=True, eq=False)
class CameraGeometry:
    """How a camera is drawn: its pose (metres) and its frustum's image plane.

    ``plane_depth`` is the distance of the frustum's image plane from the centre;
    ``half_size`` its half width and half height, metres (the plane spans the image).
    """

    name: str
    wxyz: np.ndarray  # (4,) R_world_camera
    position: np.ndarray  # (3,) camera centre, m
    fov: float  # vertical, radians
    aspect: float  # width / height
    frustum_scale: float
    plane_depth: float
    half_size: np.ndarray  # (2,)
    image_size: np.ndarray  # (2,) width, height px

    def pixels_to_plane(self, pixels: np.ndarray, *, lift: float = 0.99) -> np.ndarray:
        """(..., 2) pixels -> (..., 3) camera-frame metres on the frustum's image plane."""
        uv = (np.asarray(pixels, float) + 0.5) / self.image_size * 2.0 - 1.0
        xy = uv * self.half_size
        z = np.full(xy.shape[:-1] + (1,), self.plane_depth * lift)
        return np.concatenate([xy, z], -1)


def camera_geometry(camera: Camera, *, plane_depth: float = 0.6) -> CameraGeometry:
    """Frustum parameters so that its image plane lies ``plane_depth`` metres ahead.

    Mirrors viser's client: the frustum is normalised to unit volume, so
    ``depth = scale / cbrt(tan(fov/2)^2 * aspect / 3)``.
    """
    W, H = camera.width, camera.height
    fov = 2.0 * np.arctan2(H / 2.0, camera.K[1, 1])
    aspect = W / H
    t = np.tan(fov / 2.0)
    volume_scale = np.cbrt(t * t * aspect / 3.0)
    return CameraGeometry(
        name=camera.name,
        wxyz=vtf.SO3.from_matrix(camera.R.T).wxyz,
        position=camera.center * MM,
        fov=float(fov),
        aspect=float(aspect),
        frustum_scale=float(plane_depth * volume_scale),
        plane_depth=plane_depth,
        half_size=np.array([t * aspect * plane_depth, t * plane_depth]),
        image_size=np.array([W, H], float),
    )


@dataclass(frozen=True, eq=False)
class ViewerData:
    """Everything the viewer derives once from a scene and its results (read-only).

    Shapes: N detection rows, Q person-frames, K tracks, F frames, V views, J joints of
    the results' joint set. 3D arrays here are still millimetres, as in the results.
    """

    scene: Scene
    results: PipelineResults
    joint_set: JointSet  # of the results (what was triangulated)
    gt_joint_set: JointSet  # of ``gt_points``
    rows_per_frame: list[np.ndarray]  # detection rows of each frame
    people_per_frame: list[np.ndarray]  # person-frame rows (q) of each frame
    gt_rows_per_frame: list[np.ndarray]
    # Per detection row, computed for the rows a frame indexes (never all N at start-up):
    det_track: LazyRows  # (N,) track of the row's person; -1 untracked / unassigned
    det_rays: LazyRows  # (N, J, 3) world unit ray through each detected joint; NaN
    det_plane: LazyRows  # (N, J, 3) float32 each detected joint on its frustum's image plane, m
    track_person: np.ndarray  # (K, F) person-frame row of each track and frame, -1
    filtered: np.ndarray  # (K, F, J, 3) the configured filter's output, mm
    gt_points: np.ndarray | None  # (M, Jg, 3) mm
    cameras: list[CameraGeometry]
    bodies: GtBodies | None
    fit_bodies: Bodies | None
    min_confidence: float
    center: np.ndarray  # (3,) m, middle of the action, in the display frame
    spread: float  # m, horizontal half-size of the action
    extent: float  # m, radius of the rig (at least 3)
    camera_distance: float  # m, median distance of the cameras from the action
    # (4, 4) world metres -> the display frame (z up, the floor at z = 0 where the people
    # tell it): identity for a z-up world; see :func:`display_transform`
    T_display_world: np.ndarray = field(default_factory=lambda: np.eye(4))

    @property
    def num_frames(self) -> int:
        return self.scene.num_frames

    @property
    def num_tracks(self) -> int:
        return self.results.num_tracks


def prepare(
    scene: Scene,
    results: PipelineResults,
    model: BodyModel | BodyModelData | None,
    *,
    bodies: GtBodies | None = None,
) -> ViewerData:
    """Precompute per-frame indices, colours, camera geometry and GT bone poses
    (``bodies`` reuses already computed ones, e.g. when only the results changed)."""
    F = scene.num_frames
    if results.num_frames != F or len(results.det_person) != len(scene.detections):
        raise ValueError(
            f"results ({results.num_frames} frames, {len(results.det_person)} detections) "
            f"are not of this scene ({F} frames, {len(scene.detections)} detections)"
        )
    joint_set = get_joint_set(results.joint_set)
    gt, gt_points, gt_js, gt_rows = scene.gt, None, SMPL24, [np.zeros(0, int)] * F
    if gt is not None:
        if gt.keypoints3d is not None and results.joint_set == scene.joint_set.name:
            gt_points, gt_js = gt.keypoints3d, scene.joint_set
        else:
            gt_points = gt.joints3d
        gt_rows = group_by_frame(gt.frame, F)

    step = max(1, -(-F // CENTER_FRAMES))
    T_display_world = display_transform(scene, results, joint_set, step=step)
    centers = to_display(T_display_world, scene.rig.centers * MM)
    # at most CENTER_FRAMES frames, evenly spread: enough for percentiles, and a long
    # sequence's (memory-mapped) tracks are not read whole at start-up
    pts = np.asarray(results.track_raw[:, ::step]).reshape(-1, 3)
    pts = pts[np.isfinite(pts).all(1)]
    if len(pts) == 0 and gt_points is not None:
        pts = gt_points.reshape(-1, 3)
    if len(pts) == 0 and scene.references:
        pts = np.concatenate([r.joints.reshape(-1, 3) for r in scene.references.values()])
        pts = pts[np.isfinite(pts).all(1)]
    pts = to_display(T_display_world, pts * MM) / MM
    if len(pts):  # the middle of where people go, and how far they spread
        lo, hi = np.percentile(pts * MM, 5, axis=0), np.percentile(pts * MM, 95, axis=0)
        center = np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, np.median(pts[:, 2]) * MM])
        spread = float(np.linalg.norm(hi[:2] - lo[:2]) / 2)
    else:
        center, spread = np.array([0.0, 0.0, 1.0]), 2.0
    to_action = np.linalg.norm(centers - center, axis=1)  # (V,) m
    extent = float(np.max(np.linalg.norm((centers - center)[:, :2], axis=1), initial=3.0))
    # Frusta sized to the rig: their image planes ~1/6 of the way to the action (at most
    # 0.6 m, as on a room-sized rig), so a rig a metre from a person does not hide them.
    depth = float(np.clip(np.median(to_action) / 6.0, 0.08, 0.6)) if len(to_action) else 0.6
    cameras = [camera_geometry(c, plane_depth=depth) for c in scene.rig]
    return ViewerData(
        scene=scene,
        results=results,
        joint_set=joint_set,
        gt_joint_set=gt_js,
        rows_per_frame=frame_rows(scene, results.config),  # re-timed rows where they were used
        **person_indices(results, F),
        **lazy_detection_rays(scene, results, cameras),
        gt_rows_per_frame=gt_rows,
        filtered=results.track_filtered,
        gt_points=gt_points,
        cameras=cameras,
        bodies=bodies if bodies is not None else gt_bodies(scene, model) if model else None,
        fit_bodies=fitted_bodies(results),
        min_confidence=results.config.triangulation.min_confidence,
        center=center,
        spread=spread,
        extent=extent,
        camera_distance=float(np.median(to_action)) if len(to_action) else 3.0,
        T_display_world=T_display_world,
    )


UPRIGHT_TOLERANCE_DEG = 30.0
"""A world whose "up" (from the people, else the cameras) is further than this from +z is
shown turned upright: a calibration in its first camera's frame (y down) is ~90 degrees
off; a z-up capture whose people lean is a few degrees off and is shown as it is."""


def display_transform(
    scene: Scene, results: PipelineResults, joint_set: JointSet, *, step: int = 1
) -> np.ndarray:
    """(4, 4) world metres -> the display frame the viewer draws in.

    Up comes from the people (:func:`pipeline.diagnose.floor.estimate_floor`: the plane of
    their planted feet, else their body axis), the floor at z = 0 under them; without
    enough people, from the cameras (mounted upright, their image's "up" averaged). A
    world already z-up within :data:`UPRIGHT_TOLERANCE_DEG` is drawn as it is."""
    from pipeline.diagnose.floor import estimate_floor, level_rotation

    T = np.eye(4)
    tracks = np.asarray(results.track_filtered[:, ::step])
    floor = estimate_floor(tracks, list(joint_set.names)) if tracks.size else None
    if floor is not None:
        if floor.angle_to_z_deg <= UPRIGHT_TOLERANCE_DEG:
            return T
        T[:3, :3] = level_rotation(floor.up)
        T[2, 3] = -floor.height_mm * MM
        return T
    R = np.asarray([c.R for c in scene.rig], float)  # (V, 3, 3) world -> camera
    if not len(R):
        return T
    up = -R[:, 1, :].sum(0)  # each camera's image "up" (-y) in world coordinates
    norm = np.linalg.norm(up)
    if norm < 1e-9 or np.degrees(np.arccos(np.clip(up[2] / norm, -1, 1))) <= UPRIGHT_TOLERANCE_DEG:
        return T
    T[:3, :3] = level_rotation(up / norm)
    # No floor to go by: the grid goes under everything seen (people and cameras).
    seen = [scene.rig.centers * MM @ T[:3, :3].T]
    if tracks.size:
        pts = tracks.reshape(-1, 3)
        seen.append(pts[np.isfinite(pts).all(1)] * MM @ T[:3, :3].T)
    heights = np.concatenate([p[:, 2] for p in seen])
    T[2, 3] = -(float(np.percentile(heights, 1)) - 0.2)
    return T


def to_display(T_display_world: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(..., 3) world metres -> the display frame."""
    points = np.asarray(points, float)
    return points @ T_display_world[:3, :3].T + T_display_world[:3, 3]


def person_indices(results: PipelineResults, num_frames: int) -> dict[str, object]:
    """The :class:`ViewerData` indices of ``results``' people (F = ``num_frames``):
    ``people_per_frame`` (F lists of person-frame rows), ``det_track`` (N,) the track of
    each detection's person (-1 untracked or unassigned; computed for the rows indexed)
    and ``track_person`` (K, F) each track's person-frame row (-1)."""
    pf, pt = np.asarray(results.person_frame), np.asarray(results.person_track)
    track_of_person = np.append(pt, -1)  # det_person -1 -> the -1 at the end
    det_person = results.det_person

    def det_track(rows: np.ndarray) -> tuple[np.ndarray]:
        return (track_of_person[det_person[rows]],)

    track_person = np.full((results.num_tracks, num_frames), -1)
    tracked = np.flatnonzero(pt >= 0)
    track_person[pt[tracked], pf[tracked]] = tracked
    return {
        "people_per_frame": group_by_frame(pf, num_frames),
        "det_track": RowBlocks(det_track, len(det_person)).array(0),
        "track_person": track_person,
    }


def lazy_detection_rays(
    scene: Scene, results: PipelineResults, cameras: list[CameraGeometry]
) -> dict[str, LazyRows]:
    """``det_rays`` and ``det_plane`` of :class:`ViewerData`: :func:`detection_rays` of
    the rows a frame indexes, computed on first use (both from one computation)."""
    blocks = RowBlocks(
        lambda rows: detection_rays(scene, results, cameras, rows), len(results.det_joints2d)
    )
    return {"det_rays": blocks.array(0), "det_plane": blocks.array(1)}


def detection_rays(
    scene: Scene,
    results: PipelineResults,
    cameras: list[CameraGeometry],
    rows: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Per detected joint, once for the sequence (a frame change then only indexes):
    (n, J, 3) world unit rays through it, and (n, J, 3) float32 camera-frame metres on
    its frustum's image plane, for detection ``rows`` (default: all N). NaN where the 2D
    joint is not finite."""
    rows = np.arange(len(results.det_joints2d)) if rows is None else np.asarray(rows)
    kp = np.asarray(results.det_joints2d[rows, :, :2], float)  # (n, J, 2) px
    finite = np.isfinite(kp).all(-1)
    view = scene.detections.view[rows]
    # cameras without distortion in one product for all views; the others one by one
    rays_, plain = pinhole_rays(scene.rig, view, kp)
    for v in np.unique(view[~plain]):
        ok = finite & (view == v)[:, None]
        rays_[ok] = scene.rig[int(v)].pixels_to_rays(kp[ok])
    size = np.array([g.image_size for g in cameras])[view][:, None]  # (n, 1, 2)
    half = np.array([g.half_size for g in cameras])[view][:, None]
    depth = np.array([g.plane_depth for g in cameras])[view][:, None, None]
    xy = ((kp + 0.5) / size * 2.0 - 1.0) * half  # as CameraGeometry.pixels_to_plane
    plane = np.concatenate([xy, np.broadcast_to(depth * 0.99, xy.shape[:-1] + (1,))], -1)
    rays_[~finite], plane[~finite] = np.nan, np.nan
    return rays_, plane.astype(np.float32)


# --------------------------------------------------------------------------- per frame


@dataclass(frozen=True, eq=False)
class Skeleton:
    """One person's joints and the bones between joints that exist, metres."""

    joints: np.ndarray  # (J, 3), NaN where missing
    segments: np.ndarray  # (S, 2, 3)
    color: np.ndarray  # (3,) uint8


@dataclass(frozen=True, eq=False)
class Detections2D:
    """One view's 2D joints on its frustum's image plane, in that camera's frame (m)."""

    points: np.ndarray  # (n, 3)
    colors: np.ndarray  # (n, 3) uint8
    segments: np.ndarray  # (s, 2, 3)
    segment_colors: np.ndarray  # (s, 2, 3) uint8


@dataclass(frozen=True, eq=False)
class Rays:
    """Rays from camera centres through 2D joints, to a little past the 3D joint (m)."""

    segments: np.ndarray  # (R, 2, 3)
    colors: np.ndarray  # (R, 3) uint8
    outlier: np.ndarray  # (R,) bool: the view was rejected for this joint
    view: np.ndarray  # (R,)
    joint: np.ndarray  # (R,)
    track: np.ndarray  # (R,) -1 untracked
    person: np.ndarray  # (R,) person-frame row q


@dataclass(frozen=True, eq=False)
class Trail:
    """The selected joint of one track over a window of frames (segments, metres)."""

    raw: np.ndarray  # (a, 2, 3)
    filtered: np.ndarray  # (b, 2, 3)
    color: np.ndarray  # (3,) uint8


@dataclass(frozen=True, eq=False)
class BonePoses:
    wxyz: np.ndarray  # (24, 4)
    position: np.ndarray  # (24, 3) m


@dataclass(frozen=True, eq=False)
class FrameGeometry:
    """What every layer draws for one frame; a layer that is off is empty."""

    frame: int
    detections2d: dict[str, Detections2D] = field(default_factory=dict)
    rays: Rays | None = None
    raw: dict[int, Skeleton] = field(default_factory=dict)
    filtered: dict[int, Skeleton] = field(default_factory=dict)
    gt: dict[int, Skeleton] = field(default_factory=dict)
    references: dict[str, Skeleton] = field(default_factory=dict)  # by reference name
    trails: dict[int, Trail] = field(default_factory=dict)
    meshes: dict[int, BonePoses] = field(default_factory=dict)
    fit_meshes: dict[int, BonePoses] = field(default_factory=dict)


def bone_segments(joints: np.ndarray, bones: tuple[tuple[int, int], ...]) -> np.ndarray:
    """(J, 3) joints -> (S, 2, 3) segments of the bones whose two ends are finite."""
    if not bones:
        return np.zeros((0, 2, 3))
    b = np.asarray(bones)
    seg = np.stack([joints[b[:, 0]], joints[b[:, 1]]], 1)
    return seg[np.isfinite(seg).all((1, 2))]


def polyline_segments(points: np.ndarray) -> np.ndarray:
    """(n, 3) points with NaN gaps -> (s, 2, 3) segments between consecutive finite points."""
    seg = np.stack([points[:-1], points[1:]], 1) if len(points) > 1 else np.zeros((0, 2, 3))
    return seg[np.isfinite(seg).all((1, 2))]


def _skeletons(points: np.ndarray, ids, js: JointSet, colors) -> dict[int, Skeleton]:
    """(P, J, 3) mm -> each person with a finite joint: joints and bones in metres. The
    bones of all P people are gathered at once (per person it was ~50 us of NumPy calls,
    60 people a frame at 31 cameras x 20 people)."""
    pts = np.asarray(points, float) * MM
    if pts.size == 0:
        return {}
    has = np.isfinite(pts).any((1, 2))
    if js.bones:
        b = np.asarray(js.bones)
        seg = np.stack([pts[:, b[:, 0]], pts[:, b[:, 1]]], 2)  # (P, S, 2, 3)
        ok = np.isfinite(seg).all((2, 3))
    out = {}
    for i, (pid, col) in enumerate(zip(ids, colors, strict=True)):
        if has[i]:
            segs = seg[i][ok[i]] if js.bones else np.zeros((0, 2, 3))
            out[int(pid)] = Skeleton(pts[i], segs, col)
    return out


def reference_skeletons(
    data: ViewerData, frame: int, off: frozenset[str] = frozenset()
) -> dict[str, Skeleton]:
    """Each reference track of the scene (but those in ``off``) at ``frame``: its joints
    (J, 3) in metres and the scene joint set's bones, in :data:`REFERENCE_SKELETON`."""
    js, out = data.scene.joint_set, {}
    for name, ref in data.scene.references.items():
        pts = ref.joints[frame] * MM  # (J, 3) m
        if name not in off and np.isfinite(pts).any():
            out[name] = Skeleton(pts, bone_segments(pts, js.bones), REFERENCE_SKELETON)
    return out


def detections_2d(
    data: ViewerData, frame: int, views: list[int] | None = None
) -> dict[str, Detections2D]:
    """Each view's (or each of ``views``') 2D joints (confidence > 0) of ``frame`` on its
    frustum's image plane. One gather of the frame's rows for every view (31 views cost
    ~1/5 of a per-view loop)."""
    rows = data.rows_per_frame[frame]
    res, bones = data.results, np.asarray(data.joint_set.bones).reshape(-1, 2)
    if views is not None:
        rows = rows[np.isin(data.scene.detections.view[rows], views)]
    view, t = data.scene.detections.view[rows], data.det_track[rows]
    # by view, then in track order (unassigned last): a view's colour arrays then repeat
    # from frame to frame while the same people are seen, and viser does not send them again
    order = np.lexsort((np.where(t < 0, np.iinfo(np.int64).max, t), view))
    r, view, t = rows[order], view[order], t[order]
    kp = res.det_joints2d[r]  # (n, J, 3)
    col = np.where((res.det_person[r] < 0)[:, None], UNASSIGNED, track_color(t)).astype(np.uint8)
    ok = (kp[..., 2] > 0) & np.isfinite(kp[..., :2]).all(-1)  # (n, J)
    plane = data.det_plane[r]  # (n, J, 3)
    pts = plane[ok]
    pcol = np.broadcast_to(col[:, None], ok.shape + (3,))[ok]
    bok = ok[:, bones[:, 0]] & ok[:, bones[:, 1]]  # (n, B)
    seg = np.stack([plane[:, bones[:, 0]], plane[:, bones[:, 1]]], 2)[bok]
    scol = np.broadcast_to(col[:, None, None], bok.shape + (2, 3))[bok]
    # each view's rows are consecutive: split the flattened points and segments there
    row_end = np.searchsorted(view, np.arange(len(data.cameras) + 1))
    pt_end = np.concatenate([[0], np.cumsum(ok.sum(1))])[row_end]
    seg_end = np.concatenate([[0], np.cumsum(bok.sum(1))])[row_end]
    out = {}
    for v, cam in enumerate(data.cameras):
        if views is None or v in views:
            p, q = slice(pt_end[v], pt_end[v + 1]), slice(seg_end[v], seg_end[v + 1])
            out[cam.name] = Detections2D(pts[p], pcol[p], seg[q], scol[q])
    return out


def rays(data: ViewerData, frame: int, *, track: int | None = None) -> Rays:
    """Rays of ``frame``: for each person-frame q, joint j and view v that observed j
    (confidence >= the triangulation threshold) where q's joint j was triangulated:
    coloured by q's track if v was used, :data:`OUTLIER` if v was rejected.
    ``track`` keeps only that track's rays."""
    res = data.results
    qs = data.people_per_frame[frame]
    if track is not None:
        qs = qs[res.person_track[qs] == track]
    # every (view, person) pair with a member, view-major: one gather for all views
    v, qi = np.nonzero(np.asarray(res.person_members[qs]).T >= 0)
    q = qs[qi]
    m = res.person_members[q, v]
    kp = res.det_joints2d[m]  # (n, J, 3)
    X = res.person_joints[q]  # (n, J, 3) mm
    obs = (kp[..., 2] >= data.min_confidence) & (kp[..., 2] > 0)
    obs &= np.isfinite(kp[..., :2]).all(-1) & np.isfinite(X).all(-1)
    pair, j = np.nonzero(obs)
    d = data.det_rays[m[pair], j]  # (r, 3) unit
    c = np.asarray(data.scene.rig.centers, float)[v[pair]]  # (r, 3) mm
    length = np.einsum("rc,rc->r", X[pair, j] - c, d) * 1.1
    ok = np.isfinite(d).all(1) & (length > 0)
    pair, j, d, c, length = pair[ok], j[ok], d[ok], c[ok], length[ok]
    view, person = v[pair], q[pair]
    used = res.person_used[person, j, view].astype(bool)
    trk = res.person_track[person]
    return Rays(
        np.stack([c, c + d * length[:, None]], 1).reshape(-1, 2, 3) * MM,
        np.where(used[:, None], track_color(trk), OUTLIER).astype(np.uint8).reshape(-1, 3),
        ~used,
        view,
        j,
        trk,
        person,
    )


def trails(
    data: ViewerData, frame: int, joint: int, window: int, *, track: int | None = None
) -> dict[int, Trail]:
    """``joint`` of each track (or of ``track`` only) over ``[frame - window, frame + window]``."""
    lo, hi = max(0, frame - window), min(data.num_frames, frame + window + 1)
    raw = data.results.track_raw[:, lo:hi, joint] * MM  # (K, w, 3)
    filt = data.filtered[:, lo:hi, joint] * MM
    out = {}
    for k in range(data.num_tracks) if track is None else [track]:
        a, b = polyline_segments(raw[k]), polyline_segments(filt[k])
        if len(a) or len(b):
            out[k] = Trail(a, b, track_color(k))
    return out


class FrameView(Protocol):
    """What :func:`frame_geometry` reads of the viewer's state (a
    :class:`mvviz.state.ViewerState` is one; scene code never imports the state)."""

    data: ViewerData
    frame: int
    selection: Selection
    layers: LayerToggles
    camera: int  # the camera panel's view


def frame_geometry(state: FrameView, frame: int | None = None) -> FrameGeometry:
    """What to draw for ``frame`` (default: the state's frame) given layers and selection."""
    data, lay, sel = state.data, state.layers, state.selection
    f = int(state.frame if frame is None else frame)
    if not 0 <= f < data.num_frames:
        raise ValueError(f"frame {f} outside [0, {data.num_frames})")
    K = data.num_tracks
    track = sel.track if sel.track is not None and 0 <= sel.track < K else None
    geom: dict = {"frame": f}
    if lay.detections2d:
        views = [state.camera] if lay.detections2d_panel_camera_only else None
        geom["detections2d"] = detections_2d(data, f, views)
    if lay.rays:
        geom["rays"] = rays(data, f, track=track if lay.rays_selected_only else None)
    colors = track_color(np.arange(K))
    if lay.raw:
        geom["raw"] = _skeletons(data.results.track_raw[:, f], range(K), data.joint_set, colors)
    if lay.filtered:
        geom["filtered"] = _skeletons(data.filtered[:, f], range(K), data.joint_set, colors)
    if lay.gt and data.gt_points is not None:
        r = data.gt_rows_per_frame[f]
        pid = data.scene.gt.person_id[r]
        geom["gt"] = _skeletons(data.gt_points[r], pid, data.gt_joint_set, [GT_SKELETON] * len(r))
    geom["references"] = reference_skeletons(data, f, lay.references_off)
    if lay.trails and lay.trail_window > 0 and 0 <= sel.joint < data.joint_set.num_joints:
        # the selected track's trail; every track's while none is selected
        geom["trails"] = trails(data, f, sel.joint, lay.trail_window, track=track)
    only = lay.meshes_selected_only
    for key, on, b, keep in (
        ("meshes", lay.meshes, data.bodies, {gt_person_of(data, track, f)} if only else None),
        ("fit_meshes", lay.fit_meshes, data.fit_bodies, {track} if only else None),
    ):
        if on and b is not None:
            geom[key] = {
                int(p): BonePoses(b.bone_wxyz[i, f], b.bone_position[i, f])
                for i, p in enumerate(b.ids)
                if b.present[i, f] and (keep is None or int(p) in keep)
            }
    return FrameGeometry(**geom)


def gt_person_of(data: ViewerData, track: int | None, frame: int) -> int | None:
    """The ground-truth person nearest ``track`` at ``frame`` (mean joint position of
    its filtered, else raw, joints against each person's), or None."""
    if track is None or data.gt_points is None:
        return None
    rows = data.gt_rows_per_frame[frame]
    pts = data.filtered[track, frame]
    if not np.isfinite(pts).any():
        pts = data.results.track_raw[track, frame]
    if len(rows) == 0 or not np.isfinite(pts).any():
        return None
    c = np.nanmean(pts, 0)
    d = [np.linalg.norm(np.nanmean(data.gt_points[r], 0) - c) for r in rows]
    return int(data.scene.gt.person_id[rows[int(np.nanargmin(d))]])
