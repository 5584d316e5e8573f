"""Benchmark the viewer on a Panoptic-sized scene: 31 cameras, 20 people.

Synthesises (once, into --cache; fast, no video) a ``dome:31:5000`` scene with 20 people
over --frames frames, runs the pipeline once and writes its results in both layouts of
:mod:`pipeline.results.store`: the memory-mapped directory (``results/``) and, as the baseline,
the one compressed file read whole (``results.npz``). Then, each layout in turn, --runs
times alternated:

- ``python app.py SCENE --out RESULTS`` as a user starts it: seconds from the command to
  the first HTTP answer and to the "ready" line (scene loaded, viewer built, first frame
  drawn), the process's CPU seconds and its resident memory (VmRSS, and the peak VmHWM)
  at that point;
- in this process, the viewer on that layout with the layers ``python app.py`` opens
  with (:data:`APP_LAYERS`: meshes off; past 8 cameras the 2D detections on the camera
  panel's frustum only), started by bench/bench_viewer.py's ``start_app`` and measured
  by its ``measure``: --changes random frame changes, server time and CPU per change
  (median, p95) and the bytes on the wire per change with 31 frusta, broken down by what
  they update. Then, on the directory only, every layer on (:data:`EVERY_LAYER`: meshes,
  fitted bodies on the image, 2D detections on all 31 frusta).

With --video-frames F (default 20; 0: skip) a twin scene of the same rig and people with
videos (``--video-scale``) is synthesised over F frames: the same frame-change figures
with the 31 frusta showing video, which is what the frustum images cost on the wire.

With --scene DIR (and --config FILE) the same start and frame-change figures on an
existing scene, results directory only (e.g. bench_memory.py's tiled 10,000-frame dome,
whose ``results.npz`` would take longer to write than the rest).

Nothing is extrapolated: the figures are those of the frames synthesised.

Usage:
    python bench/bench_viewer_scale.py [--frames 150] [--runs 3] [--changes 30]
                                       [--video-frames 20] [--cache DIR] [--json FILE]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench.bench_startup import poll_http, repo_env  # noqa: E402
from bench.bench_viewer import measure, report, start_app  # noqa: E402
from bench.common import free_port, write_json  # noqa: E402
from mvviz.scene.images import FrameStore  # noqa: E402
from pipeline.body.model import load_body_model  # noqa: E402
from pipeline.config import PipelineConfig, load_config  # noqa: E402
from pipeline.core.files import CACHE_DIR  # noqa: E402
from pipeline.data.scene import Scene, load_scene  # noqa: E402
from pipeline.results.store import load_results, save_results  # noqa: E402
from pipeline.run.pipeline import run_or_load  # noqa: E402

DOME_MM, AREA_MM = 5000.0, 4200.0  # 20 people cannot walk 150 frames in the 3 m circle
LAYOUTS = {"directory": "results", "npz": "results.npz"}  # under SCENE/.mvviz
TARGET_S, TARGET_MS, TARGET_KB = 5.0, 20.0, 100.0
START_KEYS = ("http_s", "ready_s", "cpu_s", "rss_mb", "peak_rss_mb")
CHANGE_KEYS = ("median_ms", "p95_ms", "median_cpu_ms", "median_kb", "open_and_build_cpu_s")
# start_app turns every layer on; these options give the layers app.py opens a
# 31-camera scene with, and every layer with the 2D detections on every frustum
APP_LAYERS = {"meshes": False, "fit_meshes": False, "bodies_on_images": False,
              "detections2d_panel_camera_only": True}  # fmt: skip
EVERY_LAYER = {"detections2d_panel_camera_only": False}


def dome_scene(out: Path, cams: int, people: int, frames: int, seed: int, video: float) -> Scene:
    """The scene, synthesised once (``video`` > 0: with videos at that scale)."""
    if not (out / "scene.json").exists():
        from pipeline.synth.rigs import dome_rig
        from pipeline.synth.scene_gen import SynthConfig, write_synth_scene

        t0 = time.perf_counter()
        cfg = SynthConfig(
            num_people=people, num_frames=frames, seed=seed, render_video=video > 0,
            video_scale=video or 1.0, area_radius_mm=AREA_MM, occlusion="auto",
        )  # fmt: skip
        write_synth_scene(out, dome_rig(cams, radius_mm=DOME_MM), load_body_model(), cfg,
                          progress=False)  # fmt: skip
        print(f"synthesised {out.name} in {time.perf_counter() - t0:.0f} s", flush=True)
    return load_scene(out)


def results_in_both_layouts(
    scene: Scene, model, config: PipelineConfig | None = None, layouts: dict = LAYOUTS
) -> dict[str, Path]:
    """Run the pipeline once (or reuse its results) and write ``layouts`` (default both)."""
    paths = {k: scene.root / CACHE_DIR / v for k, v in layouts.items()}
    t0 = time.perf_counter()
    config = PipelineConfig() if config is None else config
    results, cached = run_or_load(scene, config, model, out=paths["directory"])
    print(f"pipeline: {'cached' if cached else 'ran'} in {time.perf_counter() - t0:.0f} s; "
          f"{len(results.det_person)} detections, {len(results.person_frame)} person-frames, "
          f"{len(results.edge_a)} edges, {results.num_tracks} tracks", flush=True)  # fmt: skip
    if "npz" in paths:
        save_results(results, paths["npz"])
    for k, p in paths.items():
        size = sum(f.stat().st_size for f in p.iterdir()) if p.is_dir() else p.stat().st_size
        print(f"  {k}: {p} {size / 2**20:.1f} MB", flush=True)
    return paths


def proc_figures(pid: int) -> dict[str, float]:
    """CPU seconds, resident and peak resident MB of process ``pid`` (Linux /proc)."""
    status = dict(
        line.split(":", 1) for line in Path(f"/proc/{pid}/status").read_text().splitlines()
    )
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    ticks = os.sysconf("SC_CLK_TCK")
    return {
        "cpu_s": (int(fields[11]) + int(fields[12])) / ticks,  # utime + stime
        "rss_mb": int(status["VmRSS"].split()[0]) / 1024,
        "peak_rss_mb": int(status["VmHWM"].split()[0]) / 1024,
    }


def time_app_start(scene: Path, results: Path, extra: tuple = ()) -> dict[str, float]:
    """``python app.py SCENE --out RESULTS``: seconds to the first HTTP answer and to the
    ready line, and the process's CPU and memory then."""
    port = free_port()
    out: dict[str, float] = {}
    stop = threading.Event()
    t0 = time.perf_counter()
    poller = threading.Thread(
        target=poll_http, args=(f"http://127.0.0.1:{port}", t0, out, stop), daemon=True
    )
    poller.start()
    cmd = [sys.executable, "app.py", str(scene), "--out", str(results), "--port", str(port),
           *extra]  # fmt: skip
    proc = subprocess.Popen(
        cmd, cwd=REPO, env=repo_env(REPO), stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
        text=True,
    )  # fmt: skip
    try:
        for line in proc.stdout:
            if line.startswith(("associate", "computed results")):
                raise RuntimeError(
                    "app.py re-runs the pipeline: its code changed since the results were made "
                    "(run the benchmark in a checkout nobody edits, e.g. a git worktree)"
                )
            if line.startswith("ready in"):
                out["ready_s"] = time.perf_counter() - t0
                out |= proc_figures(proc.pid)
                break
        else:
            raise RuntimeError(f"app.py exited with {proc.wait()} before it was ready")
    finally:
        poller.join(timeout=10)
        stop.set()
        proc.terminate()
        proc.wait(timeout=30)
    return out


