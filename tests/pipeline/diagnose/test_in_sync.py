"""pipeline.diagnose.in_sync: a late camera is reported out of sync, not as a calibration
suspect, on the shipped Shelf scene (default detector noise, the scene of
test_calibration's rotated and moved cameras) with the faults put in by
pipeline.diagnose.perturb and the pipeline re-run on it."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pipeline.config import PipelineConfig
from pipeline.diagnose.calibration import check_calibration
from pipeline.diagnose.in_sync import check_calibration_in_sync, retimed_run
from pipeline.diagnose.perturb import delay_camera, perturb_camera_pose
from pipeline.diagnose.report import diagnose
from pipeline.diagnose.sync import estimate_offsets
from pipeline.run.pipeline import run_pipeline
from tests.pipeline.diagnose.shipped import body_model, run_without_fit, shipped_scene

pytestmark = pytest.mark.slow

CONFIG = PipelineConfig(fit_smpl=False)


def _suspects(found) -> list[str]:
    return [k for k, f in found.items() if f.suspect]


@pytest.mark.parametrize(("camera", "delay"), [("3", 4), ("0", -7), ("4", 10)])
def test_late_camera_is_out_of_sync_not_a_calibration_suspect(camera, delay):
    scene = delay_camera(shipped_scene(), camera, delay)
    results = run_without_fit(scene)
    # The cause: judged as recorded, the late camera looks miscalibrated.
    as_recorded = check_calibration(scene, results, refine=False)
    assert _suspects(as_recorded) == [camera]
    sync = estimate_offsets(scene, results)
    r = check_calibration_in_sync(scene, results, sync)
    found, judged = r.findings, r.run
    assert r.sync is sync and r.sync_without == ()
    assert _suspects(found) == []
    f = found[camera]
    assert f.out_of_sync and f.retimed_by_frames == pytest.approx(delay, abs=0.15)
    assert f.refined is None  # nothing to refine: its pose is right
    # Its residual is explained by time: large as recorded, like the others' re-timed.
    assert f.systematic_as_recorded_px > 4.0
    assert f.systematic_px < 1.5 and f.systematic_px < 2 * f.others_systematic_px
    assert f.systematic_as_recorded_px == pytest.approx(as_recorded[camera].systematic_px)
    assert judged.config.sync.by_camera() == {camera: pytest.approx(delay, abs=0.15)}
    assert not any(g.out_of_sync for k, g in found.items() if k != camera)


def test_late_and_rotated_cameras_told_apart():
    """Camera 4 ten frames late and camera 2 rotated 1 degree: 2 is the suspect, refined
    back to the truth on 2D that is in time; 4 is out of sync."""
    truth = shipped_scene()
    scene = perturb_camera_pose(
        delay_camera(truth, "4", 10), "2", rotation_deg=1.0, axis=(0.3, 1.0, 0.2)
    )
    results = run_without_fit(scene)
    found = check_calibration_in_sync(scene, results, estimate_offsets(scene, results)).findings
    assert _suspects(found) == ["2"]
    assert found["4"].out_of_sync and not found["2"].out_of_sync
    _assert_back_to_truth(found["2"].refined, truth.rig[2])


def test_a_rotated_camera_hiding_a_late_one():
    """Camera 3 four frames late and camera 2 rotated 1 degree: with camera 2 in its
    reference camera 3's offset is not trusted (confidence < 0.5), so as recorded both
    are suspects; with the suspects left out of each other's references camera 3's offset
    is found, and judged in sync only camera 2 is a suspect."""
    truth = shipped_scene()
    scene = perturb_camera_pose(
        delay_camera(truth, "3", 4), "2", rotation_deg=1.0, axis=(0.3, 1.0, 0.2)
    )
    results = run_without_fit(scene)
    first = estimate_offsets(scene, results)
    assert not first["3"].trusted
    assert _suspects(check_calibration(scene, results, refine=False)) == ["2", "3"]
    r = check_calibration_in_sync(scene, results, first)
    assert r.sync_without == ("2", "3") and r.sync["3"].trusted
    assert abs(r.sync["3"].offset_frames - 4) < 0.15
    assert all(abs(e.offset_frames) < 0.15 for k, e in r.sync.items() if k != "3")
    assert _suspects(r.findings) == ["2"] and r.findings["3"].out_of_sync
    _assert_back_to_truth(r.findings["2"].refined, truth.rig[2])


@pytest.mark.parametrize(
    "fault", [dict(rotation_deg=1.0, axis=(0.3, 1.0, 0.2)), dict(translation_mm=(50.0, 0, 0))]
)
def test_a_wrong_camera_alone_is_named_and_nothing_re_timed(fault):
    """The faults of test_calibration judged in sync: the suspect left out of the sync
    references finds no offset (|offset| < 0.15 frame for every camera), nothing is
    re-timed, camera 2 alone is named and refined back."""
    truth = shipped_scene()
    scene = perturb_camera_pose(truth, "2", **fault)
    results = run_without_fit(scene)
    r = check_calibration_in_sync(scene, results, estimate_offsets(scene, results))
    assert r.run is results and r.sync_without == ()
    again = estimate_offsets(scene, results, reference_exclude=frozenset({2}))
    assert all(abs(e.offset_frames) < 0.15 for e in again.values()), again
    assert _suspects(r.findings) == ["2"] and not any(f.out_of_sync for f in r.findings.values())
    _assert_back_to_truth(r.findings["2"].refined, truth.rig[2])


def _assert_back_to_truth(new, true_cam):
    assert np.degrees(Rotation.from_matrix(new.R @ true_cam.R.T).magnitude()) < 0.1
    assert np.linalg.norm(new.center - true_cam.center) < 5.0


def test_in_sync_scene_is_judged_as_recorded():
    scene = shipped_scene()
    results = run_without_fit(scene)
    r = check_calibration_in_sync(scene, results, estimate_offsets(scene, results))
    found = r.findings
    assert r.run is results and r.sync_without == ()  # no confident offset: nothing re-run
    assert _suspects(found) == [] and not any(f.out_of_sync for f in found.values())
    assert all(f.retimed_by_frames == 0 for f in found.values())


def test_retimed_run_adds_to_the_applied_offsets():
    """A run that re-times camera 3 by 1 frame already, re-timed by 3 more, is the run
    with 4: the same rows at the same frames, the same 2D."""
    scene = delay_camera(shipped_scene(), "3", 4)
    applied = CONFIG.with_overrides(["sync.offsets=3:+1"])
    partly = run_pipeline(scene, applied, body_model(), progress=False)
    more = retimed_run(scene, partly, {"3": 3.0})
    whole = run_pipeline(scene, CONFIG.with_overrides(["sync.offsets=3:+4"]), body_model(),
                         progress=False)  # fmt: skip
    assert more.config.sync.by_camera() == {"3": 4.0}
    np.testing.assert_array_equal(more.person_frame, whole.person_frame)
    np.testing.assert_allclose(more.det_joints2d, whole.det_joints2d, equal_nan=True)


def test_diagnose_reports_the_late_camera_as_out_of_sync():
    scene = delay_camera(shipped_scene(), "3", 4)
    d = diagnose(scene, run_without_fit(scene), refine=False)
    out = d.to_json()
    assert out["calibration"]["3"]["out_of_sync"] is True
    assert out["calibration"]["3"]["suspect"] is False
    assert out["calibration_retimed_by_frames"]["3"] == pytest.approx(4, abs=0.15)
    assert out["calibration"]["3"]["systematic_as_recorded_px"] > 4.0
    assert d.calibration_run.config.sync.by_camera()["3"] == pytest.approx(4, abs=0.15)
    text = "\n".join(d.lines())
    assert "OUT OF SYNC" in text and "SUSPECT" not in text
