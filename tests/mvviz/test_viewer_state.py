"""The viewer's pure side: frame_geometry and overlays for a tiny synthesized scene, frame
decoding, the "latest wins" render slot, and a server run without a browser."""

from __future__ import annotations

import dataclasses
import threading
import time

import cv2
import numpy as np
import pytest
import torch

from mvviz.app import LatestWins, ViewerApp
from mvviz.scene.geometry import (
    FRUSTUM_WIDTHS,
    MANY_CAMERAS_FRUSTUM_WIDTH,
    MM,
    OFFSET_FILTERED_M,
    OUTLIER,
    UNASSIGNED,
    LayerToggles,
    camera_geometry,
    frame_geometry,
    track_color,
)
from mvviz.scene.images import FrameStore, blank_frame, draw_overlay, image_overlay
from mvviz.state import PANEL_WIDTHS, ViewerState
from pipeline.config import PipelineConfig
from pipeline.data.scene import Detections
from pipeline.importers.calibration import read_voxelpose_calibration
from pipeline.run.pipeline import run_pipeline
from tests.conftest import RIGS
from tests.mvviz.conftest import NUM_FRAMES, free_port, wait_until


def all_on(state: ViewerState) -> ViewerState:
    state.layers = dataclasses.replace(
        state.layers, meshes=True, rays_selected_only=False, trail_window=5
    )
    return state


# --------------------------------------------------------------------------- counts


def test_detection_points_match_the_results(viewer_state):
    st, res = all_on(viewer_state), viewer_state.results
    det = st.scene.detections
    for f in range(NUM_FRAMES):
        g = frame_geometry(st, f)
        for v, cam in enumerate(st.scene.rig):
            rows = np.flatnonzero((det.frame == f) & (det.view == v))
            kp = res.det_joints2d[rows]
            d = g.detections2d[cam.name]
            assert len(d.points) == int((kp[..., 2] > 0).sum())
            assert d.points.shape == d.colors.shape
            assert d.segments.shape[1:] == (2, 3)


def test_rays_match_used_views(viewer_state):
    st, res = all_on(viewer_state), viewer_state.results
    total = 0
    for f in range(NUM_FRAMES):
        r = frame_geometry(st, f).rays
        qs = np.flatnonzero(res.person_frame == f)
        # every view that a triangulated joint used is one non-outlier ray
        assert int((~r.outlier).sum()) == int(res.person_used[qs].sum())
        assert set(np.unique(r.person)) <= set(qs.tolist())
        assert r.segments.shape == (len(r.outlier), 2, 3)
        # a ray starts at its camera's centre (metres)
        centers = st.scene.rig.centers * MM
        np.testing.assert_allclose(r.segments[:, 0], centers[r.view], atol=1e-9)
        # ... and misses its triangulated joint by about its reprojection error
        X = res.person_joints[r.person, r.joint] * MM
        a, b = r.segments[:, 0], r.segments[:, 1]
        d = (b - a) / np.linalg.norm(b - a, axis=1, keepdims=True)
        miss = np.linalg.norm(np.cross(X - a, d), axis=1)
        fx = np.array([c.K[0, 0] for c in st.scene.rig])[r.view]
        px = res.person_reproj[r.person, r.joint, r.view]
        bound = 1.5 * px * np.linalg.norm(X - a, axis=1) / fx + 0.005
        assert (miss[~r.outlier] < bound[~r.outlier]).all()
        total += len(r.outlier)
    assert total > 0


def test_skeleton_counts(viewer_state):
    st, res = all_on(viewer_state), viewer_state.results
    gt = st.scene.gt
    for f in range(NUM_FRAMES):
        g = frame_geometry(st, f)
        present = np.isfinite(res.track_raw[:, f]).any((1, 2))
        assert sorted(g.raw) == np.flatnonzero(present).tolist()
        assert (
            sorted(g.filtered)
            == np.flatnonzero(np.isfinite(res.track_filtered[:, f]).any((1, 2))).tolist()
        )
        assert sorted(g.gt) == sorted(gt.person_id[gt.frame == f].tolist())
        assert sorted(g.meshes) == sorted(gt.person_id[gt.frame == f].tolist())
        bones = np.asarray(st.data.joint_set.bones)
        for k, s in g.filtered.items():
            ok = np.isfinite(res.track_filtered[k, f]).all(-1)
            assert len(s.segments) == int((ok[bones[:, 0]] & ok[bones[:, 1]]).sum())
            np.testing.assert_allclose(s.joints, res.track_filtered[k, f] * MM)
            assert (s.color == track_color(k)).all()
        for t in g.trails.values():
            assert len(t.raw) <= 2 * st.layers.trail_window


