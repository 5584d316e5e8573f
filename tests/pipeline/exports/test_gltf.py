"""GLB: trimesh loads it; an independent evaluator of its nodes, skins and animation
(the glTF 2.0 skinning equations) gives the fitted vertices back."""

from __future__ import annotations

import numpy as np
import trimesh
from scipy.spatial.transform import Rotation

from pipeline.exports import export_results
from pipeline.exports.common import WORLD_TO_Y_UP
from pipeline.exports.gltf import accessor_array, read_glb, write_glb
from tests.pipeline.exports.conftest import synthetic_fit


def _trs(node: dict) -> np.ndarray:
    m = np.eye(4)
    s = np.asarray(node.get("scale", [1, 1, 1]), float)
    m[:3, :3] = Rotation.from_quat(node.get("rotation", [0, 0, 0, 1])).as_matrix() * s
    m[:3, 3] = node.get("translation", [0, 0, 0])
    return m


def posed_meshes(doc: dict, blob: bytes, frame: int) -> dict[str, np.ndarray]:
    """Mesh node name -> (V, 3) skinned vertices at keyframe ``frame`` (glTF axes)."""
    nodes = [dict(n) for n in doc["nodes"]]
    for anim in doc.get("animations", []):
        for ch in anim["channels"]:
            s = anim["samplers"][ch["sampler"]]
            nodes[ch["target"]["node"]][ch["target"]["path"]] = accessor_array(
                doc, blob, s["output"]
            )[frame].tolist()
    world = [None] * len(nodes)

    def walk(i, parent):
        world[i] = parent @ _trs(nodes[i])
        for c in nodes[i].get("children", []):
            walk(c, world[i])

    for r in doc["scenes"][doc["scene"]]["nodes"]:
        walk(r, np.eye(4))
    out = {}
    for n in nodes:
        if "skin" not in n:
            continue
        skin = doc["skins"][n["skin"]]
        ibm = accessor_array(doc, blob, skin["inverseBindMatrices"]).reshape(-1, 4, 4)
        ibm = np.transpose(ibm, (0, 2, 1))  # column-major
        mats = np.stack([world[j] for j in skin["joints"]]) @ ibm  # (J, 4, 4)
        prim = doc["meshes"][n["mesh"]]["primitives"][0]
        a = {k: accessor_array(doc, blob, v) for k, v in prim["attributes"].items()}
        v = np.c_[a["POSITION"].astype(float), np.ones(len(a["POSITION"]))]
        acc = np.zeros_like(v)
        for js, ws in (("JOINTS_0", "WEIGHTS_0"), ("JOINTS_1", "WEIGHTS_1")):
            for c in range(4):
                m = mats[a[js][:, c]]  # (V, 4, 4)
                acc += a[ws][:, c, None] * np.einsum("vab,vb->va", m, v)
        out[n["name"]] = acc[:, :3]
    return out


def test_glb_round_trip_of_the_vertices(fitted_run, tmp_path):
    scene, res = fitted_run
    fit = res.smpl_vae
    [f] = export_results(res, "glb", tmp_path / "run.glb", fps=scene.fps)
    doc, blob = read_glb(f.path)
    assert doc["asset"]["version"] == "2.0" and len(doc["skins"]) == 2
    times = accessor_array(doc, blob, doc["animations"][0]["samplers"][0]["input"])
    np.testing.assert_allclose(times, np.arange(res.num_frames) / scene.fps, atol=1e-6)
    worst = 0.0
    for frame in (0, 5, res.num_frames - 1):
        posed = posed_meshes(doc, blob, frame)
        for k in range(2):
            want = fit.vertices(k, frame) / 1000.0 @ WORLD_TO_Y_UP.T
            err = np.linalg.norm(posed[f"track{k}_body"] - want, axis=-1)
            worst = max(worst, err.max())
            assert np.median(err) < 1e-5  # float32 storage
    # 8 influences per vertex of the model's up to 10: the few truncated vertices move
    assert worst < 2e-3, worst


def test_glb_loads_in_trimesh_with_one_coloured_body_per_track(fitted_run, model, tmp_path):
    scene, res = fitted_run
    [f] = export_results(res, "glb", tmp_path / "run.glb", fps=scene.fps)
    loaded = trimesh.load(f.path)
    assert isinstance(loaded, trimesh.Scene)
    bodies = list(loaded.geometry.values())
    assert len(bodies) == 2
    for b in bodies:
        assert len(b.vertices) == model.num_vertices and len(b.faces) == len(model.faces)
        assert 1.2 < b.extents[1] < 2.2  # a standing rest body, y up, metres
    colours = {tuple(np.round(b.visual.material.baseColorFactor[:3])) for b in bodies}
    assert len(colours) == 2


def test_glb_hides_a_track_outside_its_span_and_holds_gaps(gappy_results, fitted_run, tmp_path):
    scene, _ = fitted_run
    fit = gappy_results.smpl_vae
    [f] = export_results(gappy_results, "glb", tmp_path / "g.glb", fps=scene.fps)
    assert any("hidden (scale 0) outside frames 2-10" in n for n in f.notes)
    assert any("2 frames without a body" in n for n in f.notes)
    doc, blob = read_glb(f.path)
    track1 = next(n for n in doc["nodes"] if n["name"] == "track1")
    assert track1["extras"]["held_frames"] == [5, 6]
    scale = [s for s in doc["animations"][0]["samplers"] if s["interpolation"] == "STEP"]
    assert len(scale) == 1
    collapsed = posed_meshes(doc, blob, 0)["track1_body"]
    assert np.ptp(collapsed, axis=0).max() < 1e-9  # scale 0: nothing drawn
    held = posed_meshes(doc, blob, 5)["track1_body"]
    want = fit.vertices(1, 4) / 1000.0 @ WORLD_TO_Y_UP.T
    assert np.median(np.linalg.norm(held - want, axis=-1)) < 1e-5


def test_glb_of_large_rotations(model, tmp_path):
    fit = synthetic_fit(model, num_frames=3, scale=2.5, seed=2)
    write_glb(tmp_path / "t.glb", fit, [0, 1], fps=30.0)
    doc, blob = read_glb(tmp_path / "t.glb")
    for frame in range(3):
        posed = posed_meshes(doc, blob, frame)
        for k in range(2):
            want = fit.vertices(k, frame) / 1000.0 @ WORLD_TO_Y_UP.T
            err = np.linalg.norm(posed[f"track{k}_body"] - want, axis=-1)
            assert np.median(err) < 1e-5 and np.percentile(err, 99) < 1e-4
