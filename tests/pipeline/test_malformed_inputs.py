"""Malformed inputs at the loaders: the corpus of tests/pipeline/malformed.py (each file
case raises a SceneFormatError naming file and field), the importers' files through
``mvviz convert`` (exit 2, one line, nothing written), hypothesis fuzzing of every
loader (only SceneFormatError ever escapes), and a malicious checkpoint (never runs)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mvviz.cli import main
from pipeline.config import PipelineConfig
from pipeline.core.files import SceneFormatError
from pipeline.data.cameras import load_cameras
from pipeline.data.scene import check_detections, check_ground_truth, load_scene
from pipeline.fit.prior import load_prior
from pipeline.importers.detections import read_mmpose_predictions, read_openpose_folders
from tests.conftest import CAMPUS_CALIB
from tests.pipeline.malformed import copy_scene, scene_cases, write_tiny_scene

FILE_CASES = [c for c in scene_cases() if not c.args]


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> Path:
    return write_tiny_scene(tmp_path_factory.mktemp("tiny") / "scene")


def test_the_shipped_sample_scenes_load():
    for name in ("shelf_synth", "shelf_synth_noisy", "pose2sim_demo", "pose2sim_balancing"):
        load_scene(Path(__file__).resolve().parents[2] / "sample_data" / name)


@pytest.mark.parametrize("case", FILE_CASES, ids=[c.name for c in FILE_CASES])
def test_each_malformed_file_names_file_and_field(case, tiny, tmp_path):
    scene = copy_scene(tiny, tmp_path / "scene")
    case.mutate(scene)
    with pytest.raises(SceneFormatError) as info:
        load_scene(scene)
    assert case.file in info.value.path
    assert info.value.field == case.field or (info.value.field or "").startswith(case.field or "")


# --------------------------------------------------------------------------- importers

BODY25_VALUES = [float(v) for _ in range(25) for v in (100, 200, 0.9)]


def _openpose_tree(root: Path, edit=None, name="c_{f:012d}_keypoints.json") -> Path:
    for cam in ("0", "1", "2"):
        (root / cam).mkdir(parents=True)
        for f in range(3):
            data = {"people": [{"pose_keypoints_2d": list(BODY25_VALUES)}]}
            if edit is not None and cam == "0" and f == 0:
                result = edit(data)  # edits in place, or returns the file's raw text
                data = result if isinstance(result, str) else data
            text = data if isinstance(data, str) else json.dumps(data)
            (root / cam / name.format(f=f)).write_text(text)
    return root


def _kp(value):
    def edit(d):
        d["people"][0]["pose_keypoints_2d"][2] = value

    return edit


F = "people[0].pose_keypoints_2d"
OPENPOSE_CASES = [
    ("strings", _kp("0.9"), F),
    ("true", _kp(True), F),
    ("null", _kp(None), F),
    ("object", _kp({}), F),
    ("conf Infinity", _kp(math.inf), F),
    ("conf -Infinity", _kp(-math.inf), F),
    ("not triples", lambda d: d["people"][0]["pose_keypoints_2d"].pop(), F),
    ("keypoints a dict", lambda d: d["people"][0].update(pose_keypoints_2d={}), F),
    ("people missing", lambda d: d.pop("people"), "people"),
    ("people a number", lambda d: d.update(people=3), "people"),
    ("person a list", lambda d: d.update(people=[[1]]), F),
    ("not JSON", lambda d: "{", None),
    ("a list", lambda d: "[]", "people"),
    ("other count", lambda d: d["people"][0].update(pose_keypoints_2d=BODY25_VALUES[:-3]),
     F),
]  # fmt: skip


def _convert(tmp_path, det: Path, *extra) -> tuple[int, str, Path]:
    out = tmp_path / "out"
    code = main([
        "convert", "--from", "voxelpose", str(CAMPUS_CALIB), "--detections-from", "openpose",
        "--detections", str(det), "--layout", "body25", "-o", str(out), *extra,
    ])  # fmt: skip
    return code, out


def _check_clean_failure(code, capsys, tmp_path, out, file_part, field):
    err = capsys.readouterr().err.strip().splitlines()
    err = [e for e in err if "warning" not in e]
    assert code == 2 and len(err) == 1 and "Traceback" not in err[0], err
    assert file_part in err[0], err
    if field:
        assert f"field '{field}'" in err[0], err
    assert not out.exists()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


@pytest.mark.parametrize("name, edit, field", OPENPOSE_CASES, ids=[c[0] for c in OPENPOSE_CASES])
def test_openpose_malformed_file(name, edit, field, tmp_path, capsys):
    det = _openpose_tree(tmp_path / "det", edit)
    code, out = _convert(tmp_path, det)
    _check_clean_failure(code, capsys, tmp_path, out, "c_000000000000_keypoints.json", field)


def test_openpose_frame_numbers_are_bounded_by_the_files_read(tmp_path, capsys):
    det = _openpose_tree(tmp_path / "det")
    (det / "1" / "c_999999999999_keypoints.json").write_text(json.dumps({"people": []}))
    code, out = _convert(tmp_path, det)
    _check_clean_failure(code, capsys, tmp_path, out, "c_999999999999", "frame number")
    # an offset start (a clip cut from a longer video) is fine: frames stay as numbered
    ok = _openpose_tree(tmp_path / "ok", name="c_50{f:02d}_keypoints.json")
    assert read_openpose_folders(ok, ["0", "1", "2"], layout="body25").num_frames == 5003


def test_openpose_file_name_without_a_frame_number(tmp_path, capsys):
    det = _openpose_tree(tmp_path / "det")
    (det / "2" / "keypoints.json").write_text(json.dumps({"people": []}))
    code, out = _convert(tmp_path, det)
    _check_clean_failure(code, capsys, tmp_path, out, "keypoints.json", "file name")


def test_convert_with_bad_calibration_or_reference(tmp_path, capsys):
    det = _openpose_tree(tmp_path / "det")
    calib = json.loads(CAMPUS_CALIB.read_text())
    for key, value, field in (("fx", "1000", "fx"), ("R", [["1"] * 3] * 3, "R"),
                              ("T", {}, "T"), ("fx", True, "fx"), ("k", [0, 0], "k")):  # fmt: skip
        bad = json.loads(json.dumps(calib))
        bad["0"][key] = value
        path = tmp_path / "calib.json"
        path.write_text(json.dumps(bad))
        out = tmp_path / "out"
        code = main(["convert", "--from", "voxelpose", str(path), "--detections-from", "openpose",
                     "--detections", str(det), "--layout", "body25", "-o", str(out)])  # fmt: skip
        _check_clean_failure(code, capsys, tmp_path, out, "calib.json", f"0.{field}")
    (tmp_path / "ref.trc").write_text("garbage\n")
    code, out = _convert(tmp_path, det, "--reference", "r=" + str(tmp_path / "ref.trc"))
    _check_clean_failure(code, capsys, tmp_path, out, "ref.trc", None)


def _mmpose_file(root: Path, info) -> Path:
    (root).mkdir(parents=True, exist_ok=True)
    for cam in ("0", "1", "2"):
        (root / f"{cam}.json").write_text(json.dumps({"instance_info": info}))
    return root


XY = [[1, 2]] * 17


@pytest.mark.parametrize(
    "entry, field",
    [
        ({"frame_id": -1, "instances": []}, "instance_info[0].frame_id"),
        ({"frame_id": "3", "instances": []}, "instance_info[0].frame_id"),
        ({"frame_id": True, "instances": []}, "instance_info[0].frame_id"),
        ({"frame_id": 10**12, "instances": []}, "frame number"),
        ({"frame_id": 0, "instances": 3}, "instance_info[0].instances"),
        ({"frame_id": 0, "instances": [{"keypoints": [["1", "2"]] * 17}]},
         "instance_info[0].instances[0].keypoints"),
        ({"frame_id": 0, "instances": [{"keypoints": XY, "keypoint_scores": [True] * 17}]},
         "instance_info[0].instances[0].keypoint_scores"),
        ({"frame_id": 0, "instances": [{"keypoints": XY, "keypoint_scores": [1] * 3}]},
         "instance_info[0].instances[0].keypoint_scores"),
    ],
)  # fmt: skip
def test_mmpose_malformed_file(entry, field, tmp_path):
    root = _mmpose_file(tmp_path / "mm", [entry])
    with pytest.raises(SceneFormatError) as info:
        read_mmpose_predictions(root, ["0", "1", "2"], layout="coco17")
    assert info.value.field == field and info.value.path.endswith(".json")


# --------------------------------------------------------------------------- fuzzing

JSON = st.recursive(
    st.none() | st.booleans() | st.integers(-(10**13), 10**13)
    | st.floats(allow_nan=True, allow_infinity=True) | st.text(max_size=5),
    lambda inner: st.lists(inner, max_size=4)
    | st.dictionaries(st.text(max_size=5), inner, max_size=4),
    max_leaves=12,
)  # fmt: skip
SCENE_KEYS = ["name", "fps", "units", "joint_set", "num_frames", "cameras", "detections", "gt",
              "videos", "images", "references"]  # fmt: skip
CAMERA_KEYS = ["name", "width", "height", "K", "dist", "R", "t"]
FUZZ = settings(max_examples=150, deadline=None,
                suppress_health_check=[HealthCheck.function_scoped_fixture])  # fmt: skip


@pytest.mark.slow
@FUZZ
@given(edits=st.dictionaries(st.sampled_from(SCENE_KEYS), JSON, max_size=4))
def test_fuzz_scene_json(edits, tiny, tmp_path_factory):
    scene = copy_scene(tiny, tmp_path_factory.mktemp("f") / "s")
    meta = json.loads((scene / "scene.json").read_text())
    meta.update(edits)
    (scene / "scene.json").write_text(json.dumps(meta))
    try:
        load_scene(scene)
    except SceneFormatError:
        pass


@pytest.mark.slow
@FUZZ
@given(edits=st.dictionaries(st.sampled_from(CAMERA_KEYS), JSON, max_size=3), whole=JSON)
def test_fuzz_cameras_json(edits, whole, tmp_path_factory):
    cams = json.loads(CAMPUS_CALIB.read_text())  # any valid rig, rewritten below
    path = tmp_path_factory.mktemp("c") / "cameras.json"
    good = {"name": "a", "width": 10, "height": 10, "K": [[1, 0, 5], [0, 1, 5], [0, 0, 1]],
            "dist": [0] * 5, "R": np.eye(3).tolist(), "t": [0, 0, 1]}  # fmt: skip
    for data in ([dict(good, **edits)], whole, {"cameras": whole}):
        path.write_text(json.dumps(data))
        try:
            load_cameras(path)
        except SceneFormatError:
            pass
    assert cams


ARRAYS = st.one_of(
    st.integers(0, 5).flatmap(lambda n: st.sampled_from([
        np.zeros(n), np.arange(n), np.full((n, 17, 3), 0.5), np.full((n, 3), np.nan),
        np.zeros((n, 24, 3)), np.array(["x"] * n), np.zeros((n, 72)), np.zeros((n, 10)),
        np.tile([0.0, 0, 1, 1], (n, 1)), -np.ones(n), np.full(n, 1e18),
    ])),
    st.just(np.zeros(())),
)  # fmt: skip
DET_KEYS = ["frame", "view", "keypoints", "smpl_pose", "smpl_betas", "cam_weak", "bbox",
            "mono_joints3d", "gt_person_id"]  # fmt: skip


@settings(max_examples=300, deadline=None)
@given(arrays=st.dictionaries(st.sampled_from(DET_KEYS), ARRAYS, max_size=7))
def test_fuzz_detection_and_gt_arrays(arrays):
    for check in (
        lambda a: check_detections(a, source="d.npz", num_joints=17, num_views=3),
        lambda a: check_ground_truth(
            {("person_id" if k == "view" else "joints3d" if k == "mono_joints3d" else k): v
             for k, v in a.items()}, source="g.npz"),
    ):  # fmt: skip
        try:
            check(arrays)
        except SceneFormatError:
            pass


@pytest.mark.slow
@settings(max_examples=300, deadline=None)
@given(data=st.dictionaries(
    st.sampled_from(["source", "disabled_views", "fit_smpl", "kalman", "triangulation",
                     "association", "smpl_fit", "tracking", "pose_prior"]),
    JSON | st.dictionaries(st.sampled_from(["q", "r", "min_views", "model", "gate", "iters"]),
                           JSON, max_size=3), max_size=4),
    sets=st.lists(st.text(max_size=12), max_size=3))  # fmt: skip
def test_fuzz_config_and_set(data, sets):
    try:
        PipelineConfig.from_dict(data)
    except SceneFormatError:
        pass
    try:
        PipelineConfig().with_overrides(sets)
    except SceneFormatError:
        pass


@pytest.mark.slow
@FUZZ
@given(doc=JSON)
def test_fuzz_openpose_and_mmpose_files(doc, tmp_path_factory):
    root = tmp_path_factory.mktemp("op")
    (root / "0").mkdir()
    (root / "0" / "x_000000000000_keypoints.json").write_text(json.dumps({"people": doc}))
    (root / "0" / "x_000000000001_keypoints.json").write_text(json.dumps(doc))
    for read in (read_openpose_folders, read_mmpose_predictions):
        try:
            read(root, ["0"], layout="body25" if read is read_openpose_folders else "coco17")
        except SceneFormatError:
            pass


# --------------------------------------------------------------------------- code in files


class _Payload:
    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return (Path.touch, (self.marker,))


def test_a_malicious_checkpoint_never_runs(tmp_path):
    marker = tmp_path / "pwned"
    torch.save({"version": 1, "state_dict": _Payload(marker)}, tmp_path / "evil.pt")
    with pytest.raises(SceneFormatError, match=r"evil\.pt: not a readable checkpoint"):
        load_prior(tmp_path / "evil.pt")
    assert not marker.exists()
