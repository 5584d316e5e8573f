"""Benchmark the fitted bodies drawn on the camera panel's image (layer "Fitted bodies on
the camera image", mvviz.scene.images.body_outlines / draw_bodies).

On the shipped Shelf scene (4 people, fitted bodies from its cached results), per frame
change, the camera panel's image job (the overlay computed and drawn on the picture)
with the layer off and on, alternated frame by frame in one run: at the panel's widths
(400 and 640 px of the 1032 x 776 camera) and at 1280 x 720 (the same camera with a
1280 x 720 image: K scaled, the picture cropped to 16:9). "on, new frame" is a frame
not seen before (playback), "on, cached" the same frame again (a layer toggled, a
scrub back). Also the silhouettes' agreement with every mesh face filled (IoU).

Usage:
    python bench/bench_bodies_on_images.py [--frames 60] [--json FILE]
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import sys
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.common import write_json  # noqa: E402
from mvviz.scene.geometry import LayerToggles, prepare  # noqa: E402
from mvviz.scene.images import (  # noqa: E402
    blank_frame,
    body_labels,
    body_outlines,
    draw_overlay,
    image_overlay,
    posed_vertices,
)
from pipeline.body.model import load_body_model  # noqa: E402
from pipeline.config import PipelineConfig  # noqa: E402
from pipeline.data.cameras import CameraRig  # noqa: E402
from pipeline.data.scene import load_scene  # noqa: E402
from pipeline.run.pipeline import run_or_load  # noqa: E402

REPO = Path(__file__).resolve().parents[1]


def hd_rig(rig: CameraRig, width: int = 1280, height: int = 720) -> CameraRig:
    """Every camera scaled to ``width`` px and cropped (about its centre) to ``height``."""
    cams = []
    for c in rig:
        s = width / c.width
        K = c.K.copy()
        K[:2] *= s
        K[1, 2] -= (c.height * s - height) / 2
        cams.append(dataclasses.replace(c, width=width, height=height, K=K))
    return CameraRig(tuple(cams))


def image_job_ms(data, view: int, frame: int, lay: LayerToggles, width: int) -> float:
    cam = data.scene.rig[view]
    base = blank_frame(width, round(cam.height * width / cam.width))
    t0 = time.perf_counter()
    draw_overlay(base, image_overlay(data, view, frame, lay))
    return (time.perf_counter() - t0) * 1e3


def iou_with_faces(data, view: int, frame: int) -> float:
    cam, b = data.scene.rig[view], data.fit_bodies
    exact = np.zeros((cam.height, cam.width), np.uint8)
    for i in np.flatnonzero(b.present[:, frame]):
        tri = cam.project(posed_vertices(b, i, frame) * 1000.0)[b.faces]
        for t in tri[np.isfinite(tri).all((1, 2))]:
            cv2.fillConvexPoly(exact, np.round(t * 8).astype(np.int32), 1, cv2.LINE_8, 3)
    mine = body_labels(body_outlines(data, view, frame), exact.shape, 1.0) > 0
    exact = exact > 0
    return float((mine & exact).sum() / max((mine | exact).sum(), 1))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    scene = load_scene(REPO / "sample_data" / "shelf_synth")
    results, _ = run_or_load(scene, PipelineConfig(), load_body_model(), progress=False)
    figures: dict = {}
    cases = [("400 px", scene, 400), ("640 px", scene, 640)]
    cases.append(("1280x720", dataclasses.replace(scene, rig=hd_rig(scene.rig)), 1280))
    off = LayerToggles()
    on = dataclasses.replace(off, bodies_on_images=True)
    frames = range(20, 20 + args.frames)
    for name, sc, width in cases:
        data = prepare(sc, results, None)
        t = {"off": [], "on, new frame": [], "on, cached": []}
        for f in frames:  # alternated: off, on (first visit), on (again)
            t["off"].append(image_job_ms(data, 0, f, off, width))
            t["on, new frame"].append(image_job_ms(data, 0, f, on, width))
            t["on, cached"].append(image_job_ms(data, 0, f, on, width))
        med = {k: statistics.median(v) for k, v in t.items()}
        med["added, new frame"] = med["on, new frame"] - med["off"]
        figures[name] = med
        print(f"{name:>9}: " + ", ".join(f"{k} {v:.1f} ms" for k, v in med.items()))
    data = prepare(scene, results, None)
    ious = [iou_with_faces(data, v, f) for v in range(len(scene.rig)) for f in (30, 90, 150)]
    figures["iou_min"], figures["iou_median"] = min(ious), statistics.median(ious)
    print(f"silhouettes vs every face filled: IoU min {min(ious):.3f}, median "
          f"{statistics.median(ious):.3f} ({len(ious)} camera-frames)")  # fmt: skip
    if args.json:
        write_json(args.json, figures)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
