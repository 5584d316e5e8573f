"""The "Reference: <name>" layer: a TRC attached with ``mvviz add-reference`` (and
``mvviz convert --reference``) is drawn per frame with the scene's bones, headlessly
checked like test_viewer_state.py, plus one chromium screenshot of it."""

from __future__ import annotations

import dataclasses
import shutil
from pathlib import Path

import numpy as np
import pytest

from mvviz.app import ViewerApp
from mvviz.cli import main
from mvviz.scene.geometry import MM, REFERENCE_SKELETON, frame_geometry
from mvviz.state import ViewerState
from pipeline.data.scene import load_scene
from pipeline.importers.trc import POSE2SIM_MARKERS, world_mm_to_trc, write_trc
from tests.mvviz.conftest import (
    CAMPUS,
    NUM_FRAMES,
    REPO,
    canvas_image,
    free_port,
    keep_screenshot,
    open_viewer,
    wait_rendered,
)

TRC_FRAMES = 15  # shorter than the scene: frames 15.. have no reference
SHIFT_MM = np.array([0.0, -900.0, 0.0])  # beside the person it copies


def _truth(scene) -> np.ndarray:
    """(F, J, 3) world mm: ground-truth person 0's keypoints in the scene's joint set."""
    gt, out = scene.gt, np.full((scene.num_frames, scene.joint_set.num_joints, 3), np.nan)
    rows = np.flatnonzero(gt.person_id == gt.person_id.min())
    out[gt.frame[rows]] = gt.keypoints3d[rows]
    return out


@pytest.fixture(scope="module")
def ref_scene(viewer_scene, tmp_path_factory):
    """(scene, results, model, expected (F, J, 3) mm): a copy of the tiny scene with a
    reference "pose2sim" attached from a TRC by ``mvviz add-reference``."""
    scene, results, model = viewer_scene
    root = tmp_path_factory.mktemp("ref") / "scene"
    shutil.copytree(scene.root, root, ignore=shutil.ignore_patterns(".mvviz"))
    js = scene.joint_set
    expected = _truth(scene) + SHIFT_MM
    expected[TRC_FRAMES:] = np.nan
    expected[3, js.index["left_wrist"]] = np.nan  # an empty cell
    inverse = {ours: p2s for p2s, ours in POSE2SIM_MARKERS[js.name].items()}
    trc = root.parent / "pose2sim.trc"
    write_trc(
        trc,
        [inverse[n] for n in js.names],
        world_mm_to_trc(expected[:TRC_FRAMES]),
        rate=scene.fps,
    )
    assert main(["add-reference", str(root), "pose2sim", str(trc)]) == 0
    assert main(["add-reference", str(root), "pose2sim", str(trc)]) == 2  # exists
    return load_scene(root), results, model, expected


def test_add_reference_cli_stores_world_mm(ref_scene, capsys):
    scene, _, _, expected = ref_scene
    ref = scene.references["pose2sim"]
    assert ref.joints.shape == (NUM_FRAMES, scene.joint_set.num_joints, 3)
    np.testing.assert_allclose(ref.joints, expected, atol=1e-6, equal_nan=True)
    assert "pose2sim.trc (TRC, m, Y up" in ref.source


def test_reference_geometry_per_frame(ref_scene):
    scene, results, model, expected = ref_scene
    state = ViewerState.create(scene, results, model)
    bones = np.asarray(scene.joint_set.bones)
    for f in range(NUM_FRAMES):
        g = frame_geometry(state, f)
        if f >= TRC_FRAMES:
            assert "pose2sim" not in g.references
            continue
        s = g.references["pose2sim"]
        np.testing.assert_allclose(s.joints, expected[f] * MM, atol=1e-9, equal_nan=True)
        ok = np.isfinite(expected[f]).all(-1)
        assert len(s.segments) == int((ok[bones[:, 0]] & ok[bones[:, 1]]).sum())
        assert (s.color == REFERENCE_SKELETON).all()
        # beside the truth it copies: every drawn joint 0.9 m off in -y
        gt = g.gt[int(scene.gt.person_id.min())]
        d = s.joints - gt.joints
        np.testing.assert_allclose(d[ok], np.broadcast_to(SHIFT_MM * MM, d[ok].shape), atol=1e-6)
    state.layers = dataclasses.replace(state.layers, references_off=frozenset({"pose2sim"}))
    assert frame_geometry(state, 0).references == {}


def test_reference_checkbox_and_nodes(ref_scene):
    scene, results, model, _ = ref_scene
    state = ViewerState.create(scene, results, model)
    app = ViewerApp(state, port=free_port())
    try:
        app.set_frame(2)
        assert app.wait_idle(20) and not app.render_errors
        cb = app.layers_panel.gui.toggles["reference:pose2sim"]
        assert cb.label == "Reference: pose2sim" and cb.value
        base = "/world/skeletons/reference/pose2sim"
        bones = app.layers.nodes[f"{base}/bones"]
        assert bones.visible and len(bones.points) == len(frame_geometry(state).references[
            "pose2sim"].segments)  # fmt: skip
        assert app.layers.groups[base].visible
        cb.value = False  # the user unticks it
        assert app.wait_idle(20)
        assert state.layers.references_off == frozenset({"pose2sim"})
        assert not app.layers.groups[base].visible
        cb.value = True
        assert app.wait_idle(20) and app.layers.groups[base].visible
        app.set_frame(TRC_FRAMES + 1)  # past the TRC's end: nothing drawn
        assert app.wait_idle(20) and not bones.visible
    finally:
        app.stop()


def test_convert_with_reference_flag(tmp_path, capsys):
    trc = (
        REPO
        / "sample_data"
        / "pose2sim_balancing"
        / "ref3d"
        / "S00_P00_T01_BalancingTrial_0-100.trc"
    )
    out = tmp_path / "conv"
    argv = ["convert", "--from", "voxelpose", str(CAMPUS), "--joint-set", "body25b"]
    argv += ["--fps", "60", "--reference", f"pose2sim={trc}", "-o", str(out)]
    assert main(argv) == 0
    scene = load_scene(out)
    assert scene.num_frames == 100 and scene.references["pose2sim"].joints.shape == (100, 25, 3)
    assert main(argv[:-2] + ["--reference", "bad", "-o", str(tmp_path / "x")]) == 2
    assert "NAME=FILE.trc" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()


@pytest.mark.slow
def test_screenshot_of_the_reference_layer(ref_scene, browser, tmp_path):
    """One look in a real browser: the grey reference skeleton beside the others."""
    scene, results, model, _ = ref_scene
    state = ViewerState.create(scene, results, model)
    state.layers = dataclasses.replace(state.layers, rays=False, frustum_images=False)
    app = ViewerApp(state, port=free_port())
    try:
        app.set_frame(5)
        page = open_viewer(browser, app.url)
        wait_rendered(app, page)
        path = Path(tmp_path) / "reference_layer.png"
        page.screenshot(path=str(path))
        keep_screenshot(path, "reference_layer.png")
        img = canvas_image(page).astype(int)
        # the reference's grey is on screen: pixels within a few levels of it
        near = np.abs(img - REFERENCE_SKELETON.astype(int)).max(-1) < 12
        assert near.sum() > 300, f"only {near.sum()} reference-grey pixels"
        page.close()
    finally:
        app.stop()
