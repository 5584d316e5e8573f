"""pipeline.synth.mocap_scene (``mvviz synth --motion``): people from real motion capture,
truth = the mocap skeleton's joints, detections of its points, and the pipeline on it."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from mvviz.cli import main
from pipeline.body.model import load_body_model
from pipeline.config import PipelineConfig
from pipeline.data.joint_sets import COCO17, SMPL24
from pipeline.data.scene import load_scene
from pipeline.evaluation.evaluate import evaluate, format_table
from pipeline.mocap.clips import CMU_TO_SMPL24, load_mocap_clip
from pipeline.run.pipeline import run_pipeline
from pipeline.synth.mocap_scene import _segments, place_on_floor
from pipeline.synth.scene_gen import visible_floor_area

CMU = Path(__file__).resolve().parents[3] / "sample_data" / "mocap" / "cmu131"
CLIPS = (CMU / "131_01.bvh", CMU / "131_03.bvh")


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    out = tmp_path_factory.mktemp("mocap") / "scene"
    args = ["synth", str(out), "--rig", "campus", "--people", "2", "--frames", "40"]
    for c in CLIPS:
        args += ["--motion", str(c)]
    assert main(args) == 0
    return load_scene(out)


@pytest.mark.slow
def test_scene_has_detections_of_both_people_and_no_video(scene):
    det = scene.detections
    assert scene.joint_set.name == "coco17" and scene.num_frames == 40
    assert not scene.videos
    for p in (0, 1):
        rows = det.gt_person_id == p
        assert len(np.unique(det.frame[rows])) == 40  # seen in every frame
        assert len(np.unique(det.view[rows])) >= 2
        conf = det.keypoints[rows][..., 2]
        assert (conf > 0).mean() > 0.7
    meta = scene.meta["synth"]
    assert meta["kind"] == "mocap" and [c["file"] for c in meta["clips"]] == [str(c) for c in CLIPS]
    assert all("NSF" in c["licence"] for c in meta["clips"])


@pytest.mark.slow
def test_ground_truth_is_the_bvh_skeleton(scene):
    gt = scene.gt
    assert gt.smpl_pose is None and gt.keypoints3d.shape[1:] == (17, 3)
    people = scene.meta["synth"]["people"]
    for rec in people:
        clip = load_mocap_clip(CMU / rec["clip"], fps=scene.fps)
        s, n = rec["start_frame"], rec["num_frames"]
        want24 = place_on_floor(clip.smpl24[s : s + n], rec["heading_rad"], rec["shift_mm"])
        want17 = place_on_floor(clip.coco17[s : s + n], rec["heading_rad"], rec["shift_mm"])
        rows = np.flatnonzero(gt.person_id == rec["person_id"])
        rows = rows[np.argsort(gt.frame[rows])]
        np.testing.assert_allclose(gt.joints3d[rows], want24, atol=1e-6)
        np.testing.assert_allclose(gt.keypoints3d[rows], want17, atol=1e-6)
        # a rigid motion of the skeleton: bone lengths are the BVH's (up to the linear
        # interpolation 120 -> 25 fps, which shortens a moving bone by < 0.5 mm)
        ix = {n: i for i, n in enumerate(clip.joint_names)}
        thigh = np.linalg.norm(
            gt.joints3d[rows, SMPL24.index["left_hip"]]
            - gt.joints3d[rows, SMPL24.index["left_knee"]],
            axis=-1,
        )
        bvh = np.linalg.norm(
            clip.skeleton[:, ix["LeftHip"]] - clip.skeleton[:, ix["LeftKnee"]], axis=-1
        )
        np.testing.assert_allclose(thigh, bvh[0], atol=0.5)
    mapped = [SMPL24.index[n] for n in CMU_TO_SMPL24]
    unmapped = np.setdiff1d(np.arange(24), mapped)
    assert np.isfinite(gt.joints3d[:, mapped]).all() and np.isnan(gt.joints3d[:, unmapped]).all()
    # placed where the cameras see them
    area = visible_floor_area(scene.rig)
    hips = gt.keypoints3d[:, [COCO17.index["left_hip"], COCO17.index["right_hip"]], :2].mean(1)
    d = np.abs(hips[:, None] - area[None]).max(-1).min(1)
    assert (d < 300).mean() > 0.9


def test_repeated_clips_start_at_other_frames():
    clip = load_mocap_clip(CLIPS[0], fps=25)
    short = replace(clip, skeleton=clip.skeleton[:100], smpl24=clip.smpl24[:100])
    assert _segments([short], 3, 40) == [(0, 15), (0, 30), (0, 45)]
    assert _segments([short, clip], 2, 40)[1][0] == 1


@pytest.mark.slow
def test_pipeline_on_real_motion(scene):
    model = load_body_model()
    results = run_pipeline(scene, PipelineConfig(), model, progress=False)
    ev = evaluate(scene, results)
    print(format_table(ev, view_names=scene.rig.names))
    raw, rts = ev.stages["raw"], ev.stages["rts"]
    # measured (campus, 2 people, 40 frames, seed 0): raw 13.8 mm, RTS 11.0, SMPL step I
    # 23.2, SMPL + VAE 84.9 on the 12 measured joints
    assert raw["recall"] > 0.95 and raw["mpjpe"] < 40
    assert rts["mpjpe"] < raw["mpjpe"] + 5
    assert ev.gt_source == "keypoints3d"
    assert ev.stages["smpl"]["mpjpe"] < 60
    assert "smpl" in ev.smpl24 and np.isfinite(ev.smpl24["smpl"]["mpjpe"])
    assert json.dumps(ev.to_json(), allow_nan=True)
