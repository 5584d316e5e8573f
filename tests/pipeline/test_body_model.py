"""Body model: LBS identities on a tiny model and on the shipped open model."""

from __future__ import annotations

import pickle
import sys
import types

import numpy as np
import pytest
import torch

from pipeline.body.model import (
    DEFAULT_MODEL_PATH,
    BodyModel,
    forward_kinematics,
    forward_kinematics_components,
    load_body_model,
    load_body_model_arrays,
)
from pipeline.core.files import SceneFormatError
from pipeline.core.rotations import axis_angle_to_matrix
from pipeline.data.joint_sets import SMPL24

torch.manual_seed(0)


def random_pose(batch: int, scale: float = 0.4, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.randn(batch, 24, 3, generator=g) * scale


def test_axis_angle_to_matrix_matches_cv2_rodrigues():
    import cv2

    rv = np.random.default_rng(1).normal(0, 1.5, (20, 3))
    rv[0] = 0
    rv[1] = 1e-7
    R = axis_angle_to_matrix(torch.tensor(rv, dtype=torch.float64)).numpy()
    for r, M in zip(rv, R, strict=True):
        np.testing.assert_allclose(M, cv2.Rodrigues(r)[0], atol=1e-12)


def test_zero_pose_gives_template(tiny_model_arrays):
    m = BodyModel(tiny_model_arrays)
    out = m(torch.zeros(2, 72), torch.zeros(2, 10))
    np.testing.assert_allclose(out.vertices[0].numpy(), tiny_model_arrays["v_template"], atol=1e-6)


def test_joints_only_path_equals_regressed_vertices_on_rigid_model(tiny_model_arrays):
    # In the tiny model every joint's regressor vertices are rigid with that joint,
    # so FK joints and J_regressor @ posed vertices must agree exactly.
    m = BodyModel(tiny_model_arrays)
    pose, betas = random_pose(5), torch.randn(5, 10)
    transl = torch.randn(5, 3)
    out = m(pose, betas, transl)
    regressed = torch.einsum("jv,nvc->njc", m.J_regressor, out.vertices)
    fk = m.joints(pose, betas, transl)
    assert (fk - out.joints).abs().max() < 1e-6
    assert (fk - regressed).abs().max() < 1e-5


def test_rotating_one_joint_moves_only_its_descendants(tiny_model_arrays):
    m = BodyModel(tiny_model_arrays)
    base = random_pose(1, seed=3)
    moved = base.clone()
    elbow = SMPL24.index["left_elbow"]
    moved[0, elbow] += torch.tensor([0.0, 0.8, 0.3])
    j0, j1 = m.joints(base)[0], m.joints(moved)[0]
    changed = set(torch.nonzero((j0 - j1).norm(dim=-1) > 1e-6).flatten().tolist())
    # The elbow itself is the rotation centre: only wrist and hand move.
    assert changed == {SMPL24.index["left_wrist"], SMPL24.index["left_hand"]}


def test_pkl_and_npz_loaders_agree(tmp_path, tiny_model_arrays):
    np.savez(tmp_path / "m.npz", **tiny_model_arrays)

    # A SMPL .pkl stores some arrays as chumpy objects and J_regressor as scipy.sparse;
    # fake a chumpy module while pickling so the file needs chumpy to load naively.
    import scipy.sparse

    fake = types.ModuleType("chumpy")
    fake_ch = types.ModuleType("chumpy.ch")

    class Ch:
        def __init__(self, x):
            self.x = x

        def __getstate__(self):
            return {"x": self.x}

    Ch.__module__ = "chumpy.ch"
    Ch.__qualname__ = "Ch"
    fake_ch.Ch = Ch
    sys.modules["chumpy"], sys.modules["chumpy.ch"] = fake, fake_ch
    try:
        d = dict(tiny_model_arrays)
        d["shapedirs"] = Ch(d["shapedirs"])
        d["J_regressor"] = scipy.sparse.csc_matrix(d["J_regressor"])
        with open(tmp_path / "m.pkl", "wb") as fh:
            pickle.dump(d, fh, protocol=2)
    finally:
        del sys.modules["chumpy"], sys.modules["chumpy.ch"]

    a = load_body_model_arrays(tmp_path / "m.npz")
    b = load_body_model_arrays(tmp_path / "m.pkl")
    for k in ("v_template", "shapedirs", "J_regressor", "weights", "faces"):
        np.testing.assert_allclose(a[k], b[k])
    pose = random_pose(3)
    ma, mb = BodyModel(a), BodyModel(b)
    assert (ma(pose).vertices - mb(pose).vertices).abs().max() < 1e-6


class _Evil:
    """Pickles as a call of os.system: loading it naively runs a shell command."""

    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        import os

        return (os.system, (f"touch {self.marker}",))


def test_a_model_pickle_cannot_run_code(tmp_path, tiny_model_arrays):
    marker = tmp_path / "pwned"
    for payload in (_Evil(marker), {"v_template": _Evil(marker)}):
        path = tmp_path / "evil.pkl"
        path.write_bytes(pickle.dumps(payload, protocol=2))
        with pytest.raises(SceneFormatError, match=r"evil\.pkl.*(posix|os|nt)\.system"):
            load_body_model_arrays(path)
        assert not marker.exists()
    # eval by name, protocol 0 text pickle
    path.write_bytes(b"cbuiltins\neval\n(S'1+1'\ntR.")
    with pytest.raises(SceneFormatError, match=r"builtins\.eval"):
        load_body_model_arrays(path)


def test_bad_model_file_names_the_field(tmp_path, tiny_model_arrays):
    d = dict(tiny_model_arrays)
    d["weights"] = d["weights"][:, :20]
    np.savez(tmp_path / "bad.npz", **d)
    with pytest.raises(SceneFormatError, match=r"bad\.npz: field 'weights'"):
        BodyModel(load_body_model_arrays(tmp_path / "bad.npz"), source=str(tmp_path / "bad.npz"))
    with pytest.raises(SceneFormatError, match="not found"):
        load_body_model_arrays(tmp_path / "missing.npz")


def test_env_var_selects_model(tmp_path, tiny_model_arrays, monkeypatch):
    np.savez(tmp_path / "licensed.npz", **tiny_model_arrays)
    monkeypatch.setenv("MVVIZ_SMPL_MODEL", str(tmp_path / "licensed.npz"))
    assert load_body_model().num_vertices == tiny_model_arrays["v_template"].shape[0]


# ---------------------------------------------------------------- the shipped open model


@pytest.fixture(scope="module")
def open_model() -> BodyModel:
    return load_body_model(DEFAULT_MODEL_PATH)


def test_open_model_layout(open_model):
    assert open_model.num_vertices > 5000
    assert open_model.joint_names == list(SMPL24.names)
    assert open_model.coco_regressor.shape == (17, open_model.num_vertices)
    np.testing.assert_allclose(open_model.weights.sum(1).numpy(), 1, atol=1e-4)


def test_open_model_zero_pose_is_template_t_pose(open_model):
    out = open_model(torch.zeros(1, 72))
    np.testing.assert_allclose(out.vertices[0].numpy(), open_model.v_template.numpy(), atol=1e-6)
    j = out.joints[0].numpy()
    ix = SMPL24.index
    assert j[ix["left_wrist"], 0] > 0.45 and j[ix["right_wrist"], 0] < -0.45  # arms along +-x
    assert abs(j[ix["left_wrist"], 1] - j[ix["left_shoulder"], 1]) < 0.08  # horizontal
    assert j[ix["head"], 1] - j[ix["left_ankle"], 1] > 1.2  # y up
    nose = open_model.coco_keypoints(out.vertices)[0, 0].numpy()
    assert nose[2] > j[ix["head"], 2] + 0.03  # facing +z


def test_forward_kinematics_equals_the_chain_of_matrix_products(open_model):
    # The level-by-level, component-major composition against the textbook chain: each
    # joint's global rotation is its parent's times its own, its position the parent's
    # plus the parent's rotation of the rest offset (float64, so the two agree to 1e-12).
    R = axis_angle_to_matrix(random_pose(7, scale=0.8, seed=11)).double().requires_grad_(True)
    rest = (torch.randn(7, 24, 3, dtype=torch.float64) * 0.2).requires_grad_(True)
    parents = open_model.tree.parents
    glob, pos = [None] * 24, [None] * 24
    for j in range(24):  # SMPL's parents come before their children
        p = int(parents[j])
        if p < 0:
            glob[j], pos[j] = R[:, j], rest[:, j]
            continue
        glob[j] = glob[p] @ R[:, j]
        pos[j] = pos[p] + (glob[p] @ (rest[:, j] - rest[:, p])[..., None])[..., 0]
    want_g, want_p = torch.stack(glob, 1), torch.stack(pos, 1)
    got_g, got_p = forward_kinematics(R, rest, open_model.tree)
    assert got_g.shape == (7, 24, 3, 3) and got_p.shape == (7, 24, 3)
    assert float((got_g - want_g).abs().max()) < 1e-12
    assert float((got_p - want_p).abs().max()) < 1e-12
    comp_g, comp_p = forward_kinematics_components(R, rest, open_model.tree)
    assert comp_g.is_contiguous() and comp_g.shape == (3, 3, 24, 7)
    assert torch.equal(comp_g.permute(3, 2, 0, 1), got_g)
    assert torch.equal(comp_p.permute(2, 1, 0), got_p)
    # and the gradients (a weighted sum of both outputs)
    wg, wp = torch.randn_like(want_g), torch.randn_like(want_p)
    pairs = ((want_g, want_p), forward_kinematics(R, rest, open_model.tree))
    grads = [torch.autograd.grad((g * wg).sum() + (q * wp).sum(), (R, rest)) for g, q in pairs]
    for a, b in zip(*grads, strict=True):
        assert float((a - b).abs().max()) < 1e-11


def test_open_model_fk_close_to_regressed_posed_vertices(open_model):
    pose = random_pose(8, scale=0.3, seed=5)
    pose[:, 0] = 0
    betas = torch.randn(8, 10)
    out = open_model(pose, betas)
    regressed = torch.einsum("jv,nvc->njc", open_model.J_regressor, out.vertices)
    err_mm = (regressed - open_model.joints(pose, betas)).norm(dim=-1) * 1000
    # Exact at rest; under pose LBS blends near joints, so the two agree to a few mm.
    assert err_mm.mean() < 10.0, err_mm.mean()
    rest = open_model(torch.zeros(2, 72), betas[:2])
    reg_rest = torch.einsum("jv,nvc->njc", open_model.J_regressor, rest.vertices)
    assert (reg_rest - rest.joints).abs().max() < 1e-5


def test_open_model_first_shape_direction_changes_height(open_model):
    heights = []
    for b0 in (-2.0, 0.0, 2.0):
        betas = torch.zeros(1, 10)
        betas[0, 0] = b0
        v = open_model(torch.zeros(1, 72), betas).vertices[0]
        heights.append(float(v[:, 1].max() - v[:, 1].min()))
    assert heights[0] < heights[1] < heights[2]
    assert heights[2] - heights[0] > 0.15  # at least 15 cm across +-2 sd
    assert 1.4 < heights[0] and heights[2] < 2.1


def test_open_model_bending_knee_moves_only_leg_below(open_model):
    pose = torch.zeros(1, 24, 3)
    pose[0, SMPL24.index["left_knee"], 0] = 1.4
    v0 = open_model(torch.zeros(1, 72)).vertices[0]
    v1 = open_model(pose).vertices[0]
    moved = (v1 - v0).norm(dim=-1) > 1e-4
    ankle_w = open_model.weights[
        :, [SMPL24.index[n] for n in ("left_knee", "left_ankle", "left_foot")]
    ]
    # Every vertex that moved is skinned (at least partly) to the lower left leg.
    assert bool((ankle_w[moved].sum(1) > 0.0).all())
    # And the shin swung backwards (-z) while the head stayed put.
    ankle = open_model.joints(pose)[0, SMPL24.index["left_ankle"]]
    assert ankle[2] < -0.2