@pytest.mark.slow
def test_outlier_views_are_flagged(viewer_scene):
    """Push one view's wrist 80 px off: triangulation rejects that view, and its ray is
    drawn as an outlier, in the warning colour."""
    scene, _, model = viewer_scene
    det = scene.detections
    j = scene.joint_set.index["left_wrist"]
    rows = np.flatnonzero((det.frame == 5) & (det.view == 1) & (det.keypoints[:, j, 2] > 0.5))
    assert len(rows)
    kp = det.keypoints.copy()
    kp[rows[0], j, 0] += 80.0
    bad = dataclasses.replace(scene, detections=dataclasses.replace(det, keypoints=kp))
    res = run_pipeline(bad, PipelineConfig(), model, progress=False)
    state = all_on(ViewerState.create(bad, res, model))
    r = frame_geometry(state, 5).rays
    q = res.det_person[rows[0]]
    assert q >= 0 and not res.person_used[q, j, 1]
    hit = (r.person == q) & (r.joint == j) & (r.view == 1)
    assert hit.sum() == 1 and r.outlier[hit].all()
    assert (r.colors[hit] == OUTLIER).all()
    assert (r.colors[~r.outlier] != OUTLIER).any(axis=1).all()


@pytest.mark.slow
def test_camera_without_detections(blind_camera_scene):
    scene, res, model = blind_camera_scene
    state = all_on(ViewerState.create(scene, res, model))
    name = scene.rig[0].name
    for f in range(NUM_FRAMES):
        g = frame_geometry(state, f)
        assert len(g.detections2d[name].points) == 0
        assert (g.rays.view != 0).all()
        ov = image_overlay(state.data, 0, f, state.layers)
        assert len(ov.detections) == 0
        img = draw_overlay(blank_frame(320, 256), ov)
        assert img.shape == (256, 320, 3)


def test_toggles_remove_geometry(viewer_state):
    st = all_on(viewer_state)
    full = frame_geometry(st, 10)
    assert full.detections2d and full.raw and full.filtered and full.gt and full.meshes
    assert len(full.rays.segments) and full.trails
    st.layers = LayerToggles(
        **{
            f.name: (False if isinstance(getattr(st.layers, f.name), bool) else 0)
            for f in dataclasses.fields(LayerToggles)
        }
    )
    g = frame_geometry(st, 10)
    assert not (g.detections2d or g.raw or g.filtered or g.gt or g.trails or g.meshes)
    assert g.rays is None


def test_rays_of_the_selected_track_only(viewer_state):
    st = all_on(viewer_state)
    st.layers.rays_selected_only = True
    st.selection = dataclasses.replace(st.selection, track=1)
    r = frame_geometry(st, 10).rays
    assert len(r.track) and (r.track == 1).all()


def test_mesh_bones_reproduce_the_body_model(viewer_scene, viewer_state):
    """Skinning the bind-pose vertices with the per-frame bone transforms, as the browser
    does, gives the body model's vertices; bone positions are the GT joints."""
    scene, _, model = viewer_scene
    b = viewer_state.data.bodies
    gt = scene.gt
    m = np.flatnonzero(gt.frame == 7)[0]
    i = int(np.searchsorted(b.person_ids, gt.person_id[m]))
    np.testing.assert_allclose(b.bone_position[i, 7] / MM, gt.joints3d[m], atol=0.05)
    import viser.transforms as vtf

    R = vtf.SO3(b.bone_wxyz[i, 7]).as_matrix()  # (24, 3, 3)
    rel = np.einsum("jab,vjb->vja", R, b.vertices[i][:, None] - b.rest_joints[i][None])
    skinned = np.einsum("vj,vja->va", b.weights, rel + b.bone_position[i, 7][None])
    with torch.no_grad():
        out = model(gt.smpl_pose[m : m + 1], gt.smpl_betas[m : m + 1], gt.transl[m : m + 1] * MM)
    np.testing.assert_allclose(skinned, out.vertices[0].numpy(), atol=2e-4)


