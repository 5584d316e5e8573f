"""Display meshes: a body mesh decimated by vertex clustering, skin weights carried over.

A full SMPL-topology body (6,890 vertices, 13,776 faces) per person, skinned in the
browser, is what makes software WebGL crawl (~1 fps with two mesh layers on). The viewer
draws a decimated copy: vertices are clustered on a grid of ``cell`` metres over one
bind pose, each cluster becomes one vertex (the mean of its members, per body, so every
body keeps its own shape), its skin weights the mean of its members' (renormalised),
and faces whose corners fall into fewer than three clusters are dropped. Every body of
a :class:`~mvviz.scene.bodies.Bodies` shares one clustering, so they keep one face array.
Exports use the full meshes; this is display only.

Units: metres, as :mod:`mvviz.scene.bodies`.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from mvviz.scene.bodies import Bodies

DISPLAY_CELL_M = 0.03  # ~1/6 of the vertices and faces of the body model, fingers merged
# A wireframe draws every edge as a line, which software WebGL rasterises slowly: a
# coarser mesh for it (~1/16 of the faces).
WIREFRAME_CELL_M = 0.05


@dataclasses.dataclass(frozen=True, eq=False)
class Clustering:
    """``labels`` (V,): the cluster of each full vertex; ``faces`` (T', 3) the faces
    between clusters (indices into ``num_clusters``)."""

    labels: np.ndarray
    faces: np.ndarray
    num_clusters: int


def cluster_vertices(vertices: np.ndarray, faces: np.ndarray, cell: float) -> Clustering:
    """Cluster ``vertices`` (V, 3) m on a grid of ``cell`` m; remap ``faces`` (T, 3),
    dropping the ones that collapse and duplicates (a face's winding is kept)."""
    vertices, faces = np.asarray(vertices, float), np.asarray(faces, np.int64)
    if vertices.ndim != 2 or vertices.shape[1] != 3:
        raise ValueError(f"vertices: expected (V, 3), got {vertices.shape}")
    if cell <= 0:
        raise ValueError(f"cell must be > 0 m, got {cell}")
    keys = np.floor((vertices - vertices.min(0)) / cell).astype(np.int64)
    _, labels = np.unique(keys, axis=0, return_inverse=True)
    labels = labels.reshape(-1)
    f = labels[faces]  # (T, 3)
    ok = (f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])
    f = f[ok]
    _, first = np.unique(np.sort(f, 1), axis=0, return_index=True)
    return Clustering(labels, f[np.sort(first)].astype(np.uint32), int(labels.max()) + 1)


def cluster_mean(values: np.ndarray, labels: np.ndarray, n: int) -> np.ndarray:
    """(..., V, C) -> (..., n, C): the mean of each cluster's members."""
    values = np.asarray(values, float)
    out = np.zeros(values.shape[:-2] + (n, values.shape[-1]))
    np.add.at(out, (..., labels, slice(None)), values)
    count = np.bincount(labels, minlength=n).astype(float)
    return out / count[:, None]


def decimate_bodies(bodies: Bodies, *, cell: float = DISPLAY_CELL_M) -> Bodies:
    """``bodies`` with decimated meshes (same bone poses, ids, presence): clustered on
    the first body's bind pose, each body's vertices the means of its clusters."""
    c = cluster_vertices(bodies.vertices[0], bodies.faces, cell)
    weights = cluster_mean(bodies.weights, c.labels, c.num_clusters)
    weights /= np.maximum(weights.sum(1, keepdims=True), 1e-12)
    return dataclasses.replace(
        bodies,
        vertices=cluster_mean(bodies.vertices, c.labels, c.num_clusters).astype(np.float32),
        faces=c.faces,
        weights=weights.astype(np.float32),
    )
