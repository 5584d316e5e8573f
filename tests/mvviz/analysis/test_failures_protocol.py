"""The protocol's truth stored in a scene: `mvviz eval --protocol` reads it, and the
failure review lists the limbs it counts wrong (the ``protocol`` criterion) with the
per-actor PCP beside them."""

from __future__ import annotations

import json

import numpy as np
import pytest

from mvviz.analysis.failures import all_failures, available_criteria
from mvviz.analysis.failures.protocol import protocol_summary
from mvviz.cli import main
from pipeline.body.model import load_body_model
from pipeline.config import PipelineConfig
from pipeline.data.joint_sets import COCO17
from pipeline.data.scene import load_scene
from pipeline.evaluation.protocol import (
    PROTOCOL_JOINTS,
    ProtocolTruth,
    load_scene_protocol,
    protocol_joints,
    save_scene_protocol,
)
from pipeline.importers.calibration import read_voxelpose_calibration
from pipeline.run.pipeline import run_or_load
from pipeline.synth.scene_gen import SynthConfig, write_synth_scene
from tests.conftest import CAMPUS_CALIB

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")
WRIST = PROTOCOL_JOINTS.index("right_wrist")


@pytest.fixture(scope="module")
def scene_with_truth(tmp_path_factory):
    """A 2-person, 20-frame synthetic COCO-17 scene whose stored protocol truth is its own
    true keypoints, except actor 1's right wrist in frames 5-7, moved to a tenth of the
    forearm from the elbow (a limb scored against half its true length: now ~12 mm)."""
    model = load_body_model()
    root = tmp_path_factory.mktemp("protocol") / "scene"
    write_synth_scene(
        root, read_voxelpose_calibration(CAMPUS_CALIB), model,
        SynthConfig(num_people=2, num_frames=20, seed=3, render_video=False), progress=False,
    )  # fmt: skip
    scene = load_scene(root)
    gt = scene.gt
    joints = protocol_joints(gt.keypoints3d, COCO17)
    moved = (gt.person_id == 0) & np.isin(gt.frame, [5, 6, 7])
    elbow = joints[moved, PROTOCOL_JOINTS.index("right_elbow")]
    joints[moved, WRIST] = elbow + 0.1 * (joints[moved, WRIST] - elbow)
    truth = ProtocolTruth(frame=gt.frame, actor=gt.person_id, joints=joints)
    save_scene_protocol(root, "campus", truth)
    results, _ = run_or_load(scene, PipelineConfig(), model, progress=False)
    return load_scene(root), results


@pytest.mark.slow
def test_stored_truth_round_trip(scene_with_truth):
    scene, _ = scene_with_truth
    protocol, truth = load_scene_protocol(scene.root)
    assert protocol == "campus" and truth.joints.shape == (len(scene.gt.frame), 15, 3)


def test_failure_review_lists_the_wrong_limbs(scene_with_truth):
    scene, results = scene_with_truth
    assert "protocol" in available_criteria(scene, results)
    found = all_failures(scene, results, criterion="protocol")
    wrist = [f for f in found if f.kind == "right_lower_arm" and "actor 1" in f.where
             and f.first <= 7 and f.last >= 5]  # fmt: skip
    assert len(wrist) == 1 and (wrist[0].first, wrist[0].last) == (5, 7)
    assert wrist[0].score > 5.0 and "off by" in wrist[0].detail
    assert wrist[0] is max(found, key=lambda f: f.score)  # the worst entry
    summary = protocol_summary(scene, results)
    assert summary.startswith("**campus PCP** (filtered): actor 1 ") and "average" in summary


def test_eval_reads_the_stored_truth(scene_with_truth, tmp_path):
    scene, _ = scene_with_truth
    out = tmp_path / "pcp.json"
    assert main(["eval", str(scene.root), "--protocol", "campus", "--json", str(out),
                 "--no-sync"]) == 0  # fmt: skip
    figures = json.loads(out.read_text())
    rts = figures["stages"]["rts"]
    # 3 frames of actor 1 lose their right forearm: 3 of its 200 limbs
    assert rts["per_actor"]["0"] <= 1.0 - 3 / 200 + 1e-9
    assert figures["stages"]["rts"]["per_limb"]["right_lower_arm"] < 1.0
    assert rts["average"] > 0.9 and figures["tracks"]["count"] == 2


def test_no_stored_truth_is_a_clear_error(tmp_path, capsys):
    scene_dir = tmp_path / "scene"
    assert main(["convert", "--from", "voxelpose", str(CAMPUS_CALIB), "-o", str(scene_dir)]) == 0
    assert load_scene_protocol(scene_dir) is None
    code = main(["eval", str(scene_dir), "--protocol", "shelf", "--no-sync"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "protocol_gt.npz" in err[0] and "--gt" in err[0]


def test_convert_stores_the_truth(tmp_path, capsys):
    truth = tmp_path / "gt.npz"
    np.savez(truth, frame=np.array([0, 1]), person_id=np.array([0, 0]),
             joints3d=np.zeros((2, 14, 3)))  # fmt: skip
    scene_dir = tmp_path / "scene"
    assert main(["convert", "--from", "voxelpose", str(CAMPUS_CALIB), "--protocol-gt",
                 str(truth), "--protocol", "campus", "-o", str(scene_dir)]) == 0  # fmt: skip
    protocol, stored = load_scene_protocol(scene_dir)
    assert protocol == "campus" and stored.joints.shape == (2, 15, 3)
    # a bad truth file: nothing written
    np.savez(truth, frame=np.array([0]), person_id=np.array([0]))
    capsys.readouterr()
    code = main(["convert", "--from", "voxelpose", str(CAMPUS_CALIB), "--protocol-gt",
                 str(truth), "-o", str(tmp_path / "other")])  # fmt: skip
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "gt.npz" in err[0] and "'joints3d'" in err[0]
    assert not (tmp_path / "other").exists()
