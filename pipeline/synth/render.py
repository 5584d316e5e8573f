"""A CPU z-buffer rasteriser for synthetic multi-view scenes, in numpy.

Units and conventions: world millimetres, z up, floor at z = 0; cameras as in
:mod:`pipeline.data.cameras` (``x_cam = R @ X + t``, x right, y down, z forward, OpenCV
distortion). Pixel centres sit at integer pixel coordinates (OpenCV), so pixel
``(row, col)`` is sampled at ``(u, v) = (col, row)``. Depth is camera z in mm.

How :func:`render_meshes` works (no Python loop over triangles):

1. Project every vertex with distortion (:func:`~pipeline.data.cameras.distort_and_project`);
   drop triangles with a vertex closer than ``near_mm`` or beyond the radius where
   the distortion polynomial folds back, and back-facing triangles (image-space
   winding; the meshes' faces wind counter-clockwise around their outward normals).
2. :func:`rasterise_triangles`: cut each triangle's pixel bounding box into tiles of
   at most 8 x 8 (most boxes are one tile; tiles wholly outside the triangle are
   dropped), group the tiles by exact size, and per group evaluate the three edge
   functions (barycentrics) of every tile at every pixel centre by broadcasting;
   keep the pixels inside; interpolate ``1/z`` linearly in the image
   (perspective-correct depth). The Python loop runs over tile sizes (<= 64), never
   over triangles.
3. Resolve the z-buffer with one ``np.minimum.at`` over a packed uint64 key
   ``(float32 depth bits << 32) | triangle id`` (positive float32 bit patterns sort
   like the floats): the nearest fragment wins, ties go to the lower triangle id.
   (A lexsort by pixel then depth gives the same answer: 130 ms instead of 1.7 ms
   for 600k fragments on the reference machine.)
4. Flat Lambert shading per face from world normals (two-sided) times the mesh colour.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.data.cameras import Camera, distort_and_project, max_valid_radius2

__all__ = [
    "MeshInstance",
    "Render",
    "occluded_by_other",
    "rasterise_triangles",
    "render_background",
    "render_meshes",
    "scale_camera",
    "visible_mask",
]

NEAR_MM = 100.0
_TILE = 8  # bounding boxes are cut into tiles of at most this many pixels a side
_MAX_TILES = 1 << 18  # tiles per batch: bounds memory when triangles are huge
_EDGE_EPS = np.float32(1e-5)  # barycentric slack so shared edges never crack


@dataclass(frozen=True, eq=False)
class MeshInstance:
    """One triangle mesh to draw.

    Attributes:
        vertices: (num_vertices, 3) world mm.
        faces: (num_faces, 3) int vertex indices, counter-clockwise around the
            outward normal (right-hand rule), as trimesh writes closed meshes.
        color: RGB 0-255.
    """

    vertices: np.ndarray
    faces: np.ndarray
    color: tuple[int, int, int] = (200, 200, 200)

    def __post_init__(self) -> None:
        v = np.asarray(self.vertices, dtype=float)
        f = np.asarray(self.faces)
        if v.ndim != 2 or v.shape[1] != 3:
            raise ValueError(f"vertices: expected (num_vertices, 3), got {v.shape}")
        if f.ndim != 2 or f.shape[1] != 3 or not np.issubdtype(f.dtype, np.integer):
            raise ValueError(f"faces: expected (num_faces, 3) integers, got {f.shape} {f.dtype}")
        if f.size and (f.min() < 0 or f.max() >= len(v)):
            raise ValueError(f"faces: indices must lie in [0, {len(v)}), got {f.min()}..{f.max()}")
        if len(self.color) != 3 or not all(0 <= int(c) <= 255 for c in self.color):
            raise ValueError(f"color: expected three ints in 0..255, got {self.color!r}")
        object.__setattr__(self, "vertices", v)
        object.__setattr__(self, "faces", f.astype(np.int64, copy=False))
        object.__setattr__(self, "color", tuple(int(c) for c in self.color))


@dataclass(frozen=True, eq=False)
class Render:
    """One rendered view.

    Attributes:
        image: (height, width, 3) uint8 RGB.
        depth: (height, width) float32 camera z in mm; +inf where no mesh.
        mesh_index: (height, width) int16 index into the list of meshes; -1 background.
        face_index: (height, width) int32 face of that mesh drawn at the pixel; -1 background.
        num_faces_drawn: faces that survived near-plane and back-face culling and
            were rasterised (whether or not any of their pixels won the z-buffer).
    """

    image: np.ndarray
    depth: np.ndarray
    mesh_index: np.ndarray
    face_index: np.ndarray
    num_faces_drawn: int = 0

    @property
    def height(self) -> int:
        return int(self.depth.shape[0])

    @property
    def width(self) -> int:
        return int(self.depth.shape[1])


# --------------------------------------------------------------------------- cameras


def scale_camera(camera: Camera, scale: float) -> Camera:
    """The same camera seen through an image resized by ``scale`` (e.g. 0.5).

    Keeps the pixel-centre-at-integer convention: ``u' = scale * (u + 0.5) - 0.5``.
    """
    if scale == 1.0:
        return camera
    if not scale > 0:
        raise ValueError(f"scale must be positive, got {scale}")
    width = max(1, int(round(camera.width * scale)))
    height = max(1, int(round(camera.height * scale)))
    sx, sy = width / camera.width, height / camera.height
    K = camera.K.copy()
    K[0, :] *= sx
    K[1, :] *= sy
    K[0, 2] += 0.5 * sx - 0.5
    K[1, 2] += 0.5 * sy - 0.5
    return Camera(camera.name, width, height, K, camera.dist.copy(), camera.R, camera.t)


def _camera_for(render_hw: tuple[int, int], camera: Camera) -> Camera:
    """The camera at the render's resolution (a render made with ``scale``)."""
    h, w = render_hw
    if (w, h) == (camera.width, camera.height):
        return camera
    scaled = scale_camera(camera, w / camera.width)
    if (scaled.width, scaled.height) != (w, h):
        raise ValueError(
            f"render is {w}x{h}, which is no scaled version of camera {camera.name!r} "
            f"({camera.width}x{camera.height})"
        )
    return scaled


