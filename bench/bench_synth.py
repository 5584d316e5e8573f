"""Synthesis speed and detection statistics: the fast path without video against the
path before it and against full renders.

``mvviz synth`` finds occluded keypoints either from each view's full-resolution render
(``SynthConfig.occlusion="render"``, what it always did) or from a 50 mm decimated body
evaluated at the keypoints' pixels only, all views at once (``"proxy"``, the default
without video). The proxy path now runs torch on one thread, drops, in integers, the
triangles whose cells hold no keypoint before the float work, and runs the monocular
regressor once per 16 frames. Three modes:

render  full renders (the shipped sample was made so), --render-frames frames;
before  the proxy path as it was: torch's own threads (``torch_threads=0``), the float
        work on every triangle (``point_occlusion(cell_prefilter=False)``), the
        regressor frame by frame (``batch_frames=1``);
proxy   the fast path: the same statistics, other random draws (the regressor's come
        later); with ``batch_frames=1`` the same detections as ``before``
        (tests/pipeline/synth/test_detection_stats.py).

speed   a dome of --cameras cameras x --people people, no video: the per-frame cost of
        each mode (the frame loop only: a run of N frames minus a run of 1, the set-up
        both share), the modes alternated over --repeats runs; medians of wall and CPU
        seconds (CPU time is this process's own, less sensitive to other load on the
        machine; wall time on a loaded machine mostly measures the others).
stats   the shipped sample's settings (sample_data/shelf_synth/scene.json: the Shelf rig,
        its people, seed and detector noise; --stats-frames frames), the three modes,
        and the shipped sample's own detections (all its frames), by
        :func:`pipeline.synth.detection_stats.detection_statistics`.

Usage:
    python bench/bench_synth.py [--cameras 16] [--people 10] [--frames 10] [--repeats 3]
        [--render-frames 3] [--stats-frames 250] [--json FILE]
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import functools
import json
import sys
import time
from pathlib import Path
from unittest import mock

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.common import write_json  # noqa: E402
from pipeline.body.model import load_body_model  # noqa: E402
from pipeline.data.scene import load_scene  # noqa: E402
from pipeline.importers.calibration import read_voxelpose_calibration  # noqa: E402
from pipeline.synth import scene_gen  # noqa: E402
from pipeline.synth.detection_stats import detection_statistics  # noqa: E402
from pipeline.synth.detectors import DetectorNoise  # noqa: E402
from pipeline.synth.occlusion import point_occlusion  # noqa: E402
from pipeline.synth.rigs import dome_capture_radius, dome_rig  # noqa: E402
from pipeline.synth.scene_gen import SynthConfig, synthesize  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
SAMPLE = REPO / "sample_data" / "shelf_synth"
MODES = ("render", "before", "proxy")
Context = contextlib.AbstractContextManager


def mode_config(mode: str, config: SynthConfig) -> tuple[SynthConfig, Context]:
    """The config of ``mode`` and the context it runs in (``before``: no cell pre-filter)."""
    if mode == "render":
        return dataclasses.replace(config, occlusion="render"), contextlib.nullcontext()
    if mode == "before":
        slow = functools.partial(point_occlusion, cell_prefilter=False)
        patch = mock.patch.object(scene_gen, "point_occlusion", slow)
        before = dataclasses.replace(config, occlusion="proxy", torch_threads=0, batch_frames=1)
        return before, patch
    return dataclasses.replace(config, occlusion="proxy"), contextlib.nullcontext()


def frame_cost(rig, model, config: SynthConfig, mode: str = "proxy") -> tuple[float, float]:
    """(wall, CPU) seconds per frame of the frame loop: a run of ``num_frames`` minus
    a run of 1 frame (the set-up, which both share)."""
    out = []
    for n in (1, config.num_frames):
        cfg, context = mode_config(mode, dataclasses.replace(config, num_frames=n))
        with context:
            w, c = time.perf_counter(), time.process_time()
            synthesize(rig, model, cfg, progress=False)
            out.append((time.perf_counter() - w, time.process_time() - c))
    k = config.num_frames - 1
    return (out[1][0] - out[0][0]) / k, (out[1][1] - out[0][1]) / k


def sample_config(frames: int) -> tuple[object, SynthConfig]:
    meta = json.loads((SAMPLE / "scene.json").read_text())["synth"]
    rig = read_voxelpose_calibration(REPO / "sample_data" / "rigs" / "shelf_voxelpose.json")
    cfg = SynthConfig(
        num_people=meta["num_people"], num_frames=frames, seed=meta["seed"],
        render_video=False, noise=DetectorNoise(**meta["noise"]),
    )  # fmt: skip
    return rig, cfg


def shipped_statistics(noise: DetectorNoise) -> dict:
    """:func:`detection_statistics` of the shipped sample's own detections."""
    scene = load_scene(SAMPLE)
    gt = scene.gt
    P, F = int(gt.person_id.max()) + 1, scene.num_frames
    truth = np.full((P, F) + gt.keypoints3d.shape[1:], np.nan)
    truth[gt.person_id, gt.frame] = gt.keypoints3d
    return detection_statistics(scene.rig, truth, scene.detections, noise)


