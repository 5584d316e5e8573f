"""``mvviz export`` on the tiny viewer scene: every format written, clear refusals."""

from __future__ import annotations

import numpy as np

from mvviz.cli import main
from pipeline.importers.trc import read_trc


def test_export_every_format(viewer_scene, tmp_path, capsys):
    scene, results, _ = viewer_scene
    root = str(scene.root)
    assert main(["export", root, "--format", "trc", "-o", str(tmp_path / "r.trc")]) == 0
    out = capsys.readouterr().out
    assert "reused cached results" in out and "r.trc" in out
    trc = read_trc(tmp_path / "r.trc")
    assert trc.num_frames == results.num_frames and trc.data_rate == scene.fps
    args = ["export", root, "--format", "c3d", "--per-track", "-o", str(tmp_path / "p.c3d")]
    assert main(args) == 0
    assert sorted(p.name for p in tmp_path.glob("p_track*.c3d")) == [
        f"p_track{k}.c3d" for k in range(results.num_tracks)
    ]  # fmt: skip
    assert (
        main(["export", root, "--format", "bvh", "--track", "0", "-o", str(tmp_path / "a.bvh")])
        == 0
    )
    assert (tmp_path / "a.bvh").read_text().startswith("HIERARCHY")
    args = [
        "export",
        root,
        "--format",
        "smpl-npz",
        "--stage",
        "smpl",
        "-o",
        str(tmp_path / "b.npz"),
    ]
    assert main(args) == 0
    z = np.load(tmp_path / "b_track0.npz")
    assert z["poses"].shape[1] == 72 and str(z["stage"]) == "smpl"
    assert main(["export", root, "--format", "glb", "-o", str(tmp_path / "all.glb")]) == 0
    assert (tmp_path / "all.glb").read_bytes()[:4] == b"glTF"


def test_export_refusals_are_one_line_and_exit_2(viewer_scene, tmp_path, capsys):
    scene, results, _ = viewer_scene
    root = str(scene.root)
    out = str(tmp_path / "x.bvh")
    assert main(["export", root, "--format", "bvh", "--stage", "kalman", "-o", out]) == 2
    err = capsys.readouterr().err.strip()
    assert err == (
        "mvviz export: error: bvh holds fitted bodies: --stage must be one of smpl, "
        "smpl_vae, not 'kalman'"
    )
    assert main(["export", root, "--format", "trc", "--track", "99", "-o", out]) == 2
    assert "track 99 does not exist" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []
