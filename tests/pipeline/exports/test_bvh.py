"""BVH: read back by pipeline.importers.bvh, its forward kinematics gives the fitted
joints (within 1 mm; measured ~1e-3 mm), for real fits and for large random rotations."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.exports import export_results
from pipeline.exports.bvh import write_bvh_track
from pipeline.importers.bvh import bvh_to_world_mm, read_bvh
from tests.pipeline.exports.conftest import GAPS, synthetic_fit


def _world_joints(path, names):
    motion = read_bvh(path)
    world = bvh_to_world_mm(motion, scale_to_m=1.0)  # metres, Y up -> world mm
    idx = [motion.index[n] for n in names]
    return motion, world[:, idx]


@pytest.mark.slow
def test_bvh_round_trip_of_a_real_fit_within_1mm(fitted_run, tmp_path):
    scene, res = fitted_run
    fit = res.smpl_vae
    files = export_results(res, "bvh", tmp_path / "run.bvh", fps=scene.fps)
    for f in files:
        [k] = f.tracks
        motion, joints = _world_joints(f.path, fit.model.joint_names)
        assert motion.num_joints == 24 and motion.num_frames == res.num_frames
        assert abs(motion.fps - scene.fps) < 1e-6
        err = np.linalg.norm(joints - fit.joints[k], axis=-1)
        assert err.max() < 1.0, err.max()
        assert err.max() < 0.01  # the writer's 6 decimals (1 µm, 1e-6 deg) and float32 fit
        # bone lengths are the fitted betas' (the reader's offsets, metres)
        rest = np.linalg.norm(motion.offsets[motion.index["left_knee"]])
        assert 0.25 < rest < 0.55


def test_bvh_round_trip_of_large_rotations(model, tmp_path):
    fit = synthetic_fit(model, num_frames=8, scale=2.5, seed=4)
    for k in range(2):
        write_bvh_track(tmp_path / f"t{k}.bvh", fit, k, fps=30.0)
        _, joints = _world_joints(tmp_path / f"t{k}.bvh", model.joint_names)
        assert np.linalg.norm(joints - fit.joints[k], axis=-1).max() < 0.01


def test_bvh_holds_the_last_pose_over_gaps_and_says_so(gappy_results, fitted_run, tmp_path):
    scene, _ = fitted_run
    fit = gappy_results.smpl_vae
    [f] = export_results(gappy_results, "bvh", tmp_path / "g.bvh", fps=scene.fps, track=1)
    assert "5 frames without a body (frames 0-1, 5-6, 11)" in f.notes[0]
    assert "held" in f.notes[0]
    _, joints = _world_joints(f.path, fit.model.joint_names)
    held = {0: 2, 1: 2, 5: 4, 6: 4, 11: 10}  # before the start: the first fitted frame
    for frame in range(joints.shape[0]):
        src = held.get(frame, frame)
        assert frame in GAPS or src == frame
        np.testing.assert_allclose(joints[frame], fit.joints[1, src], atol=0.01)


def test_bvh_structure_for_blender(fitted_run, tmp_path):
    scene, res = fitted_run
    [f] = export_results(res, "bvh", tmp_path / "b.bvh", fps=scene.fps, track=0)
    text = f.path.read_text()
    assert text.startswith("HIERARCHY\nROOT pelvis\n")
    assert text.count("End Site") == 5  # head, hands, feet
    assert "CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation" in text
    motion = read_bvh(f.path)
    # Y up: the pelvis is ~1 m above the feet in the file's Y
    y = motion.positions[:, :, 1]
    assert 0.6 < np.median(y[:, motion.index["pelvis"]] - y[:, motion.index["left_foot"]]) < 1.2