def test_pixels_land_on_the_frustum_image_plane(viewer_scene):
    cam = viewer_scene[0].rig[0]
    g = camera_geometry(cam, plane_depth=0.5)
    W, H = cam.width, cam.height
    c = g.pixels_to_plane(np.array([(W - 1) / 2, (H - 1) / 2]), lift=1.0)
    np.testing.assert_allclose(c, [0, 0, 0.5], atol=1e-12)
    corner = g.pixels_to_plane(np.array([-0.5, -0.5]), lift=1.0)
    np.testing.assert_allclose(corner[:2], -g.half_size)
    # viser's client puts the image plane at scale / cbrt(tan(fov/2)^2 * aspect / 3)
    t = np.tan(g.fov / 2)
    assert g.frustum_scale / np.cbrt(t * t * g.aspect / 3) == pytest.approx(0.5)


@pytest.mark.parametrize("rig", ["shelf_voxelpose.json", "campus_voxelpose.json"])
def test_float16_image_plane_points_stay_within_a_pixel(rig):
    """2D joints go to the browser as float16 camera-frame metres on the image plane:
    the rounding must stay under a pixel for the real rigs (and a 1920 px, 90 deg one)."""
    cams = list(read_voxelpose_calibration(RIGS / rig))
    wide = dataclasses.replace(cams[0], K=np.array([[960.0, 0, 960], [0, 960, 540], [0, 0, 1]]))
    wide = dataclasses.replace(wide, width=1920, height=1080)
    for cam in cams + [wide]:
        g = camera_geometry(cam)
        u, v = np.meshgrid(np.linspace(0, cam.width - 1, 97), np.linspace(0, cam.height - 1, 61))
        px = np.stack([u, v], -1).reshape(-1, 2)
        plane = g.pixels_to_plane(px).astype(np.float16).astype(float)
        back = (plane[:, :2] / g.half_size + 1.0) / 2.0 * g.image_size - 0.5
        assert np.abs(back - px).max() < 1.0, cam.name


# --------------------------------------------------------------------------- 2D


def test_overlay_draws_detections_in_their_colours(viewer_state, frame_store):
    st = viewer_state
    f, v = 4, 1
    ov = image_overlay(st.data, v, f, st.layers)
    assert len(ov.detections) > 0 and ov.label.startswith(st.scene.rig[v].name)
    base = frame_store.frame(st.scene.rig[v].name, f)
    assert base is not None
    img = draw_overlay(base, ov)
    scale = base.shape[1] / ov.image_size[0]
    n_checked = 0
    for det, col in zip(ov.detections, ov.detection_colors, strict=True):
        for x, y, c in det:
            if c > 0 and 5 < x * scale < base.shape[1] - 5 and 5 < y * scale < base.shape[0] - 5:
                px = img[int(round(y * scale)), int(round(x * scale))].astype(int)
                assert np.abs(px - col.astype(int)).max() < 60
                n_checked += 1
    assert n_checked > 5
    rows = st.data.rows_per_frame[f]
    rows = rows[st.scene.detections.view[rows] == v]
    person = st.results.det_person[rows]
    want = np.where((person < 0)[:, None], UNASSIGNED, track_color(st.data.det_track[rows]))
    np.testing.assert_array_equal(ov.detection_colors, want)


def test_frame_store_decodes_and_caches(viewer_scene, frame_store):
    scene = viewer_scene[0]
    name = scene.rig.names[0]
    img = frame_store.frame(name, 3)
    cam = scene.rig[0]
    w = min(640, cam.width)  # downscaled to 640 px, never upscaled
    assert img.shape == (round(cam.height * w / cam.width), w, 3) and img.dtype == np.uint8
    thumb = frame_store.thumbnail(name, 3, 2)
    assert abs(thumb.shape[1] - w / 2) <= 1
    assert frame_store.frame(name, NUM_FRAMES) is None
    assert (scene.root / ".mvviz" / "frames" / f"{name}_w640.npz").is_file()
    again = FrameStore(scene, cache_dir=scene.root / ".mvviz" / "frames").start()
    assert again.wait(10)
    np.testing.assert_array_equal(again.frame(name, 3), img)


