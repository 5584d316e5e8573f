"""The native scene format: reading, writing atomically, and errors that name file and field."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from pipeline.files import SceneFormatError
from pipeline.joint_sets import COCO17
from pipeline.scene import Detections, load_scene, write_scene
from tests.pipeline.helpers import campus_rig


def _write_small(tmp_path, **det_overrides):
    rig = campus_rig()
    n = 4
    kp = np.random.default_rng(0).uniform(10, 200, (n, 17, 3))
    kp[..., 2] = 0.8
    arrays = dict(frame=np.array([0, 0, 1, 1]), view=np.array([0, 1, 0, 2]), keypoints=kp)
    arrays.update(det_overrides)
    return write_scene(
        tmp_path / "scene",
        name="t",
        fps=25,
        num_frames=2,
        joint_set=COCO17,
        rig=rig,
        detections=Detections(**arrays),
    )


def test_write_then_load(tmp_path):
    root = _write_small(tmp_path)
    s = load_scene(root)
    assert s.name == "t" and len(s.rig) == 3 and len(s.detections) == 4 and s.gt is None
    assert s.joint_set is COCO17 and s.num_frames == 2
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temp leftovers


def test_bad_values_are_refused_and_nothing_is_written(tmp_path):
    kp = np.full((4, 17, 3), 0.5)
    kp[1, 3, 2] = np.nan
    with pytest.raises(SceneFormatError, match=r"detections\.npz: field 'keypoints\[\.\.\., 2\]'"):
        _write_small(tmp_path, keypoints=kp)
    kp[1, 3, 2] = -0.2
    with pytest.raises(SceneFormatError, match=r"confidence in \[0, 1\]"):
        _write_small(tmp_path, keypoints=kp)
    with pytest.raises(SceneFormatError, match=r"field 'view'"):
        _write_small(tmp_path, view=np.array([0, 1, 0, 7]))
    with pytest.raises(SceneFormatError, match=r"expected 17 joints"):
        _write_small(tmp_path, keypoints=np.full((4, 25, 3), 0.5))
    assert list(tmp_path.iterdir()) == []


def _edit(root, name, fn):
    p = root / name
    data = json.loads(p.read_text())
    fn(data)
    p.write_text(json.dumps(data))


def test_load_errors_name_file_and_field(tmp_path):
    root = _write_small(tmp_path)
    bad = tmp_path / "bad"
    for mutate, pattern in [
        (
            lambda d: d.update(joint_set="blaze33"),
            r"scene\.json: field 'joint_set': expected one of",
        ),
        (lambda d: d.update(units="m"), r"scene\.json: field 'units'"),
        (lambda d: d.update(fps=-1), r"scene\.json: field 'fps'"),
    ]:
        shutil.rmtree(bad, ignore_errors=True)
        shutil.copytree(root, bad)
        _edit(bad, "scene.json", mutate)
        with pytest.raises(SceneFormatError, match=pattern):
            load_scene(bad)
    shutil.rmtree(bad)
    shutil.copytree(root, bad)
    _edit(bad, "cameras.json", lambda d: d[1].update(R=[[1, 0, 0], [0, 1, 0], [0, 0, 2]]))
    with pytest.raises(SceneFormatError, match=r"cameras\.json: field 'cameras\[1\]\.R'.*rotation"):
        load_scene(bad)
    shutil.rmtree(bad)
    shutil.copytree(root, bad)
    _edit(bad, "cameras.json", lambda d: d[0].update(K=[[1, 0], [0, 1]]))
    with pytest.raises(SceneFormatError, match=r"field 'cameras\[0\]\.K': expected shape \(3, 3\)"):
        load_scene(bad)
    shutil.rmtree(bad)
    shutil.copytree(root, bad)
    (bad / "detections.npz").unlink()
    with pytest.raises(SceneFormatError, match=r"detections\.npz: file not found"):
        load_scene(bad)
    with pytest.raises(SceneFormatError, match="scene.json: file not found"):
        load_scene(tmp_path / "nowhere")


def test_view_names_map_onto_the_rig_and_unknown_cameras_fail(tmp_path):
    root = _write_small(tmp_path)
    with np.load(root / "detections.npz") as z:
        arrays = {k: z[k] for k in z.files}
    arrays["view_names"] = np.array(["2", "0"])
    arrays["view"] = np.array([0, 0, 1, 1])
    np.savez(root / "detections.npz", **arrays)
    s = load_scene(root)
    assert s.detections.view.tolist() == [2, 2, 0, 0]
    arrays["view_names"] = np.array(["2", "cam9"])
    np.savez(root / "detections.npz", **arrays)
    with pytest.raises(SceneFormatError, match=r"field 'view_names'.*cam9"):
        load_scene(root)


def test_overwrite_replaces_whole_scene(tmp_path):
    root = _write_small(tmp_path)
    with pytest.raises(FileExistsError):
        _write_small(tmp_path)
    rig = campus_rig()
    write_scene(
        root,
        name="again",
        fps=30,
        num_frames=1,
        joint_set=COCO17,
        rig=rig,
        detections=Detections(
            frame=np.zeros(0, int), view=np.zeros(0, int), keypoints=np.zeros((0, 17, 3))
        ),
        overwrite=True,
    )
    s = load_scene(root)
    assert s.name == "again" and len(s.detections) == 0