# --------------------------------------------------------------------------- rasteriser


def rasterise_triangles(
    xy: np.ndarray, inv_z: np.ndarray, width: int, height: int
) -> tuple[np.ndarray, np.ndarray]:
    """Z-buffer rasterisation of image-space triangles, either winding.

    Args:
        xy: (num_tris, 3, 2) vertex pixel coordinates (pixel centres at integers).
        inv_z: (num_tris, 3) positive 1 / depth of each vertex, 1/mm.
        width, height: image size in pixels.
    Returns:
        triangle: (height, width) int32 index of the nearest triangle covering each
            pixel centre, -1 where none does.
        depth: (height, width) float32 depth (mm) there, perspective-correct; +inf elsewhere.
    """
    xy = np.asarray(xy, dtype=float)
    inv_z = np.asarray(inv_z, dtype=float)
    if xy.ndim != 3 or xy.shape[1:] != (3, 2) or inv_z.shape != xy.shape[:2]:
        raise ValueError(
            f"expected xy (num_tris, 3, 2) and inv_z (num_tris, 3), got {xy.shape}, {inv_z.shape}"
        )
    x = tuple(np.ascontiguousarray(xy[:, i, 0]) for i in range(3))
    y = tuple(np.ascontiguousarray(xy[:, i, 1]) for i in range(3))
    iz = tuple(np.ascontiguousarray(inv_z[:, i]) for i in range(3))
    return _rasterise(x, y, iz, int(width), int(height))


# empty z-buffer cell: depth +inf (float32 bits 0x7F800000), triangle 0xFFFFFFFF (-1 as int32)
_EMPTY_KEY = np.uint64(0x7F800000_FFFFFFFF)


