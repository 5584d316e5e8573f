"""Detection statistics (pipeline.synth.detection_stats) and what they guard: synthesis
without video (occlusion from the proxy body, the fast path) gives the statistics of the
full renders the shipped sample was made with, and the speed-ups of the fast path change
no output."""

from __future__ import annotations

import dataclasses
import functools
import json

import numpy as np
import pytest
import torch

from pipeline.body.model import load_body_model
from pipeline.data.scene import Detections
from pipeline.importers.calibration import read_voxelpose_calibration
from pipeline.synth import scene_gen
from pipeline.synth.detection_stats import detection_statistics
from pipeline.synth.detectors import DetectorNoise
from pipeline.synth.occlusion import point_occlusion
from pipeline.synth.scene_gen import SynthConfig, synthesize
from tests.conftest import REPO

SAMPLE = REPO / "sample_data" / "shelf_synth"

# the fast path against the renders and against the path before it, absolute, on the mean
# of two seeds' 10-frame Shelf scenes: a few times the spread seen between seeds on the
# sample's settings (bench/bench_synth.py)
TOLERANCE = {
    "detections_per_view_frame": 0.15,
    "people_per_view_frame": 0.1,
    "keypoints_detected": 0.015,
    "keypoints_low_confidence": 0.025,
    "confidence_mean": 0.015,
    "confidence_p10": 0.03,
    "confidence_p50": 0.015,
    "confidence_p90": 0.01,
    "error_px_median": 0.3,
    "error_px_p90": 0.8,
    "ghosts_per_view_frame": 0.06,
}
MISSING_BY_VIEW = 0.05  # per view, fraction of in-image keypoints not detected


@pytest.fixture(scope="module")
def shelf():
    """The shipped sample's rig, people, seed and detector noise; 10 frames."""
    meta = json.loads((SAMPLE / "scene.json").read_text())["synth"]
    rig = read_voxelpose_calibration(REPO / "sample_data" / "rigs" / "shelf_voxelpose.json")
    cfg = SynthConfig(
        num_people=meta["num_people"], num_frames=10, seed=meta["seed"],
        render_video=False, noise=DetectorNoise(**meta["noise"]),
    )  # fmt: skip
    return load_body_model(), rig, cfg


def test_statistics_of_exact_detections():
    rig = read_voxelpose_calibration(REPO / "sample_data" / "rigs" / "shelf_voxelpose.json")
    rng = np.random.default_rng(0)
    centre = rig.centers.mean(0) * np.array([1, 1, 0]) + np.array([0, 0, 1000])
    truth = centre + rng.uniform(-300, 300, (2, 3, 17, 3))  # (P, F, T, 3)
    rows = [(p, f, v) for p in range(2) for f in range(3) for v in range(len(rig))]
    kp = np.stack([rig[v].project(truth[p, f]) for p, f, v in rows])
    kp = np.concatenate([kp, np.full(kp.shape[:2] + (1,), 0.9)], -1)
    kp[0, 0] = (np.nan, np.nan, 0.0)  # one keypoint missed in view 0
    p, f, v = (np.array(x) for x in zip(*rows, strict=True))
    det = Detections(frame=f, view=v, keypoints=kp, gt_person_id=p)
    s = detection_statistics(rig, truth, det, DetectorNoise())
    assert s["error_px_median"] == pytest.approx(0.0, abs=1e-9)
    assert s["people_per_view_frame"] == 2.0 and s["ghosts_per_view_frame"] == 0.0
    assert s["confidence_mean"] == pytest.approx(0.9) and s["keypoints_low_confidence"] == 0
    size = np.array([(rig[k].width, rig[k].height) for k in v])[:, None]
    inside = ((kp[..., :2] >= 0) & (kp[..., :2] < size)).all(-1).sum() + 1  # + the missed
    assert s["keypoints_detected"] == pytest.approx(1 - 1 / inside)
    assert s["missing_by_view"][0] > 0 and (s["missing_by_view"][1:] == 0).all()


def _before(rig, model, cfg: SynthConfig, monkeypatch):
    """The proxy path before its speed-ups: torch's own threads, the float work of the
    occlusion on every triangle, the regressor frame by frame."""
    slow = functools.partial(point_occlusion, cell_prefilter=False)
    cfg = dataclasses.replace(cfg, occlusion="proxy", torch_threads=0, batch_frames=1)
    with monkeypatch.context() as m:
        m.setattr(scene_gen, "point_occlusion", slow)
        return synthesize(rig, model, cfg, progress=False)


@pytest.mark.slow
def test_one_thread_and_the_cell_prefilter_change_no_detection(shelf, monkeypatch):
    model, rig, cfg = shelf
    threads = torch.get_num_threads()
    cfg = dataclasses.replace(cfg, occlusion="proxy", num_frames=4, batch_frames=1)
    _, new = synthesize(rig, model, cfg, progress=False)
    assert torch.get_num_threads() == threads  # restored
    _, old = _before(rig, model, cfg, monkeypatch)
    assert len(new) > 4 * len(rig)  # people were seen
    for field in dataclasses.fields(Detections):
        a, b = getattr(new, field.name), getattr(old, field.name)
        assert (a is None) == (b is None), field.name
        if field.name == "keypoints":
            # The same keypoints detected, with the same confidences; their pixels may
            # differ in float32's last bits: torch's products split their sums by thread
            # count on some CPUs (1.2e-4 px at most on an AVX-512 Xeon, 1 vs 2 threads;
            # bit for bit on others).
            np.testing.assert_array_equal(np.isnan(a), np.isnan(b))
            np.testing.assert_array_equal(a[..., 2], b[..., 2], err_msg="confidence")
            np.testing.assert_allclose(a[..., :2], b[..., :2], rtol=0, atol=1e-3)
        elif a is not None:
            np.testing.assert_array_equal(a, b, err_msg=field.name)


@pytest.mark.slow
def test_fast_path_statistics_are_those_before_it_and_of_the_renders(shelf, monkeypatch):
    """The fast path (regressor batched over frames: other random draws) against the
    path before it and against the full renders the shipped sample was made with."""
    model, rig, cfg = shelf
    stats = {"render": [], "before": [], "proxy": []}
    for seed in (0, 1):
        c = dataclasses.replace(cfg, seed=seed)
        runs = {
            "render": synthesize(rig, model, dataclasses.replace(c, occlusion="render"),
                                 progress=False),
            "before": _before(rig, model, c, monkeypatch),
            "proxy": synthesize(rig, model, dataclasses.replace(c, occlusion="proxy"),
                                progress=False),
        }  # fmt: skip
        for mode, (people, det) in runs.items():
            stats[mode].append(detection_statistics(rig, people.keypoints, det, cfg.noise))
    mean = {m: {k: np.mean([s[k] for s in v], axis=0) for k in v[0]} for m, v in stats.items()}
    for other in ("render", "before"):
        for key, tol in TOLERANCE.items():
            assert abs(mean["proxy"][key] - mean[other][key]) <= tol, (other, key, mean, tol)
        gap = np.abs(mean["proxy"]["missing_by_view"] - mean[other]["missing_by_view"])
        assert gap.max() <= MISSING_BY_VIEW, (other, gap)
    assert mean["render"]["keypoints_low_confidence"] > 0.05  # occlusion happens: not vacuous
