"""Every malformed input of the corpus (tests/pipeline/malformed.py) through the command
line: exit code 2, one line naming the file and the field, no traceback, nothing
written. And the other side of the rule: an unexpected error is one line, exit code 1,
its traceback only with --debug."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from mvviz import cli
from mvviz.cli import main
from tests.conftest import REPO
from tests.pipeline.malformed import copy_scene, scene_cases, write_tiny_scene

CASES = scene_cases()


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> Path:
    return write_tiny_scene(tmp_path_factory.mktemp("tiny") / "scene")


def _listing(root: Path) -> dict[str, float]:
    return {str(p.relative_to(root)): p.stat().st_mtime for p in root.rglob("*")}


def test_the_corpus_is_large_enough():
    files = {c.file for c in CASES}
    assert {"scene.json", "cameras.json", "detections.npz", "gt.npz", "--set"} <= files
    assert len(CASES) >= 200


@pytest.mark.parametrize("case", CASES, ids=[c.name for c in CASES])
def test_malformed_input_is_one_line_exit_2_and_writes_nothing(case, tiny, tmp_path, capsys):
    scene = copy_scene(tiny, tmp_path / "scene")
    case.mutate(scene)
    before = _listing(tmp_path)
    args = [a.replace("{scene}", str(scene)) for a in case.args]
    code = main(["run", str(scene), *args])
    err = capsys.readouterr().err.strip()
    assert code == 2, err
    assert "Traceback" not in err and len(err.splitlines()) == 1, err
    assert err.startswith("mvviz run: error: ") and case.file in err, err
    if case.field is not None:
        assert f"field '{case.field}" in err, err
    assert _listing(tmp_path) == before  # nothing written, nothing touched


def test_the_valid_tiny_scene_runs(tiny, tmp_path, capsys):
    scene = copy_scene(tiny, tmp_path / "scene")
    assert main(["run", str(scene), "--set", "fit_smpl=false"]) == 0
    assert main(["run", str(scene), "--set", "disabled_views=0,1", "--set", "fit_smpl=false"]) == 0


def test_an_unexpected_error_is_one_line_and_its_traceback_is_behind_debug(
    tiny, monkeypatch, capsys
):
    def boom(scene):
        raise TypeError("a bug")

    monkeypatch.setattr("mvviz.cli.run.load_scene", boom)
    assert main(["run", str(tiny)]) == 1
    err = capsys.readouterr().err
    assert err.strip() == (
        "mvviz run: internal error: TypeError: a bug (run with --debug for the traceback)"
    )
    assert main(["run", str(tiny), "--debug"]) == 1
    assert "Traceback" in capsys.readouterr().err
    assert cli.INPUT_ERRORS  # documented in mvviz/cli/__init__.py


@pytest.mark.slow
def test_app_py_and_mvviz_exit_2_on_a_bad_scene(tmp_path):
    """Real processes: the exit code and stderr a user sees."""
    for argv in (["app.py", str(tmp_path)], ["-m", "mvviz.cli", "view", str(tmp_path)]):
        proc = subprocess.run(
            [sys.executable, *argv], cwd=REPO, capture_output=True, text=True, timeout=120
        )
        assert proc.returncode == 2, proc.stderr
        assert "Traceback" not in proc.stderr
        assert "scene.json: file not found" in proc.stderr


@pytest.mark.parametrize(
    ("option", "value"),
    [("--people", "-1"), ("--people", "0"), ("--frames", "0"), ("--frames", "x")],
)
def test_synth_counts_below_one_are_a_usage_error_and_write_nothing(
    option, value, tmp_path, capsys
):
    out = tmp_path / "scene"
    with pytest.raises(SystemExit) as exc:
        main(["synth", str(out), option, value, "--no-video"])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert f"argument {option}: expected an integer" in err and "Traceback" not in err
    assert not out.exists()


@pytest.mark.parametrize(
    ("option", "value"),
    [("--num-cpus", "0"), ("--retries", "-1"), ("--chunk-frames", "-5"), ("--retries", "two")],
)
def test_batch_counts_out_of_range_are_a_usage_error_before_ray_starts(
    option, value, tmp_path, capsys
):
    """Checked by argparse, before any scene is planned or Ray started (no report)."""
    with pytest.raises(SystemExit) as exc:
        main(["batch", str(tmp_path), option, value, "--report", str(tmp_path / "r")])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert f"argument {option}: expected an integer" in err and "Traceback" not in err
    assert not (tmp_path / "r").exists()


def assert_one_line_exit_2(code: int, err: str, prog: str, file: str, field: str) -> None:
    assert code == 2, err
    assert "Traceback" not in err and len(err.splitlines()) == 1, err
    assert err.startswith(f"{prog}: error: ") and file in err and f"field '{field}'" in err, err


def test_null_detections_in_scene_json_is_one_line_exit_2(tiny, tmp_path, capsys):
    scene = copy_scene(tiny, tmp_path / "scene")
    meta = json.loads((scene / "scene.json").read_text())
    (scene / "scene.json").write_text(json.dumps({**meta, "detections": None}))
    before = _listing(tmp_path)
    code = main(["run", str(scene)])
    err = capsys.readouterr().err.strip()
    assert_one_line_exit_2(code, err, "mvviz run", str(scene / "scene.json"), "detections")
    assert _listing(tmp_path) == before


def _not_pose_data(path: Path, kind: str) -> Path:
    if kind == "text":  # np.load: "This file contains pickled (object) data"
        path.write_text("not poses\n")
    elif kind == "object array":
        np.savez(path, poses=np.array([{"a": 1}], dtype=object))
    elif kind == "no poses":
        np.savez(path, betas=np.zeros(10))
    elif kind == "a checkpoint":  # a zip that np.load opens, without 'poses'
        shutil.copy(REPO / "sample_data" / "priors" / "pose_vae.pt", path)
    elif kind == "bad shape":
        np.savez(path, poses=np.zeros((5, 10)))
    return path


@pytest.mark.parametrize("kind", ["text", "object array", "no poses", "a checkpoint", "bad shape"])
def test_train_prior_on_a_file_that_is_no_pose_data_is_one_line_exit_2(kind, tmp_path, capsys):
    data = _not_pose_data(tmp_path / "data.npz", kind)
    out = tmp_path / "prior.pt"
    code = main(["train-prior", "--data", str(data), "--out", str(out), "--epochs", "1"])
    err = capsys.readouterr().err.strip()
    assert_one_line_exit_2(code, err, "mvviz train-prior", str(data), "poses")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["data.npz"]  # nothing written
