"""The native scene format: reading, writing atomically, and errors that name file and field."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from pipeline.core.files import SceneFormatError
from pipeline.data.joint_sets import COCO17
from pipeline.data.scene import Detections, load_scene, write_scene
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


def test_scores_above_one_are_a_scene(tmp_path):
    kp = np.full((4, 17, 3), 0.5)
    kp[1, 3, 2] = 1.3  # a detector's score, not a probability
    s = load_scene(_write_small(tmp_path, keypoints=kp))
    assert s.detections.keypoints[1, 3, 2] == 1.3


def test_bad_values_are_refused_and_nothing_is_written(tmp_path):
    kp = np.full((4, 17, 3), 0.5)
    kp[1, 3, 2] = np.nan
    with pytest.raises(SceneFormatError, match=r"detections\.npz: field 'keypoints\[\.\.\., 2\]'"):
        _write_small(tmp_path, keypoints=kp)
    kp[1, 3, 2] = -0.2
    with pytest.raises(SceneFormatError, match=r"expected confidence >= 0"):
        _write_small(tmp_path, keypoints=kp)
    kp[1, 3, 2] = np.inf
    with pytest.raises(SceneFormatError, match=r"NaN or infinite"):
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


@pytest.mark.parametrize("layout", ["detections.npz", "detections"])
def test_monocular_columns_are_checked_in_blocks_naming_the_field(tmp_path, monkeypatch, layout):
    """The SMPL columns are checked a block of rows at a time (a long scene's stay mapped);
    a bad row in a later block is still refused, naming the field, and nothing is written."""
    import pipeline.data.scene as scene_mod

    monkeypatch.setattr(scene_mod, "CHECK_ROWS", 3)
    n = 8
    kp = np.random.default_rng(1).uniform(10, 200, (n, 17, 3))
    kp[..., 2] = 0.9
    good = dict(
        frame=np.repeat(np.arange(4), 2), view=np.tile([0, 1], 4), keypoints=kp,
        smpl_pose=np.zeros((n, 72)), smpl_betas=np.zeros((n, 10)),
        cam_weak=np.tile([1.0, 0.0, 0.0], (n, 1)), bbox=np.tile([0.0, 0.0, 50.0, 80.0], (n, 1)),
    )  # fmt: skip

    def write(name, **bad):
        cols = {k: v.copy() for k, v in good.items()}
        for k, (row, value) in bad.items():
            cols[k][row] = value
        return write_scene(
            tmp_path / name, name="m", fps=25, num_frames=4, joint_set=COCO17, rig=campus_rig(),
            detections=Detections(**cols), detections_file=layout,
        )  # fmt: skip

    assert len(load_scene(write("ok")).detections) == n
    cases = [
        ("smpl_betas", dict(smpl_betas=(7, np.nan)), "NaN in a row whose smpl_pose"),
        ("bbox", dict(bbox=(6, [0.0, 0.0, -1.0, 80.0])), r"x1 > x0"),
    ]
    for field, bad, says in cases:
        with pytest.raises(SceneFormatError, match=rf"field '{field}'.*{says}"):
            write(f"bad_{field}", **bad)
        assert not (tmp_path / f"bad_{field}").exists()
    # a row without its SMPL pose may carry NaN in the rest of the group
    out = write("gap", smpl_pose=(7, np.nan), smpl_betas=(7, np.nan))
    assert np.isnan(load_scene(out).detections.smpl_betas[7]).all()
