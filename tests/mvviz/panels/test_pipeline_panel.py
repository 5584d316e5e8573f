"""The "Pipeline" panel on the tiny synthesized scene: a parameter change re-runs the
current frame at once and the sequence in the background (equal to ``run_pipeline``),
reset, save into the run config, the list of changed fields, the .rrd export, and one
browser check that switching a camera off changes the canvas."""

from __future__ import annotations

import dataclasses
import shutil
import threading
import time

import numpy as np
import pytest

from mvviz.app import ViewerApp
from mvviz.panels import pipeline_panel
from mvviz.panels.pipeline_panel import (
    PipelinePanel,
    config_diff,
    patch_frame,
    preview_data,
)
from mvviz.scene.geometry import frame_geometry, prepare
from mvviz.state import ViewerState
from pipeline.config import PipelineConfig, load_config
from pipeline.data.scene import load_scene
from pipeline.results.store import PipelineResults, default_results_path, load_results
from pipeline.run.frames import run_frame
from pipeline.run.pipeline import run_or_load, run_pipeline
from tests.mvviz.conftest import (
    canvas_image,
    free_port,
    keep_screenshot,
    open_tab,
    open_viewer,
    settle,
    wait_drawn,
)

FRAME = 10

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")


@pytest.fixture
def scene_copy(viewer_scene, tmp_path):
    """The tiny scene copied to a fresh directory (saving writes into it), its results."""
    scene, results, model = viewer_scene
    root = tmp_path / "scene"
    shutil.copytree(scene.root, root, ignore=shutil.ignore_patterns(".mvviz"))
    return load_scene(root), results, model


@pytest.fixture
def app(scene_copy):
    scene, results, model = scene_copy
    state = ViewerState.create(scene, results, model)
    state.layers = dataclasses.replace(state.layers, rays_selected_only=False)
    a = ViewerApp(state, host="127.0.0.1", port=free_port())
    assert a.wait_idle(30)
    a.set_frame(FRAME)
    assert a.wait_idle(30)
    yield a
    a.pipeline_panel.wait_idle(60)
    a.stop()


def people(res: PipelineResults, frame: int) -> np.ndarray:
    return np.flatnonzero(res.person_frame == frame)


def assert_same_results(a: PipelineResults, b: PipelineResults) -> None:
    assert a.config == b.config and a.joint_set == b.joint_set
    assert a.cache_key == b.cache_key
    for field in dataclasses.fields(PipelineResults):
        name = field.name
        x, y = getattr(a, name), getattr(b, name)
        assert (x is None) == (y is None), name
        if isinstance(x, np.ndarray):
            assert x.shape == y.shape, name
            np.testing.assert_array_equal(x, y, err_msg=name)
        elif name in ("smpl", "smpl_vae") and x is not None:  # SMPL fits
            fx, fy = x.arrays(""), y.arrays("")
            assert fx.keys() == fy.keys()
            for k in fx:
                np.testing.assert_array_equal(fx[k], fy[k], err_msg=f"{name}.{k}")


# --------------------------------------------------------------------------- pure parts


def test_config_diff_lists_exactly_the_changed_fields():
    run = PipelineConfig()
    assert config_diff(run, run) == []
    cur = dataclasses.replace(
        run,
        disabled_views=("3",),
        triangulation=dataclasses.replace(run.triangulation, outlier_threshold_px=35.0),
    )
    assert config_diff(run, cur) == [
        "disabled cameras: 3",
        "triangulation.outlier_threshold_px: 20 -> 35",
    ]
    back = dataclasses.replace(run, disabled_views=("1",))
    assert config_diff(back, run) == ["disabled cameras: none (run config: 1)"]


