"""Synthesis speed and detection statistics: proxy occlusion against full renders.

``mvviz synth`` finds occluded keypoints either from each view's full-resolution render
(``SynthConfig.occlusion="render"``, what it always did) or from a 50 mm decimated body
evaluated at the keypoints' pixels only, all views at once (``"proxy"``, the default
without video). Two parts:

speed   a dome of --cameras cameras x --people people, no video: the per-frame cost of
        each mode (the frame loop only: set-up is timed apart), alternated
        render / proxy over --repeats runs; medians of wall and CPU seconds (CPU time
        is this process's own, less sensitive to other load on the machine).
stats   the shipped sample's settings (sample_data/shelf_synth/scene.json: the Shelf rig,
        its people, seed and detector noise; --stats-frames frames), both modes:
        detections per view and frame, true people detected per view and frame,
        fraction of true keypoints detected, fraction of low confidence (below
        confidence_visible - other_occlusion_penalty / 2: mostly occluded ones),
        2D error of detected keypoints (median px against the true projection),
        ghosts per view and frame.

Usage:
    python bench/bench_synth.py [--cameras 16] [--people 10] [--frames 10] [--repeats 3]
        [--stats-frames 60] [--json FILE]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.common import write_json  # noqa: E402
from pipeline.body_model import load_body_model  # noqa: E402
from pipeline.importers.calibration import read_voxelpose_calibration  # noqa: E402
from pipeline.synth.detectors import DetectorNoise  # noqa: E402
from pipeline.synth.rigs import dome_capture_radius, dome_rig  # noqa: E402
from pipeline.synth.scene_gen import SynthConfig, synthesize  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
SAMPLE = REPO / "sample_data" / "shelf_synth"


def frame_cost(rig, model, config: SynthConfig) -> tuple[float, float]:
    """(wall, CPU) seconds per frame of the frame loop: a run of ``num_frames`` minus
    a run of 1 frame (the set-up, which both share)."""
    out = []
    for n in (1, config.num_frames):
        cfg = dataclasses.replace(config, num_frames=n)
        w, c = time.perf_counter(), time.process_time()
        synthesize(rig, model, cfg, progress=False)
        out.append((time.perf_counter() - w, time.process_time() - c))
    k = config.num_frames - 1
    return (out[1][0] - out[0][0]) / k, (out[1][1] - out[0][1]) / k


def detection_stats(rig, people, det, noise: DetectorNoise) -> dict[str, float]:
    """The statistics the detectors' users see, per view and frame."""
    F, V = people.keypoints.shape[1], len(rig)
    real = det.gt_person_id >= 0
    kp = det.keypoints
    true = np.zeros((0, kp.shape[1], 2))
    if real.any():
        rows = zip(det.view[real], det.gt_person_id[real], det.frame[real], strict=True)
        true = np.stack([rig[v].project(people.keypoints[p, f]) for v, p, f in rows])
    k = kp[real]
    found = np.isfinite(k[..., 0]) & (k[..., 2] > 0)
    err = np.linalg.norm(k[..., :2] - true, axis=-1)[found]
    in_img = np.isfinite(true).all(-1)
    other_conf = noise.confidence_visible - noise.other_occlusion_penalty / 2
    return {
        "detections_per_view_frame": len(det.frame) / (F * V),
        "people_per_view_frame": float(real.sum()) / (F * V),
        "keypoints_detected": float(found.sum() / max(in_img.sum(), 1)),
        "keypoints_low_confidence": float(
            (found & (k[..., 2] < other_conf)).sum() / max(found.sum(), 1)
        ),
        "error_px_median": float(np.median(err)) if err.size else float("nan"),
        "error_px_p90": float(np.percentile(err, 90)) if err.size else float("nan"),
        "ghosts_per_view_frame": float((~real).sum()) / (F * V),
    }  # fmt: skip


def sample_config(frames: int) -> tuple[object, SynthConfig]:
    meta = json.loads((SAMPLE / "scene.json").read_text())["synth"]
    rig = read_voxelpose_calibration(REPO / "sample_data" / "rigs" / "shelf_voxelpose.json")
    cfg = SynthConfig(
        num_people=meta["num_people"], num_frames=frames, seed=meta["seed"],
        render_video=False, noise=DetectorNoise(**meta["noise"]),
    )  # fmt: skip
    return rig, cfg


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cameras", type=int, default=16)
    ap.add_argument("--people", type=int, default=10)
    ap.add_argument("--frames", type=int, default=10)
    ap.add_argument("--render-frames", type=int, default=3, help="frames of the slow mode")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--stats-frames", type=int, default=60)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    model = load_body_model()
    figures: dict = {}

    rig = dome_rig(args.cameras)
    base = SynthConfig(
        num_people=args.people, render_video=False, area_radius_mm=dome_capture_radius()
    )
    runs = {"render": [], "proxy": []}
    for r in range(args.repeats):
        for mode, n in (("render", args.render_frames), ("proxy", args.frames)):
            cost = frame_cost(rig, model, dataclasses.replace(base, occlusion=mode, num_frames=n))
            runs[mode].append(cost)
            print(f"run {r}: {mode:6s} {cost[0]:.3f} s/frame wall, {cost[1]:.3f} s CPU", flush=True)
    med = {m: np.median(np.array(v), axis=0) for m, v in runs.items()}
    print(f"\nspeed, dome:{args.cameras} x {args.people} people, no video, "
          f"medians of {args.repeats}")  # fmt: skip
    for m in ("render", "proxy"):
        print(f"  {m:6s} {1 / med[m][0]:7.2f} frames/s wall   {1 / med[m][1]:7.2f} frames/s CPU")
    print(f"  ratio  {med['render'][0] / med['proxy'][0]:7.1f} x wall     "
          f"{med['render'][1] / med['proxy'][1]:7.1f} x CPU")  # fmt: skip
    figures["speed"] = {
        m: {"frames_per_s_wall": float(1 / med[m][0]), "frames_per_s_cpu": float(1 / med[m][1])}
        for m in med
    }

    srig, scfg = sample_config(args.stats_frames)
    stats = {}
    for mode in ("render", "proxy"):
        people, det = synthesize(
            srig, model, dataclasses.replace(scfg, occlusion=mode), progress=False
        )
        stats[mode] = detection_stats(srig, people, det, scfg.noise)
    print(f"\ndetection statistics, shelf_synth's settings, {args.stats_frames} frames")
    print(f"  {'':30s} {'render':>9s} {'proxy':>9s}")
    for k in stats["render"]:
        print(f"  {k:30s} {stats['render'][k]:9.4f} {stats['proxy'][k]:9.4f}")
    figures["stats"] = stats
    if args.json:
        write_json(args.json, figures)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
