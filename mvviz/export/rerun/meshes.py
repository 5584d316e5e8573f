"""Display meshes of a body model: decimation that keeps skinning exact, and skinning
of the kept vertices only (GT meshes and fitted bodies, see :mod:`mvviz.export.rerun`)."""

from __future__ import annotations

import numpy as np
import torch

from mvviz.export.rerun.layout import MM_TO_M
from pipeline.body.model import BodyModel, rigid_chain, scale_bones
from pipeline.core.rotations import axis_angle_to_matrix


def decimate_mesh(
    rest_vertices: np.ndarray, faces: np.ndarray, weights: np.ndarray, cell: float
) -> tuple[np.ndarray, np.ndarray]:
    """Vertex clustering that keeps skinning exact: a subset of the mesh's own vertices.

    Vertices are grouped by (grid cell of size ``cell`` in the rest pose, dominant
    skinning joint), so parts that touch at rest but move apart (arm and torso) never
    merge; each group keeps the vertex nearest its mean, faces are re-indexed and the
    collapsed ones dropped. Posing the kept vertices equals decimating the posed mesh.

    Args:
        rest_vertices: (num_vertices, 3) rest pose, in the unit of ``cell``.
        faces: (num_faces, 3); weights: (num_vertices, num_joints) skinning weights.
    Returns:
        keep: (num_kept,) indices of the kept vertices; faces: (num_kept_faces, 3) into them.
    """
    rest = np.asarray(rest_vertices, float)
    key = np.column_stack([np.floor(rest / cell).astype(np.int64), np.argmax(weights, 1)])
    _, group = np.unique(key, axis=0, return_inverse=True)
    group = group.ravel()
    n = int(group.max()) + 1
    mean = np.zeros((n, 3))
    np.add.at(mean, group, rest)
    mean /= np.bincount(group, minlength=n)[:, None]
    dist = np.linalg.norm(rest - mean[group], axis=1)
    order = np.lexsort((dist, group))  # by group, nearest to the mean first
    keep = order[np.unique(group[order], return_index=True)[1]]
    f = group[np.asarray(faces)]
    f = f[(f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])]
    _, first = np.unique(np.sort(f, 1), axis=0, return_index=True)
    return keep, f[np.sort(first)]


def display_mesh(body_model: BodyModel, cell_mm: float | None) -> tuple[np.ndarray, np.ndarray]:
    """``(keep, faces)`` of ``body_model``'s mesh decimated by :func:`decimate_mesh` at
    ``cell_mm`` (None: every vertex): kept vertex indices, uint32 faces into them."""
    faces = body_model.faces.cpu().numpy()
    keep = np.arange(body_model.num_vertices)
    if cell_mm:
        keep, faces = decimate_mesh(
            body_model.v_template.cpu().numpy(),
            faces,
            body_model.weights.cpu().numpy(),
            cell_mm * MM_TO_M,
        )
    return keep, faces.astype(np.uint32)


def skin_subset(
    body_model: BodyModel,
    pose: np.ndarray,
    betas: np.ndarray,
    keep: np.ndarray,
    bone_scales: np.ndarray | None = None,
) -> np.ndarray:
    """Linear blend skinning of the vertices ``keep`` only (the model's forward skins all).

    Args:
        pose: (B, 72) axis-angle; betas: (B, <=num_betas); keep: (V',) vertex indices;
        bone_scales: optional (B, 24) bone length factors (``BodyModel.forward``'s).
    Returns:
        (B, V', 3) float32 posed vertices, metres, without translation.
    """
    bm = body_model
    scales = None
    if bone_scales is not None:
        scales = torch.as_tensor(np.nan_to_num(np.asarray(bone_scales, float), nan=1.0))
        scales = scales.to(bm.v_template.dtype).reshape(len(pose), -1)
    if bm.has_posedirs:  # pose blend shapes need every vertex: the model's own path
        out = bm(torch.as_tensor(pose, dtype=torch.float32), betas, bone_scales=scales)
        return out.vertices.numpy()[:, keep]
    pose = torch.as_tensor(pose, dtype=bm.v_template.dtype).reshape(len(pose), -1, 3)
    b = torch.zeros(len(pose), bm.num_betas, dtype=pose.dtype)
    given = torch.as_tensor(betas, dtype=pose.dtype).reshape(len(pose), -1)[:, : bm.num_betas]
    b[:, : given.shape[1]] = given
    idx = torch.as_tensor(keep)
    # 1. shape blend shapes of the kept vertices
    v_shaped = bm.v_template[idx] + torch.einsum("vcb,nb->nvc", bm.shapedirs[idx], b)
    rest = bm.rest_joints(b)
    # 2. forward kinematics (of the scaled skeleton); transforms relative to the bind pose
    chain_rest = rest if scales is None else scale_bones(rest, scales, bm.parents)
    posed, T = rigid_chain(axis_angle_to_matrix(pose), chain_rest, bm.tree)
    rel_t = posed - (T[..., :3, :3] @ rest[..., None])[..., 0]  # (B, J, 3)
    # 3. blend per-vertex transforms by the skinning weights
    w = bm.weights[idx]
    Rv = torch.einsum("vj,njab->nvab", w, T[..., :3, :3])
    return ((Rv @ v_shaped[..., None])[..., 0] + w @ rel_t).numpy().astype(np.float32)
