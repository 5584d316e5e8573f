"""Tests for pipeline.synth.render: geometry against analytic projections, z-buffer
order, culling, visibility queries, the backdrop, and the rasteriser against brute force.

Units: world millimetres, pixels with centres at integer coordinates.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import trimesh
from hypothesis import example, given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

import pipeline.synth.render as render_module
from pipeline.data.cameras import Camera, make_camera
from pipeline.synth.render import (
    MeshInstance,
    Render,
    occluded_by_other,
    rasterise_triangles,
    render_background,
    render_meshes,
    scale_camera,
    visible_mask,
)

SHELF_CALIB = Path(__file__).resolve().parents[3] / "sample_data/rigs/shelf_voxelpose.json"


def pinhole(
    *, R=None, center=(0.0, 0.0, 0.0), f=800.0, size=(640, 480), dist=(0, 0, 0, 0, 0)
) -> Camera:
    """A camera at ``center`` (world mm) with rotation R (identity: looking along +z)."""
    w, h = size
    R = np.eye(3) if R is None else np.asarray(R, float)
    K = [[f, 0, w / 2], [0, f, h / 2], [0, 0, 1]]
    return make_camera(
        name="test", width=w, height=h, K=K, dist=dist, R=R, t=-R @ np.asarray(center, float)
    )


def level_camera(*, height_mm=1100.0, **kw) -> Camera:
    """Looking along world +y, level, at ``height_mm`` above the floor (z up)."""
    R = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])  # cam x = world x, cam y = -z, z = y
    return pinhole(R=R, center=(0.0, 0.0, height_mm), **kw)


def sphere(center, radius, subdivisions=4, color=(200, 60, 60)) -> MeshInstance:
    m = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return MeshInstance(m.vertices + np.asarray(center, float), m.faces, color)


def shelf_camera(index: int = 0) -> Camera:
    c = json.loads(SHELF_CALIB.read_text())[str(index)]
    R, T = np.array(c["R"]), np.array(c["T"]).ravel()
    k, p = np.array(c["k"]).ravel(), np.array(c["p"]).ravel()
    return make_camera(
        name=str(index),
        width=1032,
        height=776,
        K=[[c["fx"], 0, c["cx"]], [0, c["fy"], c["cy"]], [0, 0, 1]],
        dist=[k[0], k[1], p[0], p[1], k[2]],
        R=R,
        t=-R @ T,
    )


def centroid(mask: np.ndarray) -> np.ndarray:
    """(2,) mean (u, v) of the True pixels."""
    rows, cols = np.nonzero(mask)
    return np.array([cols.mean(), rows.mean()])


# --------------------------------------------------------------------------- geometry


def test_trimesh_primitives_wind_outward():
    """The convention render_meshes culls with: faces CCW around outward normals."""
    assert trimesh.creation.icosphere(subdivisions=2).volume > 0
    assert trimesh.creation.box(extents=(1, 1, 1)).volume > 0


def test_sphere_silhouette_area_centre_and_depth():
    cam = pinhole()
    d, r = 3000.0, 300.0
    render = render_meshes(cam, [sphere((0, 0, d), r)])
    assert render.image.shape == (480, 640, 3) and render.image.dtype == np.uint8
    assert render.depth.dtype == np.float32 and render.mesh_index.dtype == np.int16
    covered = render.mesh_index == 0
    # the silhouette of a sphere on the optical axis is a circle of radius f r / sqrt(d^2 - r^2)
    rho = 800.0 * r / np.sqrt(d**2 - r**2)
    assert covered.sum() == pytest.approx(np.pi * rho**2, rel=0.02)
    np.testing.assert_allclose(centroid(covered), cam.project([0, 0, d]), atol=0.1)
    # the centre pixel (320, 240) sees the nearest point of the sphere
    assert render.depth[240, 320] == pytest.approx(d - r, abs=1.0)
    assert np.isinf(render.depth[~covered]).all() and (render.mesh_index[~covered] == -1).all()
    assert (render.image[~covered] == 0).all()


@pytest.mark.parametrize("where", [(-900.0, 500.0, 4000.0), (700.0, -400.0, 2500.0)])
def test_off_axis_sphere_lands_where_project_says(where):
    R = Rotation.from_rotvec([0.1, -0.2, 0.05]).as_matrix()
    cam = pinhole(R=R, center=(50.0, -20.0, 30.0))
    center = cam.R.T @ (np.asarray(where) - cam.t)  # world point at camera coords `where`
    render = render_meshes(cam, [sphere(center, 60.0)])
    np.testing.assert_allclose(centroid(render.mesh_index == 0), cam.project(center), atol=0.5)
    # depth is camera z: the visible surface point nearest the camera centre
    ray = (center - cam.center) / np.linalg.norm(center - cam.center)
    front = cam.world_to_camera(center - 60.0 * ray)[2]
    u, v = np.rint(cam.project(center)).astype(int)
    assert render.depth[v, u] == pytest.approx(front, abs=2.0)


def test_cube_silhouette_matches_projected_hull():
    cam = pinhole(R=Rotation.from_rotvec([0.05, 0.1, 0.0]).as_matrix())
    box = trimesh.creation.box(extents=(600, 500, 400))
    box.apply_transform(trimesh.transformations.rotation_matrix(0.6, [0.3, 1, 0.2]))
    verts = box.vertices + cam.R.T @ np.array([40.0, -30.0, 2500.0]) + cam.center
    render = render_meshes(cam, [MeshInstance(verts, box.faces, (90, 160, 220))])
    covered = render.mesh_index == 0
    uv = cam.project(verts)
    hull = cv2.convexHull(uv.astype(np.float32))
    assert covered.sum() == pytest.approx(cv2.contourArea(hull), rel=0.02)
    rows, cols = np.nonzero(covered)
    # pixel centres inside the projected hull: extremes within one pixel of the vertices
    np.testing.assert_allclose([cols.min(), rows.min()], uv.min(0), atol=1.0)
    np.testing.assert_allclose([cols.max(), rows.max()], uv.max(0), atol=1.0)
    # a closed convex solid: no holes, every face drawn at most once per pixel
    filled = np.zeros_like(covered, np.uint8)
    cv2.fillConvexPoly(filled, np.rint(hull[:, 0] * 16).astype(np.int32), 1, shift=4)
    eroded = cv2.erode(filled, np.ones((3, 3), np.uint8)).astype(bool)
    assert covered[eroded].all()


def test_distortion_moves_pixels_with_the_model():
    dist = (-0.28, 0.09, 0.001, -0.0015, -0.01)
    cam = pinhole(dist=dist)
    ideal = pinhole()
    center = np.array([-700.0, -500.0, 2200.0])  # near the top-left corner: strong distortion
    assert np.linalg.norm(cam.project(center) - ideal.project(center)) > 10
    render = render_meshes(cam, [sphere(center, 30.0, subdivisions=3)])
    np.testing.assert_allclose(centroid(render.mesh_index == 0), cam.project(center), atol=0.5)


def test_points_past_the_distortion_fold_are_not_drawn():
    # k1 = -0.3: r_d = r (1 - 0.3 r^2) peaks at r^2 = 1 / 0.9; a point 61 degrees off-axis
    # (r = 1.8) wraps back into the middle of the image under the polynomial model
    cam = pinhole(dist=(-0.3, 0, 0, 0, 0))
    center = np.array([1800.0, 0.0, 1000.0])
    assert np.isnan(cam.project(center)).all()  # project() knows about the fold too
    render = render_meshes(cam, [sphere(center, 50.0, subdivisions=2)])
    assert render.num_faces_drawn == 0 and (render.mesh_index == -1).all()


def test_shelf_camera_sphere_on_floor():
    cam = shelf_camera(0)
    fwd = cam.R[2, :2] / np.linalg.norm(cam.R[2, :2])
    side = np.array([-fwd[1], fwd[0]])
    for dist_mm, off in ((4000.0, 0.0), (3000.0, 1200.0), (5000.0, -1500.0)):
        xy = cam.center[:2] + dist_mm * fwd + off * side
        center = np.array([xy[0], xy[1], 100.0])  # a 100 mm ball resting on the floor
        uv = cam.project(center)
        assert 0 < uv[0] < cam.width and 0 < uv[1] < cam.height
        render = render_meshes(cam, [sphere(center, 100.0)])
        np.testing.assert_allclose(centroid(render.mesh_index == 0), uv, atol=1.5)


# --------------------------------------------------------------------------- z-buffer


def test_front_sphere_wins_the_z_buffer():
    cam = pinhole()
    front, back = sphere((0, 0, 2000), 200, color=(255, 0, 0)), sphere((150, 0, 3500), 300)
    both = render_meshes(cam, [front, back])
    alone = [render_meshes(cam, [m]) for m in (front, back)]
    overlap = (alone[0].mesh_index == 0) & (alone[1].mesh_index == 0)
    assert overlap.sum() > 1000
    assert (both.mesh_index[overlap] == 0).all()
    np.testing.assert_array_equal(both.depth, np.minimum(alone[0].depth, alone[1].depth))
    only_back = (alone[1].mesh_index == 0) & ~overlap
    assert (both.mesh_index[only_back] == 1).all()
    np.testing.assert_array_equal(both.image[overlap], alone[0].image[overlap])
    # face_index: the face of that mesh seen at the pixel
    seen = both.face_index[overlap]
    np.testing.assert_array_equal(seen, alone[0].face_index[overlap])


def test_occlusion_queries():
    cam = pinhole()
    front, back = sphere((0, 0, 2000), 200), sphere((400, 0, 3500), 300)
    both = render_meshes(cam, [front, back])
    on_back = lambda nx, nz: np.array([400.0, 0, 3500]) + 300 * np.array([nx, 0, nz])  # noqa: E731
    points = np.array(
        [
            on_back(-0.5, -0.866),  # faces the camera, but behind the front sphere
            on_back(0.6, -0.8),  # faces the camera beside the front sphere: in plain view
            [0, 0, 1800],  # front sphere's nearest point
            on_back(0.5, 0.866),  # back sphere's far side: hidden by its own front
            [400, 0, 3500],  # back sphere's centre (a "joint" 300 mm inside)
            [5000, 0, 3000],  # outside the image
            [0, 0, -1000],  # behind the camera
        ],
        float,
    )
    ids = np.array([1, 1, 0, 1, 1, 1, 1])
    np.testing.assert_array_equal(occluded_by_other(both, cam, points, ids), [1, 0, 0, 0, 0, 0, 0])
    np.testing.assert_array_equal(visible_mask(both, cam, points, ids), [0, 1, 1, 0, 0, 0, 0])
    relaxed = visible_mask(both, cam, points, ids, tolerance_mm=600.0)  # chord: 552 mm
    np.testing.assert_array_equal(relaxed, [0, 1, 1, 1, 1, 0, 0])
    # nothing in front once the front sphere is gone
    alone = render_meshes(cam, [back])
    ids0 = np.zeros(len(points), int)
    assert not occluded_by_other(alone, cam, points, ids0).any()
    np.testing.assert_array_equal(visible_mask(alone, cam, points, ids0), [1, 1, 1, 0, 0, 0, 0])
    with pytest.raises(ValueError, match="mesh_ids"):
        visible_mask(both, cam, points, ids[:3])


# --------------------------------------------------------------------------- culling


def test_back_face_culling_draws_the_near_cap():
    cam = pinhole()
    d, r = 2000.0, 200.0
    ball = sphere((0, 0, d), r)
    culled = render_meshes(cam, [ball])
    # the faces that face a point at distance d cover a cap of (1 - r/d) / 2 of the sphere
    assert culled.num_faces_drawn / len(ball.faces) == pytest.approx((1 - r / d) / 2, abs=0.02)
    two_sided = render_meshes(cam, [ball], cull_back_faces=False)
    assert two_sided.num_faces_drawn == len(ball.faces)
    np.testing.assert_array_equal(two_sided.mesh_index, culled.mesh_index)
    np.testing.assert_allclose(two_sided.depth, culled.depth, rtol=1e-6)
    np.testing.assert_array_equal(two_sided.image, culled.image)


def test_inside_out_winding_shows_the_far_side():
    cam = pinhole()
    d, r = 2000.0, 200.0
    ball = sphere((0, 0, d), r)
    flipped = MeshInstance(ball.vertices, ball.faces[:, ::-1], ball.color)
    normal, inside_out = render_meshes(cam, [ball]), render_meshes(cam, [flipped])
    assert inside_out.num_faces_drawn + normal.num_faces_drawn == len(ball.faces)
    # same silhouette, but we now see the inside of the far hemisphere
    a, b = (normal.mesh_index == 0).sum(), (inside_out.mesh_index == 0).sum()
    assert b == pytest.approx(a, rel=0.01)
    assert normal.depth[240, 320] == pytest.approx(d - r, abs=1.0)
    assert inside_out.depth[240, 320] == pytest.approx(d + r, abs=1.0)


def test_camera_inside_a_closed_mesh_sees_nothing():
    cam = pinhole()
    room = sphere((0, 0, 0), 5000.0, subdivisions=3)
    assert render_meshes(cam, [room]).num_faces_drawn == 0
    assert (render_meshes(cam, [room]).mesh_index == -1).all()
    # turned inside out, it is a room: every pixel sees a wall
    room_in = MeshInstance(room.vertices, room.faces[:, ::-1])
    assert (render_meshes(cam, [room_in]).mesh_index == 0).all()


def test_near_plane_drops_triangles_behind_the_camera():
    cam = pinhole()
    big = sphere((0, 0, 150), 300.0)  # straddles the camera
    render = render_meshes(cam, [big], cull_back_faces=False)
    z = cam.world_to_camera(big.vertices)[:, 2]
    expected = (z[big.faces] > 100.0).all(1).sum()
    assert 0 < render.num_faces_drawn == expected < len(big.faces)
    seen = np.isfinite(render.depth)
    assert seen.any() and render.depth[seen].min() > 100.0


# --------------------------------------------------------------------------- shading, scale


def test_lambert_shading_is_brightest_towards_the_light():
    cam = pinhole()  # R = I: world -y is image up
    ball = sphere((0, 0, 2000), 300, color=(200, 200, 200))
    render = render_meshes(cam, [ball], light_dir_world=(0.0, -1.0, 0.0))  # from above
    grey = render.image[..., 0].astype(float)
    covered = render.mesh_index == 0
    rows = np.nonzero(covered)[0]
    top, bottom = rows.min() + 10, rows.max() - 3
    assert grey[top][covered[top]].mean() > 150  # faces turned up: lit
    assert grey[bottom][covered[bottom]].mean() == pytest.approx(0.35 * 200, abs=3)  # ambient
    assert grey[covered].max() <= 200 and grey[covered].min() >= 0.35 * 200 - 1


def test_scaled_render_matches_scaled_projection():
    cam = pinhole(R=Rotation.from_rotvec([0, 0.1, 0]).as_matrix())
    center = cam.R.T @ np.array([300.0, -100.0, 3000.0]) + cam.center
    half = render_meshes(cam, [sphere(center, 150)], scale=0.5)
    assert half.image.shape == (240, 320, 3)
    small = scale_camera(cam, 0.5)
    np.testing.assert_allclose(small.project(center), (cam.project(center) + 0.5) * 0.5 - 0.5)
    np.testing.assert_allclose(centroid(half.mesh_index == 0), small.project(center), atol=0.5)
    front = center - 150 * (center - cam.center) / np.linalg.norm(center - cam.center)
    assert visible_mask(half, cam, front[None], np.array([0]))[0]
    with pytest.raises(ValueError, match="scaled version"):
        visible_mask(half, pinhole(size=(500, 480)), front[None], np.array([0]))


# --------------------------------------------------------------------------- background


def test_background_floor_below_horizon_wall_above():
    cam = level_camera()
    bg = render_background(cam)
    assert bg.shape == (480, 640, 3) and bg.dtype == np.uint8
    horizon = 240  # a level camera sees the horizon at cy
    wall = bg[: horizon - 5].reshape(-1, 3).astype(int)
    assert (wall[:, 2] > wall[:, 0]).all() and (wall.min(0) > 170).all()  # light, bluish
    floor = bg[horizon + 40 :].reshape(-1, 3).astype(int)
    assert (floor.max(1) - floor.min(1) <= 12).all()  # greys
    tones = np.unique(bg[-60:].reshape(-1, 3), axis=0)
    brightness = tones.sum(1)
    assert brightness.max() - brightness.min() > 40  # two tile tones near the camera
    near_tiles = bg[-30:, ::4].reshape(-1, 3).sum(1)
    assert len(np.unique(near_tiles)) >= 2
    # the floor tiles are 500 mm: the pattern flips where the floor point crosses a tile edge
    v = 470
    ray = cam.pixels_to_rays(np.stack([np.arange(640.0), np.full(640, v)], 1))
    hit = cam.center + ray * (-cam.center[2] / ray[:, 2])[:, None]
    parity = (np.floor(hit[:, 0] / 500) + np.floor(hit[:, 1] / 500)) % 2
    edge = (np.abs(hit[:, :2] / 500 - np.rint(hit[:, :2] / 500)) * 500).min(1)
    tone = bg[v].sum(1).astype(int)
    away = edge > 40  # edges are anti-aliased over the pixel footprint (~10 mm here)
    a, b = tone[away & (parity == 0)], tone[away & (parity == 1)]
    assert np.ptp(a) <= 8 and np.ptp(b) <= 8  # each tone only fades slowly with distance
    assert abs(a.mean() - b.mean()) > 40


def test_meshes_are_composited_over_the_background():
    cam = level_camera()
    bg = render_background(cam)
    render = render_meshes(cam, [sphere((0, 3000, 1100), 300)], background=bg)
    assert (render.image[render.mesh_index < 0] == bg[render.mesh_index < 0]).all()
    assert (render.mesh_index == 0).sum() > 1000
    with pytest.raises(ValueError, match="background"):
        render_meshes(cam, [], background=bg[:10])


def test_shelf_background_has_a_floor():
    cam = shelf_camera(0)
    bg = render_background(cam, scale=0.25)
    assert bg.shape == (194, 258, 3)
    bottom = bg[-20:].reshape(-1, 3).astype(int)
    assert (bottom.max(1) - bottom.min(1) <= 12).all()
    top = bg[:5].reshape(-1, 3).astype(int)
    assert (top[:, 2] > top[:, 0]).all()


# --------------------------------------------------------------------------- rasteriser


def brute_force(xy: np.ndarray, inv_z: np.ndarray, width: int, height: int):
    """Reference z-buffer: every triangle against every pixel centre, in float64.

    Also returns where the answer is ambiguous: a pixel centre within 1e-4 (barycentric)
    of some triangle's edge, where either answer is right.
    """
    v, u = np.mgrid[0:height, 0:width].astype(float)
    best = np.full((height, width), np.inf)
    tri = np.full((height, width), -1)
    ambiguous = np.zeros((height, width), bool)
    for i, ((x0, y0), (x1, y1), (x2, y2)) in enumerate(xy):
        area = (x1 - x0) * (y2 - y0) - (y1 - y0) * (x2 - x0)
        if abs(area) < 1e-9:
            continue
        w0 = ((x1 - u) * (y2 - v) - (y1 - v) * (x2 - u)) / area
        w1 = ((x2 - u) * (y0 - v) - (y2 - v) * (x0 - u)) / area
        w2 = 1 - w0 - w1
        margin = np.minimum(np.minimum(w0, w1), w2)
        ambiguous |= np.abs(margin) < 1e-4
        depth = 1 / (w0 * inv_z[i, 0] + w1 * inv_z[i, 1] + w2 * inv_z[i, 2])
        win = (margin >= 0) & (depth < best)
        best[win], tri[win] = depth[win], i
    return tri, best, ambiguous


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 2**32 - 1))
@example(836)  # slivers whose float32 1/z was 1.3e-5 off (1/z is now float64)
@example(841)
def test_rasteriser_matches_brute_force(seed):
    rng = np.random.default_rng(seed)
    width, height, n = 48, 36, 25
    centers = rng.uniform([-5, -5], [width + 5, height + 5], (n, 1, 2))
    xy = centers + rng.normal(0, rng.choice([1.5, 4.0, 12.0], (n, 1, 1)), (n, 3, 2))
    inv_z = 1.0 / rng.uniform(500, 5000, (n, 3))
    tri, depth = rasterise_triangles(xy, inv_z, width, height)
    ref_tri, ref_depth, ambiguous = brute_force(xy, inv_z, width, height)
    clear = ~ambiguous
    assert clear.mean() > 0.95
    # allow ties in depth (pixels where two triangles are within float32 of each other)
    same = (tri == ref_tri) | np.isclose(depth, ref_depth, rtol=1e-6)
    assert same[clear].all()
    hit = ref_tri >= 0
    # the depth is float32, interpolated in float64: its rounding only (float32 eps 6e-8)
    np.testing.assert_allclose(depth[hit & clear], ref_depth[hit & clear], rtol=1e-6)
    assert np.isinf(depth[tri < 0]).all()


def test_shared_edges_do_not_crack():
    rng = np.random.default_rng(1)
    # a jittered grid of triangles tiling a rectangle; pixel centres sit on many edges
    gx, gy = np.meshgrid(np.linspace(2, 40, 20), np.linspace(1, 30, 16))
    gx[1:-1, 1:-1] += rng.uniform(-0.6, 0.6, (14, 18))
    gy[1:-1, 1:-1] += rng.uniform(-0.6, 0.6, (14, 18))
    gx[:, 1:-1] = np.round(gx[:, 1:-1] * 2) / 2  # many vertices exactly on pixel centres
    p = np.stack([gx, gy], -1)
    a, b, c, d = p[:-1, :-1], p[:-1, 1:], p[1:, 1:], p[1:, :-1]
    xy = np.concatenate([np.stack([a, b, c], 2), np.stack([a, c, d], 2)]).reshape(-1, 3, 2)
    tri, _ = rasterise_triangles(xy, np.full(xy.shape[:2], 1e-3), 44, 33)
    v, u = np.mgrid[0:33, 0:44]
    inside = (u > 2) & (u < 40) & (v > 1) & (v < 30)
    assert (tri[inside] >= 0).all()
    assert (tri[(u < 2) | (u > 40) | (v < 1) | (v > 30)] < 0).all()


def test_huge_and_offscreen_triangles():
    xy = np.array(
        [
            [[-1e6, -1e6], [1e6, -1e6], [0, 1e6]],  # covers the whole image
            [[-50, -50], [-10, -40], [-20, -5]],  # entirely off-screen
            [[5, 5], [5, 5], [5, 5]],  # degenerate
        ]
    )
    inv_z = np.array([[1e-3] * 3, [1e-2] * 3, [1e-2] * 3])
    tri, depth = rasterise_triangles(xy, inv_z, 32, 24)
    assert (tri == 0).all()
    np.testing.assert_allclose(depth, 1000.0, rtol=1e-6)


def test_mesh_instance_checks_its_arrays():
    with pytest.raises(ValueError, match="vertices"):
        MeshInstance(np.zeros((4, 2)), np.zeros((1, 3), int))
    with pytest.raises(ValueError, match="faces"):
        MeshInstance(np.zeros((4, 3)), np.array([[0, 1, 4]]))
    with pytest.raises(ValueError, match="color"):
        MeshInstance(np.zeros((4, 3)), np.array([[0, 1, 2]]), (0, 0, 300))
    empty = render_meshes(pinhole(), [])
    assert isinstance(empty, Render) and (empty.mesh_index == -1).all()


def test_batching_huge_triangles_changes_nothing(monkeypatch):
    cam = pinhole()
    scene = [sphere((0, 0, 900), 300, subdivisions=2), sphere((200, 50, 1500), 400)]
    reference = render_meshes(cam, scene)
    monkeypatch.setattr(render_module, "_MAX_TILES", 7)
    batched = render_meshes(cam, scene)
    np.testing.assert_array_equal(batched.depth, reference.depth)
    np.testing.assert_array_equal(batched.face_index, reference.face_index)
