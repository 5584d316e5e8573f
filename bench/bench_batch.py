"""Benchmark ``mvviz batch`` on embedded local Ray against ``mvviz run`` scene after scene.

Makes (once) 8 sample-sized scenes with ``mvviz synth`` (Shelf rig, 5 cameras, 3
people, 100 frames, no videos, seeds 101..108) under --scenes, then alternates, --repeats
times:

- serial: one ``python`` process running ``mvviz run SCENE --force`` for every scene,
  one after another (what a user does today, imports paid once);
- batch: ``mvviz batch SCENE... --force`` (embedded Ray on every core: its start, the
  workers' imports and its shutdown are counted).

Both are timed from the command to its exit. Prints the medians, the ratio, the load
average at each run (the machine is shared) and Ray's own start-up cost (``ray.init``, a
trivial task, ``ray.shutdown`` in a fresh process); checks the last repeat's results of
the two ways are equal array for array.

Usage:
    python bench/bench_batch.py [--scenes DIR] [--repeats N] [--json FILE]
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench.common import write_json  # noqa: E402

NUM_SCENES = 8
SERIAL = """
import sys
from pathlib import Path
from mvviz.cli import main
out = Path(sys.argv[1])
for scene in sys.argv[2:]:
    code = main(["run", scene, "--force", "--out", str(out / Path(scene).name / "results.npz")])
    assert code == 0, scene
"""
RAY_START = """
import time, tempfile, os
t0 = time.perf_counter()
from pipeline.batch.ray_run import start_ray, stop_ray
import ray
t1 = time.perf_counter()
start_ray()
t2 = time.perf_counter()
ray.get([ray.remote(lambda: 1).remote() for _ in range(2)])
t3 = time.perf_counter()
stop_ray()
t4 = time.perf_counter()
print(f"{t1 - t0:.3f} {t2 - t1:.3f} {t3 - t2:.3f} {t4 - t3:.3f}")
"""


def make_scenes(root: Path) -> list[Path]:
    scenes = [root / f"s{i}" for i in range(1, NUM_SCENES + 1)]
    for i, s in enumerate(scenes, 1):
        if not (s / "scene.json").is_file():
            print(f"synthesising {s} ...", flush=True)
            cmd = [sys.executable, "-m", "mvviz.cli", "synth", str(s), "--frames", "100",
                   "--people", "3", "--seed", str(100 + i), "--no-video"]  # fmt: skip
            subprocess.run(cmd, check=True, cwd=REPO, stdout=subprocess.DEVNULL)
    return scenes


def timed(cmd: list[str]) -> float:
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True, cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return time.perf_counter() - t0


def same_results(a: Path, b: Path) -> bool:
    with np.load(a) as x, np.load(b) as y:
        if sorted(x.files) != sorted(y.files):
            return False
        return all(np.array_equal(x[k], y[k], equal_nan=x[k].dtype.kind == "f") for k in x.files)


def main() -> int:
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--scenes", type=Path, default=Path(tempfile.gettempdir()) / "mvviz_bench_batch")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--json", type=Path, default=None)
    args = p.parse_args()
    scenes = make_scenes(args.scenes)
    names = [str(s) for s in scenes]
    ray_start = [float(x) for x in subprocess.run(
        [sys.executable, "-c", RAY_START], check=True, cwd=REPO, capture_output=True, text=True
    ).stdout.split()]  # fmt: skip
    print(f"ray: import {ray_start[0]:.2f} s, init {ray_start[1]:.2f} s, "
          f"first tasks {ray_start[2]:.2f} s, shutdown {ray_start[3]:.2f} s")  # fmt: skip
    serial, batch, loads = [], [], []
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(args.repeats):
            loads.append(os.getloadavg()[0])
            serial.append(timed([sys.executable, "-c", SERIAL, f"{tmp}/serial", *names]))
            loads.append(os.getloadavg()[0])
            cmd = [sys.executable, "-m", "mvviz.cli", "batch", *names, "--force",
                   "--out", f"{tmp}/batch", "--report", f"{tmp}/report"]  # fmt: skip
            batch.append(timed(cmd))
            print(f"repeat {r + 1}: serial {serial[-1]:.1f} s, batch {batch[-1]:.1f} s "
                  f"(load {loads[-2]:.1f} / {loads[-1]:.1f})", flush=True)  # fmt: skip
        equal = all(
            same_results(
                Path(tmp, "serial", s.name, "results.npz"),
                Path(tmp, "batch", s.name, "results.npz"),
            )
            for s in scenes
        )
    figures = {
        "scenes": NUM_SCENES,
        "cpus": os.cpu_count(),
        "serial_s": serial,
        "batch_s": batch,
        "serial_median_s": statistics.median(serial),
        "batch_median_s": statistics.median(batch),
        "speedup": statistics.median(serial) / statistics.median(batch),
        "load_1min": loads,
        "ray_start_s": dict(
            zip(("import", "init", "first_tasks", "shutdown"), ray_start, strict=True)
        ),
        "results_equal": equal,
    }
    print(f"serial median {figures['serial_median_s']:.1f} s, batch median "
          f"{figures['batch_median_s']:.1f} s: {figures['speedup']:.2f}x "
          f"(target 1.7x); results equal: {equal}")  # fmt: skip
    if args.json:
        write_json(args.json, figures)
    return 0


if __name__ == "__main__":
    sys.exit(main())