def _rasterise(x, y, iz, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """:func:`rasterise_triangles` on vertex columns: x, y, iz are 3-tuples of (T,) arrays."""
    if x[0].size >= 2**32 - 1:
        raise ValueError("too many triangles for a 32-bit triangle id")
    zbuf = np.full(width * height, _EMPTY_KEY, dtype=np.uint64)
    for tri, pix, inv_depth in _fragments(x, y, iz, width, height):
        depth = (1.0 / np.maximum(inv_depth, 1e-12)).astype(np.float32)
        key = depth.view(np.uint32).astype(np.uint64) << np.uint64(32)
        key |= tri
        np.minimum.at(zbuf, pix, key)
    triangle = (zbuf & np.uint64(0xFFFFFFFF)).astype(np.uint32).view(np.int32)
    depth = (zbuf >> np.uint64(32)).astype(np.uint32).view(np.float32)
    return triangle.reshape(height, width), depth.reshape(height, width)


def _fragments(x, y, iz, width: int, height: int):
    """Yield (triangle id uint64, flat pixel index, float64 1/z) of covered pixel centres."""
    (xa, xb, xc), (ya, yb, yc), (za, zb, zc) = x, y, iz
    # 1. pixel-centre bounding boxes, clipped to the image (clip first: no int overflow)
    x0 = np.maximum(np.ceil(np.clip(np.minimum(np.minimum(xa, xb), xc), -1, width)), 0)
    x1 = np.minimum(np.floor(np.clip(np.maximum(np.maximum(xa, xb), xc), -1, width)), width - 1)
    y0 = np.maximum(np.ceil(np.clip(np.minimum(np.minimum(ya, yb), yc), -1, height)), 0)
    y1 = np.minimum(np.floor(np.clip(np.maximum(np.maximum(ya, yb), yc), -1, height)), height - 1)
    area2 = (xb - xa) * (yc - ya) - (yb - ya) * (xc - xa)
    with np.errstate(invalid="ignore"):
        ok = np.isfinite(area2) & (np.abs(area2) > 1e-12) & (x1 >= x0) & (y1 >= y0)
        ok &= (za > 0) & (zb > 0) & (zc > 0) & np.isfinite(za + zb + zc)
    ids = np.flatnonzero(ok)
    if ids.size == 0:
        return
    xa, xb, xc, ya, yb, yc, za, zb, zc = (v[ids] for v in (xa, xb, xc, ya, yb, yc, za, zb, zc))
    x0, x1, y0, y1 = (v[ids].astype(np.int64) for v in (x0, x1, y0, y1))
    inv = 1.0 / area2[ids]

    # 2. edge functions w_i = a_i x + b_i y + c_i: barycentrics (either winding), and
    #    1/z = sum_i w_i / z_i, affine in the image too. Columns: w0, w1, w2, 1/z.
    A = np.empty((ids.size, 4))
    B = np.empty((ids.size, 4))
    C = np.empty((ids.size, 4))
    A[:, 0], A[:, 1], A[:, 2] = (yb - yc) * inv, (yc - ya) * inv, (ya - yb) * inv
    B[:, 0], B[:, 1], B[:, 2] = (xc - xb) * inv, (xa - xc) * inv, (xb - xa) * inv
    C[:, 0] = (xb * yc - xc * yb) * inv
    C[:, 1] = (xc * ya - xa * yc) * inv
    C[:, 2] = (xa * yb - xb * ya) * inv
    for M in (A, B, C):
        M[:, 3] = M[:, 0] * za + M[:, 1] * zb + M[:, 2] * zc

    # 3. in chunks of at most _MAX_TILES tiles (bounded memory for huge triangles)
    tiles_x, tiles_y = (x1 - x0) // _TILE + 1, (y1 - y0) // _TILE + 1
    n_tiles = tiles_x * tiles_y
    chunk = (np.cumsum(n_tiles) - n_tiles) // _MAX_TILES
    bounds = np.flatnonzero(np.diff(chunk, prepend=-1, append=chunk[-1] + 1))
    for lo, hi in zip(bounds[:-1], bounds[1:], strict=True):
        part = slice(lo, hi)
        yield from _tile_fragments(
            ids[part], A[part], B[part], C[part], x0[part], x1[part], y0[part], y1[part],
            tiles_x[part], n_tiles[part], width,
        )  # fmt: skip


def _tile_fragments(ids, A, B, C, x0, x1, y0, y1, tiles_x, n_tiles, width: int):
    """:func:`_fragments` after set-up: (T,) boxes and (T, 4) edge/depth coefficients."""
    # 1. cut boxes into tiles of at most S x S pixels (most boxes are one tile already)
    S = _TILE
    src = np.arange(ids.size)  # the triangle (row of A, B, C) of each tile
    w, h = x1 - x0 + 1, y1 - y0 + 1
    multi = np.flatnonzero(n_tiles > 1)
    if multi.size:
        one = np.flatnonzero(n_tiles == 1)
        prim = np.repeat(multi, n_tiles[multi])
        first = np.cumsum(n_tiles[multi]) - n_tiles[multi]
        local = np.arange(prim.size) - np.repeat(first, n_tiles[multi])
        ty, tx = np.divmod(local, tiles_x[prim])
        tx0, ty0 = x0[prim] + tx * S, y0[prim] + ty * S
        tw, th = np.minimum(x1[prim] - tx0 + 1, S), np.minimum(y1[prim] - ty0 + 1, S)
        # drop tiles whose four corners lie outside one edge (long thin triangles)
        a, b = A[prim, :3], B[prim, :3]
        corner = a * tx0[:, None] + b * ty0[:, None] + C[prim, :3]
        right, down = a * (tw - 1)[:, None], b * (th - 1)[:, None]
        out = (corner < -_EDGE_EPS) & (corner + right < -_EDGE_EPS)
        out &= (corner + down < -_EDGE_EPS) & (corner + right + down < -_EDGE_EPS)
        live = ~out.any(1)
        src = np.concatenate([one, prim[live]])
        x0, y0 = np.concatenate([x0[one], tx0[live]]), np.concatenate([y0[one], ty0[live]])
        w, h = np.concatenate([w[one], tw[live]]), np.concatenate([h[one], th[live]])

    # 2. sort tiles by exact size; each size is one broadcast over (tiles, h, w)
    group = ((h - 1) * S + (w - 1)).astype(np.uint8)
    order = np.argsort(group, kind="stable")
    counts = np.bincount(group, minlength=S * S)
    ends = np.cumsum(counts)
    src, x0, y0 = src[order], x0[order], y0[order]
    a, b = A[src], B[src]
    # (4, P) rows w0 w1 w2 1/z: value at the tile origin and steps along x and y
    base64 = (a * x0[:, None] + b * y0[:, None] + C[src]).T
    base = base64.astype(np.float32)
    base[:3] += _EDGE_EPS  # slack so that edges shared by two triangles never crack
    step_x, step_y = a.T.astype(np.float32), b.T.astype(np.float32)
    # 1/z of covered pixels only, in float64: on a sliver the steps are large and cancel,
    # and float32 lost ~1e-5 of the depth there (found by test_rasteriser_matches_brute_force)
    z_base, z_step_x, z_step_y = base64[3], a[:, 3], b[:, 3]
    origin = y0 * width + x0
    tri_id = ids[src].astype(np.uint64)
    for g in np.flatnonzero(counts):
        lo, hi = int(ends[g] - counts[g]), int(ends[g])
        gh, gw = divmod(int(g), S)
        fx = np.arange(gw + 1, dtype=np.float32)
        fy = np.arange(gh + 1, dtype=np.float32)
        # inside: base_i + step_x_i fx + step_y_i fy >= 0 for i = 0, 1, 2
        mask = None
        for i in range(3):
            row = base[i, lo:hi, None] + step_x[i, lo:hi, None] * fx  # (n, gw)
            col = -(step_y[i, lo:hi, None] * fy)  # (n, gh)
            inside = row[:, None, :] >= col[:, :, None]
            mask = inside if mask is None else np.logical_and(mask, inside, out=mask)
        hit = np.flatnonzero(mask)
        if hit.size == 0:
            continue
        t, k = np.divmod(hit, (gh + 1) * (gw + 1))
        dy, dx = np.divmod(k, gw + 1)
        t += lo
        inv_depth = z_base[t] + z_step_x[t] * dx + z_step_y[t] * dy
        yield tri_id[t], origin[t] + dy * width + dx, inv_depth


# --------------------------------------------------------------------------- rendering


def _canvas(cam: Camera, background: np.ndarray | None) -> np.ndarray:
    """(height, width, 3) uint8 image to draw on: a copy of ``background``, else black."""
    h, w = cam.height, cam.width
    if background is None:
        return np.zeros((h, w, 3), dtype=np.uint8)
    image = np.asarray(background)
    if image.shape != (h, w, 3) or image.dtype != np.uint8:
        raise ValueError(
            f"background: expected ({h}, {w}, 3) uint8, got {image.shape} {image.dtype}"
        )
    return np.ascontiguousarray(image).copy()


def _visible_faces(
    cam: Camera, verts: np.ndarray, f: np.ndarray, *, near_mm: float, cull_back_faces: bool
) -> tuple[np.ndarray, list[np.ndarray], list[np.ndarray], np.ndarray]:
    """Project with distortion; drop faces near/behind the camera or past the fold.

    Args:
        verts: (num_vertices, 3) world mm; f: (3, num_faces) vertex indices.
    Returns:
        drawn face indices, per face corner the pixel u and v (3 x (num_faces,)), and
        (num_vertices,) 1 / camera z.
    """
    p_cam = verts @ cam.R.T + cam.t
    z = p_cam[:, 2]
    uv = distort_and_project(p_cam, cam.K, cam.dist)
    u, v = uv[:, 0].copy(), uv[:, 1].copy()
    with np.errstate(divide="ignore", invalid="ignore"):
        r2 = (p_cam[:, 0] ** 2 + p_cam[:, 1] ** 2) / z**2
        good = (z > near_mm) & (r2 <= max_valid_radius2(cam.dist)) & np.isfinite(u + v)
        inv_z = np.where(good, 1.0 / z, 1.0)
    keep = good[f[0]] & good[f[1]] & good[f[2]]
    fu = [u[i] for i in f]
    fv = [v[i] for i in f]
    if cull_back_faces:
        # with y down, a face whose outward normal points at the camera winds clockwise
        # on screen: its signed area (x-right, y-down cross product) is negative
        with np.errstate(invalid="ignore"):
            keep &= (fu[1] - fu[0]) * (fv[2] - fv[0]) - (fv[1] - fv[0]) * (fu[2] - fu[0]) < 0
    return np.flatnonzero(keep), fu, fv, inv_z


def _lambert_shades(
    cam: Camera,
    verts: np.ndarray,
    fd: list[np.ndarray],
    light_dir_world: tuple[float, float, float],
    ambient: float,
) -> np.ndarray:
    """Flat two-sided Lambert shade (ambient..1) from world normals of the faces whose
    corners are ``fd`` (3 x (n,) vertex indices): (n,)."""
    X = [verts[:, k].copy() for k in range(3)]
    p0 = [c[fd[0]] for c in X]
    e1 = [c[fd[1]] - q for c, q in zip(X, p0, strict=True)]
    e2 = [c[fd[2]] - q for c, q in zip(X, p0, strict=True)]
    n = np.stack(
        [
            e1[1] * e2[2] - e1[2] * e2[1],
            e1[2] * e2[0] - e1[0] * e2[2],
            e1[0] * e2[1] - e1[1] * e2[0],
        ]
    )
    towards = sum(nk * (ck - qk) for nk, ck, qk in zip(n, cam.center, p0, strict=True))
    light = np.asarray(light_dir_world, dtype=float)
    light = light / np.linalg.norm(light)
    cos = (light @ n) * np.sign(towards) / np.maximum(np.sqrt((n * n).sum(0)), 1e-12)
    return ambient + (1.0 - ambient) * np.clip(cos, 0.0, 1.0)


def render_meshes(
    camera: Camera,
    meshes: list[MeshInstance],
    *,
    background: np.ndarray | None = None,
    light_dir_world: tuple[float, float, float] = (0.3, -0.5, 1.0),
    scale: float = 1.0,
    ambient: float = 0.35,
    near_mm: float = NEAR_MM,
    cull_back_faces: bool = True,
) -> Render:
    """Render meshes seen by one camera, distortion included.

    Args:
        camera: the camera (full resolution; ``scale`` resizes the image).
        meshes: what to draw; ``Render.mesh_index`` indexes this list.
        background: (height, width, 3) uint8 RGB at the output resolution, e.g. from
            :func:`render_background`; black if None.
        light_dir_world: direction towards the light, world frame.
        scale: output size relative to the camera's image (K scaled accordingly).
        ambient: shade of an unlit face; lit faces get ``ambient + (1 - ambient) cos``.
        near_mm: triangles with any vertex closer than this (camera z) are dropped.
        cull_back_faces: drop faces turned away from the camera (correct for closed,
            outward-wound meshes); shading is two-sided either way.
    Returns:
        :class:`Render` at ``scale`` times the camera's resolution.
    """
    cam = scale_camera(camera, scale)
    h, w = cam.height, cam.width
    image = _canvas(cam, background)
    if len(meshes) > np.iinfo(np.int16).max:
        raise ValueError(f"at most {np.iinfo(np.int16).max} meshes, got {len(meshes)}")
    mesh_index = np.full((h, w), -1, dtype=np.int16)
    face_index = np.full((h, w), -1, dtype=np.int32)
    empty = Render(image, np.full((h, w), np.inf, np.float32), mesh_index, face_index, 0)
    if sum(len(m.faces) for m in meshes) == 0:
        return empty

    # 1. all meshes as one; face columns f[0], f[1], f[2] index the stacked vertices
    offsets = np.cumsum([0] + [len(m.vertices) for m in meshes])
    verts = np.concatenate([m.vertices for m in meshes])
    f = np.concatenate([m.faces.T + o for m, o in zip(meshes, offsets[:-1], strict=True)], 1)
    sizes = [len(m.faces) for m in meshes]

    # 2. project with distortion; drop faces near/behind the camera or past the fold
    drawn, fu, fv, inv_z = _visible_faces(
        cam, verts, f, near_mm=near_mm, cull_back_faces=cull_back_faces
    )
    if drawn.size == 0:
        return empty

    # 3. rasterise
    fd = [i[drawn] for i in f]
    tri, depth = _rasterise(
        tuple(c[drawn] for c in fu), tuple(c[drawn] for c in fv), tuple(inv_z[i] for i in fd), w, h
    )

    # 4. flat two-sided Lambert shading from world normals, per drawn face
    shade = _lambert_shades(cam, verts, fd, light_dir_world, ambient)
    owner = np.repeat(np.arange(len(meshes), dtype=np.int16), sizes)[drawn]
    colors = np.array([m.color for m in meshes], dtype=float)[owner]
    face_rgb = np.clip(np.rint(colors * shade[:, None]), 0, 255).astype(np.uint8)

    # 5. write the covered pixels (3-byte rows as void scalars: one fancy assignment)
    pix = np.flatnonzero(tri >= 0)
    won = tri.ravel()[pix]
    image.reshape(-1, 3).view("V3").ravel()[pix] = face_rgb.view("V3").ravel()[won]
    mesh_index.ravel()[pix] = owner[won]
    local_face = drawn - np.repeat(np.cumsum(sizes) - sizes, sizes)[drawn]
    face_index.ravel()[pix] = local_face[won]
    return Render(image, depth, mesh_index, face_index, int(drawn.size))


def render_background(
    camera: Camera,
    *,
    floor_size_mm: tuple[float, float] = (12000, 12000),
    floor_center: tuple[float, float] = (0, 0),
    tile_mm: float = 500.0,
    scale: float = 1.0,
) -> np.ndarray:
    """A static backdrop: a tiled floor at z = 0 fading with distance, a wall above.

    Casts one undistorted ray per pixel centre (:meth:`Camera.pixels_to_rays`) against
    the plane z = 0. Compute once per camera and pass to :func:`render_meshes`.

    Args:
        floor_size_mm: (x, y) extent of the tiled floor, centred on ``floor_center``;
            the ground beyond it is plain.
        tile_mm: side of one checker tile.
        scale: output size relative to the camera's image.
    Returns:
        (height, width, 3) uint8 RGB.
    """
    cam = scale_camera(camera, scale)
    h, w = cam.height, cam.width
    v, u = np.mgrid[0:h, 0:w].astype(float)
    rays = cam.pixels_to_rays(np.stack([u, v], axis=-1))  # (h, w, 3)
    origin = cam.center
    dz = rays[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(dz < -1e-9, -origin[2] / dz, np.inf)
    hits = np.isfinite(s) & (s > 0)
    s = np.where(hits, s, 0.0)
    xy = origin[:2] + rays[..., :2] * s[..., None]
    rel = xy - np.asarray(floor_center, dtype=float)
    half = np.asarray(floor_size_mm, dtype=float) / 2
    on_floor = hits & (np.abs(rel) <= half).all(-1)
    # checker filtered over each pixel's footprint on the floor (no jaggies, no moire):
    # the box-filtered square wave of period 2 tiles, per axis (Inigo Quilez's formula)
    p = rel / tile_mm
    foot = np.abs(np.gradient(p, axis=0)) + np.abs(np.gradient(p, axis=1))
    foot = np.clip(np.nan_to_num(foot, nan=2.0), 1e-3, 2.0)

    def tri(q: np.ndarray) -> np.ndarray:
        return np.abs(np.mod(q * 0.5, 1.0) - 0.5)

    i = 2.0 * (tri(p - 0.5 * foot) - tri(p + 0.5 * foot)) / foot
    checker = (0.5 - 0.5 * i[..., 0] * i[..., 1])[..., None]  # 1 on light tiles, 0 on dark

    wall_top = np.array([176.0, 186.0, 198.0])
    wall_low = np.array([214.0, 218.0, 222.0])
    # wall: a gentle gradient with the ray's elevation
    elev = np.clip(dz, 0.0, 1.0)[..., None]
    out = wall_low + (wall_top - wall_low) * np.sqrt(elev)
    light_tile, dark_tile, ground = (
        np.array([150.0, 148.0, 142.0]),
        np.array([126.0, 124.0, 119.0]),
        np.array([108.0, 106.0, 102.0]),
    )
    floor = dark_tile + (light_tile - dark_tile) * checker
    floor = np.where(on_floor[..., None], floor, ground)
    # shading fades with distance into the wall colour (a little fog)
    fog = (np.exp(-s / 25000.0) * (0.85 + 0.15 * np.exp(-s / 4000.0)))[..., None]
    floor = floor * fog + wall_low * (1 - fog)
    out = np.where(hits[..., None], floor, out)
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)


# --------------------------------------------------------------------------- visibility


def _lookup(render: Render, camera: Camera, points_world: np.ndarray, mesh_ids: np.ndarray):
    """Pixel of each point in the render, its camera z, and whether it is in the image."""
    points = np.asarray(points_world, dtype=float)
    ids = np.asarray(mesh_ids)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points_world: expected (num_points, 3), got {points.shape}")
    if ids.shape != (points.shape[0],):
        raise ValueError(f"mesh_ids: expected ({points.shape[0]},), got {ids.shape}")
    cam = _camera_for((render.height, render.width), camera)
    z = cam.world_to_camera(points)[:, 2]
    uv = cam.project(points)
    with np.errstate(invalid="ignore"):
        col = np.rint(uv[:, 0])
        row = np.rint(uv[:, 1])
        inside = (
            np.isfinite(uv).all(1)
            & (z > 0)
            & (col >= 0)
            & (col < render.width)
            & (row >= 0)
            & (row < render.height)
        )
    col = np.where(inside, col, 0).astype(np.int64)
    row = np.where(inside, row, 0).astype(np.int64)
    return row, col, z, inside, ids


def visible_mask(
    render: Render,
    camera: Camera,
    points_world: np.ndarray,
    mesh_ids: np.ndarray,
    *,
    tolerance_mm: float = 60.0,
) -> np.ndarray:
    """Which points the render shows.

    A point is visible when it projects inside the image and the surface drawn at its
    pixel is not in front of it: by more than ``tolerance_mm`` if that surface is the
    point's own mesh (slack for points on or just under their own surface, such as
    joints), by any amount if it is another mesh (see :func:`occluded_by_other`).

    Args:
        render: a render of ``camera`` (at any ``scale``).
        points_world: (num_points, 3) world mm.
        mesh_ids: (num_points,) index of the mesh each point belongs to (-1: none).
    Returns:
        (num_points,) bool; False for points outside the image or behind the camera.
    """
    row, col, z, inside, ids = _lookup(render, camera, points_world, mesh_ids)
    depth = render.depth[row, col]
    owner = render.mesh_index[row, col]
    own = owner == ids
    in_front = np.where(own, depth < z - tolerance_mm, (owner >= 0) & (depth < z))
    return inside & ~in_front


def occluded_by_other(
    render: Render,
    camera: Camera,
    points_world: np.ndarray,
    mesh_ids: np.ndarray,
) -> np.ndarray:
    """Whether another mesh hides each point.

    Args:
        render: a render of ``camera`` (at any ``scale``).
        points_world: (num_points, 3) world mm.
        mesh_ids: (num_points,) index of the mesh each point belongs to (-1: none).
    Returns:
        (num_points,) bool: the surface at the point's pixel belongs to a different mesh
        and lies in front of the point. False for points outside the image.
    """
    row, col, z, inside, ids = _lookup(render, camera, points_world, mesh_ids)
    owner = render.mesh_index[row, col]
    return inside & (owner >= 0) & (owner != ids) & (render.depth[row, col] < z)
