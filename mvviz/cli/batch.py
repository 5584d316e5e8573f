"""``mvviz batch``: the pipeline and its evaluation over many scenes on Ray, sweeps, and
the dataset report (see :mod:`pipeline.batch`)."""

from __future__ import annotations

import argparse
import logging
import signal
import socket
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

from mvviz.cli import at_least
from mvviz.cli.run import add_config_options, prepare
from pipeline.batch.jobs import SceneJob
from pipeline.batch.sweep import setting_slug, sweep_grid
from pipeline.config import PipelineConfig, load_config
from pipeline.core.files import SceneFormatError, scene_cache_dir
from pipeline.results.store import cache_key, default_results_path


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "batch",
        help="run many scenes (and parameter sweeps) on Ray; write the dataset report",
        description=(
            "Runs the pipeline, and the evaluation where a scene has ground truth, on every "
            "SCENE (or every scene directory under --root) as Ray tasks: an embedded local "
            "Ray on this machine's cores, or a cluster with --address. A scene longer than an "
            "even share of the work (one long scene, or fewer scenes than CPUs) splits into "
            "frame chunks for association and triangulation. Results are the same, bit for "
            "bit, as mvviz run's, written atomically beside each scene (SCENE/.mvviz/"
            "results.npz) or under --out; a re-run skips scenes whose results are current. "
            "Writes batch_report.json and batch_report.html (--report, default --out, "
            "--root or the current directory)."
        ),
    )
    p.add_argument("scenes", type=Path, nargs="*", metavar="SCENE", help="scene directories")
    p.add_argument("--root", type=Path, default=None, help="run every scene directory under DIR")
    add_config_options(p)
    p.add_argument(
        "--sweep", action="append", default=[], metavar="SECTION.FIELD=V1,V2",
        help="run the grid of these values (same fields as --set; repeatable: the product)",
    )  # fmt: skip
    p.add_argument(
        "--address", default=None, metavar="auto|HOST:PORT",
        help="join this Ray cluster (default: start an embedded local Ray)",
    )  # fmt: skip
    p.add_argument(
        "--shared-storage", action="store_true",
        help="with --address: every node sees the scenes, the body model and the results at "
        "the driver's paths (e.g. NFS), so the workers read and write them themselves "
        "instead of the driver shipping them through Ray's object store (always so for "
        "the embedded Ray)",
    )  # fmt: skip
    p.add_argument(
        "--num-cpus",
        type=at_least(1),
        default=None,
        help="embedded Ray's CPUs (default: all cores)",
    )
    p.add_argument("--out", type=Path, default=None, help="results under DIR/<scene>/")
    p.add_argument("--report", type=Path, default=None, help="directory of the report files")
    p.add_argument(
        "--chunk-frames", type=at_least(0), default=None,
        help="split every scene into association/triangulation tasks of N frames (0: one "
        "task per scene; default: a scene longer than an even share of the work splits "
        "into chunks of 500, the others run as one task)",
    )  # fmt: skip
    p.add_argument(
        "--retries", type=at_least(0), default=2, help="retries of a failing task (default 2)"
    )
    p.add_argument("--force", action="store_true", help="recompute current results too")
    p.set_defaults(func=run)


def scene_dirs(args: argparse.Namespace) -> list[Path]:
    """The SCENE arguments, then every directory under --root holding a scene.json."""
    dirs = list(args.scenes)
    if args.root is not None:
        if not args.root.is_dir():
            raise SceneFormatError(args.root, None, "--root: not a directory")
        dirs += sorted(d for d in args.root.iterdir() if (d / "scene.json").is_file())
    if not dirs:
        raise SceneFormatError(
            args.root or "mvviz batch", None, "no scenes: give SCENE... or --root DIR"
        )
    return [d.absolute() for d in dirs]  # not resolved: a symlinked scene keeps its name


def results_path(args: argparse.Namespace, d: Path, scene, setting: tuple[str, ...]) -> Path:
    """Where a job's results go: mvviz run's file without --out and sweep (so the two
    share the cache); per setting under SCENE/.mvviz/sweep/ or --out/<scene>/."""
    name = setting_slug(setting)
    if args.out is not None:
        return args.out.absolute() / d.name / (f"{name}.npz" if setting else "results.npz")
    if not setting:
        return default_results_path(scene)
    return scene_cache_dir(scene.root) / "sweep" / f"{name}.npz"


