"""``mvviz diagnose`` through the command line, on copies of the shipped noisy Shelf scene
with known faults: a camera 3 frames late in a world turned upside down, and a camera
rotated by 1 degree. The JSON names them; the fixes are written only when asked."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mvviz.cli import main
from pipeline.body.model import load_body_model
from pipeline.data.cameras import load_cameras
from pipeline.data.scene import load_scene, write_scene
from pipeline.diagnose.floor import transform_scene
from pipeline.diagnose.perturb import delay_camera, perturb_camera_pose
from tests.pipeline.helpers import REPO

NOISY = REPO / "sample_data" / "shelf_synth_noisy"
FAST = ["--set", "fit_smpl=false"]  # the diagnoses need no bodies


def _write(scene, path):
    write_scene(
        path, name=scene.name, fps=scene.fps, num_frames=scene.num_frames,
        joint_set=scene.joint_set, rig=scene.rig, detections=scene.detections, gt=scene.gt,
    )  # fmt: skip
    return path


@pytest.mark.slow
def test_late_camera_and_upside_down_world(tmp_path, capsys):
    scene = load_scene(NOISY)
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("x", 180, degrees=True).as_matrix()
    T[2, 3] = 1500.0
    bad = transform_scene(delay_camera(scene, "1", 3), T, load_body_model())
    root = _write(bad, tmp_path / "bad")
    out_json, fixed_dir = tmp_path / "d.json", tmp_path / "fixed"
    args = ["diagnose", str(root), "--json", str(out_json), "--fix-floor", str(fixed_dir)]
    assert main(args + FAST) == 0
    printed = capsys.readouterr().out
    assert "LATE" in printed and "NOT z-up" in printed
    found = json.loads(out_json.read_text())
    setting = re.search(
        r"to apply the offsets: mvviz run \S+ --set sync.offsets=1:\+(\S+)", printed
    )
    assert setting and abs(float(setting.group(1)) - 3) < 0.15, printed
    assert found["sync_apply"] == f"--set sync.offsets=1:+{setting.group(1)}"
    assert set(found) >= {"sync", "calibration", "floor"}
    assert abs(found["sync"]["1"]["offset_frames"] - 3) < 0.15
    assert all(abs(v["offset_frames"]) < 0.15 for k, v in found["sync"].items() if k != "1")
    assert found["floor"]["z_up"] is False and found["floor"]["angle_to_z_deg"] > 170
    # The fixed copy is z-up with the floor at 0 (a second diagnosis says so) ...
    assert main(["diagnose", str(fixed_dir), "--json", str(out_json)] + FAST) == 0
    again = json.loads(out_json.read_text())["floor"]
    assert again["z_up"] and again["floor_at_zero"] and again["angle_to_z_deg"] < 1.0
    # ... with the original's cameras back (the floor cannot see a horizontal shift).
    fixed = load_cameras(fixed_dir / "cameras.json")
    for a, b in zip(fixed, scene.rig, strict=True):
        assert np.degrees(Rotation.from_matrix(a.R @ b.R.T).magnitude()) < 1e-4
        assert abs(a.center[2] - b.center[2]) < 30.0


@pytest.mark.slow
def test_the_printed_offset_applied_puts_the_camera_in_sync(tmp_path, capsys):
    root = _write(delay_camera(load_scene(NOISY), "3", -2), tmp_path / "late")
    out_json = tmp_path / "d.json"
    assert main(["diagnose", str(root), "--json", str(out_json)] + FAST) == 0
    apply = json.loads(out_json.read_text())["sync_apply"]
    assert re.fullmatch(r"--set sync.offsets=3:-(1\.9\d|2\.0\d)", apply), apply
    capsys.readouterr()
    assert main(["diagnose", str(root), "--json", str(out_json), *apply.split()] + FAST) == 0
    printed = capsys.readouterr().out
    again = json.loads(out_json.read_text())
    assert abs(again["sync"]["3"]["offset_frames"]) < 0.15, again["sync"]["3"]
    assert "sync_apply" not in again and "to apply" not in printed


@pytest.mark.slow
def test_rotated_camera_named_and_refined_on_request(tmp_path, capsys):
    scene = perturb_camera_pose(load_scene(NOISY), "3", rotation_deg=1.0, axis=(0, 0, 1))
    root = _write(scene, tmp_path / "rot")
    cams, out_json = tmp_path / "cams.json", tmp_path / "d.json"
    args = ["diagnose", str(root), "--json", str(out_json), "--write-cameras", str(cams)]
    assert main(args + FAST) == 0
    assert "SUSPECT" in capsys.readouterr().out
    cal = json.loads(out_json.read_text())["calibration"]
    assert [k for k, v in cal.items() if v["suspect"]] == ["3"]
    assert abs(cal["3"]["rotation_error_deg"] - 1.0) < 0.2
    truth = load_scene(NOISY).rig[3]
    new = load_cameras(cams)[3]
    assert np.degrees(Rotation.from_matrix(new.R @ truth.R.T).magnitude()) < 0.2
    assert not (root / "cameras.json").read_text() == cams.read_text()  # the scene untouched


def test_bad_arguments_are_one_line_errors(tmp_path, capsys):
    assert main(["diagnose", str(tmp_path / "nowhere")]) == 2
    err = capsys.readouterr().err
    assert "nowhere" in err and "Traceback" not in err
    assert main(["diagnose", str(NOISY), "--max-shift", "0"] + FAST) == 2
    assert "--max-shift" in capsys.readouterr().err
