"""Benchmark ``mvviz batch`` on embedded local Ray against ``mvviz run`` scene after scene.

Makes (once) 8 sample-sized scenes with ``mvviz synth`` (Shelf rig, 5 cameras and, as
the shipped ``sample_data/shelf_synth``, 4 people and 250 frames; ``--people`` /
``--frames`` for other sizes; no videos, seeds 101..108) under --scenes, then alternates, --repeats
times:

- serial: one ``python`` process running ``mvviz run SCENE --force`` for every scene,
  one after another (what a user does without batch: the same code path, imports paid once,
  torch's default threads, ended as the ``mvviz`` script ends), each followed by the
  evaluation the batch's report holds for it (the results read back,
  :func:`pipeline.batch.jobs.summarize`), timed apart: the speed-up is printed against
  the same work and against ``mvviz run`` alone;
- batch: ``mvviz batch SCENE... --force`` (embedded Ray on every core: its start, the
  workers' imports, the report and its shutdown are counted);
- the no-Ray split: the serial process's work split by hand into one plain process per
  core (scenes dealt round-robin), all started at once: what this machine gives that many
  busy processes at that moment, Ray or not. On this shared VM two busy processes each
  run 10-20 % slower than one alone (their CPU seconds grow too: caches, memory and the
  host's other tenants), so even a perfect split stays below 2x; the batch is printed
  against it as well.

- with ``--per-command``, the scenes as a user runs them by hand: one ``mvviz run
  SCENE --force`` command after another (each pays its imports and its exit; no
  evaluation, so the batch, which evaluates every scene, is compared against less work).

Both are timed from the command to its exit. Prints, each repeat with the 1-minute load
average before it and the seconds in which the machine stalled on I/O meanwhile (the
kernel's ``/proc/pressure/io``: a shared VM's page cache drops torch's and Ray's
libraries, and a command that reads them back from disk waits seconds for it), then the
medians and their ratio (and the median of the per-repeat ratios: a repeat's two run
back to back, on a VM whose speed drifts), and the parts. On a shared machine the ratio
means nothing while other work runs: with a load above the core count the
cores are taken, and with the kernel's autogroup scheduling on
(``/proc/sys/kernel/sched_autogroup_enabled``, printed) CPU time is shared per session,
and Ray's workers are in the session of ``mvviz batch``, so beside other busy sessions
the two workers together get the share the serial process gets alone. The parts:

- Ray's own start-up in a fresh process: import, ``ray.init``, the first task on every
  worker that imports the pipeline (worker start + torch), ``ray.shutdown``, and the CPU
  seconds of Ray's processes (GCS, raylet, agents, idle workers) by then;
- the driver of ``mvviz batch`` in a fresh process: its imports and the planning of the
  scenes (scene, config, body model, cache key), wall and CPU, and whether torch loaded;
- per repeat, the batch's wall beyond its tasks' work: wall - the sum of the task walls /
  the cores (what Ray's start, the workers' first imports, the driver's own work and the
  shutdown add where the tasks do not hide them), and its timeline from the tasks' start
  and end times: the start-up (command to first scene task), the tail (last task's end
  to the exit), the workers that ran scenes, and the core-seconds left idle between the
  first and the last task;
- per scene, medians over scenes and repeats: ``mvviz run``'s wall and CPU seconds in
  the serial process, and the batch task's per stage (load, frames = restoration +
  association + triangulation, sequence_fit = tracking + filters + SMPL fit,
  summary_save = the report's figures + writing the results), wall and CPU;
- the SMPL fit of one scene with 1 and with 2 torch threads (``smpl_fit.num_threads``,
  alternated), and whether the two give the same numbers.

Then the bound: the batch's tasks' CPU seconds, Ray's start-up CPU and the driver's,
perfectly packed on the cores, and the speed-up that allows.

Checks that the last repeat's results of the two ways (and of the commands, with
``--per-command``) are equal array for array (and names the entries that differ, if any).

Usage:
    python bench/bench_batch.py [--scenes DIR] [--frames N] [--people N] [--repeats N]
                                [--per-command] [--json FILE]
"""

from __future__ import annotations

