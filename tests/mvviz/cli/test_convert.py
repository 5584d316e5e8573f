"""Tests of ``mvviz convert`` (mvviz/cli/convert.py), called through ``mvviz.cli.main``."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from mvviz.cli import main
from pipeline.data.cameras import CameraRig
from pipeline.data.joint_sets import BODY25, COCO17
from pipeline.data.scene import load_scene
from pipeline.importers import (
    read_voxelpose_calibration,
    write_easymocap_calibration,
    write_pose2sim_calibration,
    write_voxelpose_calibration,
)

# the real Shelf/Campus rigs, shipped byte-identical to ../shared/data/calibration
CALIBRATION_DIR = Path(__file__).resolve().parents[3] / "sample_data" / "rigs"


@pytest.fixture
def shelf():
    return CALIBRATION_DIR / "shelf_voxelpose.json"


def assert_same_rig(a, b, atol=1e-6):
    assert a.names == b.names
    for ca, cb in zip(a, b, strict=True):
        assert (ca.width, ca.height) == (cb.width, cb.height)
        for field in ("K", "dist", "R", "t"):
            np.testing.assert_allclose(getattr(cb, field), getattr(ca, field), atol=atol, rtol=0)


def test_help(capsys):
    with pytest.raises(SystemExit) as info:
        main(["convert", "--help"])
    assert info.value.code == 0
    text = capsys.readouterr().out
    for word in ("voxelpose", "easymocap", "pose2sim", "openpose", "--image-size", "SCENE_DIR"):
        assert word in text


def test_convert_each_format_round_trip(tmp_path, shelf, capsys):
    rig = read_voxelpose_calibration(shelf)
    # Distortion, so that it is carried too (Pose2Sim has no k3: keep it 0 for all).
    dist = np.array([0.05, -0.01, 0.001, 0.002, 0.0])
    rig = CameraRig(tuple(dataclasses.replace(c, dist=dist) for c in rig))
    inputs = {
        "voxelpose": [str(write_voxelpose_calibration(rig, tmp_path / "vp.json"))],
        "easymocap": [str(p) for p in write_easymocap_calibration(rig, tmp_path / "em")],
        "pose2sim": [str(write_pose2sim_calibration(rig, tmp_path / "Calib.toml"))],
    }
    for fmt, files in inputs.items():
        out = tmp_path / f"scene_{fmt}"
        assert main(["convert", "--from", fmt, *files, "-o", str(out)]) == 0
        scene = load_scene(out)
        assert_same_rig(rig, scene.rig)
        assert scene.name == out.name and len(scene.detections) == 0
    assert "5 cameras" in capsys.readouterr().out

    # The original json itself (no width/height keys: the Shelf size is known).
    out = tmp_path / "shelf"
    assert main(["convert", "--from", "voxelpose", str(shelf), "-o", str(out), "--name", "S"]) == 0
    scene = load_scene(out)
    assert scene.name == "S"
    assert all((c.width, c.height) == (1032, 776) for c in scene.rig)
    np.testing.assert_allclose(
        scene.rig.centers, [np.ravel(v["T"]) for v in json.loads(shelf.read_text()).values()]
    )


def _openpose(root: Path, camera: str, frame: int, people: list[np.ndarray]) -> None:
    path = root / camera / f"{camera}_{frame:012d}_keypoints.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    people_json = [{"pose_keypoints_2d": np.asarray(p).ravel().tolist()} for p in people]
    path.write_text(json.dumps({"version": 1.3, "people": people_json}))


def _body25(seed: float) -> np.ndarray:
    j = np.arange(25.0)
    return np.column_stack([100 * seed + j, 50 + j, np.full(25, 0.8)])


def test_convert_with_detections(tmp_path, shelf, capsys):
    root = tmp_path / "openpose"
    for cam in ("0", "1", "2", "3", "4"):
        _openpose(root, cam, 0, [_body25(1), _body25(2)])
        _openpose(root, cam, 1, [])
    out = tmp_path / "scene"
    argv = [
        "convert",
        "--from",
        "voxelpose",
        str(shelf),
        "--detections-from",
        "openpose",
        "--detections",
        str(root),
        "--fps",
        "30",
        "--layout",
        "body25",
        "--joint-set",
        "coco17",
        "-o",
        str(out),
    ]
    assert main(argv) == 0
    assert "10 detections in 2 frames (body25 -> coco17)" in capsys.readouterr().out
    scene = load_scene(out)
    assert scene.fps == 30.0 and scene.num_frames == 2 and len(scene.detections) == 10
    kp = scene.detections.keypoints
    np.testing.assert_allclose(
        kp[:, COCO17.index["left_wrist"], 0] % 100, BODY25.index["left_wrist"]
    )

    # --joint-set body25 keeps every joint.
    out25 = tmp_path / "scene25"
    assert main([*argv[:-1], str(out25), "--joint-set", "body25"]) == 0
    assert load_scene(out25).detections.keypoints.shape == (10, 25, 3)


def test_bad_input_exit_code_and_nothing_written(tmp_path, shelf, capsys):
    raw = json.loads(shelf.read_text())
    raw["2"]["R"][0] = [2.0, 0.0, 0.0]
    bad = tmp_path / "bad_shelf.json"
    bad.write_text(json.dumps(raw))
    out = tmp_path / "scene"
    assert main(["convert", "--from", "voxelpose", str(bad), "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert "bad_shelf.json" in err and "'2.R'" in err and "rotation" in err
    assert not out.exists()

    # A detection folder for a camera the calibration lacks.
    root = tmp_path / "openpose"
    _openpose(root, "0", 0, [_body25(1)])
    _openpose(root, "cam7", 0, [_body25(1)])
    argv = [
        "convert",
        "--from",
        "voxelpose",
        str(shelf),
        "--detections-from",
        "openpose",
        "--detections",
        str(root),
        "-o",
        str(out),
    ]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "cam7" in err and "'camera'" in err
    assert not out.exists()

    # EasyMocap without H_/W_ needs --image-size.
    rig = read_voxelpose_calibration(shelf)
    intri, extri = write_easymocap_calibration(rig, tmp_path / "em")
    intri.write_text(
        "\n".join(ln for ln in intri.read_text().splitlines() if ln[:2] not in ("H_", "W_"))
    )
    argv = ["convert", "--from", "easymocap", str(intri), str(extri), "-o", str(out)]
    assert main(argv) == 2
    assert "'H_0'" in capsys.readouterr().err and not out.exists()
    assert main([*argv, "--image-size", "1032", "776"]) == 0
    assert_same_rig(rig, load_scene(out).rig)


def test_usage_errors(tmp_path, shelf, capsys):
    out = tmp_path / "scene"
    with pytest.raises(SystemExit) as info:
        main(
            [
                "convert",
                "--from",
                "voxelpose",
                str(shelf),
                "--detections-from",
                "openpose",
                "-o",
                str(out),
            ]
        )
    assert info.value.code == 2 and "go together" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["convert", "--from", "colmap", str(shelf), "-o", str(out)])
    with pytest.raises(SystemExit):
        main(
            ["convert", "--from", "voxelpose", str(shelf), "--joint-set", "coco99", "-o", str(out)]
        )
    assert not out.exists()


def test_existing_output_needs_overwrite(tmp_path, shelf, capsys):
    out = tmp_path / "scene"
    argv = ["convert", "--from", "voxelpose", str(shelf), "-o", str(out)]
    assert main(argv) == 0
    assert main([*argv, "--fps", "50"]) == 2
    assert "exists" in capsys.readouterr().err and load_scene(out).fps == 25.0
    assert main([*argv, "--fps", "50", "--overwrite"]) == 0
    assert load_scene(out).fps == 50.0


def test_missing_camera_folder_is_a_warning(tmp_path, shelf, capsys):
    root = tmp_path / "openpose"
    _openpose(root, "3", 2, [_body25(1)])
    out = tmp_path / "scene"
    argv = ["convert", "--from", "voxelpose", str(shelf), "--detections-from", "openpose"]
    argv += ["--layout", "body25"]
    assert main([*argv, "--detections", str(root), "-o", str(out)]) == 0
    captured = capsys.readouterr()
    assert "warning:" in captured.err and "['0', '1', '2', '4']" in captured.err
    assert "1 detections in 3 frames" in captured.out
    np.testing.assert_array_equal(load_scene(out).detections.view, [3])


def test_layout_identified_printed_or_refused_and_nothing_written(tmp_path, shelf, capsys):
    from pipeline.data.joint_sets import BODY25B
    from tests.pipeline.layout_data import layout_detections, write_openpose_tree

    dets = layout_detections(BODY25B, frames=slice(0, 100, 10))
    write_openpose_tree(tmp_path / "op", dets, ["0", "1", "2", "3", "4"])
    argv = ["convert", "--from", "voxelpose", str(shelf), "--detections-from", "openpose"]
    out = tmp_path / "scene"
    assert main([*argv, "--detections", str(tmp_path / "op"), "-o", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "layout: layout body25b taken from the data" in printed
    assert "(body25b -> body25b)" in printed and load_scene(out).joint_set is BODY25B

    # People lying down (images turned by 90 degrees): refused, exit 2, nothing written.
    lying = {k: [p[:, [1, 0, 2]] for p in v] for k, v in dets.items()}
    write_openpose_tree(tmp_path / "lying", lying, ["0", "1", "2", "3", "4"])
    out2 = tmp_path / "scene2"
    assert main([*argv, "--detections", str(tmp_path / "lying"), "-o", str(out2)]) == 2
    err = capsys.readouterr().err
    assert "lying" in err and "25-keypoint" in err and "--layout" in err
    assert "Traceback" not in err and not out2.exists()
    # --layout names it.
    assert (
        main(
            [*argv, "--detections", str(tmp_path / "lying"), "--layout", "body25b", "-o", str(out2)]
        )
        == 0
    )
    assert "forced by --layout" in capsys.readouterr().out