def plan(
    args: argparse.Namespace, needs_compute: Callable[[], None] | None = None
) -> tuple[list[SceneJob], dict, object, list[dict]]:
    """(jobs, scenes by directory, body model, rows of scenes that failed to load);
    ``needs_compute`` is called for each job whose results are not current (``--force``:
    every job) as soon as that is known (the caller starts Ray then)."""
    grid = sweep_grid(args.sweep)
    # --config, --set and each sweep setting are the same for every scene: a value that
    # does not parse is the command's error, not a failed row per scene
    base = load_config(args.config) if args.config else PipelineConfig()
    for setting in grid:
        base.with_overrides([*args.set, *setting])
    jobs, scenes, bad, model = [], {}, [], None
    seen: dict[str, Path] = {}
    for d in scene_dirs(args):
        if args.out is not None and seen.setdefault(d.name, d) != d:
            raise SceneFormatError(d, None, f"--out: two scenes named {d.name!r} ({seen[d.name]})")
        for setting in grid:
            ns = argparse.Namespace(
                scene=d, config=args.config, set=[*args.set, *setting], smpl_model=args.smpl_model
            )
            try:  # the prior checkpoint is read on a worker (torch): pipeline.batch.ray_run
                scene, config, model = prepare(ns, read_prior=False)
            except (SceneFormatError, OSError, ValueError) as exc:
                bad.append(_failed_row(d, setting, ns.set, args, f"{type(exc).__name__}: {exc}"))
                continue
            scenes.setdefault(d, scene)
            jobs.append(
                SceneJob(
                    scene_dir=d, config=config, results_path=results_path(args, d, scene, setting),
                    key=cache_key(scene, config, model), setting=setting,
                    set_args=tuple(ns.set),
                    config_file=args.config.resolve() if args.config else None,
                )
            )  # fmt: skip
            if needs_compute is not None and (args.force or _stale(jobs[-1])):
                needs_compute()
    return jobs, scenes, model, bad


def _stale(job: SceneJob) -> bool:
    """The job's results or their report figures are not stored with its key."""
    from pipeline.batch.ray_run import cached_summary  # Ray

    return cached_summary(job)[1] is None


class _RayStart:
    """Ray in a background thread, started once something is to be computed: its
    processes' start-up (~2-4 s, mostly waiting on them) overlaps the driver's planning,
    and on an embedded Ray one warm-up task per CPU follows at once, so every worker
    imports torch and the stages meanwhile (pipeline.batch.ray_run.warm_workers).

    The thread lives until :meth:`stop` and shuts Ray down itself: the embedded Ray's
    processes die with the thread that started them (Ray starts them with Linux's
    parent-death signal, which follows the parent thread, not the process)."""

    def __init__(self, args: argparse.Namespace) -> None:
        self.args, self.warm = args, []
        self._thread: threading.Thread | None = None
        self._ready, self._stop = threading.Event(), threading.Event()
        self._result: float | BaseException = 0.0

    @property
    def started(self) -> bool:
        return self._thread is not None

    def start(self) -> None:
        if self._thread is None:
            if threading.current_thread() is threading.main_thread():
                # What ray.init sets when called from the main thread: a kill exits
                # through the caller's cleanup (Ray's processes stopped).
                signal.signal(signal.SIGTERM, lambda signum, _frame: sys.exit(signum))
            self._thread = threading.Thread(target=self._run, name="ray", daemon=True)
            self._thread.start()

    def _run(self) -> None:
        ray_run = None
        try:
            from pipeline.batch import ray_run  # Ray

            logging.getLogger("ray").setLevel(logging.ERROR)  # no "not the main thread" note
            args = self.args
            cpus = ray_run.start_ray(args.address, num_cpus=args.num_cpus).get("CPU", 0)
            if args.address is None:  # a cluster's workers are warm or far: not worth it
                self.warm = ray_run.warm_workers(int(cpus), args.smpl_model)
            self._result = cpus
        except BaseException as exc:  # noqa: BLE001  (raised by wait, in the main thread)
            self._result = exc
        self._ready.set()
        self._stop.wait()
        self.warm = []
        if ray_run is not None:
            ray_run.stop_ray()
            if self.args.address is None:  # the embedded Ray's: ended sessions' logs
                ray_run.prune_ray_sessions()

    def wait(self) -> float:
        """Ray's CPUs once it is up (the start's error raised here)."""
        self.start()
        self._ready.wait()
        if isinstance(self._result, BaseException):
            raise self._result
        return self._result

    def stop(self, *, wait: bool = True) -> None:
        """Ray shut down (``wait`` False: the shutdown, ~1.4 s, goes on meanwhile; call
        again to wait for it)."""
        if self._thread is not None:
            self._stop.set()
            if wait:
                self._thread.join()


