"""Keypoint layouts identified from the data (pipeline/importers/layouts.py), through the
OpenPose, EasyMocap and MMPose readers."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from pipeline.core.files import SceneFormatError
from pipeline.data.joint_sets import BODY25, BODY25B, COCO17, JOINT_SETS, convert_keypoints
from pipeline.data.scene import load_scene
from pipeline.importers import (
    SOURCE_LAYOUTS,
    convert_scene,
    identify_layout,
    read_easymocap_annots,
    read_mmpose_predictions,
    read_openpose_folders,
)
from tests.pipeline.layout_data import SAMPLE, layout_detections, write_openpose_tree

# Cameras without a detection folder are a warning these tests provoke on purpose.
pytestmark = pytest.mark.filterwarnings("ignore:.*no folder for camera:UserWarning")
CAMS = ["0", "1", "2", "3", "4"]
REAL_2D = Path(__file__).resolve().parents[2] / "sample_data" / "pose2sim_balancing" / "pose2d"


def _stack(dets) -> np.ndarray:
    return np.stack([p for people in dets.values() for p in people])


@pytest.mark.parametrize("name", sorted(SOURCE_LAYOUTS))
def test_every_layout_is_identified_and_kept(tmp_path, name):
    js = JOINT_SETS[name]
    dets = layout_detections(js, frames=slice(0, 250, 10))
    write_openpose_tree(tmp_path / "op", dets, CAMS)
    imp = read_openpose_folders(tmp_path / "op", CAMS)
    d = imp.layout_decision
    assert imp.source_layout == name and not d.forced
    assert d.scores[name] >= 0.9, d.evidence
    others = [s for k, s in d.scores.items() if k != name]
    assert all(d.scores[name] - s >= 0.25 for s in others), d.scores
    kept = "coco23" if name == "coco_wholebody133" else name
    assert imp.joint_set.name == kept
    # Kept joints are the file's numbers, in the kept order.
    first = dets[min(dets)][0]
    row = imp.detections.keypoints[0]
    src = convert_keypoints(first[None], js, imp.joint_set)[0]
    seen = src[:, 2] > 0
    np.testing.assert_allclose(row[seen], src[seen])


@pytest.mark.parametrize("truth,wrong", [(BODY25B, BODY25), (BODY25, BODY25B)])
def test_colliding_25_point_layouts_back_facing_and_missing(truth, wrong):
    # Only the people a camera sees from behind (faces weak), and 40 % of points missed.
    dets = layout_detections(truth, miss_rate=0.4, seed=3)
    kp = _stack(dets)
    faces = kp[:, truth.index["nose"], 2] < 0.3
    assert faces.sum() > 100  # plenty of back views
    d = identify_layout(kp[faces], source="op")
    assert d.layout == truth.name and d.scores[truth.name] - d.scores[wrong.name] > 0.25
    assert d.front_facing == 0


def test_one_mirrored_camera_is_tolerated_all_mirrored_is_refused(tmp_path):
    kp = _stack(layout_detections(BODY25, mirror_views=(2,)))
    d = identify_layout(kp, source="op")
    assert d.layout == "body25" and 0.6 < d.left_on_image_right / d.front_facing < 0.95
    kp = _stack(layout_detections(BODY25, mirror_views=tuple(range(5))))
    with pytest.raises(SceneFormatError, match=r"op: field 'keypoints'.*look swapped"):
        identify_layout(kp, source="op")
    forced = identify_layout(kp, source="op", forced="body25")
    assert forced.forced and forced.layout == "body25" and forced.left_on_image_right == 0
    assert "forced" in forced.evidence[0]


def test_weak_evidence_is_refused_with_the_count_and_layout_flag(tmp_path):
    dets = layout_detections(BODY25B, frames=slice(0, 250, 10))
    # Two detections: too few tests.
    few = dict(list(dets.items())[:1])
    few = {k: v[:1] for k, v in few.items()}
    write_openpose_tree(tmp_path / "few", few, CAMS)
    with pytest.raises(SceneFormatError) as info:
        read_openpose_folders(tmp_path / "few", CAMS)
    text = str(info.value)
    assert "few" in text and "25-keypoint" in text and "--layout" in text
    assert "only 1 detections" in text
    # People lying down (the images turned by 90 degrees): no layout stands out.
    lying = {k: [p[:, [1, 0, 2]] for p in v] for k, v in dets.items()}
    write_openpose_tree(tmp_path / "lying", lying, CAMS)
    with pytest.raises(SceneFormatError, match=r"lying.*cannot tell the layout.*--layout"):
        read_openpose_folders(tmp_path / "lying", CAMS)
    # Named, it reads.
    imp = read_openpose_folders(tmp_path / "lying", CAMS, layout="body25b")
    assert imp.source_layout == "body25b" and imp.layout_decision.forced


def test_unknown_count_names_file_field_and_count(tmp_path):
    root = tmp_path / "op"
    path = root / "0" / "0_000000000003_keypoints.json"
    path.parent.mkdir(parents=True)
    path.write_text(json.dumps({"people": [{"pose_keypoints_2d": [1.0, 2.0, 0.5] * 15}]}))
    with pytest.raises(SceneFormatError) as info:
        read_openpose_folders(root, CAMS)
    text = str(info.value)
    assert path.name in text and "people[0].pose_keypoints_2d" in text and "15 keypoints" in text
    assert "--layout" in text


def test_easymocap_annots_identified(tmp_path):
    dets = layout_detections(BODY25B, frames=slice(0, 100, 10))
    for (v, f), people in dets.items():
        p = tmp_path / "annots" / CAMS[v] / f"{f:06d}.json"
        p.parent.mkdir(parents=True, exist_ok=True)
        annots = [{"personID": i, "keypoints": k.tolist()} for i, k in enumerate(people)]
        p.write_text(json.dumps({"annots": annots}))
    imp = read_easymocap_annots(tmp_path / "annots", CAMS, "coco17")
    assert imp.source_layout == "body25b" and imp.joint_set is COCO17


def _mmpose_instance(kp: np.ndarray, scale: float = 1.0) -> dict:
    return {"keypoints": kp[:, :2].tolist(), "keypoint_scores": (kp[:, 2] * scale).tolist()}


@pytest.mark.slow
def test_mmpose_per_frame_files_and_instance_info(tmp_path):
    js = JOINT_SETS["coco_wholebody133"]
    dets = layout_detections(js, frames=slice(0, 60, 3))
    frames = sorted({f for _, f in dets})
    # Cameras 0-2: one file per frame (RTMPose SimCC scores reach above 1: kept).
    for v in range(3):
        for f in frames:
            p = tmp_path / "mm" / CAMS[v] / f"{f:06d}.json"
            p.parent.mkdir(parents=True, exist_ok=True)
            people = dets.get((v, f), [])
            p.write_text(json.dumps([_mmpose_instance(k, 1.2) for k in people]))
    # Cameras 3-4: one instance_info file per camera (MMPose's demos).
    for v in (3, 4):
        info = [
            {"frame_id": f, "instances": [_mmpose_instance(k) for k in dets.get((v, f), [])]}
            for f in frames
        ]
        (tmp_path / "mm" / f"{CAMS[v]}.json").write_text(
            json.dumps({"meta_info": {"dataset_name": "coco_wholebody"}, "instance_info": info})
        )
    imp = read_mmpose_predictions(tmp_path / "mm", CAMS)
    assert imp.source_layout == "coco_wholebody133" and imp.joint_set.name == "coco23"
    assert imp.num_frames == frames[-1] + 1
    n = sum(len(v) for v in dets.values())
    assert len(imp.detections) == n and 1.0 < imp.detections.keypoints[:, :, 2].max() <= 1.2
    full = read_mmpose_predictions(tmp_path / "mm", CAMS, "coco_wholebody133")
    assert full.detections.keypoints.shape == (n, 133, 3)


def test_mmpose_bad_input_names_file_and_field(tmp_path):
    p = tmp_path / "mm" / "0" / "000001.json"
    p.parent.mkdir(parents=True)
    kp = np.ones((17, 3))
    bad = {"keypoints": kp[:, :2].tolist(), "keypoint_scores": [0.5] * 16}
    p.write_text(json.dumps([bad]))
    with pytest.raises(SceneFormatError, match=r"000001\.json: field '\[0\]\.keypoint_scores'.*17"):
        read_mmpose_predictions(tmp_path / "mm", CAMS)
    (tmp_path / "mm" / "0" / "000001.json").unlink()
    (tmp_path / "mm" / "1.json").write_text(json.dumps({"instance_info": [{"instances": []}]}))
    with pytest.raises(SceneFormatError, match=r"1\.json: field 'instance_info\[0\]\.frame_id'"):
        read_mmpose_predictions(tmp_path / "mm", CAMS)


def test_convert_records_the_decision(tmp_path):
    dets = layout_detections(BODY25B, frames=slice(0, 100, 10))
    write_openpose_tree(tmp_path / "op", dets, CAMS)
    out = convert_scene(
        calib_format="voxelpose",
        calib_paths=[SAMPLE.parent / "rigs" / "shelf_voxelpose.json"],
        out_dir=tmp_path / "scene",
        detections_format="openpose",
        detections_path=tmp_path / "op",
    )
    scene = load_scene(out)
    assert scene.joint_set is BODY25B
    decision = scene.meta["imported_from"]["detections"]["layout_decision"]
    assert decision["layout"] == "body25b" and decision["forced"] is False
    assert decision["scores"]["body25b"] > decision["scores"]["body25"] + 0.25
    assert decision["evidence"][0] == "layout body25b taken from the data"


@pytest.mark.skipif(not REAL_2D.is_dir(), reason="the balancing sample is not built")
def test_real_pose2sim_trial_is_body25b():
    rows = [
        np.asarray(p["pose_keypoints_2d"], float).reshape(-1, 3)
        for path in sorted(REAL_2D.glob("*/*.json"))
        for p in json.loads(path.read_text())["people"]
    ]
    d = identify_layout(np.stack(rows), source=REAL_2D)
    assert d.layout == "body25b" and d.scores["body25b"] > 0.9 and d.scores["body25"] < 0.7
    assert d.front_facing > 50 and d.left_on_image_right == d.front_facing
