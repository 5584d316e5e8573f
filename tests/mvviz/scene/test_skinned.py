"""mvviz.scene.skinned: bulk bone posing sends what viser's per-bone setters send."""

from __future__ import annotations

import numpy as np
import pytest
import viser
import viser.transforms as vtf

from mvviz.scene.skinned import POSITION_DECIMALS, WXYZ_DECIMALS, BonePoser, fast_path_available
from tests.mvviz.conftest import free_port

B = 5


@pytest.fixture
def server():
    srv = viser.ViserServer(host="127.0.0.1", port=free_port(), verbose=False)
    queued = []
    ws = srv._websock_server
    orig = ws.queue_message

    def tap(message) -> None:
        queued.append(message)
        orig(message)

    ws.queue_message = tap
    srv.queued = queued
    yield srv
    srv.stop()


def add_mesh(server: viser.ViserServer, name: str) -> viser.MeshSkinnedHandle:
    rng = np.random.default_rng(0)
    verts = rng.normal(size=(12, 3)).astype(np.float32)
    faces = np.array([[0, 1, 2], [3, 4, 5], [6, 7, 8], [9, 10, 11]], np.uint32)
    weights = rng.random((12, B)).astype(np.float32)
    weights /= weights.sum(1, keepdims=True)
    return server.scene.add_mesh_skinned(
        name, verts, faces, bone_wxyzs=np.tile([1.0, 0, 0, 0], (B, 1)),
        bone_positions=np.arange(B * 3, dtype=float).reshape(B, 3) * 0.1, skin_weights=weights,
    )  # fmt: skip


def random_pose(seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    q = vtf.SO3.exp(rng.normal(size=(B, 3))).wxyz
    return q, rng.normal(size=(B, 3))


def bone_messages(server, name: str) -> list[tuple]:
    """(kind, bone, values) of the bone messages queued for ``name``, in order."""
    out = []
    for m in server.queued:
        if type(m).__name__.startswith("SetBone") and m.name == name:
            values = m.wxyz if hasattr(m, "wxyz") else m.position
            out.append((type(m).__name__, m.bone_index, tuple(values), m.owner))
    return out


def test_bulk_path_is_used_on_the_installed_viser(server):
    mesh = add_mesh(server, "/a")
    assert fast_path_available(mesh)
    assert BonePoser(mesh).fast


def test_bulk_and_public_setters_send_the_same_messages(server):
    fast, slow = add_mesh(server, "/fast"), add_mesh(server, "/slow")
    pf, ps = BonePoser(fast, fast=True), BonePoser(slow, fast=False)
    for seed in range(3):
        q, p = random_pose(seed)
        assert pf.pose(q, p) == ps.pose(q, p) == 2 * B
    mf, ms = bone_messages(server, "/fast"), bone_messages(server, "/slow")
    assert len(mf) == 3 * 2 * B
    assert mf == ms  # same kinds, bones, values and owner, in the same order
    # the handles read back what was sent (the public API stays coherent)
    q, p = random_pose(2)
    for i, bone in enumerate(fast.bones):
        np.testing.assert_allclose(bone.wxyz, np.round(q[i], WXYZ_DECIMALS))
        np.testing.assert_allclose(bone.position, np.round(p[i], POSITION_DECIMALS))
        np.testing.assert_array_equal(bone.wxyz, slow.bones[i].wxyz)


def test_only_moved_bones_are_sent(server):
    mesh = add_mesh(server, "/m")
    poser = BonePoser(mesh)
    q, p = random_pose(0)
    q, p = np.round(q, WXYZ_DECIMALS), np.round(p, POSITION_DECIMALS)  # on the grid
    assert poser.pose(q, p) == 2 * B
    assert poser.pose(q, p) == 0  # unchanged
    assert poser.pose(q + 1e-6, p - 1e-6) == 0  # below the rounding: not re-sent
    q2, p2 = q.copy(), p.copy()
    q2[3] = vtf.SO3.exp(np.array([0.3, 0.0, 0.0])).wxyz
    p2[1, 2] += 0.01  # 1 cm
    server.queued.clear()
    assert poser.pose(q2, p2) == 2
    sent = bone_messages(server, "/m")
    assert [(k, i) for k, i, _, _ in sent] == [
        ("SetBoneOrientationMessage", 3),
        ("SetBonePositionMessage", 1),
    ]
    # a setter used alongside sees the poser's state (no redundant message)
    server.queued.clear()
    mesh.bones[3].wxyz = np.round(q2[3], WXYZ_DECIMALS)
    assert bone_messages(server, "/m") == []


def test_rounding_error_is_below_a_hundredth_of_a_degree_and_half_a_mm(server):
    mesh = add_mesh(server, "/r")
    q, p = random_pose(5)
    BonePoser(mesh).pose(q, p)
    sent = np.array([b.wxyz for b in mesh.bones])
    sent /= np.linalg.norm(sent, axis=1, keepdims=True)
    angle = 2 * np.degrees(np.arccos(np.clip(np.abs((sent * q).sum(1)), 0, 1)))
    assert angle.max() < 0.01
    assert np.abs(np.array([b.position for b in mesh.bones]) - p).max() <= 0.5e-3 + 1e-12


def test_bad_poses_and_removed_meshes_are_refused(server):
    mesh = add_mesh(server, "/x")
    poser = BonePoser(mesh)
    q, p = random_pose(1)
    q[2, 0] = np.nan
    with pytest.raises(ValueError, match="/x: bone poses must be finite"):
        poser.pose(q, p)
    with pytest.raises(ValueError):
        poser.pose(q[:3], p)  # wrong number of bones
    mesh.remove()
    with pytest.raises(RuntimeError, match="removed"):
        poser.pose(*random_pose(2))