def speed(args, model) -> dict:
    rig = dome_rig(args.cameras)
    base = SynthConfig(
        num_people=args.people, render_video=False, area_radius_mm=dome_capture_radius()
    )
    frames = {"render": args.render_frames, "before": args.frames, "proxy": args.frames}
    runs: dict[str, list] = {m: [] for m in MODES}
    for r in range(args.repeats):
        for mode in MODES:
            cfg = dataclasses.replace(base, num_frames=frames[mode])
            runs[mode].append(frame_cost(rig, model, cfg, mode))
            w, c = runs[mode][-1]
            print(f"run {r}: {mode:6s} {w:.3f} s/frame wall, {c:.3f} s CPU", flush=True)
    med = {m: np.median(np.array(v), axis=0) for m, v in runs.items()}
    print(f"\nspeed, dome:{args.cameras} x {args.people} people, no video, "
          f"medians of {args.repeats}")  # fmt: skip
    for m in MODES:
        print(f"  {m:6s} {med[m][0]:7.3f} s/frame wall ({1 / med[m][0]:6.2f} frames/s)  "
              f"{med[m][1]:7.3f} s CPU ({1 / med[m][1]:6.2f} frames/s)")  # fmt: skip
    for m in ("render", "before"):
        print(f"  {m}/proxy  {med[m][0] / med['proxy'][0]:6.1f} x wall  "
              f"{med[m][1] / med['proxy'][1]:6.1f} x CPU")  # fmt: skip
    return {
        m: {"s_per_frame_wall": float(med[m][0]), "s_per_frame_cpu": float(med[m][1])} for m in med
    }


def statistics(args, model) -> dict:
    srig, scfg = sample_config(args.stats_frames)
    stats = {"shipped": shipped_statistics(scfg.noise)}
    for mode in MODES:
        cfg, context = mode_config(mode, scfg)
        with context:
            people, det = synthesize(srig, model, cfg, progress=False)
        stats[mode] = detection_statistics(srig, people.keypoints, det, scfg.noise)
    print(f"\ndetection statistics, shelf_synth's settings, {args.stats_frames} frames "
          "(shipped: the sample's own detections, all its frames)")  # fmt: skip
    cols = ("shipped",) + MODES
    print(f"  {'':28s}" + "".join(f"{c:>9s}" for c in cols))
    for k in stats["render"]:
        if k == "missing_by_view":
            for v in range(len(srig)):
                print(f"  {'missing, view ' + str(v):28s}"
                      + "".join(f"{stats[c][k][v]:9.4f}" for c in cols))  # fmt: skip
        else:
            print(f"  {k:28s}" + "".join(f"{stats[c][k]:9.4f}" for c in cols))
    return {c: {k: np.asarray(x).tolist() for k, x in s.items()} for c, s in stats.items()}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cameras", type=int, default=16)
    ap.add_argument("--people", type=int, default=10)
    ap.add_argument("--frames", type=int, default=10)
    ap.add_argument("--render-frames", type=int, default=3, help="frames of the slow mode")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--stats-frames", type=int, default=250, help="the sample has 250")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    model = load_body_model()
    figures = {"speed": speed(args, model), "stats": statistics(args, model)}
    if args.json:
        write_json(args.json, figures)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
