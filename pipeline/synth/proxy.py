"""A coarse stand-in for the body mesh, for occlusion tests only.

The open body model has 13,348 vertices and 26,692 faces; skinning and rasterising
that for 10 people in 16 views costs seconds per frame, while the detectors only ask
whether a keypoint is hidden (by its own body beyond a tolerance of 60-120 mm, or by
anyone else). A mesh a few centimetres coarse answers the same question.

:func:`proxy_mesh` decimates the template once by vertex clustering (Rossignac and
Borrel): cut the rest-pose template into cubes of ``cell_mm``, keep in each cube the
vertex nearest to the mean of its vertices, map every face onto the kept vertices and
drop the faces that collapse. Vertices are clustered per body part (the joint with the
largest skinning weight), so that a cube spanning both thighs or an arm and the torso
never welds them together when the body moves. The kept vertices are original ones,
so :func:`pose_proxy` poses them with the model's own skinning (linear blend skinning
of those rows only).

Units: the body model works in metres; :func:`pose_proxy` returns metres like it.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
import torch

from pipeline.body.model import BodyModel, rigid_chain
from pipeline.core.rotations import axis_angle_to_matrix

__all__ = ["ProxyBodies", "ProxyMesh", "pose_proxy", "proxy_bodies", "proxy_for", "proxy_mesh"]


@dataclass(frozen=True, eq=False)
class ProxyMesh:
    """A decimated body mesh made of a subset of the model's vertices.

    Attributes:
        vertex_ids: (num_proxy_vertices,) rows of the model's vertices kept.
        faces: (num_proxy_faces, 3) indices into ``vertex_ids``, the original winding.
    """

    vertex_ids: np.ndarray
    faces: np.ndarray


def proxy_mesh(
    vertices: np.ndarray, faces: np.ndarray, part: np.ndarray, *, cell: float
) -> ProxyMesh:
    """Vertex clustering of a mesh.

    Args:
        vertices: (num_vertices, 3) rest-pose positions (any unit; ``cell`` in the same).
        faces: (num_faces, 3) vertex indices.
        part: (num_vertices,) int label; vertices of different labels never merge.
        cell: side of the clustering cubes.
    Returns:
        the :class:`ProxyMesh`.
    """
    v = np.asarray(vertices, float)
    cube = np.floor((v - v.min(0)) / cell).astype(np.int64)
    key = np.column_stack([cube, np.asarray(part, np.int64)])
    _, cluster = np.unique(key, axis=0, return_inverse=True)
    cluster = cluster.ravel()
    n = int(cluster.max()) + 1
    counts = np.bincount(cluster, minlength=n).astype(float)
    mean = np.stack([np.bincount(cluster, v[:, k], n) for k in range(3)], 1) / counts[:, None]
    # representative: the vertex nearest its cluster's mean (lexsort: cluster, distance)
    dist = np.linalg.norm(v - mean[cluster], axis=1)
    order = np.lexsort((dist, cluster))
    first = order[np.flatnonzero(np.diff(cluster[order], prepend=-1))]
    rep = np.empty(n, np.int64)
    rep[cluster[first]] = first
    f = cluster[np.asarray(faces)]  # (F, 3) cluster ids
    keep = (f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])
    f = f[keep]
    # the same triangle from several source faces: keep one
    _, uniq = np.unique(np.sort(f, axis=1), axis=0, return_index=True)
    f = f[np.sort(uniq)]
    used = np.unique(f)
    remap = np.full(n, -1, np.int64)
    remap[used] = np.arange(used.size)
    return ProxyMesh(vertex_ids=rep[used], faces=remap[f])


@functools.lru_cache(maxsize=8)  # a model hashes by identity: once per loaded model
def proxy_for(model: BodyModel, cell_mm: float = 50.0) -> ProxyMesh:
    """The model's proxy mesh (cubes of ``cell_mm``), computed once per model."""
    part = model.weights.numpy().argmax(1)
    return proxy_mesh(model.v_template.numpy(), model.faces.numpy(), part, cell=cell_mm / 1000)


@dataclass(frozen=True, eq=False)
class ProxyBodies:
    """The proxy of each person of a scene, shaped once (their betas never change).

    Attributes:
        faces: (num_proxy_faces, 3) as :attr:`ProxyMesh.faces`.
        v_shaped: (P, num_proxy_vertices, 3) rest-pose vertices with shape blend, m.
        rest_joints: (P, 24, 3) rest-pose joints, m.
        weights: (num_proxy_vertices, 24) skinning weights.
        posedirs: (207, num_proxy_vertices * 3) pose blend shapes, or None (open model).
    """

    faces: np.ndarray
    v_shaped: torch.Tensor
    rest_joints: torch.Tensor
    weights: torch.Tensor
    posedirs: torch.Tensor | None
    tree: object


def proxy_bodies(model: BodyModel, proxy: ProxyMesh, betas: np.ndarray) -> ProxyBodies:
    """Shape the proxy for people of ``betas`` (P, <= num_betas)."""
    ids = torch.as_tensor(proxy.vertex_ids)
    dtype = model.v_template.dtype
    b = torch.as_tensor(np.asarray(betas), dtype=dtype)
    nb = model.shapedirs.shape[-1]
    betas_t = torch.zeros(b.shape[0], nb, dtype=dtype)
    betas_t[:, : min(nb, b.shape[1])] = b[:, :nb]
    with torch.no_grad():
        v_shaped = model.v_template[ids] + torch.einsum(
            "vcb,nb->nvc", model.shapedirs[ids], betas_t
        )
        rest = model.rest_joints(betas_t)
    posedirs = None
    if model.has_posedirs:
        d = model.posedirs.reshape(model.posedirs.shape[0], -1, 3)[:, ids]
        posedirs = d.reshape(d.shape[0], -1).contiguous()
    return ProxyBodies(
        faces=proxy.faces, v_shaped=v_shaped, rest_joints=rest,
        weights=model.weights[ids].contiguous(), posedirs=posedirs, tree=model.tree,
    )  # fmt: skip


def pose_proxy(bodies: ProxyBodies, pose: np.ndarray) -> np.ndarray:
    """The proxy's vertices posed like :meth:`BodyModel.forward` poses the full mesh
    (linear blend skinning of the kept rows only).

    Args:
        pose: (P, 24, 3) axis-angle, root in the world frame.
    Returns:
        (P, num_proxy_vertices, 3) metres, before any translation.
    """
    with torch.no_grad():
        rot = axis_angle_to_matrix(torch.as_tensor(pose, dtype=bodies.v_shaped.dtype))
        P = rot.shape[0]
        v = bodies.v_shaped
        if bodies.posedirs is not None:
            feat = (rot[:, 1:] - torch.eye(3, dtype=rot.dtype)).reshape(P, -1)
            v = v + (feat @ bodies.posedirs).reshape(P, -1, 3)
        posed, T = rigid_chain(rot, bodies.rest_joints, bodies.tree)
        rel_t = posed - (T[..., :3, :3] @ bodies.rest_joints[..., None])[..., 0]
        w = bodies.weights
        Rv = (w @ T[..., :3, :3].reshape(P, -1, 9)).reshape(P, -1, 3, 3)
        verts = (Rv @ v[..., None])[..., 0] + w @ rel_t
    return verts.numpy()
