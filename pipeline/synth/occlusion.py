"""Which keypoints a mesh hides, without rendering whole images.

The detectors only look at the z-buffer at the pixels of the keypoints (a few hundred
per view), so instead of rasterising every pixel this evaluates the nearest surface at
those pixels only, in all views at once:

1. project every vertex into each view; a triangle's pixel bounding box is cut into
   cells of ``_CELL`` x ``_CELL`` pixels; the query pixels are binned into the same
   cells (view index folded into the cell id, so all views share one pass);
2. drop, in integers over every triangle of every view, those whose corners' cells
   span no cell with a query (a summed-area table of query counts per cell); the rest
   (a quarter on a 16-camera dome of 10 people) get their exact pixel boxes, back-face test and
   the same cell test again; expand (triangle, cell) pairs, keep those whose cell holds
   queries, expand to (triangle, query) pairs;
3. edge functions at the query's pixel centre decide coverage (the same slack as
   :mod:`pipeline.synth.render`), ``1/z`` interpolated linearly in the image gives the
   perspective-correct depth, and the nearest fragment per query wins
   (``np.minimum.at`` over depth bits and triangle id packed in a uint64, as there).

The answer equals a full-resolution render of the same mesh read at those pixels
(``tests/pipeline/synth/test_occlusion.py`` checks it against
:func:`~pipeline.synth.render.render_meshes`); faces are not culled, so a decimated,
not quite closed mesh (:mod:`pipeline.synth.proxy`) works too.

World millimetres; cameras as in :mod:`pipeline.data.cameras`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.data.cameras import Camera, max_valid_radius2
from pipeline.synth.render import NEAR_MM

__all__ = ["PointOcclusion", "point_occlusion"]

_CELL = 16  # px: a proxy triangle covers one to four cells, a cell few keypoints
_EPS = 1e-5  # barycentric slack, as the rasteriser's
_EMPTY = np.uint64(0x7F800000_FFFFFFFF)  # depth +inf, triangle -1


@dataclass(frozen=True, eq=False)
class PointOcclusion:
    """Per view and point: what the detectors need from the z-buffer.

    Attributes:
        inside: (V, N) bool, the point projects inside the image, in front of the camera.
        z: (V, N) the point's camera depth, mm.
        depth: (V, N) depth of the nearest surface at the point's pixel, mm; inf if none.
        owner: (V, N) int, the mesh that surface belongs to; -1 if none.
    """

    inside: np.ndarray
    z: np.ndarray
    depth: np.ndarray
    owner: np.ndarray

    def visible(self, mesh_ids: np.ndarray, *, tolerance_mm: float) -> np.ndarray:
        """(V, N) as :func:`pipeline.synth.render.visible_mask`: no surface in front of
        the point, its own mesh's by more than ``tolerance_mm``, another's by any."""
        own = self.owner == mesh_ids
        ahead = np.where(
            own, self.depth < self.z - tolerance_mm, (self.owner >= 0) & (self.depth < self.z)
        )
        return self.inside & ~ahead

    def hidden_by_other(self, mesh_ids: np.ndarray) -> np.ndarray:
        """(V, N) as :func:`pipeline.synth.render.occluded_by_other`."""
        other = (self.owner >= 0) & (self.owner != mesh_ids)
        return self.inside & other & (self.depth < self.z)


def _project_views(cameras: list[Camera], points: np.ndarray):
    """(N, 3) world mm -> per view (V, N) u, v pixels (OpenCV distortion, as
    :func:`~pipeline.data.cameras.distort_and_project`), camera z, and whether the point is
    in front of ``near`` and inside the distortion's fold (``good``); all views at once."""
    R = np.stack([c.R for c in cameras])
    t = np.stack([c.t for c in cameras])
    K = np.stack([c.K for c in cameras])
    dist = np.stack([c.dist for c in cameras])
    k1, k2, p1, p2, k3 = (dist.T[i][:, None] for i in range(5))
    fold = np.array([max_valid_radius2(c.dist) for c in cameras])[:, None]
    pc = points @ np.swapaxes(R, 1, 2) + t[:, None]  # (V, N, 3), as Camera.world_to_camera
    z = pc[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        x, y = pc[..., 0] / z, pc[..., 1] / z
        r2 = x * x + y * y
        if dist.any():
            radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
            xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
            yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        else:  # no distortion (dome rigs): the same numbers without the polynomial
            xd, yd = x, y
        u = K[:, 0, 0, None] * xd + K[:, 0, 1, None] * yd + K[:, 0, 2, None]
        v = K[:, 1, 1, None] * yd + K[:, 1, 2, None]
        good = (z > 1e-9) & (r2 <= fold) & np.isfinite(u) & np.isfinite(v)
    return u, v, z, good


def _box_counts(sat: np.ndarray, base: np.ndarray, stride: np.ndarray, box: np.ndarray):
    """Queries inside each triangle's cell box [x0, x1] x [y0, y1] (4, T), from the
    flat summed-area tables ``sat`` of all views (``base``, ``stride`` per triangle)."""
    x0, x1, y0, y1 = box
    a = sat[base + y0 * stride + x0]
    b = sat[base + y0 * stride + x1 + 1]
    c = sat[base + (y1 + 1) * stride + x0]
    d = sat[base + (y1 + 1) * stride + x1 + 1]
    return d - b - c + a


def _cells_hold_queries(tu, tv, good, f, ncx, ncy, sat, sat_base, stride) -> np.ndarray:
    """(V, num_faces) whether a triangle's conservative cell box holds a query: the box
    of its corners' cells (``floor(u / _CELL)``), which contains the cells of the pixels
    it covers, so no triangle that covers a query is dropped."""
    cx = np.clip(np.floor(np.where(good, tu, 0.0) / _CELL), -1, ncx).astype(np.int32)
    cy = np.clip(np.floor(np.where(good, tv, 0.0) / _CELL), -1, ncy).astype(np.int32)
    a, b, c = cx[:, f[0]], cx[:, f[1]], cx[:, f[2]]
    x0 = np.maximum(np.minimum(np.minimum(a, b), c), 0)
    x1 = np.minimum(np.maximum(np.maximum(a, b), c), ncx - 1)
    a, b, c = cy[:, f[0]], cy[:, f[1]], cy[:, f[2]]
    y0 = np.maximum(np.minimum(np.minimum(a, b), c), 0)
    y1 = np.minimum(np.maximum(np.maximum(a, b), c), ncy - 1)
    # every index stays inside the tables (x0 <= ncx, x1 >= -1): no gather of survivors
    base, step = sat_base[:, None], stride[:, None]
    count = sat[base + (y1 + 1) * step + x1 + 1] - sat[base + y0 * step + x1 + 1]
    count += sat[base + y0 * step + x0] - sat[base + (y1 + 1) * step + x0]
    hold = (x1 >= x0) & (y1 >= y0) & (count > 0)
    return hold


def point_occlusion(  # long: one vectorised pass in numbered steps; splitting hides the flow
    cameras: list[Camera],
    vertices: np.ndarray,
    faces: np.ndarray,
    points_world: np.ndarray,
    *,
    near_mm: float = NEAR_MM,
    cull_back_faces: bool = False,
    cell_prefilter: bool = True,
) -> PointOcclusion:
    """The nearest surface of P meshes (one topology) at the pixels of N points, per view.

    Args:
        cameras: V views.
        vertices: (P, num_vertices, 3) world mm.
        faces: (num_faces, 3) vertex indices shared by the meshes.
        points_world: (N, 3) world mm (NaN rows are never inside).
        cell_prefilter: first drop, in integers over every triangle, those whose cells
            (each corner's, a superset of its pixels') hold no query; the float work
            then runs on the few left (the same answer; False: the float work on all).
    Returns:
        :class:`PointOcclusion` of shape (V, N).
    """
    verts = np.asarray(vertices, float)
    P, nv = verts.shape[:2]
    fcs = np.asarray(faces, np.int64)
    nf = len(fcs)
    f = (fcs.T[:, None, :] + (np.arange(P) * nv)[None, :, None]).reshape(3, -1)
    pts = np.asarray(points_world, float)
    V, N = len(cameras), len(pts)
    width = np.array([c.width for c in cameras])[:, None]
    height = np.array([c.height for c in cameras])[:, None]
    ncx, ncy = (width + _CELL - 1) // _CELL, (height + _CELL - 1) // _CELL  # (V, 1)

    # 1. queries: the rounded pixel of each point in each view, its cell
    u, v, zq, good = _project_views(cameras, pts)
    with np.errstate(invalid="ignore"):
        col, row = np.rint(u), np.rint(v)
        inside = good & (zq > 0) & (col >= 0) & (col < width) & (row >= 0) & (row < height)
    col, row = np.where(inside, col, 0).astype(np.int64), np.where(inside, row, 0).astype(np.int64)
    n_cells = (ncx * ncy).ravel()
    cell_base = (np.cumsum(n_cells) - n_cells)[:, None]
    qcell = np.where(inside, cell_base + (row // _CELL) * ncx + col // _CELL, -1).ravel()
    qx, qy = col.ravel().astype(float), row.ravel().astype(float)
    depth_key = np.full(V * N, _EMPTY, np.uint64)

    # 2. triangles in every view: corners in front of near_mm and inside the fold
    tu, tv, tz, tgood = _project_views(cameras, verts.reshape(-1, 3))
    good_t = tgood & (tz > near_mm)
    ok = good_t[:, f[0]] & good_t[:, f[1]] & good_t[:, f[2]]  # (V, P * F)
    # summed-area tables of the query counts per cell, all views in one flat array
    stride = (ncx + 1).ravel()
    sat_size = ((ncx + 1) * (ncy + 1)).ravel()
    sat_base = np.cumsum(sat_size) - sat_size
    sat = np.zeros(int(sat_size.sum()), np.int64)
    for k in range(V):  # V small tables; the cumsums are cheap
        occ = np.zeros((int(ncy[k, 0]) + 1, int(ncx[k, 0]) + 1), np.int64)
        cells = qcell[k * N : (k + 1) * N]
        cells = cells[cells >= 0] - cell_base[k, 0]
        np.add.at(occ, (cells // ncx[k, 0] + 1, cells % ncx[k, 0] + 1), 1)
        sat[sat_base[k] : sat_base[k] + sat_size[k]] = occ.cumsum(0).cumsum(1).ravel()
    if cell_prefilter:
        ok &= _cells_hold_queries(tu, tv, good_t, f, ncx, ncy, sat, sat_base, stride)
    view, face = np.nonzero(ok)
    corner = f[:, face]  # (3, T)
    flat = view * (P * nv) + corner  # the corners' rows of the flattened (V, P * nv) arrays
    u, w, iz = tu.ravel()[flat], tv.ravel()[flat], 1.0 / tz.ravel()[flat]
    if cull_back_faces:
        # with y down, a face turned towards the camera winds clockwise on screen
        with np.errstate(invalid="ignore"):
            front = (u[1] - u[0]) * (w[2] - w[0]) - (w[1] - w[0]) * (u[2] - u[0]) < 0
        u, w, iz, face, view = u[:, front], w[:, front], iz[:, front], face[front], view[front]
    wv, hv = width[view, 0], height[view, 0]
    x0 = np.clip(np.ceil(np.minimum(np.minimum(u[0], u[1]), u[2])), 0, wv - 1)
    x1 = np.clip(np.floor(np.maximum(np.maximum(u[0], u[1]), u[2])), -1, wv - 1)
    y0 = np.clip(np.ceil(np.minimum(np.minimum(w[0], w[1]), w[2])), 0, hv - 1)
    y1 = np.clip(np.floor(np.maximum(np.maximum(w[0], w[1]), w[2])), -1, hv - 1)
    box = (np.stack([x0, x1, y0, y1]) // _CELL).astype(np.int64)
    # keep triangles whose cell box holds a query
    keep = (x1 >= x0) & (y1 >= y0)
    keep[keep] = _box_counts(sat, sat_base[view[keep]], stride[view[keep]], box[:, keep]) > 0
    u, w, iz, box, face, view = (
        u[:, keep],
        w[:, keep],
        iz[:, keep],
        box[:, keep],
        face[keep],
        view[keep],
    )
    live = np.flatnonzero(qcell >= 0)
    order = live[np.argsort(qcell[live], kind="stable")]
    # the queries of cell c: order[first_query[c] : first_query[c] + per_cell[c]]
    per_cell = np.bincount(qcell[live], minlength=int(n_cells.sum()))
    first_query = np.cumsum(per_cell) - per_cell
    if order.size and face.size:
        cx0, cx1, cy0, cy1 = box
        base, ncx_t = cell_base[view, 0], ncx[view, 0]
        # 3. (triangle, cell) pairs over each bounding box's cells
        nx, ny = cx1 - cx0 + 1, cy1 - cy0 + 1
        n_cells = nx * ny
        tri = np.repeat(np.arange(face.size), n_cells)
        local = np.arange(tri.size) - np.repeat(np.cumsum(n_cells) - n_cells, n_cells)
        dy, dx = np.divmod(local, nx[tri])
        cell = base[tri] + (cy0[tri] + dy) * ncx_t[tri] + cx0[tri] + dx
        cnt = per_cell[cell]
        has = cnt > 0
        tri, lo, cnt = tri[has], first_query[cell[has]], cnt[has]
        # 4. (triangle, query) pairs
        t = np.repeat(tri, cnt)
        q = order[np.repeat(lo, cnt) + np.arange(t.size) - np.repeat(np.cumsum(cnt) - cnt, cnt)]
        px, py = qx[q], qy[q]
        xa, xb, xc = u[0, t], u[1, t], u[2, t]
        ya, yb, yc = w[0, t], w[1, t], w[2, t]
        area2 = (xb - xa) * (yc - ya) - (yb - ya) * (xc - xa)
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / area2
            w0 = ((yb - yc) * px + (xc - xb) * py + (xb * yc - xc * yb)) * inv
            w1 = ((yc - ya) * px + (xa - xc) * py + (xc * ya - xa * yc)) * inv
            w2 = ((ya - yb) * px + (xb - xa) * py + (xa * yb - xb * ya)) * inv
            hit = (np.abs(area2) > 1e-12) & (w0 >= -_EPS) & (w1 >= -_EPS) & (w2 >= -_EPS)
        t, q = t[hit], q[hit]
        inv_depth = w0[hit] * iz[0, t] + w1[hit] * iz[1, t] + w2[hit] * iz[2, t]
        d = (1.0 / np.maximum(inv_depth, 1e-12)).astype(np.float32)
        key = (d.view(np.uint32).astype(np.uint64) << np.uint64(32)) | face[t].astype(np.uint64)
        np.minimum.at(depth_key, q, key)
    face_won = (depth_key & np.uint64(0xFFFFFFFF)).astype(np.uint32).view(np.int32).astype(np.int64)
    depth = (depth_key >> np.uint64(32)).astype(np.uint32).view(np.float32).astype(float)
    owner = np.where(face_won >= 0, face_won // max(nf, 1), -1)
    return PointOcclusion(inside=inside, z=zq, depth=depth.reshape(V, N), owner=owner.reshape(V, N))
