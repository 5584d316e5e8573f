"""pipeline.stages.retime and ``sync.offsets``: a camera's 2D re-timed before
association. Unit cases on hand-made rows; then the shipped Shelf scene with one camera
delayed on purpose (pipeline.diagnose.perturb), the offset diagnose finds applied, and
the MPJPE compared with the undelayed run."""

from __future__ import annotations

import functools

import numpy as np
import pytest

from pipeline.config import PipelineConfig
from pipeline.core.files import SceneFormatError
from pipeline.diagnose.perturb import delay_camera
from pipeline.diagnose.sync import estimate_offsets
from pipeline.evaluation.evaluate import evaluate
from pipeline.run.frames import frame_rows, row_frames
from pipeline.run.pipeline import run_pipeline
from pipeline.stages.retime import partners, retimed_rows, split_offset
from tests.pipeline.diagnose.shipped import body_model, shipped_scene
from tests.pipeline.helpers import REPO

CLEAN = REPO / "sample_data" / "shelf_synth"
CONFIG = PipelineConfig(fit_smpl=False)


def _walker(frames, x0, speed, J=5):
    """(n, J, 3) a person of J joints moving ``speed`` px per frame along x."""
    kp = np.zeros((len(frames), J, 3))
    kp[..., 0] = x0 + speed * np.asarray(frames)[:, None] + 10 * np.arange(J)
    kp[..., 1] = 200 + 40 * np.arange(J)
    kp[..., 2] = 0.9
    return kp


def test_split_offset_rounds_half_up():
    assert split_offset(1.5) == (2, -0.5)
    assert split_offset(-3) == (-3, 0.0)
    assert split_offset(0.4) == (0, pytest.approx(0.4))
    assert split_offset(-0.6) == (-1, pytest.approx(0.4))


def test_whole_offset_moves_rows_and_keeps_their_2d():
    frame = np.array([0, 1, 2, 3, 0, 1])
    view = np.array([0, 0, 0, 0, 1, 1])
    kp = _walker(frame, 100, 5)
    frames, out = retimed_rows(frame, view, kp, {0: 2})
    assert frames.tolist() == [-2, -1, 0, 1, 0, 1]  # camera 0 lags 2: its frame 2 is time 0
    np.testing.assert_array_equal(out, kp)


def test_fractional_offset_interpolates_the_same_person():
    # Two people in one camera, 300 px apart, walking opposite ways, listed in a
    # different order each frame: the partner is found by distance, not by row order.
    f = np.arange(6)
    a, b = _walker(f, 100, 6), _walker(f, 400, -4)
    frame = np.r_[f, f[::-1]]
    kp = np.concatenate([a, b[::-1]])
    view = np.zeros(12, int)
    frames, out = retimed_rows(frame, view, kp, {0: 0.25})
    assert frames.tolist() == frame.tolist()  # round(0.25) = 0: no whole shift
    # Row of person a at frame 2 now shows time 2.25: x = 100 + 6 * 2.25 (+ 10 j).
    np.testing.assert_allclose(out[2, :, 0], 100 + 6 * 2.25 + 10 * np.arange(5))
    # Person b (rows 6..11 hold frames 5..0): its frame-3 row shows time 3.25.
    np.testing.assert_allclose(out[8, :, 0], 400 - 4 * 3.25 + 10 * np.arange(5))
    np.testing.assert_allclose(out[2, :, 2], 0.9)
    # Frame 5 has no frame 6: it keeps its 2D, confidence scaled by 1 - 0.25.
    np.testing.assert_array_equal(out[5, :, :2], a[5, :, :2])
    np.testing.assert_allclose(out[5, :, 2], 0.9 * 0.75)


def test_a_far_detection_is_not_a_partner():
    frame = np.array([0, 1])
    kp = np.concatenate([_walker([0], 100, 0), _walker([1], 600, 0)])
    assert partners(frame, kp, 1).tolist() == [-1, -1]


def test_sync_offsets_errors_name_the_field():
    with pytest.raises(SceneFormatError, match="sync.offsets.*CAMERA:FRAMES"):
        CONFIG.with_overrides(["sync.offsets=cam02=1.5"])
    with pytest.raises(SceneFormatError, match="sync.offsets.*'cam02'.*number of frames.*'soon'"):
        CONFIG.with_overrides(["sync.offsets=cam02:soon"])
    cfg = CONFIG.with_overrides(["sync.offsets=1:+1.5,4:-3"])
    assert cfg.sync.offsets == (("1", 1.5), ("4", -3.0))
    assert PipelineConfig.from_dict(cfg.to_dict()).sync == cfg.sync  # the file's form
    assert cfg.to_dict()["sync"]["offsets"] == {"1": 1.5, "4": -3.0}
    with pytest.raises(SceneFormatError, match="sync.offsets.*unknown \\['cam9'\\]"):
        CONFIG.with_overrides(["sync.offsets=cam9:1"]).check_cameras(["0", "1"])


def _scene():
    return shipped_scene(CLEAN)


_model = body_model


@functools.cache
def _undelayed_mpjpe():
    scene = _scene()
    return evaluate(scene, run_pipeline(scene, CONFIG, _model(), progress=False)).stages


@pytest.mark.slow
@pytest.mark.parametrize("delay", [3, 1.5])
def test_applying_the_found_offset_restores_the_mpjpe(delay):
    """Measured (shelf_synth, camera 1): undelayed raw 12.73 mm; delayed by 3: 17.78,
    offset found 2.976, applied 12.61; by 1.5: 16.37, found 1.489, applied 12.21."""
    scene = delay_camera(_scene(), "1", delay)
    model = _model()
    delayed = run_pipeline(scene, CONFIG, model, progress=False)
    found = estimate_offsets(scene, delayed)["1"]
    assert abs(found.offset_frames - delay) < 0.15
    fixed_cfg = CONFIG.with_overrides([f"sync.offsets=1:{found.offset_frames:+.3f}"])
    fixed = run_pipeline(scene, fixed_cfg, model, progress=False)
    before, after = evaluate(scene, delayed).stages, evaluate(scene, fixed).stages
    base = _undelayed_mpjpe()
    assert before["raw"]["mpjpe"] > base["raw"]["mpjpe"] + 3  # the delay did harm
    # Whole frames: the same rows as recorded, within 1 mm. Sub-frame: the interpolated
    # 2D is within 1 mm too (measured 0.5 mm better: interpolating averages noise).
    for stage in ("raw", "rts"):
        assert abs(after[stage]["mpjpe"] - base[stage]["mpjpe"]) < 1.0, (stage, after, base)
    # The re-timed rows are the ones the results used: camera 1's row of frame g + n
    # sits at frame g, and the results' 2D is the interpolated one.
    n = split_offset(found.offset_frames)[0]
    used = row_frames(scene, fixed_cfg)
    mine = scene.detections.view == 1
    assert (used[mine] == scene.detections.frame[mine] - n).all()
    rows = frame_rows(scene, fixed_cfg)[100]
    assert (scene.detections.frame[rows[scene.detections.view[rows] == 1]] == 100 + n).all()
    assert fixed.det_person[rows].max() >= 0
    # Diagnosing the fixed run finds camera 1 in sync.
    assert abs(estimate_offsets(scene, fixed)["1"].offset_frames) < 0.15
