"""Reference tracks in the native scene format (pipeline/data/references.py,
pipeline/data/scene.py): round trips, frame-count policy, errors naming file and field, and
attaching a TRC."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from pipeline.core.files import SceneFormatError
from pipeline.data.cameras import Camera, CameraRig
from pipeline.data.joint_sets import BODY25B, COCO17
from pipeline.data.references import ReferenceTrack, fit_frames
from pipeline.data.scene import Detections, add_reference, load_scene, write_scene
from pipeline.importers import convert_scene
from pipeline.importers.trc import (
    POSE2SIM_MARKERS,
    reference_from_trc,
    world_mm_to_trc,
    write_trc,
)

REPO = Path(__file__).resolve().parents[2]
BALANCING_TRC = (
    REPO / "sample_data" / "pose2sim_balancing" / "ref3d" / "S00_P00_T01_BalancingTrial_0-100.trc"
)
F = 6


def _rig() -> CameraRig:
    K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    return CameraRig(
        tuple(
            Camera(f"c{i}", 640, 480, K, np.zeros(5), np.eye(3), np.array([500.0 * i, 0, 4000]))
            for i in range(2)
        )
    )


def _no_detections(js=COCO17) -> Detections:
    return Detections(
        frame=np.zeros(0, np.int64),
        view=np.zeros(0, np.int64),
        keypoints=np.zeros((0, js.num_joints, 3)),
    )


def _joints(seed: int = 0, frames: int = F, js=COCO17) -> np.ndarray:
    j = np.random.default_rng(seed).normal(0, 300, (frames, js.num_joints, 3)) + [0, 0, 1000]
    j[1, 3] = np.nan
    return j


def _scene(tmp_path: Path, **refs: np.ndarray) -> Path:
    return write_scene(
        tmp_path / "scene",
        name="s",
        fps=30.0,
        num_frames=F,
        joint_set=COCO17,
        rig=_rig(),
        detections=_no_detections(),
        references={n: ReferenceTrack(n, j, source=f"test {n}") for n, j in refs.items()},
    )


def test_write_load_round_trip(tmp_path):
    a, b = _joints(0), _joints(1)
    root = _scene(tmp_path, toolA=a, tool_b=b)
    scene = load_scene(root)
    assert sorted(scene.references) == ["toolA", "tool_b"]
    np.testing.assert_array_equal(scene.references["toolA"].joints, a)
    np.testing.assert_array_equal(scene.references["tool_b"].joints, b)
    assert scene.references["toolA"].source == "test toolA"
    meta = json.loads((root / "scene.json").read_text())
    assert meta["references"]["toolA"] == {
        "file": "references/toolA.npz",
        "joint_set": "coco17",
        "source": "test toolA",
    }
    assert load_scene(_scene(tmp_path / "x")).references == {}


def _edit(root: Path, fn) -> None:
    meta = json.loads((root / "scene.json").read_text())
    fn(meta)
    (root / "scene.json").write_text(json.dumps(meta))


@pytest.mark.parametrize(
    ("fn", "field", "words"),
    [
        (lambda m: m["references"]["r"].update(joint_set="body25b"), "references.r.joint_set",
         "'coco17'"),
        (lambda m: m.update(references=["r"]), "references", "expected an object"),
        (lambda m: m["references"].update({"../x": {}}), "references", "'../x'"),
        (lambda m: m["references"].update(r="references/r.npz"), "references.r", "an object"),
        (lambda m: m.update(num_frames=F + 1), "joints", f"({F + 1}, 17, 3)"),
        (lambda m: m["references"]["r"].update(file="references/none.npz"), None, "not found"),
    ],
)  # fmt: skip
def test_load_errors_name_file_and_field(tmp_path, fn, field, words):
    root = _scene(tmp_path, r=_joints())
    _edit(root, fn)
    with pytest.raises(SceneFormatError) as err:
        load_scene(root)
    assert err.value.field == field and words in str(err.value)
    assert err.value.path.endswith(("scene.json", ".npz"))


def test_bad_arrays_in_the_npz(tmp_path):
    root = _scene(tmp_path, r=_joints())
    np.savez(root / "references" / "r.npz", joints=np.full((F, 17, 3), np.inf))
    with pytest.raises(SceneFormatError, match="infinite") as err:
        load_scene(root)
    assert err.value.path == str(root / "references" / "r.npz")
    np.savez(root / "references" / "r.npz", points=np.zeros((F, 17, 3)))
    with pytest.raises(SceneFormatError, match="missing") as err:
        load_scene(root)
    assert err.value.field == "joints"


def test_write_scene_checks_references(tmp_path):
    with pytest.raises(SceneFormatError, match=r"\(6, 17, 3\)"):
        _scene(tmp_path, r=_joints(frames=F - 1))
    with pytest.raises(SceneFormatError, match="reference name"):
        _scene(tmp_path, **{"a b": _joints()})
    assert not (tmp_path / "scene").exists()


def test_fit_frames_pads_shorter_and_refuses_longer():
    j = _joints(frames=4)
    out = fit_frames(j, 6, source="x")
    assert out.shape == (6, 17, 3)
    np.testing.assert_array_equal(out[:4], j)
    assert np.isnan(out[4:]).all()
    with pytest.raises(SceneFormatError, match="7 frames, the scene 6"):
        fit_frames(_joints(frames=7), 6, source="x")


def test_add_reference_keeps_the_rest_of_scene_json(tmp_path):
    root = _scene(tmp_path)
    _edit(root, lambda m: m.update(custom={"kept": 1}))
    scene = load_scene(root)
    j = _joints(2, frames=4)
    path = add_reference(scene, ReferenceTrack("p2s", j, source="a test"))
    assert path == root / "references" / "p2s.npz"
    scene = load_scene(root)
    assert scene.meta["custom"] == {"kept": 1}
    got = scene.references["p2s"].joints
    np.testing.assert_array_equal(got[:4], j)
    assert np.isnan(got[4:]).all()
    with pytest.raises(FileExistsError, match="p2s"):
        add_reference(scene, ReferenceTrack("p2s", j))
    add_reference(scene, ReferenceTrack("p2s", _joints(3)), overwrite=True)
    np.testing.assert_array_equal(load_scene(root).references["p2s"].joints, _joints(3))
    with pytest.raises(SceneFormatError, match="7 frames"):
        add_reference(scene, ReferenceTrack("long", _joints(frames=7)))
    assert "long" not in load_scene(root).references


def test_reference_from_trc_maps_pose2sim_markers(tmp_path):
    """World mm -> a TRC with Pose2Sim's BODY_25B marker names -> the scene's COCO-17."""
    world = _joints(4, frames=5, js=COCO17)
    inverse = {ours: p2s for p2s, ours in POSE2SIM_MARKERS["coco17"].items()}
    names = [inverse[n] for n in COCO17.names]
    write_trc(tmp_path / "r.trc", names, world_mm_to_trc(world), rate=30.0)
    with pytest.warns(UserWarning, match="DataRate 30 Hz, the scene 60 fps"):
        track = reference_from_trc(tmp_path / "r.trc", "p2s", "coco17", fps=60.0)
    np.testing.assert_allclose(track.joints, world, atol=1e-6, equal_nan=True)
    assert "TRC, m, Y up, 5 frames at 30 Hz, 17 joints" in track.source


def test_convert_scene_with_the_pose2sim_reference(tmp_path):
    rig_json = REPO / "sample_data" / "rigs" / "shelf_voxelpose.json"
    if not rig_json.is_file():
        pytest.skip("no shipped rig")
    out = convert_scene(
        calib_format="voxelpose",
        calib_paths=[rig_json],
        out_dir=tmp_path / "conv",
        joint_set="body25b",
        fps=60.0,
        references={"pose2sim": BALANCING_TRC},
    )
    scene = load_scene(out)
    assert scene.num_frames == 100  # no detections: the reference's length
    j = scene.references["pose2sim"].joints
    assert j.shape == (100, 25, 3)
    present = np.isfinite(j).all(-1).all(0)
    missing = {BODY25B.names[i] for i in np.flatnonzero(~present)}
    assert missing == {"left_eye", "right_eye", "left_ear", "right_ear"}
    head = j[:, BODY25B.index["head_top"], 2]
    assert 1550 < np.median(head) < 1700  # world mm, z up
    assert str(BALANCING_TRC.name) in scene.references["pose2sim"].source
    with pytest.raises(SceneFormatError, match="reference name"):
        convert_scene(
            calib_format="voxelpose",
            calib_paths=[rig_json],
            out_dir=tmp_path / "bad",
            references={"a/b": BALANCING_TRC},
        )
    assert not (tmp_path / "bad").exists()
