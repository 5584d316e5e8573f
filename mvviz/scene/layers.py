"""The viser scene nodes of every layer, created once; a frame change assigns a
:class:`~mvviz.scene.geometry.FrameGeometry` to them.

The scene tree is the layer system (hiding a parent hides its children)::

    /world/grid
    /world/cameras/<name>/frustum       current video frame on the image plane
    /world/cameras/<name>/label
    /world/detections2d/<name>          2D joints drawn on that frustum's image plane
    /world/rays                         camera centre -> used 2D joint (outliers in red)
    /world/skeletons/raw/{bones,joints} triangulated, before filtering (thin, pale; every
                                        track in one node, coloured per track)
    /world/skeletons/filtered/<track>   Kalman output (solid bones)
    /world/skeletons/filtered/joints    every track's joints, clickable (one batched mesh)
    /world/skeletons/gt/bones           ground truth (neutral colour; every person, one node)
    /world/skeletons/reference/<name>/{bones,joints}  another tool's result (grey)
    /world/trails/{raw,filtered}        selected joint over +-N frames (every track in one
                                        node each, coloured per track)
    /world/meshes/gt/<person>           ground-truth body, skinned in the browser
    /world/meshes/fit/<track>           fitted SMPL body (SMPL + VAE), skinned likewise

Metres, like :mod:`mvviz.scene.geometry`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np
import viser
import viser.transforms as vtf

from mvviz.scene.decimate import DISPLAY_CELL_M, WIREFRAME_CELL_M, decimate_bodies
from mvviz.scene.geometry import (
    FRUSTUM_JPEG_QUALITY,
    GT_MESH,
    GT_SKELETON,
    MESH_OPACITY,
    OFFSET_FILTERED_M,
    OUTLIER,
    REFERENCE_SKELETON,
    SELECTED_CAMERA,
    UNASSIGNED,
    UNTRACKED,
    CameraGeometry,
    FrameGeometry,
    LayerToggles,
    Selection,
    Skeleton,
    Trail,
    ViewerData,
    pale,
    track_color,
)
from mvviz.scene.skinned import BonePoser

# --------------------------------------------------------------------------- viser nodes

FRUSTUM_COLOR = (60, 60, 60)


@lru_cache(maxsize=4)
def icosphere(radius: float) -> tuple[np.ndarray, np.ndarray]:
    """The selected joint's marker: an icosahedron subdivided once, (42, 3) vertices (m)
    and (80, 3) faces wound outwards. Made here: trimesh's takes ~0.5 s of imports."""
    t = (1 + 5**0.5) / 2
    v = np.array([
        [-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t],
        [0, -1, -t], [0, 1, -t], [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1],
    ], float)  # fmt: skip
    f = np.array([
        [0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4],
        [11, 10, 2], [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8],
        [3, 8, 9], [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1],
    ])  # fmt: skip
    # 1. one midpoint per edge, shared by the two faces of the edge
    edges = np.sort(f[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    uniq, inverse = np.unique(edges, axis=0, return_inverse=True)
    mid = len(v) + inverse.reshape(-1, 3)  # (20, 3): midpoints of edges ab, bc, ca
    v = np.concatenate([v, v[uniq].mean(1)])
    # 2. each face into four, the same winding
    a, b, c = f.T
    ab, bc, ca = mid.T
    quads = ((a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca))
    f = np.concatenate([np.stack(x, 1) for x in quads])
    v = radius * v / np.linalg.norm(v, axis=1, keepdims=True)
    return v.astype(np.float32), f.astype(np.uint32)


def _set_segments(
    handle: viser.LineSegmentsHandle, segments: np.ndarray, colors: np.ndarray | None
) -> None:
    """Show ``segments`` (S, 2, 3) coloured by ``colors`` ((3,), (S, 3) or (S, 2, 3), sent
    per vertex; None keeps the node's uniform colour); hide the node when there are none.
    """
    if len(segments) == 0:
        handle.visible = False
        return
    handle.points = segments.astype(np.float32)
    if colors is not None:
        c = np.asarray(colors, np.uint8)
        if c.shape == (len(segments), 3):
            c = c[:, None]
        handle.colors = np.ascontiguousarray(np.broadcast_to(c, segments.shape))
    handle.visible = True


_EMPTY_SEG = np.zeros((1, 2, 3), np.float32)  # placeholder until the first frame
_EMPTY_COLORS = np.zeros((1, 2, 3), np.uint8)
_NO_SEG = np.zeros((0, 2, 3))
_NO_COLORS = np.zeros((0, 3), np.uint8)
RAW_BONES = "/world/skeletons/raw/bones"  # every track's, one node (see _apply_raw)
RAW_JOINTS = "/world/skeletons/raw/joints"
FILTERED_JOINTS = "/world/skeletons/filtered/joints"  # every track's (_apply_filtered_joints)
GT_BONES = "/world/skeletons/gt/bones"  # every ground-truth person's, one uniform colour
TRAILS_RAW = "/world/trails/raw"  # every track's trail, one node each kind (_apply_trails)
TRAILS_FILTERED = "/world/trails/filtered"


def _coloured_segments(parts: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    """[((S_i, 2, 3) segments, (3,) colour), ...] -> all segments (S, 2, 3) and (S, 3)
    colours, one per segment: several tracks' lines as one per-vertex-coloured node."""
    if not parts:
        return _NO_SEG, _NO_COLORS
    segs = np.concatenate([seg for seg, _ in parts])
    cols = np.concatenate([np.broadcast_to(c, (len(seg), 3)) for seg, c in parts])
    return segs, cols


def raw_color(k: int) -> np.ndarray:
    """Track ``k``'s raw skeleton colour: its colour, paler."""
    return pale(track_color(k), 0.45)


@dataclass
class SceneLayers:
    """The viser scene nodes of every layer, created once by :func:`make_scene_layers`;
    a frame change only assigns properties (points, colours, bone poses, images,
    visibility). The skinned meshes are added the first time their layer is shown."""

    server: viser.ViserServer
    data: ViewerData
    on_joint_click: Callable[[int, int], None] | None = None
    groups: dict[str, viser.SceneNodeHandle] = field(default_factory=dict)
    nodes: dict[str, viser.SceneNodeHandle] = field(default_factory=dict)
    colors: dict[str, np.ndarray | None] = field(default_factory=dict)  # single-colour lines
    gt_ids: list[int] = field(default_factory=list)
    meshes: dict[int, viser.MeshSkinnedHandle] = field(default_factory=dict)
    fit_meshes: dict[int, viser.MeshSkinnedHandle] = field(default_factory=dict)
    bone_posers: dict[str, BonePoser] = field(default_factory=dict)  # by mesh name
    mesh_detail: dict[str, str] = field(default_factory=dict)  # kind -> detail drawn
    _display_bodies: dict[tuple[str, str], object] = field(default_factory=dict)
    fast_bones: bool | None = None  # None: the bulk path when viser has its internals
    _frustum_key: dict[str, object] = field(default_factory=dict)
    _selected: tuple[int | None, int] = (None, -1)
    highlighted: str | None = None  # the camera shown in the camera panel

    def _lines(self, path: str, color, thickness: float, units: str = "screen") -> None:
        """A hidden line-segments node at ``path``.

        viser 1.1's client shares line shaders between lines that differ only in having
        per-vertex colours, so one kind per thickness unit: screen-space lines are always
        coloured per vertex, world-unit lines (with their antialiasing fringe pass)
        always uniformly; otherwise some lines come out white or washed out.
        """
        world = units == "world"
        self.nodes[path] = self.server.scene.add_line_segments(
            path, _EMPTY_SEG, color if world else _EMPTY_COLORS, thickness=thickness,
            thickness_units=units, visible=False,
        )  # fmt: skip
        self.colors[path] = None if world else np.asarray(color, np.uint8)

    @staticmethod
    def mesh_version(lay: LayerToggles, kind: str) -> str:
        """Which mesh ``kind`` is drawn with under ``lay``: "full", "decimated" or
        "coarse" (decimated for a wireframe, which software WebGL draws slowly)."""
        if lay.mesh_detail == "full":
            return "full"
        return "coarse" if SceneLayers.mesh_style(lay, kind) == "wireframe" else "decimated"

    @staticmethod
    def mesh_style(lay: LayerToggles, kind: str) -> str:
        """The style of ``kind``'s bodies: the chosen one, but with both mesh layers on
        and solid the ground truth is translucent (two opaque bodies in one place
        z-fight into speckle)."""
        if kind == "gt" and lay.mesh_style == "solid" and lay.meshes and lay.fit_meshes:
            return "translucent"
        return lay.mesh_style

    def display_bodies(self, kind: str, version: str):
        """The bodies of ``kind`` ("gt" or "fit") as drawn: ``version`` "full", or
        "decimated" / "coarse" (:func:`mvviz.scene.decimate.decimate_bodies`, computed once)."""
        b = self.data.bodies if kind == "gt" else self.data.fit_bodies
        if b is None or version == "full":
            return b
        key = (kind, version)
        if key not in self._display_bodies:
            cell = WIREFRAME_CELL_M if version == "coarse" else DISPLAY_CELL_M
            self._display_bodies[key] = decimate_bodies(b, cell=cell)
        return self._display_bodies[key]

    def _ensure_meshes(self, kind: str, detail: str = "decimated") -> None:
        """Create the skinned meshes of ``kind`` ("gt" or "fit") the first time their
        layer is shown, or again at another ``detail``: each full body is ~0.8 MB to the
        browser (vertices, faces, skin weights; decimated ~0.15 MB), so a page whose
        mesh layers are off loads that much less. A re-creation reuses the names, so
        viser replaces the nodes in place."""
        b = self.display_bodies(kind, detail)
        store = self.meshes if kind == "gt" else self.fit_meshes
        if b is None or (store and self.mesh_detail.get(kind) == detail):
            return
        self.mesh_detail[kind] = detail
        ident = np.tile([1.0, 0, 0, 0], (24, 1))
        for i, pid in enumerate(b.ids):
            color = GT_MESH if kind == "gt" else tuple(int(c) for c in track_color(int(pid)))
            store[int(pid)] = self.server.scene.add_mesh_skinned(
                f"/world/meshes/{kind}/{pid}",
                b.vertices[i],
                b.faces,
                bone_wxyzs=ident,
                bone_positions=b.rest_joints[i],
                skin_weights=b.weights,
                color=color,
                # Opaque unless asked ("translucent": see set_mesh_style)
                opacity=None,
                cast_shadow=False,
                receive_shadow=False,
                visible=False,
            )

    def remove(self) -> None:
        """Remove every node this object created (children before parents)."""
        handles = list(self.meshes.values()) + list(self.fit_meshes.values())
        handles += list(self.nodes.values())
        handles += sorted(self.groups.values(), key=lambda h: -h.name.count("/"))
        for h in handles:
            h.remove()

    def _click_filtered_joint(self, event: viser.SceneNodePointerEvent) -> None:
        """A click on instance k * J + j of :data:`FILTERED_JOINTS`: track k, joint j."""
        J = self.data.joint_set.num_joints
        if self.on_joint_click is not None and event.instance_index is not None and J:
            track, joint = divmod(int(event.instance_index), J)
            if track < self.data.num_tracks:
                self.on_joint_click(track, joint)

    # ------------------------------------------------------------------ updates

    def _update(self, path: str, segments: np.ndarray) -> None:
        _set_segments(self.nodes[path], segments, self.colors[path])

    def set_mesh_style(self, lay: LayerToggles) -> None:
        """Solid, translucent or wireframe bodies (see :meth:`mesh_style`)."""
        for kind, store in (("gt", self.meshes), ("fit", self.fit_meshes)):
            style = self.mesh_style(lay, kind)
            for mesh in store.values():
                mesh.wireframe = style == "wireframe"
                mesh.opacity = MESH_OPACITY if style == "translucent" else None

    def set_visibility(self, lay: LayerToggles) -> None:
        if lay.meshes:
            self._ensure_meshes("gt", self.mesh_version(lay, "gt"))
        if lay.fit_meshes:
            self._ensure_meshes("fit", self.mesh_version(lay, "fit"))
        self.set_mesh_style(lay)
        g = self.groups
        g["/world/grid"].visible = lay.grid
        g["/world/cameras"].visible = lay.cameras
        g["/world/detections2d"].visible = lay.detections2d
        g["/world/rays"].visible = lay.rays
        g["/world/skeletons/raw"].visible = lay.raw
        g["/world/skeletons/filtered"].visible = lay.filtered
        g["/world/skeletons/gt"].visible = lay.gt
        for name in self.data.scene.references:
            g[f"/world/skeletons/reference/{name}"].visible = name not in lay.references_off
        g["/world/trails"].visible = lay.trails
        g["/world/meshes"].visible = lay.meshes or lay.fit_meshes
        g["/world/meshes/gt"].visible = lay.meshes
        g["/world/meshes/fit"].visible = lay.fit_meshes
        offset = OFFSET_FILTERED_M if lay.offset_filtered else np.zeros(3)
        g["/world/skeletons/filtered"].position = offset
        for cam in self.data.cameras:
            self.nodes[f"/world/cameras/{cam.name}/label"].visible = lay.camera_labels
        self.nodes[TRAILS_FILTERED].position = offset

    def highlight_camera(self, name: str) -> None:
        """Draw camera ``name``'s frustum (the camera panel's camera) thick and in
        :data:`SELECTED_CAMERA`, its label marked; the others as before."""
        if name == self.highlighted:
            return
        for cam in self.data.cameras:
            on = cam.name == name
            frustum = self.nodes[f"/world/cameras/{cam.name}/frustum"]
            frustum.color = tuple(int(c) for c in SELECTED_CAMERA) if on else FRUSTUM_COLOR
            frustum.thickness = 4.0 if on else 1.5
            label = self.nodes[f"/world/cameras/{cam.name}/label"]
            label.text = f"▶ {cam.name}" if on else cam.name
        self.highlighted = name

    def set_frustum_images(self, images: dict[str, tuple[object, np.ndarray | None]]) -> None:
        """``images``: camera name -> (key, RGB image or None); re-encoded only when the key
        (e.g. ``(frame, width)``) changes."""
        for name, (key, img) in images.items():
            if self._frustum_key.get(name) == key:
                continue
            self._frustum_key[name] = key
            self.nodes[f"/world/cameras/{name}/frustum"].image = img

    def _apply_raw(self, raw: dict[int, Skeleton]) -> None:
        """Every track's raw skeleton in two nodes, coloured per vertex: ~40 fewer property
        writes a frame at 20 tracks (each ~60 us in viser, more than drawing them)."""
        bones, joints = self.nodes[RAW_BONES], self.nodes[RAW_JOINTS]
        skeletons = sorted(raw.items())
        _set_segments(
            bones, *_coloured_segments([(s.segments, raw_color(k)) for k, s in skeletons])
        )
        pts = [s.joints[np.isfinite(s.joints).all(1)] for _, s in skeletons]
        cols = [
            np.broadcast_to(raw_color(k), (len(p), 3))
            for (k, _), p in zip(skeletons, pts, strict=True)
        ]
        n = sum(len(p) for p in pts)
        if n:
            joints.points = np.concatenate(pts).astype(np.float32)
            joints.colors = np.ascontiguousarray(np.concatenate(cols))
        joints.visible = n > 0

    def _apply_trails(self, trails: dict[int, Trail]) -> None:
        """Every track's raw and filtered trails in one node each, coloured per vertex
        (two nodes of ~6 property writes instead of ~6 per track)."""
        for path, kind, color in (
            (TRAILS_RAW, "raw", raw_color),
            (TRAILS_FILTERED, "filtered", track_color),
        ):
            parts = [(getattr(t, kind), color(k)) for k, t in sorted(trails.items())]
            _set_segments(self.nodes[path], *_coloured_segments(parts))

    def _apply_filtered_joints(self, filtered: dict[int, Skeleton], selection: Selection) -> None:
        """Every track's filtered joints as the instances of one batched mesh, track-major
        (instance k * J + j; a missing joint or track at scale 0), the selected joint
        larger: 2 property writes a frame instead of 3 per track."""
        K, J = self.data.num_tracks, self.data.joint_set.num_joints
        node = self.nodes[FILTERED_JOINTS]
        if K * J == 0 or not filtered:
            node.visible = False
            return
        pos = np.zeros((K, J, 3), np.float32)
        scales = np.zeros((K, J), np.float32)
        for k, s in filtered.items():
            ok = np.isfinite(s.joints).all(1)
            pos[k][ok] = s.joints[ok]
            scales[k][ok] = 1.0
        if selection.track is not None and 0 <= selection.track < K and 0 <= selection.joint < J:
            scales[selection.track, selection.joint] *= 1.8
        node.batched_positions = pos.reshape(K * J, 3)
        node.batched_scales = scales.reshape(K * J)
        node.visible = True

    def apply(self, geom: FrameGeometry, selection: Selection) -> None:
        """Assign one frame's geometry to the nodes (call inside ``server.atomic()``)."""
        data, nodes = self.data, self.nodes
        for cam in data.cameras:
            d = geom.detections2d.get(cam.name)
            pc = nodes[f"/world/detections2d/{cam.name}/joints"]
            if d is None or len(d.points) == 0:
                pc.visible = False
            else:
                pc.points = d.points.astype(np.float16)
                pc.colors = d.colors
                pc.visible = True
            seg = d.segments if d is not None else _NO_SEG
            cols = d.segment_colors if d is not None else UNASSIGNED
            _set_segments(nodes[f"/world/detections2d/{cam.name}/bones"], seg, cols)
        if geom.rays is not None:
            r = geom.rays
            used = ~r.outlier
            _set_segments(nodes["/world/rays/used"], r.segments[used], r.colors[used])
            _set_segments(nodes["/world/rays/outliers"], r.segments[r.outlier], OUTLIER)
        self._apply_raw(geom.raw)
        self._apply_filtered_joints(geom.filtered, selection)
        for k in range(data.num_tracks):
            # world-unit lines are uniformly coloured (see _lines): one node per track
            s = geom.filtered.get(k)
            self._update(f"/world/skeletons/filtered/{k}/bones", s.segments if s else _NO_SEG)
        self._apply_trails(geom.trails)
        gt = [geom.gt[p].segments for p in self.gt_ids if p in geom.gt]
        self._update(GT_BONES, np.concatenate(gt) if gt else _NO_SEG)
        for name in data.scene.references:
            s, base = geom.references.get(name), f"/world/skeletons/reference/{name}"
            self._update(f"{base}/bones", s.segments if s else _NO_SEG)
            pts = s.joints[np.isfinite(s.joints).all(1)] if s else np.zeros((0, 3))
            if len(pts):
                nodes[f"{base}/joints"].points = pts.astype(np.float32)
            nodes[f"{base}/joints"].visible = len(pts) > 0
        for store, poses in ((self.meshes, geom.meshes), (self.fit_meshes, geom.fit_meshes)):
            for pid, mesh in store.items():
                bp = poses.get(pid)
                if bp is None:
                    mesh.visible = False
                    continue
                poser = self.bone_posers.get(mesh.name)
                if poser is None or poser.mesh is not mesh:
                    poser = self.bone_posers[mesh.name] = BonePoser(mesh, fast=self.fast_bones)
                poser.pose(bp.wxyz, bp.position)
                mesh.visible = True


# --------------------------------------------------------------------------- building


def make_scene_layers(
    server: viser.ViserServer,
    data: ViewerData,
    *,
    on_joint_click: Callable[[int, int], None] | None = None,
) -> SceneLayers:
    """Every layer's (hidden) nodes for ``data`` on ``server``, in the tree of the module
    docstring; ``on_joint_click(track, joint)`` runs when a filtered joint is clicked."""
    layers = SceneLayers(server, data, on_joint_click=on_joint_click)
    _add_groups(layers)
    for cam in data.cameras:
        _add_camera(layers, cam)
    layers.groups["/world/rays"] = server.scene.add_frame("/world/rays", show_axes=False)
    layers._lines("/world/rays/used", UNTRACKED, 1.6)
    layers._lines("/world/rays/outliers", OUTLIER, 2.5)
    layers._lines(RAW_BONES, UNTRACKED, 2.0)  # coloured per track (per vertex) each frame
    layers.nodes[RAW_JOINTS] = server.scene.add_point_cloud(
        RAW_JOINTS, np.zeros((1, 3), np.float32), UNTRACKED, point_size=0.03,
        point_shape="circle", precision="float32", visible=False,
    )  # fmt: skip
    _add_filtered_joints(layers)
    for k in range(data.num_tracks):
        _add_track(layers, k)
    layers._lines(TRAILS_RAW, UNTRACKED, 2.0)  # coloured per track (per vertex) each frame
    layers._lines(TRAILS_FILTERED, UNTRACKED, 3.5)
    _add_ground_truth(layers)
    _add_references(layers)
    return layers


def _add_groups(layers: SceneLayers) -> None:
    """The grid and the group frames that the layer toggles show and hide."""
    scene, data = layers.server.scene, layers.data
    # Everything is drawn in world coordinates under /world, which the display frame
    # turns upright (identity for a z-up world); the grid lies on the display's floor.
    T = data.T_display_world
    layers.groups["/world"] = scene.add_frame(
        "/world", show_axes=False, wxyz=vtf.SO3.from_matrix(T[:3, :3]).wxyz, position=T[:3, 3]
    )
    r = max(6.0, 2.5 * data.extent)
    T_grid = np.eye(4)  # the grid's pose in the display frame
    if not np.allclose(T, np.eye(4)):
        T_grid[:2, 3] = data.center[:2]  # under the people
    T_world_grid = np.linalg.inv(T) @ T_grid
    layers.groups["/world/grid"] = scene.add_grid(
        "/world/grid", width=r, height=r, cell_size=0.5, section_size=1.0, plane="xy",
        wxyz=vtf.SO3.from_matrix(T_world_grid[:3, :3]).wxyz, position=T_world_grid[:3, 3],
    )  # fmt: skip
    for path in (
        "/world/cameras",
        "/world/detections2d",
        "/world/skeletons",
        "/world/skeletons/raw",
        "/world/skeletons/filtered",
        "/world/skeletons/gt",
        "/world/skeletons/reference",
        "/world/trails",
        "/world/meshes",
        "/world/meshes/gt",
        "/world/meshes/fit",
    ):
        layers.groups[path] = scene.add_frame(path, show_axes=False)


def _add_camera(layers: SceneLayers, cam: CameraGeometry) -> None:
    """One camera's frustum (with its video), label and 2D detections."""
    scene = layers.server.scene
    base = f"/world/cameras/{cam.name}"
    layers.groups[base] = scene.add_frame(
        base, show_axes=False, wxyz=cam.wxyz, position=cam.position
    )
    layers.nodes[f"{base}/frustum"] = scene.add_camera_frustum(
        f"{base}/frustum",
        fov=cam.fov,
        aspect=cam.aspect,
        scale=cam.frustum_scale,
        thickness=1.5,
        thickness_units="screen",
        color=FRUSTUM_COLOR,
        jpeg_quality=FRUSTUM_JPEG_QUALITY,
        cast_shadow=False,
        receive_shadow=False,
    )
    layers.nodes[f"{base}/label"] = scene.add_label(
        f"{base}/label", cam.name, anchor="bottom-center"
    )
    d2 = f"/world/detections2d/{cam.name}"
    layers.groups[d2] = scene.add_frame(d2, show_axes=False, wxyz=cam.wxyz, position=cam.position)
    layers.nodes[f"{d2}/joints"] = scene.add_point_cloud(
        f"{d2}/joints",
        np.zeros((1, 3), np.float32),
        np.zeros((1, 3), np.uint8),
        point_size=0.008,
        point_shape="circle",
        # camera-frame metres on a plane 0.6 m ahead: float16 steps stay under a pixel
        precision="float16",
        visible=False,
    )
    layers._lines(f"{d2}/bones", UNASSIGNED, 1.5)


def _add_track(layers: SceneLayers, k: int) -> None:
    """Track ``k``'s filtered bones (its joints: :data:`FILTERED_JOINTS`; its trails:
    :data:`TRAILS_RAW`, :data:`TRAILS_FILTERED`)."""
    layers._lines(f"/world/skeletons/filtered/{k}/bones", track_color(k), 0.022, "world")


def _add_filtered_joints(layers: SceneLayers) -> None:
    """One clickable batched mesh of small spheres: K x J instances, coloured per track."""
    K, J = layers.data.num_tracks, layers.data.joint_set.num_joints
    n = max(K * J, 1)
    sv, sf = icosphere(0.025)
    colors = np.repeat(track_color(np.arange(K)), J, axis=0) if K * J else UNTRACKED[None]
    joints = layers.server.scene.add_batched_meshes_simple(
        FILTERED_JOINTS, sv, sf, batched_wxyzs=np.tile([1.0, 0, 0, 0], (n, 1)),
        batched_positions=np.zeros((n, 3)), batched_scales=np.zeros(n),
        batched_colors=np.asarray(colors, np.uint8), lod="off", cast_shadow=False,
        visible=False,
    )  # fmt: skip
    layers.nodes[FILTERED_JOINTS] = joints
    joints.on_click(layers._click_filtered_joint)


def _add_ground_truth(layers: SceneLayers) -> None:
    """One node of every ground-truth person's bones (their meshes come when shown)."""
    data = layers.data
    if data.gt_points is not None:
        layers.gt_ids = [int(p) for p in np.unique(data.scene.gt.person_id)]
    layers._lines(GT_BONES, GT_SKELETON, 0.012, "world")


def _add_references(layers: SceneLayers) -> None:
    """Bones and joints of each reference track (another tool's result)."""
    scene = layers.server.scene
    for name in layers.data.scene.references:
        path = f"/world/skeletons/reference/{name}"
        layers.groups[path] = scene.add_frame(path, show_axes=False)
        layers._lines(f"{path}/bones", REFERENCE_SKELETON, 0.014, "world")
        layers.nodes[f"{path}/joints"] = scene.add_point_cloud(
            f"{path}/joints", np.zeros((1, 3), np.float32), REFERENCE_SKELETON,
            point_size=0.03, point_shape="circle", precision="float32", visible=False,
        )  # fmt: skip
