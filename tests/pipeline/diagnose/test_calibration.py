"""pipeline.diagnose.calibration: a camera whose calibration is wrong (rotated 1 degree,
moved 5 cm, or knocked half-way through) is named, and the bundle adjustment brings it
back, on the shipped Shelf scene (default detector noise) with the error put in by
pipeline.diagnose.perturb; the pipeline re-run on it."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pipeline.config import PipelineConfig
from pipeline.diagnose.calibration import check_calibration, find_step, replace_camera
from pipeline.diagnose.perturb import perturb_camera_pose
from pipeline.evaluation.evaluate import evaluate
from tests.pipeline.diagnose.shipped import run_without_fit, shipped_scene

CONFIG = PipelineConfig(fit_smpl=False)


def _raw_mpjpe(scene, results) -> float:
    return evaluate(scene, results).stages["raw"]["mpjpe"]


@pytest.mark.slow
def test_good_calibration_has_no_suspect():
    scene = shipped_scene()
    found = check_calibration(scene, run_without_fit(scene))
    assert not any(f.suspect for f in found.values()), {k: f.to_dict() for k, f in found.items()}
    assert all(f.systematic_px < 2.0 for f in found.values())
    assert all(f.step is None for f in found.values())


@pytest.mark.slow
@pytest.mark.parametrize(
    "fault", [dict(rotation_deg=1.0, axis=(0.3, 1.0, 0.2)), dict(translation_mm=(50.0, 0, 0))]
)
def test_wrong_camera_is_named_and_refined_back(fault):
    truth = shipped_scene()
    scene = perturb_camera_pose(truth, "2", **fault)
    results = run_without_fit(scene)
    found = check_calibration(scene, results)
    assert [k for k, f in found.items() if f.suspect] == ["2"]
    f = found["2"]
    true_cam, bad_cam, new = truth.rig[2], scene.rig[2], f.refined
    # The error it reports is the one put in ...
    put_in_deg = np.degrees(Rotation.from_matrix(bad_cam.R @ true_cam.R.T).magnitude())
    assert abs(f.rotation_error_deg - put_in_deg) < 0.1
    assert abs(f.translation_error_mm - np.linalg.norm(bad_cam.center - true_cam.center)) < 5
    # ... and the refined camera is back within 0.1 degree and 5 mm of the truth.
    assert np.degrees(Rotation.from_matrix(new.R @ true_cam.R.T).magnitude()) < 0.1
    assert np.linalg.norm(new.center - true_cam.center) < 5.0
    assert f.residual_after_px < 0.5 * f.residual_px
    # The scene's MPJPE with the refined camera is within 1 mm of the true calibration's.
    fixed = dataclasses.replace(scene, rig=replace_camera(scene.rig, 2, new))
    mpjpe_true = _raw_mpjpe(truth, run_without_fit(truth))
    mpjpe_fixed = _raw_mpjpe(fixed, run_without_fit(fixed))
    assert mpjpe_fixed <= mpjpe_true + 1.0, (mpjpe_fixed, mpjpe_true)
    assert _raw_mpjpe(scene, results) > mpjpe_true + 1.0  # the fault did cost something


@pytest.mark.slow
def test_camera_knocked_mid_capture_shows_a_step():
    """Camera 3's 2D from frame 125 on as seen by a camera turned 1.5 degrees (the GT
    keypoints projected through it, with the same noise the detector had), its
    calibration unchanged: its residual steps up at frame 125."""
    scene = shipped_scene()
    det = scene.detections
    knocked = perturb_camera_pose(scene, "3", rotation_deg=1.5, axis=(0, 0, 1)).rig[3]
    cam = scene.rig[3]
    kp = det.keypoints.copy()
    gt = scene.gt
    rows = np.flatnonzero((det.view == 3) & (det.frame >= 125) & (det.gt_person_id >= 0))
    who = zip(gt.frame, gt.person_id, strict=True)
    slot = {(int(f), int(p)): i for i, (f, p) in enumerate(who)}
    for r in rows:
        g = slot[(int(det.frame[r]), int(det.gt_person_id[r]))]
        truth_px = cam.project(gt.keypoints3d[g])
        noise = kp[r, :, :2] - truth_px  # the detector's own error, kept
        kp[r, :, :2] = knocked.project(gt.keypoints3d[g]) + noise
    moved = dataclasses.replace(scene, detections=dataclasses.replace(det, keypoints=kp))
    found = check_calibration(moved, run_without_fit(moved), refine=False)
    step = found["3"].step
    assert step is not None and abs(step.frame - 125) <= 3, step
    assert step.after_px > 2 * step.before_px
    assert all(f.step is None for k, f in found.items() if k != "3")


def test_find_step_on_plain_series():
    rng = np.random.default_rng(0)
    flat = 5 + rng.normal(0, 1, 200)
    assert find_step(flat) is None
    jump = flat.copy()
    jump[120:] += 8
    s = find_step(jump)
    assert s is not None and abs(s.frame - 120) <= 2
    gaps = jump.copy()
    gaps[::3] = np.nan  # frames where the camera saw nobody
    assert abs(find_step(gaps).frame - 120) <= 3