def test_frustum_images_are_predecoded(viewer_scene, frame_store):
    """Once the videos are in, every frame's frustum image is ready without decoding,
    and equals what decoding it on demand gives."""
    scene = viewer_scene[0]
    assert frame_store.wait(60)
    w = FRUSTUM_WIDTHS[0]
    checked = 0
    for name in scene.rig.names:
        if not frame_store.available(name):
            continue
        checked += 1
        for f in (0, NUM_FRAMES // 2, NUM_FRAMES - 1):
            img = frame_store.small(name, f, w)
            assert img.shape[1] == w and img.dtype == np.uint8
            assert np.shares_memory(img, frame_store._small[(name, w)])  # no decode
            fresh = frame_store._decode_small_frame(name, f, w, cache=False)
            np.testing.assert_array_equal(img, fresh)
        assert frame_store.small(name, NUM_FRAMES, w) is None
    assert checked >= 2  # the fixture scene has videos
    # another width is decoded on demand
    other = frame_store.small(scene.rig.names[0], 1, 320)
    assert other.shape[1] == 320 and (scene.rig.names[0], 320) not in frame_store._small


# --------------------------------------------------------------------------- threads / server


def test_latest_wins_collapses_requests():
    seen, value, gate = [], {"v": 0}, threading.Event()

    def render():
        gate.wait(10)  # a render in progress while all the requests arrive
        seen.append(value["v"])

    worker = LatestWins(render)
    for i in range(1, 101):
        value["v"] = i
        worker.request()
    gate.set()
    assert worker.wait_idle(10)
    worker.stop()
    assert seen[-1] == 100
    # the render running, then one for every request made meanwhile: not one per request
    assert len(seen) <= 2, seen


def test_server_without_browser(viewer_scene, frame_store):
    scene, results, model = viewer_scene
    state = ViewerState.create(scene, results, model)
    app = ViewerApp(state, port=free_port(), frames=frame_store)
    try:
        seen = []
        app.subscribe(lambda st, why: seen.append((st.frame, why)))
        for f in range(NUM_FRAMES):
            app.set_frame(f)
            assert app.wait_idle(10)
        assert seen[-1][0] == NUM_FRAMES - 1
        stats = app.frame_time_stats()
        # a liveness bound on a shared machine: the speed target is bench_viewer's
        assert stats["count"] >= NUM_FRAMES and stats["median_ms"] < 1000
        app.jump_to(frame=3, track=1, joint="left_wrist", view=2)
        assert app.wait_idle(10)
        assert state.frame == 3 and state.camera == 2
        assert state.selection.track == 1
        assert state.data.joint_set.names[state.selection.joint] == "left_wrist"
        app.layers_panel.gui.toggles["rays"].value = False
        assert app.wait_idle(10) and not state.layers.rays
        # playback advances frames on its own, and pausing stops it
        app.timeline.gui.play.value = True  # a click
        assert state.playing
        wait_until(lambda: state.frame != 3, what="playback to advance")
        app.timeline.gui.play.value = True
        assert not state.playing and state.frame != 3
        assert app.wait_idle(10) and not app.render_errors
    finally:
        app.stop()


@pytest.mark.slow
def test_stop_stops_every_panel(viewer_scene):
    """The app owns its panels: stop() ends every thread the app and its panels started
    (render, images, playback, filter B, failure lists, the pipeline re-run worker, the
    diagnoses)."""
    scene, results, model = viewer_scene
    before = set(threading.enumerate())
    app = ViewerApp(ViewerState.create(scene, results, model), port=free_port())
    assert app.wait_idle(30) and app.filter_panel.wait_idle(30)
    assert app.failure_panel.wait_idle(60)
    started = [t for t in set(threading.enumerate()) - before if t.name.startswith("mvviz-")]
    names = {t.name.split("_")[0] for t in started}
    assert {"mvviz-render", "mvviz-filter-ab", "mvviz-failures", "mvviz-rerun"} <= names
    assert "mvviz-diagnose" in names
    assert len(app.panels) == 9
    app.stop()
    deadline = time.monotonic() + 10
    while any(t.is_alive() for t in started) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert [t.name for t in started if t.is_alive()] == []


def test_image_widths_follow_the_options(viewer_scene, frame_store):
    """The camera panel's picture and the frustums' videos are as wide as their dropdowns
    say, and the frustum images are only re-sent when frame or width change."""
    scene, results, model = viewer_scene
    state = ViewerState.create(scene, results, model)
    app = ViewerApp(state, port=free_port(), frames=frame_store)
    try:
        assert frame_store.wait(60) and app.wait_idle(10)
        app.set_frame(2)
        assert app.wait_idle(10)
        frustum = app.layers.nodes[f"/world/cameras/{scene.rig.names[0]}/frustum"]
        assert app.camera_panel.gui.image.image.shape[1] == PANEL_WIDTHS[0] == 400
        assert frustum.image.shape[1] == FRUSTUM_WIDTHS[0] == 128
        app.camera_panel.gui.width.value = "640 px"
        app.layers_panel.gui.frustum_width.value = "320 px"
        assert app.wait_idle(10)
        assert app.camera_panel.gui.image.image.shape[1] == 640
        assert frustum.image.shape[1] == 320
        cam = scene.rig[0]
        assert abs(frustum.image.shape[0] - 320 * cam.height / cam.width) <= 1
        before = frustum.image
        app.redraw()  # same frame and width: the frustum keeps its encoded image
        assert app.wait_idle(10) and frustum.image is before
        assert not app.render_errors
    finally:
        app.stop()


def test_meshes_are_created_when_their_layer_is_first_shown(viewer_scene, frame_store):
    """Skinned bodies (~0.8 MB each to the browser) are not sent while their layers are
    off; turning a layer on creates and poses them in the same render."""
    scene, results, model = viewer_scene
    state = ViewerState.create(scene, results, model)
    assert not state.layers.meshes and not state.layers.fit_meshes  # the defaults
    app = ViewerApp(state, port=free_port(), frames=frame_store)
    try:
        app.set_frame(4)
        assert app.wait_idle(10)
        assert app.layers.meshes == {} and app.layers.fit_meshes == {}
        app.layers_panel.gui.toggles["meshes"].value = True
        assert app.wait_idle(10)
        b = state.data.bodies
        assert sorted(app.layers.meshes) == sorted(int(p) for p in b.ids)
        assert app.layers.fit_meshes == {}
        i = next(i for i in range(len(b.ids)) if b.present[i, 4])
        mesh = app.layers.meshes[int(b.ids[i])]
        assert mesh.visible
        got = np.array([bone.position for bone in mesh.bones])
        np.testing.assert_allclose(got, b.bone_position[i, 4], atol=6e-4)  # 1 mm grid
        assert not app.render_errors
    finally:
        app.stop()


@pytest.mark.slow
def test_server_survives_odd_scenes(viewer_scene, blind_camera_scene):
    """A camera without detections, no ground truth, no videos; then new results."""
    blind, res, model = blind_camera_scene
    no_gt = dataclasses.replace(blind, gt=None, videos={})
    state = all_on(ViewerState.create(no_gt, res, model))
    assert state.data.bodies is None and state.data.gt_points is None
    app = ViewerApp(state, port=free_port(), frames=FrameStore(no_gt).start())
    try:
        assert app.layers_panel.gui.toggles["meshes"].disabled
        for f in range(0, NUM_FRAMES, 3):
            app.set_frame(f)
            assert app.wait_idle(10)
        app.jump_to(view=0, track=0)
        assert app.wait_idle(10)
        # results of another configuration replace the layers
        config = PipelineConfig().with_overrides(["triangulation.outlier_threshold_px=8"])
        other = run_pipeline(blind, config, model, progress=False)
        app.set_results(other)
        app.set_frame(7)
        assert app.wait_idle(10)
        assert state.data.results is other
        assert app.selection_panel.gui.track.options[1:] == tuple(
            str(k) for k in range(other.num_tracks)
        )
        assert not app.render_errors
        with pytest.raises(ValueError, match="not of this scene"):
            app.set_results(viewer_scene[1])
    finally:
        app.stop()


def test_cli_view_starts_and_stops(viewer_scene):
    from mvviz.cli import build_parser
    from mvviz.cli.view import start

    scene = viewer_scene[0]
    args = build_parser().parse_args(["view", str(scene.root), "--port", str(free_port())])
    app = start(args, progress=False)
    try:
        assert app.url.startswith("http://127.0.0.1:")
        done = threading.Event()
        app.subscribe(lambda *_: done.set())
        app.set_frame(5)
        assert done.wait(10)
    finally:
        app.stop()


def test_detections_dataclass_roundtrip_unchanged(viewer_scene):
    """The viewer never mutates the scene it reads."""
    scene = viewer_scene[0]
    before = scene.detections.keypoints.copy()
    st = all_on(ViewerState.create(scene, viewer_scene[1], viewer_scene[2]))
    for f in range(NUM_FRAMES):
        frame_geometry(st, f)
    assert isinstance(scene.detections, Detections)
    np.testing.assert_array_equal(scene.detections.keypoints, before)


def test_fitted_meshes_follow_the_smpl_fit(viewer_scene, viewer_state):
    """The fitted-mesh layer skins the SMPL + VAE fit: bone positions are its joints, and
    the layer draws one body per tracked person of the frame when switched on."""
    _, results, _ = viewer_scene
    fit = results.smpl_vae
    b = viewer_state.data.fit_bodies
    assert fit is not None and b is not None
    k, f = np.argwhere(fit.present)[len(np.argwhere(fit.present)) // 2]
    i = int(np.searchsorted(b.ids, k))
    np.testing.assert_allclose(b.bone_position[i, f] / MM, fit.joints[k, f], atol=0.05)
    st = viewer_state
    st.layers.fit_meshes = False
    assert frame_geometry(st, int(f)).fit_meshes == {}
    st.layers.fit_meshes = True
    geom = frame_geometry(st, int(f))
    assert set(geom.fit_meshes) == set(np.flatnonzero(fit.present[:, f]).tolist())


def test_past_the_camera_limit_2d_detections_go_on_the_panel_camera_only(viewer_scene, monkeypatch):
    scene, results, model = viewer_scene
    st = ViewerState.create(scene, results, model)
    assert not st.layers.detections2d_panel_camera_only  # 3 cameras: on every frustum
    full = frame_geometry(st, 5).detections2d
    assert len(full) == len(scene.rig)
    monkeypatch.setattr("mvviz.state.ALL_FRUSTA_MAX_CAMERAS", 2)
    st = ViewerState.create(scene, results, model)
    assert st.layers.detections2d_panel_camera_only
    for camera in range(len(scene.rig)):
        st.camera = camera
        only = frame_geometry(st, 5).detections2d
        name = scene.rig.names[camera]
        assert list(only) == [name]
        assert len(only[name].points) > 0
        for f in dataclasses.fields(only[name]):
            np.testing.assert_array_equal(getattr(only[name], f.name), getattr(full[name], f.name))


def test_past_the_camera_limit_the_frustum_video_is_narrower(
    viewer_scene, frame_store, monkeypatch
):
    scene, results, model = viewer_scene
    monkeypatch.setattr("mvviz.state.ALL_FRUSTA_MAX_CAMERAS", 2)
    st = ViewerState.create(scene, results, model)
    w = st.layers.frustum_image_width
    assert w == MANY_CAMERAS_FRUSTUM_WIDTH < FRUSTUM_WIDTHS[0]
    cam = scene.rig.names[0]
    small, wide = frame_store.small(cam, 3, w), frame_store.small(cam, 3, FRUSTUM_WIDTHS[0])
    assert small.shape[1] == w and small.shape[0] == round(wide.shape[0] * w / wide.shape[1])
    # the pre-decoded frame resized: the same picture, within a grey level or two on average
    want = cv2.resize(wide, small.shape[1::-1], interpolation=cv2.INTER_AREA)
    assert np.abs(small.astype(int) - want).mean() < 2.0


def test_merged_skeleton_nodes_show_every_track_and_clicks_map_to_track_and_joint(
    viewer_scene, frame_store
):
    """Raw skeletons of all tracks are one line node and one point cloud, filtered joints
    one batched mesh (instance k * J + j): what they hold is each track's geometry of the
    frame, coloured per track, and a click on an instance selects that track and joint."""
    from mvviz.scene.layers import FILTERED_JOINTS, RAW_BONES, RAW_JOINTS, raw_color

    scene, results, model = viewer_scene
    state = ViewerState.create(scene, results, model)
    app = ViewerApp(state, port=free_port(), frames=frame_store)
    try:
        assert app.wait_idle(10)
        app.set_frame(3)
        assert app.wait_idle(10)
        geom = frame_geometry(state)
        K, J = state.data.num_tracks, scene.joint_set.num_joints
        assert K >= 2 and len(geom.raw) >= 2
        bones = app.layers.nodes[RAW_BONES]
        segs = np.concatenate([geom.raw[k].segments for k in sorted(geom.raw)])
        np.testing.assert_allclose(bones.points, segs.astype(np.float32))
        want = np.concatenate(
            [np.tile(raw_color(k), (len(geom.raw[k].segments), 1)) for k in sorted(geom.raw)]
        )
        np.testing.assert_array_equal(bones.colors[:, 0], want)
        np.testing.assert_array_equal(bones.colors[:, 1], want)
        cloud = app.layers.nodes[RAW_JOINTS]
        n = sum(int(np.isfinite(s.joints).all(1).sum()) for s in geom.raw.values())
        assert cloud.points.shape == (n, 3) and cloud.colors.shape == (n, 3)
        mesh = app.layers.nodes[FILTERED_JOINTS]
        pos = mesh.batched_positions.reshape(K, J, 3)
        scales = mesh.batched_scales.reshape(K, J)
        for k in range(K):
            s = geom.filtered.get(k)
            ok = np.isfinite(s.joints).all(1) if s is not None else np.zeros(J, bool)
            np.testing.assert_allclose(
                pos[k][ok], s.joints[ok].astype(np.float32) if ok.any() else pos[k][ok]
            )
            assert (scales[k][ok] > 0).all() and (scales[k][~ok] == 0).all()
        clicked = []
        app.layers.on_joint_click = lambda track, joint: clicked.append((track, joint))

        class Click:
            instance_index = 1 * J + 4

        app.layers._click_filtered_joint(Click())
        assert clicked == [(1, 4)]
    finally:
        app.stop()


def test_trails_and_ground_truth_are_one_node_each_with_every_track(viewer_scene, frame_store):
    """Every track's trails (raw, filtered) and every ground-truth skeleton are one line
    node each: each holds the frame's segments of all tracks / people, in track order,
    the trails coloured per track (raw paler); with "offset filtered" only the filtered
    trail moves; no segments hides the node."""
    from mvviz.scene.layers import GT_BONES, TRAILS_FILTERED, TRAILS_RAW, raw_color

    scene, results, model = viewer_scene
    state = ViewerState.create(scene, results, model)
    app = ViewerApp(state, port=free_port(), frames=frame_store)
    try:
        assert app.wait_idle(10)
        state.selection = dataclasses.replace(state.selection, track=None, joint=3)
        app.set_frame(NUM_FRAMES // 2)
        assert app.wait_idle(10)
        geom = frame_geometry(state)
        assert len(geom.trails) >= 2  # every track's while none is selected
        for path, kind, color in (
            (TRAILS_RAW, "raw", raw_color),
            (TRAILS_FILTERED, "filtered", track_color),
        ):
            node, ks = app.layers.nodes[path], sorted(geom.trails)
            segs = np.concatenate([getattr(geom.trails[k], kind) for k in ks])
            assert node.visible and len(segs) > 0
            np.testing.assert_allclose(node.points, segs.astype(np.float32))
            want = np.concatenate(
                [np.tile(color(k), (len(getattr(geom.trails[k], kind)), 1)) for k in ks]
            )
            np.testing.assert_array_equal(node.colors[:, 0], want)
            np.testing.assert_array_equal(node.colors[:, 1], want)
        gt = app.layers.nodes[GT_BONES]
        assert len(geom.gt) >= 2 and gt.visible
        want = np.concatenate([geom.gt[p].segments for p in app.layers.gt_ids if p in geom.gt])
        np.testing.assert_allclose(gt.points, want.astype(np.float32))
        state.layers = dataclasses.replace(state.layers, offset_filtered=True, gt=False)
        app.set_frame(NUM_FRAMES // 2 + 1)
        assert app.wait_idle(10)
        assert np.allclose(app.layers.nodes[TRAILS_FILTERED].position, OFFSET_FILTERED_M)
        assert np.allclose(app.layers.nodes[TRAILS_RAW].position, 0.0)
        assert not gt.visible  # the layer off: the geometry has no ground truth
    finally:
        app.stop()


def test_a_world_that_is_not_z_up_is_shown_upright(viewer_scene):
    """A calibration in its first camera's frame (y down, as `mvviz calibrate` writes
    without --floor-frame) is drawn upright: the display frame turns the people's "up" to
    +z and puts their floor at z = 0; a z-up world is drawn as it is."""
    from mvviz.scene.geometry import prepare, to_display
    from pipeline.diagnose.floor import transform_scene

    scene, results, model = viewer_scene
    upright = prepare(scene, results, model)
    np.testing.assert_array_equal(upright.T_display_world, np.eye(4))
    T = np.eye(4)
    T[:3, :3] = [[1, 0, 0], [0, 0, -1], [0, 1, 0]]  # world' = T world: up (+z) -> -y'
    T[:3, 3] = [200.0, 1500.0, 3000.0]  # and the origin moved, mm
    tilted_scene = transform_scene(scene, T, model)
    config = dataclasses.replace(PipelineConfig(), fit_smpl=False)
    tilted = run_pipeline(tilted_scene, config, model, progress=False)
    data = prepare(tilted_scene, tilted, model)
    R = data.T_display_world[:3, :3]
    assert np.degrees(np.arccos(np.clip((R @ np.array([0, -1.0, 0]))[2], -1, 1))) < 10
    # 20 frames are too few planted feet for a floor plane: the cameras tell "up", and the
    # grid goes 0.2 m under the lowest of what is seen; heads above feet by a body height
    joints = to_display(data.T_display_world, tilted.track_filtered * 1e-3)
    names = list(data.joint_set.names)
    ankles = joints[..., [names.index("left_ankle"), names.index("right_ankle")], 2]
    nose = joints[..., names.index("nose"), 2]
    heights = np.concatenate([joints[..., 2].ravel(), data.cameras and
                              [c.position[2] for c in data.cameras]])  # fmt: skip
    assert 0.0 < np.nanmedian(ankles) < 0.5
    assert 1.3 < np.nanmedian(nose) - np.nanmedian(ankles) < 1.8
    assert np.nanpercentile(heights, 1) == pytest.approx(0.2, abs=0.05)
    # the view is aimed at the people's middle, a body's half height over the grid
    assert 0.7 < data.center[2] < 1.6 and 0.7 < upright.center[2] < 1.6


def test_frusta_are_sized_to_the_rig(viewer_scene):
    """Image planes ~1/6 of the way from a camera to the action (at most 0.6 m): a rig a
    metre from a person gets small frusta that do not hide them."""
    from mvviz.scene.geometry import prepare
    from pipeline.data.cameras import CameraRig

    scene, results, model = viewer_scene
    room = prepare(scene, results, model)
    assert room.cameras[0].plane_depth == pytest.approx(min(0.6, room.camera_distance / 6))
    # the same rig pulled in to 1/5 of its distances from the action
    centre = room.center * 1e3
    near = []
    for cam in scene.rig:
        c = centre + (cam.center - centre) / 5.0
        near.append(dataclasses.replace(cam, t=-cam.R @ c))
    small = prepare(dataclasses.replace(scene, rig=CameraRig(tuple(near))), results, model)
    assert small.camera_distance < room.camera_distance / 3
    assert small.cameras[0].plane_depth == pytest.approx(max(0.08, small.camera_distance / 6))
    assert small.cameras[0].plane_depth < 0.6 * room.cameras[0].plane_depth