@pytest.mark.slow
def test_patch_frame_equals_a_full_rerun_in_that_frame(viewer_scene):
    scene, results, model = viewer_scene
    cfg = dataclasses.replace(results.config, disabled_views=(scene.rig.names[0],))
    full = run_pipeline(scene, cfg, model, progress=False)
    fr = run_frame(scene, FRAME, cfg, results.det_joints2d)
    patched = patch_frame(results, fr, cfg, results.det_joints2d)
    a, b = people(patched, FRAME), people(full, FRAME)
    for name in ("person_joints", "person_reproj", "person_used", "person_members"):
        np.testing.assert_array_equal(getattr(patched, name)[a], getattr(full, name)[b])
    rows = fr.rows
    np.testing.assert_array_equal(patched.det_person[rows] >= 0, full.det_person[rows] >= 0)
    # every other frame is untouched, and detections still point at their own frame
    other = results.person_frame != FRAME
    np.testing.assert_array_equal(
        patched.person_joints[patched.person_frame != FRAME], results.person_joints[other]
    )
    ok = patched.det_person >= 0
    det_frame = scene.detections.frame[ok]
    np.testing.assert_array_equal(patched.person_frame[patched.det_person[ok]], det_frame)
    # the new people keep the track they had
    assert (patched.person_track[a] >= 0).all()
    np.testing.assert_array_equal(
        np.sort(patched.person_track[a]), np.sort(results.person_track[people(results, FRAME)])
    )


def test_preview_data_equals_prepare(viewer_state):
    data = viewer_state.data
    cfg = dataclasses.replace(data.results.config, disabled_views=(data.scene.rig.names[1],))
    fr = run_frame(data.scene, FRAME, cfg, data.results.det_joints2d)
    patched = patch_frame(data.results, fr, cfg, data.results.det_joints2d)
    a, b = preview_data(data, patched), prepare(data.scene, patched, None, bodies=data.bodies)
    np.testing.assert_array_equal(a.det_track, b.det_track)
    np.testing.assert_array_equal(a.track_person, b.track_person)
    for x, y in zip(a.people_per_frame, b.people_per_frame, strict=True):
        np.testing.assert_array_equal(x, y)
    assert a.results is patched and a.min_confidence == b.min_confidence
    np.testing.assert_array_equal(a.det_rays, b.det_rays)
    assert a.det_plane is data.det_plane  # same 2D joints: nothing recomputed
    # another 2D source (here: every joint moved by a few pixels) moves rays and points
    moved = data.results.det_joints2d.copy()
    moved[..., :2] += 3.0
    fr = run_frame(data.scene, FRAME, cfg, moved)
    patched = patch_frame(data.results, fr, cfg, moved)
    a, b = preview_data(data, patched), prepare(data.scene, patched, None, bodies=data.bodies)
    np.testing.assert_array_equal(a.det_rays, b.det_rays)
    np.testing.assert_array_equal(a.det_plane, b.det_plane)
    assert not np.array_equal(a.det_plane, data.det_plane, equal_nan=True)


# --------------------------------------------------------------------------- the panel


@pytest.mark.slow
def test_disabling_a_camera_reruns_the_current_frame(app):
    panel: PipelinePanel = app.pipeline_panel
    before = app.state.results
    cam, v = app.state.scene.rig.names[0], 0
    assert (before.person_members[people(before, FRAME), v] >= 0).any()
    panel.gui.cameras[cam].value = False  # as a click does; returns after the frame re-ran
    res = app.state.results
    q = people(res, FRAME)
    assert res.config.disabled_views == (cam,) and len(q)
    assert (res.person_members[q, v] == -1).all()
    assert not res.person_used[q, :, v].any()
    geom = frame_geometry(app.state)
    assert len(geom.rays.view) and v not in geom.rays.view
    r0, r1 = before.track_raw[:, FRAME], res.track_raw[:, FRAME]
    both = np.isfinite(r0) & np.isfinite(r1)
    lost = (np.isfinite(r0) & ~np.isfinite(r1)).any()
    assert lost or np.abs(r1 - r0)[both].max() > 0.1, "the joints did not move"
    assert np.isfinite(panel.last_preview_ms)
    assert panel.wait_idle(60)
    assert not panel.pending
    full = app.state.results
    assert full is panel.base and full.cache_key
    for f in range(app.state.data.num_frames):
        assert (full.person_members[people(full, f), v] == -1).all()


