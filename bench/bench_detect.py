"""Benchmark BlazePose detection (``mvviz detect``) per camera on a clip.

For each video (default: every camera of the pose2sim demo clip,
``sample_data/pose2sim_demo/videos/``, else the synthetic Shelf renders), decodes the
first ``--frames`` frames and times, per frame:

- **detector**: the person detector, whole frame plus ``--tiles`` windows (one
  interpreter run each; its per-run time is reported too);
- **landmarks**: the ROI crops and the landmark model on every person found (also
  per person);
- **total**: both stages and the post-processing, i.e. what ``mvviz detect`` spends per
  frame besides video decoding (timed separately).

Prints medians in ms and the frames per second they give for one camera; the
interpreter runs on ``--threads`` threads (default 2, this machine's cores). Wall-clock
times on a shared machine vary; the process CPU time is printed beside them.

Usage:
    python bench/bench_detect.py [--video PATH ...] [--frames N] [--tiles N]
        [--threads N] [--json FILE]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.common import write_json  # noqa: E402
from pipeline.detect.blazepose import (  # noqa: E402
    BlazePose,
    InterpreterMissingError,
    alignment_rois,
    tile_windows,
)
from pipeline.detect.video import iter_frames  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
DEFAULT_CLIPS = (
    REPO / "sample_data" / "pose2sim_demo" / "videos",
    REPO / "sample_data" / "shelf_synth" / "videos",
)


def default_videos() -> list[Path]:
    for folder in DEFAULT_CLIPS:
        found = sorted(folder.glob("*.mp4")) if folder.is_dir() else []
        if found:
            return found
    raise SystemExit("no clip found; pass --video PATH")


def bench_video(runner: BlazePose, path: Path, frames: int) -> dict:
    t_decode, t_det, t_det_run, t_lm, t_lm_person, t_total, people = [], [], [], [], [], [], []
    cpu0 = time.process_time()
    wall0 = time.perf_counter()
    t = time.perf_counter()
    for _, image in iter_frames(path, stop=frames):
        t_decode.append(time.perf_counter() - t)
        t0 = time.perf_counter()
        dets = runner.detect(image)
        t1 = time.perf_counter()
        rois = alignment_rois(dets.keypoints, scale=runner.roi_scale)
        runner.landmarks(image, rois)
        t2 = time.perf_counter()
        runs = 1 + len(tile_windows(image.shape[1], image.shape[0], runner.tiles))
        t_det.append(t1 - t0)
        t_det_run.append((t1 - t0) / runs)
        t_lm.append(t2 - t1)
        if len(rois):
            t_lm_person.append((t2 - t1) / len(rois))
        t3 = time.perf_counter()
        poses = runner(image)
        t_total.append(time.perf_counter() - t3)
        people.append(len(poses))
        t = time.perf_counter()
    wall = time.perf_counter() - wall0
    cpu = time.process_time() - cpu0

    def ms(x: list[float]) -> float:
        return float(1e3 * np.median(x)) if x else float("nan")

    return {
        "video": str(path),
        "frames": len(t_det),
        "size": list(image.shape[1::-1]),
        "people_per_frame_mean": float(np.mean(people)),
        "decode_ms": ms(t_decode),
        "detector_ms": ms(t_det),
        "detector_runs_per_frame": runs,
        "detector_ms_per_run": ms(t_det_run),
        "landmarks_ms": ms(t_lm),
        "landmarks_ms_per_person": ms(t_lm_person),
        "total_ms": ms(t_total),
        "fps_detector": 1e3 / ms(t_det),
        "fps_landmarks": 1e3 / ms(t_lm) if t_lm_person else float("nan"),
        "fps_total": 1e3 / ms(t_total),
        "cpu_over_wall": cpu / wall,
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--video", type=Path, nargs="+", default=None, help="clip(s), one per camera")
    p.add_argument("--frames", type=int, default=40, help="frames per video (default 40)")
    p.add_argument("--tiles", type=int, default=2, help="detector tiles (as mvviz detect)")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--json", type=Path, default=None, help="write the figures here")
    args = p.parse_args(argv)
    try:
        runner = BlazePose(num_threads=args.threads, tiles=args.tiles)
    except InterpreterMissingError as exc:
        raise SystemExit(str(exc)) from None
    videos = args.video or default_videos()
    rows = []
    print(
        f"{'video':<28} {'size':>10} {'ppl':>4} {'detector ms (runs)':>19} {'landmarks ms':>13} "
        f"{'/person':>8} {'total ms':>9} {'fps':>6} {'decode ms':>10}"
    )
    for path in videos:
        r = bench_video(runner, path, args.frames)
        rows.append(r)
        print(
            f"{path.parent.parent.name + '/' + path.name:<28} {r['size'][0]:>4}x{r['size'][1]:<5} "
            f"{r['people_per_frame_mean']:>4.1f} "
            f"{r['detector_ms']:>9.1f} "
            f"({r['detector_runs_per_frame']}x{r['detector_ms_per_run']:.1f}) "
            f"{r['landmarks_ms']:>13.1f} {r['landmarks_ms_per_person']:>8.1f} "
            f"{r['total_ms']:>9.1f} {r['fps_total']:>6.2f} {r['decode_ms']:>10.1f}"
        )
    print(
        f"median over cameras: detector {np.median([r['fps_detector'] for r in rows]):.2f} fps, "
        f"landmarks {np.nanmedian([r['fps_landmarks'] for r in rows]):.2f} fps, "
        f"both {np.median([r['fps_total'] for r in rows]):.2f} fps per camera "
        f"(CPU/wall {np.median([r['cpu_over_wall'] for r in rows]):.2f}, {args.threads} threads)"
    )
    if args.json:
        write_json(args.json, {"threads": args.threads, "tiles": args.tiles, "videos": rows})
    return 0


if __name__ == "__main__":
    sys.exit(main())