def _failed_row(d: Path, setting, set_args, args, error: str) -> dict:
    label = f"{d.name} [{', '.join(setting)}]" if setting else d.name
    return {
        "scene": str(d), "label": label, "setting": list(setting), "set_args": list(set_args),
        "config_file": str(args.config) if args.config else None, "status": "failed",
        "error": error, "results": "", "summary": None, "seconds": 0.0,
    }  # fmt: skip


def _row(outcome) -> dict:
    job = outcome.job
    return {
        "scene": str(job.scene_dir), "label": job.label, "setting": list(job.setting),
        "set_args": list(job.set_args),
        "config_file": str(job.config_file) if job.config_file else None,
        "status": outcome.status, "error": outcome.error, "results": str(job.results_path),
        "key": job.key, "summary": outcome.summary, "seconds": round(outcome.seconds, 2),
        "task_seconds": outcome.parts,
    }  # fmt: skip


ADDRESS_TIMEOUT_S = 5.0


def check_address(address: str | None) -> None:
    """``--address HOST:PORT`` names a host that resolves and a port that accepts a
    connection within :data:`ADDRESS_TIMEOUT_S` (Ray itself retries for minutes);
    ``auto`` and the embedded Ray are not checked. A SceneFormatError otherwise."""
    if address is None or address == "auto":
        return
    host, sep, port = address.split("://", 1)[-1].rpartition(":")  # ray://HOST:PORT too
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise SceneFormatError(address, "--address", "expected auto or [ray://]HOST:PORT")
    try:
        socket.create_connection((host, int(port)), timeout=ADDRESS_TIMEOUT_S).close()
    except OSError as exc:
        raise SceneFormatError(
            address, "--address", f"no Ray head answers there ({exc.strerror or exc})"
        ) from None


def run(args: argparse.Namespace) -> int:
    check_address(args.address)
    t0, started_at = time.perf_counter(), time.time()
    ray_start = _RayStart(args)
    if args.force:  # every job computes: Ray starts now, beside the planning
        ray_start.start()
    try:
        jobs, scenes, model, bad = plan(args, ray_start.start)
        outcomes = _run_jobs(args, ray_start, jobs, scenes, model, bad)
    except BaseException:
        ray_start.stop()
        raise
    ray_start.stop(wait=False)  # the results are written: its shutdown (~1.4 s) beside the report
    try:
        return _report(args, outcomes, bad, t0, started_at)
    finally:
        ray_start.stop()


def _run_jobs(args, ray_start: _RayStart, jobs, scenes, model, bad) -> list:
    for row in bad:
        print(f"{row['label']}: failed to load: {row['error']}", file=sys.stderr)
    if not jobs:
        return []
    from pipeline.batch.ray_run import run_jobs  # Ray

    if ray_start.started:  # Ray only when something is to be computed
        cpus = ray_start.wait()
        where = args.address or "embedded local Ray"
        print(f"{len(jobs)} runs of {len(scenes)} scenes on {where} ({cpus:g} CPUs)")
    return run_jobs(
        jobs, scenes, model, chunk_frames=args.chunk_frames, retries=args.retries,
        force=args.force, shared_files=args.address is None or args.shared_storage,
        warm=ray_start.warm, on_idle_cpu=_import_report,
    )  # fmt: skip


def _import_report() -> None:
    """The report's modules (matplotlib, ~0.4 s) imported while the last scenes run,
    not after them."""
    import pipeline.batch.report  # noqa: F401


def _report(args, outcomes, bad, t0: float, started_at: float) -> int:
    from pipeline.batch.report import build_report, write_report  # matplotlib

    rows = [_row(o) for o in outcomes] + bad
    for o in outcomes:
        if o.status == "failed":
            print(f"{o.job.label}: failed after {args.retries} retries: {o.error}", file=sys.stderr)
    report_dir = args.report or args.out or args.root or Path.cwd()
    report = build_report(rows, sweeps=args.sweep, started_at=started_at)
    js, page = write_report(report, report_dir)
    c = report["counts"]
    print(
        f"{len(rows)} runs: {c['computed']} computed, {c['cached']} current (skipped), "
        f"{c['failed']} failed in {time.perf_counter() - t0:.1f} s -> {js}, {page}"
    )
    return 1 if c["failed"] else 0