@pytest.mark.slow
def test_frames_reached_while_pending_are_rerun(app, monkeypatch):
    gate = threading.Event()
    real = pipeline_panel.run_stages

    def held(*args, **kwargs):  # the sequence re-run waits until the test lets it go
        gate.wait(60)
        return real(*args, **kwargs)

    monkeypatch.setattr(pipeline_panel, "run_stages", held)
    panel, v, later, never = app.pipeline_panel, 0, FRAME + 3, FRAME + 6
    run = app.state.results
    assert (run.person_members[people(run, never), v] >= 0).any()
    try:
        panel.gui.cameras[app.state.scene.rig.names[v]].value = False
        assert panel.pending
        app.set_frame(later)  # the timeline moves while the sequence is pending
        deadline = time.monotonic() + 20
        res = app.state.results
        while (res.person_members[people(res, later), v] >= 0).any():
            assert time.monotonic() < deadline, "the frame reached was not re-run"
            time.sleep(0.02)
            res = app.state.results
        for f in (FRAME, later):
            assert (res.person_members[people(res, f), v] == -1).all(), f
        assert (res.person_members[people(res, never), v] >= 0).any()  # not visited yet
    finally:
        gate.set()
    assert panel.wait_idle(60) and not panel.pending
    res = app.state.results
    assert (res.person_members[people(res, never), v] == -1).all()


@pytest.mark.slow
def test_outlier_threshold_changes_the_used_flags(app):
    panel = app.pipeline_panel
    res0 = app.state.results
    q0 = people(res0, FRAME)
    panel.gui.outlier_px.value = 2.0
    res1 = app.state.results
    q1 = people(res1, FRAME)
    np.testing.assert_array_equal(res1.person_members[q1], res0.person_members[q0])
    assert res1.person_used[q1].sum() < res0.person_used[q0].sum()
    assert res1.config.triangulation.outlier_threshold_px == 2.0
    assert panel.diff_lines() == ["triangulation.outlier_threshold_px: 20 -> 2"]


@pytest.mark.slow
@pytest.mark.parametrize("source", ["keypoints", "smpl"])
def test_background_rerun_equals_run_pipeline(app, source):
    panel = app.pipeline_panel
    scene, model = app.state.scene, panel.model
    if source == "smpl" and "smpl" not in panel.gui.source.options:
        pytest.skip("the tiny scene has no SMPL predictions")
    # a burst of changes: every one supersedes the previous re-run; the last one wins
    panel.gui.source.value = source
    panel.gui.min_affinity.value = 0.5
    panel.gui.outlier_px.value = 35.0
    panel.gui.cameras[scene.rig.names[1]].value = False
    assert panel.wait_idle(120)
    res = app.state.results
    assert res is panel.base and app.state.data.results is res
    expect = dataclasses.replace(
        PipelineConfig(),
        source=source,
        disabled_views=(scene.rig.names[1],),
        association=dataclasses.replace(PipelineConfig().association, min_affinity=0.5),
        triangulation=dataclasses.replace(
            PipelineConfig().triangulation, outlier_threshold_px=35.0
        ),
    )
    assert panel.config == expect
    assert_same_results(res, run_pipeline(scene, expect, model, progress=False))
    assert "re-run done" in panel.gui.status.content
    assert not panel.gui.progress.visible


def test_reset_restores_the_run_config_and_results(app):
    panel = app.pipeline_panel
    run = app.state.results
    panel.gui.outlier_px.value = 40.0
    panel.gui.tri_min_views.value = 3
    panel.gui.cameras[app.state.scene.rig.names[2]].value = False
    assert panel.wait_idle(60)
    assert app.state.results is not run
    panel.gui.reset.value = True  # the button, pressed from the server side
    assert panel.wait_idle(60)
    assert app.state.results is run and panel.config == run.config
    assert panel.gui.outlier_px.value == 20.0 and panel.gui.tri_min_views.value == 2
    assert all(cb.value for cb in panel.gui.cameras.values())
    assert panel.diff_lines() == [] and "Same as the run config" in panel.gui.changes.content


def test_reset_cancels_a_running_rerun(app):
    panel = app.pipeline_panel
    run = app.state.results
    panel.gui.min_affinity.value = 0.6
    panel.reset()  # before the background re-run can land
    assert panel.wait_idle(60)
    assert app.state.results is run and not panel.pending


@pytest.mark.slow
def test_changes_list_names_exactly_the_changed_fields(app):
    panel = app.pipeline_panel
    cam = app.state.scene.rig.names[2]
    panel.gui.cameras[cam].value = False
    panel.gui.min_affinity.value = 0.45
    panel.gui.outlier_px.value = 35.0
    panel.gui.min_affinity.value = 0.3  # back: no longer a change
    lines = [
        f"disabled cameras: {cam}",
        "triangulation.outlier_threshold_px: 20 -> 35",
    ]
    assert panel.diff_lines() == lines
    md = panel.gui.changes.content
    assert [s[2:] for s in md.splitlines() if s.startswith("- ")] == lines