def frame_changes(
    scene: Scene, path: Path, model, frames, changes: np.ndarray, layers: dict
) -> dict:
    """The viewer in this process on results ``path`` with ``layers`` (start_app's
    options): ``changes`` frame changes."""
    t0 = time.process_time()
    peak, stop = [0.0], threading.Event()

    def sample() -> None:  # this process's resident memory while the viewer runs
        while not stop.wait(0.05):
            peak[0] = max(peak[0], proc_figures(os.getpid())["rss_mb"])

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    results = load_results(path, model=model)
    app, tap = start_app(scene, results, model, frames, **layers)
    try:
        built_cpu = time.process_time() - t0
        measure(app, tap, changes[:3], None)  # warm up
        r = measure(app, tap, changes, None)
    finally:
        app.stop()
        stop.set()
        sampler.join()
    print(f"  viewer process RSS peak {peak[0]:.0f} MB", flush=True)
    return {**r, "open_and_build_cpu_s": built_cpu, "viewer_rss_peak_mb": peak[0]}


def median_of(runs: list[dict], key: str) -> float:
    return float(np.median([r[key] for r in runs]))


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--cameras", type=int, default=31)
    ap.add_argument("--people", type=int, default=20)
    ap.add_argument("--frames", type=int, default=150)
    ap.add_argument("--seed", type=int, default=3120)
    ap.add_argument("--runs", type=int, default=3, help="starts and frame-change runs per layout")
    ap.add_argument("--changes", type=int, default=30, help="frame changes per run")
    ap.add_argument("--video-frames", type=int, default=20, help="frames of the video twin")
    ap.add_argument("--video-scale", type=float, default=0.34)
    ap.add_argument("--cache", type=Path, default=Path("/tmp/mvviz_bench_viewer_scale"))
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--scene", type=Path, default=None,
                    help="an existing scene instead of the synthesised dome (results directory "
                         "only; e.g. bench_memory.py's tiled 10,000-frame scene)")  # fmt: skip
    ap.add_argument("--config", type=Path, default=None,
                    help="pipeline config JSON for the run and app.py")  # fmt: skip
    args = ap.parse_args(argv)
    model = load_body_model()
    config, extra, layouts = PipelineConfig(), (), LAYOUTS
    if args.config is not None:
        config, extra = load_config(args.config), ("--config", str(args.config))
    if args.scene is not None:
        scene, layouts = load_scene(args.scene), {"directory": LAYOUTS["directory"]}
    else:
        name = f"dome{args.cameras}_p{args.people}"
        scene = dome_scene(
            args.cache / f"{name}_f{args.frames}", args.cameras, args.people, args.frames,
            args.seed, 0.0,
        )  # fmt: skip
    print(f"scene {scene.root}: {len(scene.rig)} cameras, {scene.num_frames} frames, "
          f"{len(scene.detections)} detections", flush=True)  # fmt: skip
    paths = results_in_both_layouts(scene, model, config, layouts)
    rng = np.random.default_rng(0)
    changes = rng.integers(0, scene.num_frames, args.changes + 3)
    starts: dict[str, list[dict]] = {k: [] for k in layouts}
    changed: dict[str, list[dict]] = {k: [] for k in (*layouts, "every layer")}
    for run in range(args.runs):
        for layout in layouts:
            s = time_app_start(scene.root, paths[layout], extra)
            starts[layout].append(s)
            print(f"run {run} {layout}: app.py first HTTP answer {s.get('http_s', np.nan):.2f} s, "
                  f"ready {s['ready_s']:.2f} s (CPU {s['cpu_s']:.1f} s), RSS "
                  f"{s['rss_mb']:.0f} MB (peak {s['peak_rss_mb']:.0f})", flush=True)  # fmt: skip
            c = frame_changes(scene, paths[layout], model, None, changes, APP_LAYERS)
            changed[layout].append(c)
            report(f"run {run} {layout}: frame change, app.py's layers", c)
        c = frame_changes(scene, paths["directory"], model, None, changes, EVERY_LAYER)
        changed["every layer"].append(c)
        report(f"run {run} directory: frame change, every layer", c)
    out: dict = {"scene": str(scene.root), "frames": scene.num_frames,
                 "detections": len(scene.detections), "layouts": {}}  # fmt: skip
    for layout in layouts:
        st, ch = starts[layout], changed[layout]
        out["layouts"][layout] = {
            **{k: median_of(st, k) for k in START_KEYS},
            **{k: median_of(ch, k) for k in CHANGE_KEYS},
            "breakdown_kb": ch[-1]["breakdown_kb"],
            "starts": st,
        }  # fmt: skip
    ch = changed["every layer"]
    out["every_layer"] = {**{k: median_of(ch, k) for k in CHANGE_KEYS},
                          "breakdown_kb": ch[-1]["breakdown_kb"]}  # fmt: skip
    if args.video_frames > 0:
        out["video"] = video_twin(args, model)
    summary(out)
    if args.json:
        write_json(args.json, out)
    return out


