"""The composed pipeline on the shipped sample scene and on a Campus-rig scene the test
synthesises: the quality bars of the pipeline issue, caching, degenerate frames."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from pipeline.body.model import load_body_model
from pipeline.config import PipelineConfig
from pipeline.data.scene import Detections, Scene, load_scene
from pipeline.evaluation.evaluate import evaluate
from pipeline.results.store import load_results, save_results
from pipeline.run.frames import FRAMES_STAGE, run_frame, run_frames
from pipeline.run.pipeline import run_or_load, run_pipeline
from pipeline.stages.triangulate import triangulate_people
from pipeline.synth.scene_gen import SynthConfig, write_synth_scene
from tests.conftest import REPO
from tests.pipeline.helpers import campus_rig

SAMPLE = REPO / "sample_data" / "shelf_synth"


@pytest.fixture(scope="module")
def model():
    return load_body_model()


@pytest.fixture(scope="module")
def sample(model):
    scene = load_scene(SAMPLE)
    results = run_pipeline(scene, PipelineConfig(), model, progress=False)
    return scene, results, evaluate(scene, results)


@pytest.fixture(scope="module")
def campus(model, tmp_path_factory):
    out = tmp_path_factory.mktemp("campus") / "scene"
    cfg = SynthConfig(num_people=3, num_frames=80, seed=5, render_video=False)
    write_synth_scene(out, campus_rig(), model, cfg, progress=False)
    scene = load_scene(out)
    results = run_pipeline(scene, PipelineConfig(), model, progress=False)
    return scene, results, evaluate(scene, results)


@pytest.mark.slow
@pytest.mark.parametrize("which", ["sample", "campus"])
def test_association_precision_recall(which, request):
    _, _, ev = request.getfixturevalue(which)
    assert ev.association["precision"] >= 0.99, ev.association
    assert ev.association["recall"] >= 0.99, ev.association


def test_no_id_switches_on_the_sample(sample):
    _, results, ev = sample
    assert ev.association["id_switches"] == 0, ev.id_switch_events
    assert results.num_tracks >= 4


def noise_figures(scene: Scene, *, every: int = 5, seed: int = 0) -> tuple[float, float]:
    """What the synthetic detector's noise model implies for 3D error, in mm.

    Returns (per_view, floor): ``per_view`` is one view's 2D noise back-projected at the
    joint's depth (sqrt(2) sigma_px depth / f, averaged over observations); ``floor`` is
    the MPJPE of triangulating the true keypoints with only the Gaussian part of the
    noise model, in the same views and with the same confidences (Monte-Carlo, every
    ``every``-th frame). sigma_px as in DetectorNoise: 2.5 px for a 400 px tall person,
    scaled by the person's image height, times 1 + 2 (1 - confidence).
    """
    det, gt = scene.detections, scene.gt
    noise = scene.meta["synth"]["noise"]
    rng = np.random.default_rng(seed)
    per_view, floor = [], []
    V, K = len(scene.rig), det.keypoints.shape[1]
    for f in range(0, scene.num_frames, every):
        for p in np.unique(gt.person_id):
            rows = np.flatnonzero((det.frame == f) & (det.gt_person_id == p))
            if len(rows) < 2:
                continue
            truth = gt.keypoints3d[(gt.frame == f) & (gt.person_id == p)][0]
            kp = np.full((1, V, K, 3), np.nan)
            kp[..., 2] = 0.0
            for i in rows:
                cam = scene.rig[det.view[i]]
                uv = cam.project(truth)
                c = det.keypoints[i, :, 2]
                sigma = noise["pixel_sigma"] * max(np.ptp(uv[:, 1]), 50) / 400 * (1 + 2 * (1 - c))
                ok = c > 0
                depth = cam.world_to_camera(truth[ok])[:, 2]
                per_view.append(np.sqrt(2) * sigma[ok] * depth / cam.K[0, 0])
                noisy = uv + rng.normal(0, 1, uv.shape) * sigma[:, None]
                kp[0, det.view[i]] = np.where(ok[:, None], np.column_stack([noisy, c]), kp[0, 0])
            tri = triangulate_people(scene.rig, kp)
            floor.append(np.linalg.norm(tri.points[0] - truth, axis=-1))
    return float(np.mean(np.concatenate(per_view))), float(np.nanmean(np.concatenate(floor)))


@pytest.mark.parametrize("which", ["sample", "campus"])
def test_raw_triangulation_is_as_good_as_the_noise_allows(which, request):
    scene, _, ev = request.getfixturevalue(which)
    per_view, floor = noise_figures(scene)
    raw = ev.stages["raw"]["mpjpe"]
    # Sample scene, measured: per view 15.5 mm, Gaussian floor 12.0 mm, raw 12.6 mm.
    # Swaps, occlusion and ghost detections cost at most 15 % over the floor.
    assert raw < per_view, (raw, per_view)
    assert raw <= 1.15 * floor, (raw, floor)
    assert ev.stages["raw"]["pck"] > 0.99


@pytest.mark.parametrize("which", ["sample", "campus"])
def test_kalman_and_rts(which, request):
    _, _, ev = request.getfixturevalue(which)
    raw, kal, rts = ev.stages["raw"], ev.stages["kalman"], ev.stages["rts"]
    assert kal["accel"] <= 0.6 * raw["accel"], (kal["accel"], raw["accel"])
    assert kal["mpjpe"] <= raw["mpjpe"] + 2.0
    assert rts["accel"] < kal["accel"] and rts["mpjpe"] < kal["mpjpe"]


@pytest.mark.slow
def test_results_round_trip_and_cache(tmp_path, model, campus):
    scene, results, _ = campus
    # a frame's person-frames are consecutive rows (what the lazy layout's reads rely on)
    assert (np.diff(results.person_frame) >= 0).all()
    for name in ("r.npz", "r"):  # one compressed file; the memory-mapped directory
        path = tmp_path / name
        save_results(results, path)
        back = load_results(path)
        np.testing.assert_array_equal(back.person_joints, results.person_joints)
        np.testing.assert_array_equal(back.track_smoothed, results.track_smoothed)
        np.testing.assert_array_equal(back.track_rejected, results.track_rejected)
        assert back.config == results.config
        assert back.smpl is not None and back.smpl_vae is not None
        np.testing.assert_array_equal(back.smpl_vae.pose_rotvecs, results.smpl_vae.pose_rotvecs)
        np.testing.assert_array_equal(back.smpl.betas, results.smpl.betas)
    for name in ("c.npz", "c"):
        out = tmp_path / name
        r1, cached1 = run_or_load(scene, results.config, model, out=out, progress=False)
        r2, cached2 = run_or_load(scene, results.config, model, out=out, progress=False)
        assert not cached1 and cached2
        other = dataclasses.replace(results.config, source="smpl")
        _, cached3 = run_or_load(scene, other, model, out=out, progress=False)
        assert not cached3  # a different config is recomputed


@pytest.mark.slow
def test_smpl_source_runs_and_scores(model, campus):
    scene, _, _ = campus
    res = run_pipeline(scene, PipelineConfig(source="smpl"), model, progress=False)
    ev = evaluate(scene, res)
    assert res.joint_set == "smpl24"
    assert ev.association["precision"] >= 0.97
    assert ev.stages["raw"]["mpjpe"] < 150  # restored 2D is coarser than keypoints


def test_degenerate_frames_give_empty_results(model, campus):
    scene, results, _ = campus
    det = scene.detections
    cfg = PipelineConfig()
    # Nobody: a frame index past the detections.
    fr = run_frame(scene, 10_000, cfg, det.keypoints)
    assert fr.association.num_people == 0 and fr.triangulation.points.shape[0] == 0
    # One view only: everything of frame 5 but view 0 removed.
    rows = np.flatnonzero((det.frame == 5) & (det.view == 0))
    fr = run_frame(scene, 5, cfg, det.keypoints, rows=rows)
    assert fr.association.num_people == 0
    # All NaN joints.
    nan_kp = det.keypoints.copy()
    nan_kp[..., :2] = np.nan
    nan_kp[..., 2] = 0
    fr = run_frame(scene, 5, cfg, nan_kp)
    assert fr.association.num_people == 0
    # A camera switched off: its rows are never members.
    off = dataclasses.replace(cfg, disabled_views=(scene.rig.names[0],))
    fr = run_frame(scene, 5, off, det.keypoints)
    assert (fr.association.members[:, 0] == -1).all()
    # A whole sequence with no detections at all.
    empty = dataclasses.replace(
        scene,
        detections=Detections(
            frame=np.zeros(0, int), view=np.zeros(0, int), keypoints=np.zeros((0, 17, 3))
        ),
    )
    res = run_pipeline(empty, cfg, model, progress=False)
    assert res.num_tracks == 0 and len(res.person_frame) == 0


@pytest.mark.parametrize("which", ["sample", "campus"])
def test_smpl_rows_keep_proportions_and_plausible_joints(which, request):
    _, results, ev = request.getfixturevalue(which)
    assert results.smpl is not None and results.smpl_vae is not None
    p = ev.plausibility
    # One shape per person: bone lengths barely move, unlike triangulated skeletons.
    assert p["smpl"]["bone_length_std_mm"] < 0.5 * p["raw"]["bone_length_std_mm"]
    # The prior removes joint-limit violations of the plain fit (never adds any).
    assert p["smpl_vae"]["limit_violations_per_1000"] <= p["smpl"]["limit_violations_per_1000"]
    # (a few bodies: on the 3-person Campus scene 2 of 240, from 6 in step I)
    assert p["smpl_vae"]["limit_violations_per_1000"] < 10
    # The fits follow the joints: within a few mm of the filtered input's accuracy.
    assert ev.stages["smpl"]["mpjpe"] < ev.stages["kalman"]["mpjpe"] + 3
    assert ev.stages["smpl_vae"]["mpjpe"] < ev.stages["kalman"]["mpjpe"] + 3


def test_run_frames_reports_progress_and_stops_when_cancelled(campus):
    scene, results, _ = campus
    heard: list[tuple[str, int, int]] = []
    frames = run_frames(
        scene, results.config, results.det_joints2d, progress=lambda *a: heard.append(a)
    )
    F = scene.num_frames
    assert frames is not None and [fr.frame for fr in frames] == list(range(F))
    assert heard == [(FRAMES_STAGE, f + 1, F) for f in range(F)]
    calls = []
    stop_at_3 = lambda: len(calls.append(0) or calls) > 3  # noqa: E731  (true at the 4th check)
    assert run_frames(scene, results.config, results.det_joints2d, cancelled=stop_at_3,
                      progress=False) is None  # fmt: skip
    assert len(calls) == 4