@pytest.mark.slow
def test_save_into_run_config_is_warm_at_the_next_start(app):
    panel = app.pipeline_panel
    scene = app.state.scene
    panel.gui.outlier_px.value = 35.0
    panel.gui.cameras[scene.rig.names[0]].value = False
    panel.gui.save.value = True  # saves the config now, the results when the re-run lands
    assert panel.wait_idle(60)
    path = scene.root / "mvviz_config.json"
    assert load_config(path) == panel.config
    assert panel.diff_lines() == []  # the saved config is the run config now
    saved = load_results(default_results_path(scene))
    assert_same_results(saved, app.state.results)
    again, cached = run_or_load(scene, load_config(path), panel.model, progress=False)
    assert cached and again.cache_key == saved.cache_key
    assert "results saved" in panel.gui.status.content


@pytest.mark.slow
def test_export_rrd_writes_the_current_run(app):
    panel = app.pipeline_panel
    panel.gui.cameras[app.state.scene.rig.names[0]].value = False
    out = app.writes.export_dir.resolve() / "out" / "run.rrd"
    assert panel.gui.export_path.value == "run.rrd"  # a name inside the export folder
    panel.gui.export_path.value = "out/run.rrd"
    panel.gui.export.value = True
    assert panel.wait_idle(300)
    assert out.is_file() and out.stat().st_size > 10_000
    assert str(out) in panel.gui.export_status.content
    assert "MB" in panel.gui.export_status.content
    assert not panel.gui.export.disabled


def test_export_rrd_refuses_a_name_out_of_the_folder_or_over_a_file(app):
    panel = app.pipeline_panel
    root = app.writes.export_dir.resolve()
    root.mkdir(parents=True)
    (root / "run.rrd").write_text("mine")
    for name, why in (("../run.rrd", "leads out of"), ("run.rrd", "tick Overwrite")):
        panel.gui.export_path.value = name
        panel.gui.export.value = True  # what the click calls, at once
        status = panel.gui.export_status.content
        assert status.startswith("export refused: ") and why in status, status
        assert not panel.gui.export.disabled
    assert not (root.parent / "run.rrd").exists() and (root / "run.rrd").read_text() == "mine"


# --------------------------------------------------------------------------- browser


@pytest.fixture(scope="module")
def browser_app(viewer_scene, frame_store):
    scene, results, model = viewer_scene
    state = ViewerState.create(scene, results, model)
    a = ViewerApp(state, host="127.0.0.1", port=free_port(), frames=frame_store)
    assert a.wait_idle(30)
    yield a
    a.pipeline_panel.reset()
    a.pipeline_panel.wait_idle(60)
    a.stop()


@pytest.mark.slow
def test_switching_a_camera_off_changes_the_canvas(browser, browser_app, tmp_path):
    app, panel = browser_app, browser_app.pipeline_panel
    page = open_viewer(browser, app.url)
    try:
        open_tab(page, "Pipeline")  # its folder is open in its tab
        app.jump_to(frame=12, track=-1)  # no track selected: every person's rays
        a = wait_drawn(app, page)
        cam = app.state.scene.rig.names[0]
        box = page.get_by_label(f"camera {cam}")
        box.scroll_into_view_if_needed()
        box.click()  # in the page, as a user does
        deadline = time.monotonic() + 20
        while app.state.results.config.disabled_views != (cam,) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert app.state.results.config.disabled_views == (cam,)
        assert panel.wait_idle(60)
        wait_drawn(app, page)  # the label stays: the page's answer and a stable picture
        page.get_by_text("Changed from the run config").first.scroll_into_view_if_needed()
        notices = page.locator("button.mantine-Notification-closeButton")
        for i in range(notices.count()):  # the software-WebGL notice, if it came back
            notices.nth(i).click()
        settle(page, 0.5)
        shot = tmp_path / "pipeline_panel.png"
        page.screenshot(path=str(shot))
        keep_screenshot(shot, "pipeline_panel.png")
        b = canvas_image(page)
        d = float(np.abs(a.astype(np.int16) - b.astype(np.int16)).mean())
        assert d > 0.05, f"switching camera {cam} off barely changed the canvas ({d:.3f})"
        assert f"disabled cameras: {cam}" in page.locator("body").inner_text()
    finally:
        page.close()