import argparse
import json
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
import sys, time
from pathlib import Path
from mvviz.cli import main
out = Path(sys.argv[1])
for scene in sys.argv[2:]:
    t, c = time.perf_counter(), time.process_time()
    path = out / Path(scene).name / "results.npz"
    code = main(["run", scene, "--force", "--out", str(path)])
    assert code == 0, scene
    print("SCENE", time.perf_counter() - t, time.process_time() - c, file=sys.stderr)
    # the evaluation the batch's report holds, as a user would add it: the results read
    # back, the scene's summary (timed apart: the serial time with and without it)
    t = time.perf_counter()
    from pipeline.batch.jobs import summarize
    from pipeline.results.store import load_results
    from pipeline.data.scene import load_scene
    summarize(load_scene(scene), load_results(path))
    print("EVAL", time.perf_counter() - t, file=sys.stderr)
# ended as the mvviz script ends (mvviz batch too), without the interpreter's teardown
from mvviz.cli import exit_now
exit_now(0)
"""
RAY_START = """
import json, os, time
t0 = time.perf_counter()
from pipeline.batch.ray_run import start_ray, stop_ray
import ray
t1 = time.perf_counter()
cpus = int(start_ray()["CPU"])
t2 = time.perf_counter()

def warm():
    import pipeline.batch.jobs, torch  # what a scene task imports first
    time.sleep(0.5)  # every worker gets one
    return os.getpid()

pids = set(ray.get([ray.remote(warm).remote() for _ in range(cpus)]))
t3 = time.perf_counter()

def tree_cpu(pid):
    tick, total = os.sysconf("SC_CLK_TCK"), 0.0
    for p in os.listdir("/proc"):
        try:
            f = open(f"/proc/{p}/stat").read().rsplit(")", 1)[1].split()
        except (OSError, IndexError):
            continue
        if p.isdigit() and int(f[1]) == pid:
            total += (int(f[11]) + int(f[12])) / tick + tree_cpu(int(p))
    return total

ray_cpu = tree_cpu(os.getpid())
stop_ray()
t4 = time.perf_counter()
print(json.dumps(dict(import_s=t1 - t0, init_s=t2 - t1, warm_workers_s=t3 - t2,
      shutdown_s=t4 - t3, workers=len(pids), ray_processes_cpu_s=ray_cpu)))
"""
DRIVER = """
import json, sys, time
t0, c0 = time.perf_counter(), time.process_time()
from mvviz.cli import build_parser
argv = ["batch", *sys.argv[1:], "--force"]
args = build_parser(argv).parse_args(argv)
t1, c1 = time.perf_counter(), time.process_time()
from mvviz.cli.batch import plan
jobs, scenes, model, bad = plan(args)
t2, c2 = time.perf_counter(), time.process_time()
print(json.dumps(dict(imports_s=t1 - t0, imports_cpu_s=c1 - c0, plan_s=t2 - t1,
      plan_cpu_s=c2 - c1, torch_imported="torch" in sys.modules)))
"""
FIT_THREADS = """
import json, statistics, sys, time
import numpy as np
from pipeline.body.model import load_body_model
from pipeline.config import PipelineConfig
from pipeline.run.pipeline import fit_bodies, run_stages
from pipeline.run.frames import restored_joints, select_2d
from pipeline.data.scene import load_scene
scene, model = load_scene(sys.argv[1]), load_body_model()
base = PipelineConfig()
j2d = select_2d(scene, base, restored := restored_joints(scene, model))
packed = run_stages(scene, base, j2d, restored=restored, progress=False)
wall, fits = {1: [], 2: []}, {}
for _ in range(int(sys.argv[2])):
    for n in (1, 2):
        cfg = base.with_overrides([f"smpl_fit.num_threads={n}"])
        t = time.perf_counter()
        fits[n] = fit_bodies(packed, cfg, model, progress=False)
        wall[n].append(time.perf_counter() - t)
same = all(np.array_equal(a, fits[2].smpl.arrays("")[k], equal_nan=True)
           for k, a in fits[1].smpl.arrays("").items())
print(json.dumps(dict(fit_1_thread_s=statistics.median(wall[1]),
      fit_2_threads_s=statistics.median(wall[2]), same_numbers=same)))
