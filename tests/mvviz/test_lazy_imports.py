"""Time to a usable page: the viewer's entry module, a cached results file with SMPL fits
and the viewer's state (skinned ground-truth and fitted bodies) load without torch or
matplotlib (~3-7 s and ~0.5 s of imports here); torch loads only when a fit runs,
matplotlib with the first plot."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh

from mvviz.scene.layers import icosphere
from pipeline.results.store import default_results_path

REPO = Path(__file__).resolve().parents[2]

PROBE = """
import json, sys
import mvviz.cli.view  # the entry module of app.py and mvviz view
from mvviz.app import ViewerApp  # what it imports once the server is up
from mvviz.state import ViewerState
from pipeline.body.arrays import load_body_model_data
from pipeline.results.store import load_results
from pipeline.data.scene import load_scene

model = load_body_model_data()
results = load_results(sys.argv[1], model=model)
state = ViewerState.create(load_scene(sys.argv[2]), results, model)
print(json.dumps({
    "torch": "torch" in sys.modules, "matplotlib": "matplotlib" in sys.modules,
    "trimesh": "trimesh" in sys.modules,
    "fits": results.smpl is not None, "gt_bodies": state.data.bodies is not None,
    "fit_bodies": state.data.fit_bodies is not None,
    "vertices": int(state.data.fit_bodies.vertices.shape[1]),
}))
"""


@pytest.mark.slow
def test_viewer_and_cached_results_load_without_torch_or_matplotlib(viewer_scene):
    scene, results, model = viewer_scene
    path = default_results_path(scene)
    assert path.is_file() and results.smpl is not None  # cached, with fits
    # a fresh interpreter, so that other tests' imports do not leak in
    out = subprocess.run(
        [sys.executable, "-c", PROBE, str(path), str(scene.root)],
        cwd=REPO, capture_output=True, text=True, timeout=300, check=True,
    )  # fmt: skip
    got = json.loads(out.stdout.strip().splitlines()[-1])
    assert got["fits"] and got["gt_bodies"] and got["fit_bodies"], got  # meshes prepared
    assert got["vertices"] == model.num_vertices
    assert not got["torch"], "the viewer or loading cached results imported torch"
    assert not got["matplotlib"], "the viewer or loading cached results imported matplotlib"
    assert not got["trimesh"], "the viewer imported trimesh (~0.5 s)"


def test_icosphere_is_trimesh_s():
    """The joint marker made without trimesh is trimesh's subdivided icosahedron."""
    v, f = icosphere(0.025)
    ours = trimesh.Trimesh(v, f, process=False)
    theirs = trimesh.creation.icosphere(subdivisions=1, radius=0.025)
    assert v.shape == (42, 3) and f.shape == (80, 3)
    assert ours.is_watertight and ours.is_winding_consistent
    assert ours.volume > 0  # faces wound outwards
    assert abs(ours.volume - theirs.volume) < 1e-6 * theirs.volume
    np.testing.assert_allclose(np.linalg.norm(v, axis=1), 0.025, rtol=1e-6)


@pytest.mark.slow
def test_a_command_line_imports_only_its_subcommand():
    """``mvviz view`` builds its own parser only: the other subcommands' modules would
    bring ray, torch and matplotlib (~12 s) before the server starts."""
    probe = (
        "import sys; from mvviz.cli import build_parser; "
        "args = build_parser(sys.argv[1:]).parse_args(sys.argv[1:]); "
        "print(args.command, *[m for m in ('ray', 'torch', 'matplotlib') if m in sys.modules])"
    )
    out = subprocess.run(
        [sys.executable, "-c", probe, "view", "sample_data/shelf_synth"],
        cwd=REPO, capture_output=True, text=True, timeout=120, check=True,
    )  # fmt: skip
    assert out.stdout.split() == ["view"], out.stdout
    # no command named: every subcommand is there (mvviz --help lists them all)
    full = subprocess.run(
        [sys.executable, "-m", "mvviz.cli", "--help"],
        cwd=REPO, capture_output=True, text=True, timeout=300, check=True,
    )  # fmt: skip
    for name in ("view", "export-rrd", "batch", "run", "eval", "train-prior"):
        assert name in full.stdout


def test_calibrate_runs_without_torch(tmp_path):
    """``mvviz calibrate`` needs no torch (~3 s to import): not at its start (the
    importers it reads --intrinsics with), not in the whole run; matplotlib only when
    the report is drawn."""
    from tests.pipeline.calibrate_synth import SPEC, board_poses, default_rig, write_session

    folders = write_session(tmp_path / "footage", default_rig().subset([0, 1]),
                            board_poses(12, seed=2))  # fmt: skip
    probe = (
        "import sys; from mvviz.cli import build_parser, main; "
        "build_parser(sys.argv[1:]).parse_args(sys.argv[1:]); "
        "print('start', *[m for m in ('torch', 'matplotlib') if m in sys.modules]); "
        "code = main(sys.argv[1:]); "
        "print('end', code, *[m for m in ('torch',) if m in sys.modules])"
    )
    out = subprocess.run(
        [sys.executable, "-c", probe, "calibrate", *map(str, folders), "--board", SPEC,
         "-o", str(tmp_path / "out")],
        cwd=REPO, capture_output=True, text=True, timeout=300, check=True,
    )  # fmt: skip
    lines = [ln for ln in out.stdout.splitlines() if ln.startswith(("start", "end"))]
    assert lines == ["start", "end 0"], out.stdout