def video_twin(args: argparse.Namespace, model) -> dict:
    """Frame changes with 31 frusta showing video: the twin scene with videos."""
    scene = dome_scene(
        args.cache / f"dome{args.cameras}_p{args.people}_f{args.video_frames}_video",
        args.cameras, args.people, args.video_frames, args.seed, args.video_scale,
    )  # fmt: skip
    paths = results_in_both_layouts(scene, model)
    frames = FrameStore(scene, cache_dir=scene.root / CACHE_DIR / "frames").start()
    assert frames.wait(600), "decoding the twin's videos took too long"
    changes = np.random.default_rng(1).integers(0, scene.num_frames, args.changes + 3)
    out = {}
    for name, layers in (("app_layers", APP_LAYERS), ("every_layer", EVERY_LAYER)):
        runs = [frame_changes(scene, paths["directory"], model, frames, changes, layers)
                for _ in range(args.runs)]  # fmt: skip
        for i, r in enumerate(runs):
            report(f"video twin run {i}: frame change, {name}", r)
        out[name] = {**{k: median_of(runs, k) for k in CHANGE_KEYS},
                     "breakdown_kb": runs[-1]["breakdown_kb"]}  # fmt: skip
    return out


def summary(out: dict) -> None:
    print(f"\n{out['frames']} frames, {out['detections']} detections; medians of the runs:")
    for layout, r in out["layouts"].items():
        print(
            f"  {layout:>9s}: first HTTP answer {r['http_s']:.2f} s, ready {r['ready_s']:.2f} s "
            f"(target <= {TARGET_S:.0f} s), CPU {r['cpu_s']:.1f} s, RSS {r['rss_mb']:.0f} MB "
            f"(peak {r['peak_rss_mb']:.0f}); frame change {r['median_ms']:.1f} ms "
            f"(CPU {r['median_cpu_ms']:.1f}, target <= {TARGET_MS:.0f}), "
            f"{r['median_kb']:.1f} KB (target <= {TARGET_KB:.0f})"
        )
    e = out["every_layer"]
    print(f"  every layer (directory): frame change {e['median_ms']:.1f} ms (CPU "
          f"{e['median_cpu_ms']:.1f}), {e['median_kb']:.1f} KB")  # fmt: skip
    if "npz" in out["layouts"]:
        d, z = out["layouts"]["directory"], out["layouts"]["npz"]
        print(f"  directory / npz: ready {d['ready_s'] / z['ready_s']:.2f}x, RSS "
              f"{d['rss_mb'] / z['rss_mb']:.2f}x, frame change CPU "
              f"{d['median_cpu_ms'] / z['median_cpu_ms']:.2f}x")  # fmt: skip
    for name, v in out.get("video", {}).items():
        print(f"  video on the 31 frusta, {name}: frame change {v['median_ms']:.1f} ms (CPU "
              f"{v['median_cpu_ms']:.1f}), {v['median_kb']:.1f} KB")  # fmt: skip


if __name__ == "__main__":
    main()
