"""pipeline.diagnose.floor: the floor plane and "up" from the feet, and the rigid re-expression
of a scene that is not z-up with its floor at 0 (cameras, ground truth incl. SMPL, refs)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from pipeline.config import PipelineConfig
from pipeline.diagnose.floor import estimate_floor, level_rotation, transform_scene
from pipeline.run.pipeline import run_pipeline
from tests.pipeline.diagnose.shipped import body_model, shipped_scene
from tests.pipeline.helpers import REPO

NOISY = REPO / "sample_data" / "shelf_synth_noisy"
CONFIG = PipelineConfig(fit_smpl=False)


def _scene():
    return shipped_scene(NOISY)


_model = body_model


def _floor(scene):
    res = run_pipeline(scene, CONFIG, _model(), progress=False)
    return estimate_floor(res.track_smoothed, scene.joint_set.names)


def _rigid(rot: Rotation, shift) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = rot.as_matrix()
    T[:3, 3] = shift
    return T


@pytest.mark.slow
def test_shipped_scene_is_z_up_with_the_floor_at_zero():
    f = _floor(_scene())
    assert f.method == "feet plane" and f.ok
    assert f.angle_to_z_deg < 1.0 and abs(f.height_mm) < 30.0
    # Its fix is (nearly) the identity.
    T = f.fix_transform()
    assert np.allclose(T[:3, :3], np.eye(3)) and abs(T[2, 3]) < 30.0


@pytest.mark.slow
@pytest.mark.parametrize(
    ("rot", "expected_up"),
    [
        (Rotation.from_euler("x", 180, degrees=True), (0, 0, -1)),  # z down
        (Rotation.from_euler("x", -90, degrees=True), (0, 1, 0)),  # y up
    ],
)
def test_z_down_and_y_up_scenes_are_detected_and_fixed(rot, expected_up):
    original = _scene()
    shift = np.array([400.0, -300.0, 1200.0])
    moved = transform_scene(original, _rigid(rot, shift), _model())
    f = _floor(moved)
    assert not f.ok and not f.z_up
    assert np.degrees(np.arccos(f.up @ np.array(expected_up, float))) < 2.0
    fixed = transform_scene(moved, f.fix_transform(), _model())
    again = _floor(fixed)
    assert again.ok and again.angle_to_z_deg < 1.0 and abs(again.height_mm) < 30.0
    # Round trip: the original back, up to a horizontal shift the floor cannot see.
    d = np.array([a.center - b.center for a, b in zip(fixed.rig, original.rig, strict=True)])
    assert np.abs(d - d.mean(0)).max() < 1e-6 and abs(d[:, 2].mean()) < 30.0
    for a, b in zip(fixed.rig, original.rig, strict=True):
        assert np.degrees(Rotation.from_matrix(a.R @ b.R.T).magnitude()) < 1e-6
    gt_d = fixed.gt.joints3d - original.gt.joints3d
    assert np.allclose(gt_d, d.mean(0), atol=1e-6)


def test_transformed_smpl_ground_truth_poses_the_transformed_body():
    scene = _scene()
    T = _rigid(Rotation.from_euler("xyz", [30, -50, 110], degrees=True), [100.0, 2000.0, -50])
    moved = transform_scene(scene, T, _model()).gt
    rows = np.arange(0, len(moved.frame), 97)
    with torch.no_grad():
        joints = (
            1000
            * _model()
            .joints(torch.as_tensor(moved.smpl_pose[rows]), torch.as_tensor(moved.smpl_betas[rows]))
            .double()
            .numpy()
            + moved.transl[rows, None]
        )
    assert np.abs(joints - moved.joints3d[rows]).max() < 0.5  # mm: float32 body model


def test_level_rotation_keeps_world_x_when_it_can():
    assert np.allclose(level_rotation(np.array([0, 0, -1.0])), np.diag([1, -1, -1]))
    R = level_rotation(np.array([0, 1.0, 0]))
    assert np.allclose(R @ [0, 1, 0], [0, 0, 1]) and np.allclose(R @ [1, 0, 0], [1, 0, 0])
    tilt = np.array([0.05, 0.02, 1.0]) / np.linalg.norm([0.05, 0.02, 1.0])
    assert np.allclose(level_rotation(tilt) @ tilt, [0, 0, 1])


def test_people_standing_still_fall_back_to_the_body_axis():
    """One person, every frame frame 60's 2D: the feet never move, so they cannot tilt a
    plane (four people standing apart do: they span the floor)."""
    import dataclasses

    scene = _scene()
    det = scene.detections
    still = det.take((det.frame == 60) & (det.gt_person_id == 0))
    tiled = still.take(np.tile(np.arange(len(still)), 60))
    tiled = dataclasses.replace(tiled, frame=np.repeat(np.arange(60), len(still)))
    static = dataclasses.replace(scene, detections=tiled, num_frames=60, gt=None)
    f = _floor(static)
    assert f is not None and f.method == "body axis"
    assert f.z_up  # the body axis still says "up" to within its tolerance
