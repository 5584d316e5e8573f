"""`mvviz run` and `mvviz eval` on a tiny synthesized scene."""

from __future__ import annotations

import json
import re

import pytest

from mvviz.cli import main
from pipeline.body.model import load_body_model
from pipeline.synth.scene_gen import SynthConfig, write_synth_scene
from tests.conftest import REPO
from tests.pipeline.helpers import campus_rig


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("cli") / "scene"
    cfg = SynthConfig(num_people=2, num_frames=15, seed=2, render_video=False)
    write_synth_scene(out, campus_rig(), load_body_model(), cfg, progress=False)
    return out


@pytest.mark.slow
def test_run_writes_and_reuses_results(scene_dir, capsys):
    assert main(["run", str(scene_dir)]) == 0
    assert "computed results" in capsys.readouterr().out
    assert (scene_dir / ".mvviz" / "results.npz").is_file()
    assert main(["run", str(scene_dir)]) == 0
    assert "reused cached results" in capsys.readouterr().out
    assert main(["run", str(scene_dir), "--set", "kalman.q=20"]) == 0
    assert "computed results" in capsys.readouterr().out


@pytest.mark.slow
def test_eval_json_has_the_documented_keys(scene_dir, tmp_path, capsys):
    out = tmp_path / "eval.json"
    assert main(["eval", str(scene_dir), "--json", str(out)]) == 0
    text = capsys.readouterr().out
    assert "raw" in text and "rts" in text and "association: precision" in text
    d = json.loads(out.read_text())
    for stage in ("raw", "kalman", "rts"):
        assert set(d["stages"][stage]) >= {"mpjpe_mm", "pck160", "pcp", "accel_mm"}
        assert 0 < d["stages"][stage]["mpjpe_mm"] < 60
    assert set(d["association"]) >= {"precision", "recall", "id_switches"}
    assert d["association"]["precision"] > 0.95
    assert d["other_source"]["source"] == "smpl"
    # 15 frames: no track is long enough for the label check, which says so
    assert "labels: OK (no track long enough to judge; 3 cameras;" in text
    assert d["labels"]["ok"] is True and d["labels"]["findings"] == []


def test_eval_without_ground_truth_prints_the_label_check(tmp_path, capsys):
    """The real-video demo has no gt.npz: no pose rows, but the labels line and JSON."""
    out = tmp_path / "eval.json"
    demo = REPO / "sample_data" / "pose2sim_demo"
    args = ["eval", str(demo), "--out", str(tmp_path / "r.npz"), "--json", str(out)]
    assert main([*args, "--set", "fit_smpl=false", "--no-other-source"]) == 0
    captured = capsys.readouterr()
    assert "no gt.npz" in captured.err and "MPJPE" not in captured.out
    assert "labels: OK (2 tracks, 4 cameras; checked left_right, facing," in captured.out
    labels = json.loads(out.read_text())["labels"]
    assert labels["ok"] is True and sorted(labels["tracks"]) == ["0", "1"]
    # measured 0.154: BlazePose mirrors the woman in cam03 (the association un-mirrors her)
    assert 0.1 < labels["cameras"]["cam03"] < 0.25


def test_bad_override_and_missing_scene_fail_cleanly(scene_dir, tmp_path, capsys):
    assert main(["run", str(scene_dir), "--set", "kalman.nope=1"]) == 2
    assert "--set: field 'kalman.nope': no such field" in capsys.readouterr().err
    assert main(["run", str(tmp_path / "missing")]) == 2
    assert "scene.json: file not found" in capsys.readouterr().err


@pytest.mark.slow
def test_eval_reports_sync(tmp_path, capsys):
    """A camera of the shipped Shelf scene delayed by 2 frames: ``mvviz eval`` prints it
    LATE with the setting that applies it; ``--no-sync`` leaves the check out."""
    from pipeline.data.scene import load_scene, write_scene
    from pipeline.diagnose.perturb import delay_camera

    scene = delay_camera(load_scene(REPO / "sample_data" / "shelf_synth"), "2", 2)
    root = tmp_path / "late"
    write_scene(
        root, name=scene.name, fps=scene.fps, num_frames=scene.num_frames,
        joint_set=scene.joint_set, rig=scene.rig, detections=scene.detections, gt=scene.gt,
    )  # fmt: skip
    out = tmp_path / "e.json"
    fast = ["--set", "fit_smpl=false", "--no-other-source"]
    assert main(["eval", str(root), *fast, "--json", str(out)]) == 0
    line = next(x for x in capsys.readouterr().out.splitlines() if x.startswith("sync:"))
    got = re.search(r" 2 \+(\d\.\d\d) \(\d\.\d\d\) LATE", line)  # measured: +1.99 (0.85)
    assert got and abs(float(got.group(1)) - 2) < 0.15, line
    assert f"apply: --set sync.offsets=2:+{got.group(1)}" in line
    sync = json.loads(out.read_text())["sync"]
    assert abs(sync["2"]["offset_frames"] - 2) < 0.15 and sync["2"]["confidence"] > 0.5
    assert all(abs(v["offset_frames"]) < 0.15 for k, v in sync.items() if k != "2")
    assert main(["eval", str(root), *fast, "--no-sync", "--json", str(out)]) == 0
    assert "sync:" not in capsys.readouterr().out and "sync" not in json.loads(out.read_text())
