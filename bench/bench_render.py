"""Benchmark pipeline.synth.render: 4 body-sized meshes seen by a Shelf camera.

Builds four closed, body-like meshes (~13.3k vertices / ~26.6k triangles each,
torso, head, legs and arms as capsules with ~13 mm edges, like a densified SMPL
mesh), stands them 3-6 m in front of Shelf camera 0 (real calibration from
/work/shared/data/calibration/shelf_voxelpose.json; a synthetic camera of the same
size if that file is missing) and renders them at full resolution (1032 x 776)
over N repeats. Prints median and p95 wall-clock ms per render, ms per 1000
input triangles and the process's CPU ms (steadier on a shared machine), and
the same for a naive baseline in the same run: back-face culling,
painter's-algorithm ordering and one cv2.fillConvexPoly per triangle (colour
only: no depth or mesh-index buffers).

Usage:
    python bench/bench_render.py [--repeats N] [--baseline-repeats N] [--json FILE]
        [--save-png FILE]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.common import write_json  # noqa: E402
from pipeline.data.cameras import Camera, distort_and_project, make_camera  # noqa: E402
from pipeline.synth.render import (  # noqa: E402
    MeshInstance,
    render_background,
    render_meshes,
)

SHELF = Path("/work/shared/data/calibration/shelf_voxelpose.json")
COLORS = [(214, 84, 76), (86, 180, 96), (78, 118, 222), (226, 190, 70)]


def shelf_camera(index: int = 0) -> Camera:
    """Shelf camera ``index`` in the native convention (t = -R T)."""
    if not SHELF.is_file():
        R = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])  # looks along +y, z up
        K = [[1065.0, 0, 515.5], [0, 1070.0, 387.5], [0, 0, 1]]
        return make_camera(
            name="synthetic", width=1032, height=776, K=K, dist=np.zeros(5), R=R,
            t=-R @ np.array([0.0, -2500.0, 1100.0]),
        )  # fmt: skip
    c = json.loads(SHELF.read_text())[str(index)]
    R, T = np.array(c["R"]), np.array(c["T"]).ravel()
    k, p = np.array(c["k"]).ravel(), np.array(c["p"]).ravel()
    return make_camera(
        name=str(index), width=1032, height=776,
        K=[[c["fx"], 0, c["cx"]], [0, c["fy"], c["cy"]], [0, 0, 1]],
        dist=[k[0], k[1], p[0], p[1], k[2]], R=R, t=-R @ T,
    )  # fmt: skip


def capsule(a, b, radius: float, edge: float) -> tuple[np.ndarray, np.ndarray]:
    """Closed capsule around segment a -> b with near-uniform ``edge`` mm triangles.

    Returns (num_vertices, 3) vertices and (num_faces, 3) faces wound outward.
    """
    a, b = np.asarray(a, float), np.asarray(b, float)
    length = float(np.linalg.norm(b - a))
    w = (b - a) / length
    u = np.cross(w, [1.0, 0, 0] if abs(w[0]) < 0.9 else [0, 1.0, 0])
    u /= np.linalg.norm(u)
    v = np.cross(w, u)
    n_around = max(8, round(2 * np.pi * radius / edge))
    profile = length + np.pi * radius  # meridian length: two quarter circles + the side
    n_rings = max(3, round(profile / edge)) - 1
    arc = np.linspace(0, profile, n_rings + 2)[1:-1]
    cap = np.pi * radius / 2
    past = np.clip(arc - cap - length, 0, None) / radius
    before = np.clip(arc, None, cap) / radius
    axial = np.where(
        arc < cap,
        radius - radius * np.cos(before),
        np.where(arc > cap + length, radius + length + radius * np.sin(past), radius + arc - cap),
    )
    ring_r = np.where(
        arc < cap,
        radius * np.sin(before),
        np.where(arc > cap + length, radius * np.cos(past), radius),
    )
    th = np.linspace(0, 2 * np.pi, n_around, endpoint=False)
    around = np.cos(th)[:, None] * u + np.sin(th)[:, None] * v  # (n_around, 3)
    rings = (a - radius * w) + axial[:, None, None] * w + ring_r[:, None, None] * around
    verts = np.concatenate([[a - radius * w], rings.reshape(-1, 3), [b + radius * w]])
    j = np.arange(n_around)
    jn = (j + 1) % n_around
    first = 1 + np.arange(n_rings - 1)[:, None] * n_around
    quads = np.concatenate(
        [
            np.stack([first + j, first + jn, first + n_around + jn], -1).reshape(-1, 3),
            np.stack([first + j, first + n_around + jn, first + n_around + j], -1).reshape(-1, 3),
        ]
    )
    last, top = 1 + (n_rings - 1) * n_around, len(verts) - 1
    faces = np.concatenate(
        [
            np.stack([np.zeros(n_around, int), 1 + jn, 1 + j], 1),
            quads,
            np.stack([last + j, last + jn, np.full(n_around, top)], 1),
        ]
    )
    return verts, faces


def body_mesh(edge: float = 12.9) -> tuple[np.ndarray, np.ndarray]:
    """A closed body-like mesh standing at the origin, z up, facing -y (mm)."""
    parts = [
        capsule([0, 0, 1000], [0, 0, 1400], 150, edge),  # torso
        capsule([0, 0, 1620], [0, 0, 1680], 100, edge),  # head
    ]
    for s in (-1, 1):
        parts.append(capsule([s * 95, 0, 880], [s * 110, 20, 80], 65, edge))  # leg
        parts.append(capsule([s * 215, 0, 1420], [s * 300, -60, 860], 42, edge))  # arm
    parts[0][0][:, 1] *= 0.7  # flatten the torso front to back
    verts, faces, offset = [], [], 0
    for v, f in parts:
        verts.append(v)
        faces.append(f + offset)
        offset += len(v)
    return np.concatenate(verts), np.concatenate(faces)


def scene(camera: Camera) -> list[MeshInstance]:
    """Four bodies 3-6 m in front of ``camera``, each turned to face it."""
    verts, faces = body_mesh()
    fwd = camera.R[2, :2] / np.linalg.norm(camera.R[2, :2])
    side = np.array([-fwd[1], fwd[0]])
    meshes = []
    for (dist, off), color in zip(
        ((3000, -600), (4000, 700), (5000, -300), (6000, 1200)), COLORS, strict=True
    ):
        pos = camera.center[:2] + fwd * dist + side * off
        to_cam = camera.center[:2] - pos
        yaw = np.arctan2(to_cam[1], to_cam[0]) + np.pi / 2  # body faces -y at yaw 0
        c, s = np.cos(yaw), np.sin(yaw)
        Rz = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
        meshes.append(MeshInstance(verts @ Rz.T + [pos[0], pos[1], 0], faces, color))
    return meshes


def render_naive(camera: Camera, meshes: list[MeshInstance], background: np.ndarray) -> np.ndarray:
    """Baseline: cull, sort far to near, cv2.fillConvexPoly one triangle at a time."""
    image = background.copy()
    tris, cols, depth = [], [], []
    light = np.array([0.3, -0.5, 1.0]) / np.linalg.norm([0.3, -0.5, 1.0])
    for m in meshes:
        p_cam = camera.world_to_camera(m.vertices)
        uv = distort_and_project(p_cam, camera.K, camera.dist)[m.faces]
        e1, e2 = uv[:, 1] - uv[:, 0], uv[:, 2] - uv[:, 0]
        keep = (p_cam[m.faces, 2] > 100).all(1) & (e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0] < 0)
        fv = m.vertices[m.faces[keep]]
        n = np.cross(fv[:, 1] - fv[:, 0], fv[:, 2] - fv[:, 0])
        n /= np.linalg.norm(n, axis=1, keepdims=True) + 1e-12
        shade = 0.35 + 0.65 * np.clip(n @ light, 0, 1)
        tris.append(uv[keep])
        cols.append(np.rint(np.outer(shade, m.color)).astype(int))
        depth.append(p_cam[m.faces[keep], 2].mean(1))
    tris, cols, depth = np.concatenate(tris), np.concatenate(cols), np.concatenate(depth)
    order = np.argsort(-depth)
    pts = np.rint(tris * 16).astype(np.int32)  # 4 fractional bits
    for i in order:
        cv2.fillConvexPoly(image, pts[i], cols[i].tolist(), lineType=cv2.LINE_8, shift=4)
    return image


def timed(fn, repeats: int) -> tuple[np.ndarray, np.ndarray]:
    """(repeats,) wall-clock ms and (repeats,) CPU ms of this process per call."""
    wall, cpu = [], []
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        fn()
        wall.append((time.perf_counter() - t0) * 1e3)
        cpu.append((time.process_time() - c0) * 1e3)
    return np.array(wall), np.array(cpu)


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--repeats", type=int, default=30)
    parser.add_argument("--baseline-repeats", type=int, default=5)
    parser.add_argument("--json", type=Path, help="also write the results here")
    parser.add_argument("--save-png", type=Path, help="write the rendered image here")
    args = parser.parse_args(argv)

    camera = shelf_camera(0)
    meshes = scene(camera)
    num_vertices = sum(len(m.vertices) for m in meshes)
    num_faces = sum(len(m.faces) for m in meshes)
    t0 = time.perf_counter()
    background = render_background(camera)
    background_ms = (time.perf_counter() - t0) * 1e3

    render = render_meshes(camera, meshes, background=background)  # warm up
    ours, ours_cpu = timed(
        lambda: render_meshes(camera, meshes, background=background), args.repeats
    )
    naive_image = render_naive(camera, meshes, background)
    naive, naive_cpu = timed(
        lambda: render_naive(camera, meshes, background), args.baseline_repeats
    )
    covered = render.mesh_index >= 0
    naive_covered = (naive_image != background).any(-1)
    iou = (covered & naive_covered).sum() / (covered | naive_covered).sum()
    both = covered & naive_covered
    colour_diff = np.abs(naive_image.astype(int) - render.image).max(-1)[both]

    result = {
        "camera": camera.name,
        "image": [camera.width, camera.height],
        "meshes": len(meshes),
        "vertices": num_vertices,
        "triangles": num_faces,
        "triangles_drawn": render.num_faces_drawn,
        "pixels_covered": int(covered.sum()),
        "background_ms": background_ms,
        "render_ms_median": float(np.median(ours)),
        "render_ms_p95": float(np.percentile(ours, 95)),
        "render_ms_per_1k_triangles": float(np.median(ours) / num_faces * 1e3),
        "render_cpu_ms_median": float(np.median(ours_cpu)),
        "naive_ms_median": float(np.median(naive)),
        "naive_ms_p95": float(np.percentile(naive, 95)),
        "naive_ms_per_1k_triangles": float(np.median(naive) / num_faces * 1e3),
        "naive_cpu_ms_median": float(np.median(naive_cpu)),
        "speedup_vs_naive": float(np.median(naive) / np.median(ours)),
        "silhouette_iou_vs_naive": float(iou),
        "colour_diff_vs_naive_median": float(np.median(colour_diff)),
        "colour_diff_vs_naive_p95": float(np.percentile(colour_diff, 95)),
        "repeats": args.repeats,
        "baseline_repeats": args.baseline_repeats,
    }
    print(
        f"{len(meshes)} meshes, {num_vertices} vertices, {num_faces} triangles "
        f"({render.num_faces_drawn} front-facing), {camera.width}x{camera.height}, "
        f"{int(covered.sum())} pixels covered"
    )
    print(f"background (once per camera): {background_ms:.0f} ms")
    print(
        f"z-buffer rasteriser: median {result['render_ms_median']:.1f} ms, "
        f"p95 {result['render_ms_p95']:.1f} ms, "
        f"{result['render_ms_per_1k_triangles']:.2f} ms / 1000 triangles; "
        f"CPU {result['render_cpu_ms_median']:.1f} ms ({args.repeats} runs)"
    )
    print(
        f"naive fillConvexPoly painter: median {result['naive_ms_median']:.1f} ms, "
        f"p95 {result['naive_ms_p95']:.1f} ms, "
        f"{result['naive_ms_per_1k_triangles']:.2f} ms / 1000 triangles; "
        f"CPU {result['naive_cpu_ms_median']:.1f} ms ({args.baseline_repeats} runs)"
    )
    print(
        f"speed-up {result['speedup_vs_naive']:.1f}x; silhouettes agree (IoU {iou:.3f}); "
        f"colour difference on shared pixels: median {np.median(colour_diff):.0f}, "
        f"p95 {np.percentile(colour_diff, 95):.0f} levels (flat-shaded neighbours meet "
        "at different pixels: fillConvexPoly also fills pixels its edges touch)"
    )
    if args.json:
        write_json(args.json, result)
    if args.save_png:
        cv2.imwrite(str(args.save_png), cv2.cvtColor(render.image, cv2.COLOR_RGB2BGR))
    return result


if __name__ == "__main__":
    main()