"""


def autogroup() -> str:
    try:
        return {"0": "off", "1": "on"}[Path("/proc/sys/kernel/sched_autogroup_enabled")
                                       .read_text().strip()]  # fmt: skip
    except (OSError, KeyError):
        return "unknown"


def make_scenes(root: Path, frames: int = 250, people: int = 4) -> list[Path]:
    root = root / f"f{frames}_p{people}"
    scenes = [root / f"s{i}" for i in range(1, NUM_SCENES + 1)]
    for i, s in enumerate(scenes, 1):
        # A seed whose people cannot all be placed on the rig's floor is skipped for the
        # next one (seed 106 with 4 people on the Shelf rig, for one).
        for seed in range(100 + i, 100 + i + 10 * NUM_SCENES, NUM_SCENES):
            if (s / "scene.json").is_file():
                break
            print(f"synthesising {s} (seed {seed}) ...", flush=True)
            cmd = [sys.executable, "-m", "mvviz.cli", "synth", str(s), "--frames", str(frames),
                   "--people", str(people), "--seed", str(seed), "--no-video"]  # fmt: skip
            done = subprocess.run(
                cmd, cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True
            )
        if not (s / "scene.json").is_file():
            last = (done.stderr.strip().splitlines() or ["no error output"])[-1]
            raise SystemExit(f"bench_batch: could not synthesise {s} ({people} people): {last}")
    return scenes


def io_stall_s() -> float | None:
    """Seconds so far in which some task on this machine waited on I/O (the kernel's
    pressure stall information, ``/proc/pressure/io``; None where the kernel has none).
    A repeat whose command read its libraries from disk (a shared VM's page cache drops
    them) shows it here: the cause of most outliers, not the code."""
    try:
        some = Path("/proc/pressure/io").read_text().splitlines()[0]
        return int(some.rpartition("total=")[2]) / 1e6
    except (OSError, IndexError, ValueError):
        return None


def timed(cmd: list[str]) -> tuple[float, str, float | None]:
    """(wall seconds, stderr, seconds stalled on I/O machine-wide meanwhile) of ``cmd``."""
    io0, t0 = io_stall_s(), time.perf_counter()
    done = subprocess.run(
        cmd, check=True, cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True
    )
    took, io1 = time.perf_counter() - t0, io_stall_s()
    return took, done.stderr, (None if io0 is None or io1 is None else round(io1 - io0, 2))


def timed_commands(names: list[str], out: str) -> float:
    """Wall seconds of one ``mvviz run SCENE --force`` command per scene, one after
    another: each scene run by hand, as before ``mvviz batch``."""
    t0 = time.perf_counter()
    for scene in names:
        path = Path(out, Path(scene).name, "results.npz")
        timed([sys.executable, "-m", "mvviz.cli", "run", scene, "--force", "--out", str(path)])
    return time.perf_counter() - t0


def timed_split(groups: list[list[str]], out: str) -> float:
    """Wall seconds of one serial process per group of scenes, all started at once: the
    same work split by hand with no Ray, so each process pays its own imports and the
    cores are shared as the batch's workers share them."""
    t0 = time.perf_counter()
    procs = [
        subprocess.Popen([sys.executable, "-c", SERIAL, out, *g], cwd=REPO,
                         stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        for g in groups
    ]  # fmt: skip
    if any([p.wait() for p in procs]):  # every one waited for, not just to the first failure
        raise SystemExit("bench_batch: a process of the no-Ray split failed")
    return time.perf_counter() - t0


def python_json(code: str, *argv: str) -> dict:
    done = subprocess.run([sys.executable, "-c", code, *argv], check=True, cwd=REPO,
                          capture_output=True, text=True)  # fmt: skip
    return json.loads(done.stdout.strip().splitlines()[-1])


def differing(a: Path, b: Path) -> list[str]:
    """The entries of two results files that differ (``meta.cache_key`` alone: the
    pipeline's source changed between the two runs, e.g. someone editing the checkout)."""
    with np.load(a) as x, np.load(b) as y:
        out = sorted(set(x.files) ^ set(y.files))
        for k in sorted(set(x.files) & set(y.files)):
            if k == "meta":
                mx, my = json.loads(str(x[k])), json.loads(str(y[k]))
                out += [f"meta.{m}" for m in sorted(set(mx) | set(my)) if mx.get(m) != my.get(m)]
            elif not np.array_equal(x[k], y[k], equal_nan=x[k].dtype.kind == "f"):
                out.append(k)
        return out


def medians(rows: list[dict]) -> dict:
    """Per key ending in ``_s`` (seconds), its median over ``rows``."""
    keys = [k for k in rows[0] if k.endswith("_s")] if rows else []
    return {k: round(statistics.median(r[k] for r in rows), 3) for k in keys}


def timeline(rows: list[dict], t0: float, t1: float) -> dict:
    """Where a batch's wall went (Unix times ``t0`` the command, ``t1`` its exit), from
    the report's task timeline (:func:`pipeline.batch.report.task_timeline`): start-up
    (command to first task), tail (last task to exit), the workers that ran scenes, and
    the core-seconds idle between the first and the last task."""
    from pipeline.batch.report import task_timeline  # matplotlib

    tl = task_timeline(rows, t0)
    if tl is None:
        return {}
    span, cores = tl["span_s"], os.cpu_count() or 1
    busy = sum(t["end_s"] - t["start_s"] for t in tl["tasks"])
    return {
        "startup_s": round(tl["startup_s"], 2),
        "tail_s": round(t1 - t0 - tl["startup_s"] - span, 2),
        "workers": tl["workers"], "idle_core_s": round(cores * span - busy, 2),
    }  # fmt: skip


def alternate(names: list[str], tmp: str, repeats: int, per_command: bool = False) -> dict:
    """Serial and batch runs, alternated; their times, loads and per-scene parts."""
    serial, batch, loads, serial_scenes, task_parts, overhead = [], [], [], [], [], []
    timelines: list[dict] = []  # per repeat, where the batch's wall went
    serial_run = []  # the serial process's wall without its evaluations
    io_stalls = []  # per repeat: (serial, batch) seconds stalled on I/O
    split = []  # per repeat: the same work in one plain process per core, no Ray
    commands = []  # per repeat (--per-command): one mvviz run command per scene
    cores = os.cpu_count() or 1
    for r in range(repeats):
        loads.append(os.getloadavg()[0])
        took, err, serial_io = timed([sys.executable, "-c", SERIAL, f"{tmp}/serial", *names])
        serial.append(took)
        evaluations = 0.0
        for line in err.splitlines():
            if line.startswith("SCENE "):
                wall, cpu = map(float, line.split()[1:])
                serial_scenes.append({"wall_s": wall, "cpu_s": cpu})
            elif line.startswith("EVAL "):
                evaluations += float(line.split()[1])
        serial_run.append(took - evaluations)
        loads.append(os.getloadavg()[0])
        cmd = [sys.executable, "-m", "mvviz.cli", "batch", *names, "--force",
               "--out", f"{tmp}/batch", "--report", f"{tmp}/report"]  # fmt: skip
        t0 = time.time()
        took, _, batch_io = timed(cmd)
        batch.append(took)
        io_stalls.append((serial_io, batch_io))
        split.append(timed_split([names[i::cores] for i in range(cores)], f"{tmp}/split"))
        if per_command:
            commands.append(timed_commands(names, f"{tmp}/commands"))
        by_hand = (f"; {len(names)} mvviz run commands {commands[-1]:.1f} s (the batch "
                   f"{commands[-1] / batch[-1]:.2f}x faster)" if per_command else "")  # fmt: skip
        rows = json.loads(Path(tmp, "report", "batch_report.json").read_text())["rows"]
        task_parts += [row["task_seconds"] for row in rows if row.get("task_seconds")]
        overhead.append(batch[-1] - sum(map(task_wall, rows)) / (os.cpu_count() or 1))
        timelines.append(timeline(rows, t0, t0 + batch[-1]))
        where = (f"; start-up {timelines[-1]['startup_s']:.1f} s, tail "
                 f"{timelines[-1]['tail_s']:.1f} s, {timelines[-1]['workers']} workers, "
                 f"{timelines[-1]['idle_core_s']:.1f} core-s idle between tasks"
                 if timelines[-1] else "")  # fmt: skip
        print(f"repeat {r + 1}: serial {serial[-1]:.1f} s ({serial_run[-1]:.1f} without the "
              f"evaluations; load {loads[-2]:.1f}), batch {batch[-1]:.1f} s (load "
              f"{loads[-1]:.1f}): {serial[-1] / batch[-1]:.2f}x "
              f"({serial_run[-1] / batch[-1]:.2f}x){where}{stalls(serial_io, batch_io)}; "
              f"no-Ray split {split[-1]:.1f} s ({serial[-1] / split[-1]:.2f}x){by_hand}",
              flush=True)  # fmt: skip
    return dict(serial=serial, serial_run=serial_run, batch=batch, loads=loads,
                serial_scene=medians(serial_scenes), task=medians(task_parts),
                overhead=overhead, timelines=timelines, io_stall_s=io_stalls,
                split=split, commands=commands)  # fmt: skip


def stalls(serial_io: float | None, batch_io: float | None) -> str:
    if serial_io is None or batch_io is None:
        return ""
    return f"; stalled on I/O: serial {serial_io:.1f} s, batch {batch_io:.1f} s"


def task_wall(row: dict) -> float:
    """Wall seconds of a report row's task (the sum of its stages), 0 without one."""
    parts = row.get("task_seconds") or {}
    return sum(v for k, v in parts.items() if k.endswith("_s") and not k.endswith("_cpu_s"))


def main() -> int:
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--scenes", type=Path, default=Path(tempfile.gettempdir()) / "mvviz_bench_batch")
    p.add_argument("--frames", type=int, default=250, help="frames per scene (the sample's)")
    p.add_argument("--people", type=int, default=4, help="people per scene (the sample's)")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument(
        "--fit-repeats", type=int, default=1,
        help="fits of one scene per thread count (2 threads on a busy machine can take 20x)",
    )  # fmt: skip
    p.add_argument(
        "--per-command", action="store_true",
        help="also time the scenes as separate mvviz run commands (what a user does by hand)",
    )  # fmt: skip
    p.add_argument("--json", type=Path, default=None)
    args = p.parse_args()
    scenes = make_scenes(args.scenes, args.frames, args.people)
    names = [str(s) for s in scenes]
    print(f"{os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.1f} at the start, "
          f"autogroup scheduling {autogroup()} (see --help)")  # fmt: skip
    with tempfile.TemporaryDirectory() as tmp:
        runs = alternate(names, tmp, args.repeats, args.per_command)
        others = ["serial", *(["commands"] if args.per_command else [])]
        diffs = {
            f"{s.name} ({other})": d
            for s in scenes
            for other in others
            if (d := differing(Path(tmp, other, s.name, "results.npz"),
                               Path(tmp, "batch", s.name, "results.npz")))
        }  # fmt: skip
        equal = not diffs
    load = os.getloadavg()[0]
    ray_start = python_json(RAY_START)
    driver = python_json(DRIVER, *names)
    fit = python_json(FIT_THREADS, names[0], str(args.fit_repeats))
    figures = {
        "scenes": NUM_SCENES, "cpus": os.cpu_count(), "serial_s": runs["serial"],
        "batch_s": runs["batch"], "serial_median_s": statistics.median(runs["serial"]),
        "batch_median_s": statistics.median(runs["batch"]),
        "speedup": statistics.median(runs["serial"]) / statistics.median(runs["batch"]),
        "serial_run_only_s": runs["serial_run"],
        "serial_run_only_median_s": statistics.median(runs["serial_run"]),
        "speedup_vs_run_only": statistics.median(runs["serial_run"])
        / statistics.median(runs["batch"]),
        "speedup_per_repeat": [a / b for a, b in zip(runs["serial"], runs["batch"], strict=True)],
        "speedup_per_repeat_median": statistics.median(
            a / b for a, b in zip(runs["serial"], runs["batch"], strict=True)
        ),
        "load_1min": runs["loads"], "load_at_parts": load, "ray_start": ray_start,
        "driver": driver, "batch_overhead_s": runs["overhead"],
        "batch_timeline": runs["timelines"], "io_stall_s": runs["io_stall_s"],
        "split_s": runs["split"], "split_median_s": statistics.median(runs["split"]),
        "serial_per_scene": runs["serial_scene"], "batch_task_per_scene": runs["task"],
        "fit_threads": fit, "results_equal": equal, "results_differ": diffs,
        "autogroup": autogroup(),
    }  # fmt: skip
    if runs["commands"]:
        figures["commands_s"] = runs["commands"]
        figures["commands_median_s"] = statistics.median(runs["commands"])
        figures["speedup_vs_commands"] = figures["commands_median_s"] / figures["batch_median_s"]
    print(
        f"parts (load {load:.1f}): Ray import {ray_start['import_s']:.2f} s, ray.init "
        f"{ray_start['init_s']:.2f} s, {ray_start['workers']} workers started + pipeline "
        f"imported {ray_start['warm_workers_s']:.2f} s, shutdown {ray_start['shutdown_s']:.2f} "
        f"s; Ray's processes used {ray_start['ray_processes_cpu_s']:.2f} CPU s by then"
    )
    print(
        f"the driver: imports {driver['imports_s']:.2f} s ({driver['imports_cpu_s']:.2f} CPU s), "
        f"planning the {NUM_SCENES} scenes {driver['plan_s']:.2f} s ({driver['plan_cpu_s']:.2f} "
        f"CPU s), torch imported: {driver['torch_imported']}"
    )
    if runs["task"]:  # one task a scene: its parts are in the report
        print(
            f"batch beyond its tasks' work (wall - sum of task walls / {os.cpu_count()} cores): "
            f"{', '.join(f'{x:.1f}' for x in runs['overhead'])} s, median "
            f"{statistics.median(runs['overhead']):.1f} s"
        )
    print(f"per scene, serial mvviz run: {json.dumps(runs['serial_scene'])}")
    print(f"per scene, batch task: {json.dumps(runs['task'])}")
    print(
        f"SMPL fit of one scene: 1 thread {fit['fit_1_thread_s']:.2f} s, 2 threads "
        f"{fit['fit_2_threads_s']:.2f} s (same numbers: {fit['same_numbers']})"
    )
    # The best a batch can do on these cores: its tasks' CPU, Ray's start-up (processes
    # and warm workers) and the driver's imports and planning, perfectly packed.
    cores = os.cpu_count() or 1
    if runs["task"]:
        work = NUM_SCENES * sum(v for k, v in runs["task"].items() if k.endswith("_cpu_s"))
        fixed = ray_start["ray_processes_cpu_s"] + driver["imports_cpu_s"] + driver["plan_cpu_s"]
        best = (work + fixed) / cores
        figures["batch_bound_s"] = best
        figures["speedup_bound"] = figures["serial_median_s"] / best
        print(
            f"bound: tasks {work:.1f} CPU s + Ray's start-up and the driver {fixed:.1f} CPU s "
            f"on {cores} cores, perfectly packed: batch >= {best:.1f} s, speed-up <= "
            f"{figures['speedup_bound']:.2f}x"
        )
    else:  # scenes longer than mvviz batch's --chunk-frames: inputs, chunk and join tasks
        print("bound: not printed (the scenes ran as frame-chunk tasks: no per-scene parts)")
    print(f"serial median {figures['serial_median_s']:.1f} s (the same work: mvviz run and "
          f"the report's evaluation per scene), batch median {figures['batch_median_s']:.1f} "
          f"s: {figures['speedup']:.2f}x; against mvviz run alone "
          f"({figures['serial_run_only_median_s']:.1f} s): "
          f"{figures['speedup_vs_run_only']:.2f}x (target 1.7x, "
          f"loads {min(runs['loads']):.1f}-{max(runs['loads']):.1f}); "
          f"results equal: {equal}{'' if equal else f' (differ: {diffs})'}")  # fmt: skip
    # A repeat's serial and batch ran a minute apart; the medians above may come from
    # repeats far apart, on a VM whose speed drifts by a third within minutes.
    print(f"median of the per-repeat ratios (each pair run back to back): "
          f"{figures['speedup_per_repeat_median']:.2f}x")  # fmt: skip
    split = figures["split_median_s"]
    print(f"no-Ray split (one plain process per core, {cores} groups of scenes, the same "
          f"work): median {split:.1f} s, {figures['serial_median_s'] / split:.2f}x the serial "
          f"time: what this machine gives two processes now; the batch takes "
          f"{figures['batch_median_s'] / split:.2f}x the split's time")  # fmt: skip
    if runs["commands"]:
        print(f"{NUM_SCENES} mvviz run commands one after another (each scene by hand, no "
              f"evaluation): median {figures['commands_median_s']:.1f} s, the batch "
              f"{figures['speedup_vs_commands']:.2f}x faster")  # fmt: skip
    if args.json:
        write_json(args.json, figures)
    return 0


if __name__ == "__main__":
    sys.exit(main())
