"""The jobs of :mod:`pipeline.batch.jobs` as Ray tasks: embedded local Ray or a cluster.

The unit of work is a scene: a scene is one task that runs all its stages, on a warm
worker (Ray keeps its worker processes, so torch and the pipeline are imported once per
worker, not per scene). A scene that alone is more than an even share of the work
(:func:`split_frames`: one long scene, or fewer scenes than CPUs) is one inputs task,
one task per frame chunk (association, triangulation) and one join task (sequence
stages, SMPL fit, the report's summary).

What travels: with ``shared_files`` (always for the embedded Ray: the workers are on
this machine) a task gets the scene's directory, the body model's file and the results
path, reads the scene and the model itself (the model once per worker) and writes the
results atomically (:func:`pipeline.results.store.save_results`); only the summary comes
back. Without it (a cluster without shared storage) the driver puts each scene and the
body model into Ray's object store (``ray.put``) and writes the results that come back,
so a worker needs the same mvviz installed, not the scene files.

Start-up: the driver never imports torch (the body model's fingerprint and the cache key
are numpy; the pose prior checkpoint is read by :func:`check_prior` on a worker, once per
file, before any scene task); ``mvviz batch`` starts Ray in a background thread beside its
planning and submits :func:`warm_workers` at once, so the workers import torch and the
stages meanwhile.

Failures: every task is retried ``retries`` times, after a Python exception
(``retry_exceptions``) and after its worker or node died (``max_retries``; lost chunk
results are rebuilt from their lineage); a scene that still fails is reported with its
error while the others finish.

Bit for bit: the SMPL fit and the restoration run on fixed torch thread counts
(``FitParams.num_threads``, ``pipeline.stages.restore.RESTORE_THREADS``) whatever the process,
and the tasks run the rest of torch on :data:`TASK_TORCH_THREADS`: the numbers are the
same as ``mvviz run``'s.
"""

from __future__ import annotations

import contextlib
import inspect
import json
import logging
import os
import re
import shutil
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import ray

from pipeline.batch.jobs import (
    SceneJob,
    chunk_bounds,
    join_chunks,
    run_chunk,
    scene_inputs,
    stored_key,
    summarize,
)
from pipeline.body.arrays import BodyModelData
from pipeline.config import PipelineConfig
from pipeline.core.files import SceneFormatError, atomic_write, process_alive
from pipeline.core.progress import Progress, StageBar
from pipeline.data.scene import Scene, load_scene
from pipeline.results.store import load_results, save_results

TASK_TORCH_THREADS = 1
"""torch's threads in a task: a task holds one CPU (two workers of the driver's 2
threads would put 4 threads on 2 cores). The fit and the restoration run on their own
fixed counts anyway; the rest gives the same numbers on 1 thread as on ``mvviz run``'s
default (tests/mvviz/cli/test_batch.py; bench_batch compares 8 scenes). One scene task
alone in a process costs the same either way (6.4-7.4 CPU s at 1 and at 2 threads,
alternated, load ~10)."""
RAY_TEMP_DIR = Path(tempfile.gettempdir()) / "mvviz-ray"  # embedded Ray's sessions and logs
SUMMARY_SUFFIX = ".summary.json"  # beside a results file: its report figures and key


def start_ray(address: str | None = None, *, num_cpus: int | None = None) -> dict:
    """Connect to Ray: ``address`` None starts an embedded local Ray on this machine's
    cores (``num_cpus``, default all) bound to 127.0.0.1, without the head processes of
    :data:`LEAN_HEAD_SKIPS` (no dashboard, autoscaler or log monitor), quiet, its files
    under the system temp; ``"auto"`` or ``"HOST:PORT"`` joins a running cluster.
    Returns ``ray.cluster_resources()``."""
    # Ray's usage statistics would be sent over the network: never (no network at run time).
    os.environ["RAY_USAGE_STATS_ENABLED"] = "0"
    if ray.is_initialized():
        return ray.cluster_resources()
    quiet = dict(logging_level=logging.ERROR, log_to_driver=False, namespace="mvviz")
    if address is None:
        RAY_TEMP_DIR.mkdir(parents=True, exist_ok=True)
        with _embedded_node():
            ray.init(
                num_cpus=num_cpus or os.cpu_count(),
                include_dashboard=False,
                _node_ip_address="127.0.0.1",
                _temp_dir=str(RAY_TEMP_DIR),
                **quiet,
            )
    else:
        ray.init(address=address, **quiet)
    return ray.cluster_resources()


@contextlib.contextmanager
def _embedded_node():
    """The embedded Ray's head node: on 127.0.0.1 only, and without the processes a
    one-machine batch has no use for."""
    with _loopback_node(), _lean_head(), _embedded_config():
        yield


@contextlib.contextmanager
def _loopback_node():
    """The embedded Ray's node on 127.0.0.1: every server it starts (GCS, raylet, workers,
    agents) listens on loopback only, not on all interfaces.

    ``ray.init(_node_ip_address="127.0.0.1")`` alone does not do it: Ray replaces a
    loopback address by the machine's reachable one (``services.resolve_ip_for_localhost``
    -> ``get_node_ip_address``), and its servers then listen on every interface. Ray
    keeps the node on loopback where clusters are off (``ENABLE_RAY_CLUSTER``, from
    ``RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER``, read once when ray is imported): both are
    set while the node starts (its processes inherit the variable), then restored, so a
    later ``--address`` run in this process still reports its reachable address."""
    from ray._private import ray_constants

    name = ray_constants.ENABLE_RAY_CLUSTERS_ENV_VAR
    saved_env, saved_flag = os.environ.get(name), ray_constants.ENABLE_RAY_CLUSTER
    os.environ[name], ray_constants.ENABLE_RAY_CLUSTER = "0", False
    try:
        yield
    finally:
        ray_constants.ENABLE_RAY_CLUSTER = saved_flag
        if saved_env is None:
            os.environ.pop(name, None)
        else:
            os.environ[name] = saved_env


EMBEDDED_RAY_CONFIG = {
    "RAY_raylet_client_connect_timeout_milliseconds": "10",
    "RAY_raylet_client_num_connect_attempts": "1000",
    "RAY_enable_worker_prestart": "1",
    "RAY_worker_niceness": "0",
}
"""Ray's own config (``RayConfig``, read from the environment by each of its processes)
for the embedded node; a cluster keeps its own.

- A local socket is retried every 10 ms instead of every 1000 ms, for the same 10 s
  bound: the raylet's first connection to its own object store races the store's
  thread, and when the store is not yet listening the raylet slept a whole second. On
  this 2-core machine that was 1.00 s lost in 3 of 8 ``mvviz batch`` starts (the
  driver's planning competes for the cores), and in none of 8 with these values (the
  raylet's log: "Plasma store debug dump" to "ObjectManager server started").
- ``enable_worker_prestart``: the raylet starts its CPU count of workers as it starts,
  not once the driver has connected (Ray binds them to the job later, as it does for a
  job without a runtime env), so their start overlaps the driver's connection: ray.init
  to both warm-up tasks done 0.2-0.4 s sooner (6 alternated starts each, medians 5.27 ->
  4.87 s from the command), with the same 2 worker processes.
- ``worker_niceness`` 0, not Ray's 15: Ray lowers its workers' priority so that its own
  processes stay responsive beside them, but here the workers are the batch's work,
  and at nice 15 every other runnable thread on the machine (the raylet's and driver's
  polling, the kernel's own threads: its memory reclaim here) takes their core first, while
  ``mvviz run`` runs at the normal priority. On this 2-core VM, 4 alternated pairs of
  8-scene batches: median task 6.16 -> 5.72 s, batch 30.9 -> 28.5 s, faster in every
  pair."""


@contextlib.contextmanager
def _embedded_config():
    """:data:`EMBEDDED_RAY_CONFIG` in the environment while the embedded node starts (its
    processes inherit it), where the user has not set a value; restored after."""
    added = {k: v for k, v in EMBEDDED_RAY_CONFIG.items() if k not in os.environ}
    os.environ.update(added)
    try:
        yield
    finally:
        for k in added:
            os.environ.pop(k, None)


LEAN_HEAD_SKIPS = ("monitor", "log_monitor", "dashboard")
"""The head processes the embedded Ray does without (Ray's process-type names).

- ``monitor``, the autoscaler: one machine has nothing to scale, and ``ray.shutdown``
  waits a full second for it to go (``Node._kill_process_impl``'s timeout), every run;
- ``log_monitor``: it forwards the workers' output to the driver, which
  ``log_to_driver=False`` turns off anyway (task errors come back with the task);
- ``dashboard``, the API server that ``include_dashboard=False`` still starts: with
  Ray's minimal install (no aiohttp) it loads no module at all, and ``ray.init`` polls
  0.6 s for its address.

Together ~2.9 s of wall and ~1.6 CPU s of a batch's fixed cost (bench_batch's parts:
``ray.init`` 3.4 -> 1.6 s, ``ray.shutdown`` 1.3 -> 0.3 s). A cluster (``--address``) is
started by ``ray start`` and keeps all of them."""


@contextlib.contextmanager
def _lean_head():
    """While the embedded node starts, Ray's own switches for the autoscaler monitor and
    the log monitor (``RayParams.no_monitor``, ``include_log_monitor``, which ``ray.init``
    does not pass on) are set, and the node's API server start is skipped; both restored
    after. A Ray without these hooks starts its full head: slower, never wrong."""
    from ray._private import node as ray_node
    from ray._private import parameter

    params_cls = parameter.RayParams
    names = inspect.signature(params_cls.__init__).parameters
    if not {"no_monitor", "include_log_monitor"} <= set(names) or (
        "start_api_server" not in ray_node.Node.__dict__
    ):
        yield
        return

    class LeanParams(params_cls):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            self.no_monitor, self.include_log_monitor = True, False

    saved_api = ray_node.Node.__dict__["start_api_server"]
    parameter.RayParams = LeanParams
    ray_node.Node.start_api_server = lambda self, **kwargs: None
    try:
        yield
    finally:
        parameter.RayParams = params_cls
        ray_node.Node.start_api_server = saved_api


def stop_ray() -> None:
    if ray.is_initialized():
        ray.shutdown()


KEPT_RAY_SESSIONS = 10
"""Sessions of finished embedded Rays kept under :data:`RAY_TEMP_DIR` (their logs, for
a look at a failed batch): Ray never deletes its session directories (~180 KB each),
so one per ``mvviz batch`` piles up in the system temp without this."""
_SESSION_NAME = re.compile(r"session_\d{4}-\d{2}-\d{2}_\d{2}-\d{2}-\d{2}_\d+_(\d+)")


def prune_ray_sessions(
    temp_dir: Path = RAY_TEMP_DIR, keep: int = KEPT_RAY_SESSIONS, limit: int = 20
) -> list[Path]:
    """Delete the session directories of embedded Rays that have ended, all but the
    newest ``keep``, at most ``limit`` of them (oldest first: a backlog of hundreds takes
    seconds to delete, and goes over the next batches instead of stalling one's end). A
    session is Ray's ``session_<date>_<time>_<us>_<pid>``, named by the driver that
    started it (Ray's ``Node``), and has ended when that process is gone: a batch still
    running in another process keeps its session, whatever its age. Anything else in
    ``temp_dir`` (``session_latest``, a link) is left alone. Returns the directories
    deleted (a removal that fails is skipped: it is only disk space)."""
    try:
        entries = sorted(temp_dir.iterdir(), key=lambda p: p.name)  # names sort by date
    except OSError:
        return []
    sessions = [
        (p, int(m.group(1))) for p in entries
        if (m := _SESSION_NAME.fullmatch(p.name)) and p.is_dir() and not p.is_symlink()
    ]  # fmt: skip
    removed = []
    for path, pid in sessions[: max(len(sessions) - keep, 0)]:
        if len(removed) == limit:
            break
        if not process_alive(pid):
            shutil.rmtree(path, ignore_errors=True)
            if not path.exists():
                removed.append(path)
    return removed


def _set_threads(n: int) -> None:
    import torch  # workers only: the driver never imports torch

    torch.set_num_threads(n)


def _warm_task(model_path: str | None) -> tuple[int, str | None]:
    """A worker's first task: torch, the stages and the body model (its file, as a scene
    task reads it) loaded while the driver still plans. Returns (the worker's process
    id, the error if loading failed: the scene tasks, which load the same, report it)."""
    try:
        import pipeline.fit.prior  # noqa: F401  (torch, the fit's modules)
        import pipeline.fit.smpl  # noqa: F401
        import pipeline.stages.restore  # noqa: F401
        from pipeline.body.model import load_body_model

        load_body_model(model_path)  # once per process: the scene tasks find it loaded
    except Exception as exc:  # noqa: BLE001  (reported by the scene tasks)
        return os.getpid(), f"{type(exc).__name__}: {exc}"
    return os.getpid(), None


def warm_workers(num_cpus: int, model_path: str | None) -> list[ray.ObjectRef]:
    """One warm-up task per CPU, submitted as soon as Ray is up (the scene tasks queue
    behind them): each worker imports torch and the pipeline and loads the body model
    (~2 s) while the driver still plans, not after it has submitted the scenes."""
    warm = ray.remote(_warm_task).options(max_retries=0)
    return [warm.remote(model_path) for _ in range(max(int(num_cpus), 1))]


def check_prior(path: str | None) -> None:
    """Read the pose prior checkpoint ``path`` (None: the shipped one) as the fit will
    (a bad file raises :class:`SceneFormatError` naming it): on a worker, so the driver
    never imports torch."""
    from pipeline.fit.prior import load_prior

    load_prior(path)


# ------------------------------------------------------------------------- the tasks


@dataclass(frozen=True)
class ModelFile:
    """The body model as a file every worker reads (``shared_files``): its path and the
    driver's fingerprint of it, checked after loading."""

    path: str
    fingerprint: str


def _model(model):
    """The body model of a task: the one shipped, or the file's (read once per worker)."""
    if not isinstance(model, ModelFile):
        return model
    from pipeline.body.model import load_body_model  # torch

    loaded = load_body_model(model.path)  # once per worker process
    if loaded.fingerprint != model.fingerprint:
        raise SceneFormatError(model.path, None, "body model differs from the driver's")
    return loaded


def _scene(scene: Scene | Path) -> Scene:
    return load_scene(scene) if isinstance(scene, Path) else scene


class _Clock:
    """Wall and CPU seconds (this process, all threads) of the stages of a task, and
    when (Unix time) and where (the worker's process id) it ran: a batch's timeline."""

    def __init__(self) -> None:
        self.parts: dict[str, float] = {"started_at": round(time.time(), 3), "pid": os.getpid()}
        self._wall, self._cpu = time.perf_counter(), time.process_time()

    def done(self) -> dict[str, float]:
        self.parts["ended_at"] = round(time.time(), 3)
        return self.parts

    def lap(self, name: str) -> None:
        wall, cpu = time.perf_counter(), time.process_time()
        self.parts[f"{name}_s"] = round(wall - self._wall, 3)
        self.parts[f"{name}_cpu_s"] = round(cpu - self._cpu, 3)
        self._wall, self._cpu = wall, cpu


def _scene_task(scene, config, model, key, results_path, threads):
    """A scene of one chunk, every stage in this task; with ``results_path`` (shared
    files) the results are written here and only the summary returns. Returns
    (results or None, summary, wall and CPU seconds per stage)."""
    clock = _Clock()
    _set_threads(threads)
    scene, model = _scene(scene), _model(model)
    clock.lap("load")
    inputs = scene_inputs(scene, config, model)
    frames = run_chunk(scene, config, inputs, 0, scene.num_frames)
    clock.lap("frames")
    results = join_chunks(scene, config, model, inputs, [frames], key)
    clock.lap("sequence_fit")
    summary = summarize(scene, results)
    if results_path is not None:
        save_results(results, results_path)
        results = None
    clock.lap("summary_save")
    return results, summary, clock.done()


def _inputs_task(scene, config, model, threads):
    _set_threads(threads)
    return scene_inputs(_scene(scene), config, _model(model))


def _chunk_task(scene, config, inputs, start, stop, threads):
    _set_threads(threads)
    return run_chunk(_scene(scene), config, inputs, start, stop)


def _join_task(scene, config, model, inputs, key, results_path, threads, *chunks):
    _set_threads(threads)
    scene = _scene(scene)
    results = join_chunks(scene, config, _model(model), inputs, chunks, key)
    summary = summarize(scene, results)
    if results_path is not None:
        save_results(results, results_path)
        results = None
    return results, summary, {}


def _summary_task(scene, results, threads):
    _set_threads(threads)
    return summarize(_scene(scene), results)


@dataclass
class Outcome:
    """How one job ended: ``status`` "computed", "cached" or "failed" (``error`` says
    why); ``summary`` the figures of :func:`pipeline.batch.jobs.summarize`."""

    job: SceneJob
    status: str
    summary: dict | None = None
    error: str | None = None
    seconds: float = 0.0
    parts: dict | None = None  # seconds per stage inside a one-task scene


def summary_path(results_path: Path) -> Path:
    return results_path.with_name(results_path.stem + SUMMARY_SUFFIX)


def cached_summary(job: SceneJob) -> tuple[bool, dict | None]:
    """(results current, their summary if stored with the same key)."""
    if stored_key(job.results_path) != job.key:
        return False, None
    try:
        stored = json.loads(summary_path(job.results_path).read_text())
    except (OSError, ValueError):
        return True, None
    return True, stored.get("summary") if stored.get("key") == job.key else None


def _write_summary(job: SceneJob, summary: dict) -> None:
    with atomic_write(summary_path(job.results_path), "w") as fh:
        json.dump({"key": job.key, "summary": summary}, fh, indent=1)


def _error_text(exc: BaseException) -> str:
    """The original error of a failed task, one line (Ray wraps it with its traceback)."""
    cause = getattr(exc, "cause", None) or exc
    text = str(cause).strip().splitlines()
    return f"{type(cause).__name__}: {text[-1] if text else ''}"


class _Submitter:
    """Submits a job's tasks. Without shared files, each scene and the body model go into
    the object store once, however many jobs (sweep settings) use them."""

    def __init__(self, scenes: dict[Path, Scene], model: BodyModelData, retries: int, shared: bool):
        opts = dict(max_retries=retries, retry_exceptions=True)
        tasks = dict(
            scene=_scene_task, inputs=_inputs_task, chunk=_chunk_task, join=_join_task,
            summary=_summary_task,
        )  # fmt: skip
        self.fn = {k: ray.remote(f).options(**opts) for k, f in tasks.items()}
        self.threads = TASK_TORCH_THREADS
        self.scenes, self.model, self.shared = scenes, model, shared
        self.num_chunks = 0
        self._scene_refs: dict[Path, ray.ObjectRef] = {}
        self._model_arg = None

    def _scene_arg(self, scene_dir: Path):
        if self.shared:
            return scene_dir
        if scene_dir not in self._scene_refs:
            self._scene_refs[scene_dir] = ray.put(self.scenes[scene_dir])
        return self._scene_refs[scene_dir]

    def _model(self):
        if self._model_arg is None:
            src = Path(str(self.model.source))
            if self.shared and src.is_file():
                self._model_arg = ModelFile(str(src), self.model.fingerprint)
            else:  # a model built in memory, or no shared files: ship it
                self._model_arg = ray.put(self.model)
        return self._model_arg

    def submit(self, i: int, job: SceneJob, current: bool, chunk_frames: int) -> dict:
        """{object ref: (kind, i)} of job ``i``'s tasks; ``current``: its results are
        current and only the report's figures are missing."""
        scene, fn, n = self._scene_arg(job.scene_dir), self.fn, self.threads
        if current:
            results = load_results(job.results_path, model=self.model)
            return {fn["summary"].remote(scene, results, n): ("summary", i)}
        out = job.results_path if self.shared else None
        bounds = chunk_bounds(self.scenes[job.scene_dir].num_frames, chunk_frames)
        if len(bounds) == 1:  # a sample-sized scene: one task, no intermediate objects
            ref = fn["scene"].remote(scene, job.config, self._model(), job.key, out, n)
            return {ref: ("scene", i)}
        inputs = fn["inputs"].remote(scene, job.config, self._model(), n)
        chunks = [fn["chunk"].remote(scene, job.config, inputs, a, b, n) for a, b in bounds]
        self.num_chunks += len(chunks)
        refs = {c: ("chunk", i) for c in chunks}
        join = fn["join"].remote(scene, job.config, self._model(), inputs, job.key, out, n, *chunks)
        refs[join] = ("join", i)
        return refs


def _finish(job: SceneJob, kind: str, ref: ray.ObjectRef, took: float) -> Outcome:
    """The outcome of a job's last task: its results written (unless the task wrote
    them), its summary stored beside them."""
    try:
        value = ray.get(ref)
    except (ray.exceptions.RayError, SceneFormatError, ValueError) as exc:
        return Outcome(job, "failed", error=_error_text(exc), seconds=took)
    if kind == "summary":
        summary, status, parts = value, "cached", None
    else:
        results, summary, parts = value
        if results is not None:
            save_results(results, job.results_path)
        status = "computed"
    _write_summary(job, summary)
    return Outcome(job, status, summary, seconds=took, parts=parts or None)


def run_jobs(
    jobs: Sequence[SceneJob],
    scenes: dict[Path, Scene],
    model: BodyModelData,
    *,
    chunk_frames: int | None = 0,
    retries: int = 2,
    force: bool = False,
    progress: Progress = True,
    shared_files: bool = False,
    warm: Sequence[ray.ObjectRef] = (),
    on_idle_cpu: Callable[[], None] | None = None,
) -> list[Outcome]:
    """Run every job whose results are not current (``force``: all) on the connected
    Ray; ``scenes`` maps each job's ``scene_dir`` to its loaded scene;
    ``chunk_frames``: every scene split into frame chunks of at most that many (0:
    none; None: :func:`split_frames` decides per scene); ``shared_files``: the workers
    read the scenes and write the results at the driver's paths (see the module
    docstring); ``warm``: the refs of :func:`warm_workers` (collected at the end);
    ``on_idle_cpu``: called once, in this thread, as soon as fewer jobs are left than
    Ray has CPUs (a core has nothing more to do: the driver's own closing work, such
    as the report's imports, costs the batch no time there). Outcomes in the order of
    ``jobs``. Progress: stage "scenes" (jobs done, cached ones counted at once) and
    stage "chunks" (frame chunks done)."""
    outcomes: list[Outcome | None] = [None] * len(jobs)
    todo: list[tuple[int, bool]] = []
    for i, job in enumerate(jobs):
        current, summary = cached_summary(job) if not force else (False, None)
        if current and summary is not None:
            outcomes[i] = Outcome(job, "cached", summary)
        else:
            todo.append((i, current))
    # The biggest scenes first, so that the last tasks to start are short ones and no
    # worker idles long while another finishes a big scene.
    todo.sort(key=lambda t: -_scene_size(scenes[jobs[t[0]].scene_dir]))
    bad_prior = _prior_errors([jobs[i].config for i, current in todo if not current], retries)
    for i, current in todo:
        if not current and (error := bad_prior.get(_prior_of(jobs[i].config))):
            outcomes[i] = Outcome(jobs[i], "failed", error=error)
    todo = [(i, current) for i, current in todo if outcomes[i] is None]
    submitter = _Submitter(scenes, model, retries, shared_files)
    pending: dict[ray.ObjectRef, tuple[str, int]] = {}
    started: dict[int, float] = {}
    sizes = {i: 0 if current else _scene_size(scenes[jobs[i].scene_dir]) for i, current in todo}
    cpus = ray.cluster_resources().get("CPU", 1) if todo else 0  # (all current: no Ray)
    total = sum(sizes.values())
    for i, current in todo:
        started[i] = time.perf_counter()
        chunks = split_frames(sizes[i], total, cpus) if chunk_frames is None else chunk_frames
        pending.update(submitter.submit(i, jobs[i], current, chunks))

    done_jobs = len(jobs) - len(todo)
    left = len(todo)  # jobs not finished
    with (
        StageBar("scenes", len(jobs), progress, unit="scene", initial=done_jobs) as scene_bar,
        StageBar("chunks", submitter.num_chunks, progress, unit="chunk") as chunk_bar,
    ):
        while pending:
            if on_idle_cpu is not None and left < cpus:  # a core has nothing left to do
                on_idle_cpu()
                on_idle_cpu = None
            ready, _ = ray.wait(list(pending), num_returns=1)
            kind, i = pending.pop(ready[0])
            if kind == "chunk":
                chunk_bar.update()
                continue
            outcomes[i] = _finish(jobs[i], kind, ready[0], time.perf_counter() - started[i])
            scene_bar.update()
            left -= 1
    for ref in warm:  # done long ago; a failed load is the scene tasks' error to report
        try:
            ray.get(ref)
        except ray.exceptions.RayError:
            pass
    return [o for o in outcomes if o is not None]


def _prior_of(config: PipelineConfig) -> str | None:
    """The pose prior checkpoint a job's fit reads ("" none, None the shipped one)."""
    return (config.pose_prior or None) if config.fit_smpl and config.use_pose_prior else ""


def _prior_errors(configs: Sequence[PipelineConfig], retries: int) -> dict[str | None, str]:
    """{checkpoint: error} of the pose priors these configs' fits read that cannot be
    read: each checked once, on a worker (a task queued behind the warm-ups), before any
    scene task is submitted, so a bad file fails its jobs at once, not after each
    scene's restoration, association and retries."""
    priors = sorted({p for c in configs if (p := _prior_of(c)) != ""}, key=str)
    check = ray.remote(check_prior).options(max_retries=retries, retry_exceptions=False)
    refs = {p: check.remote(p) for p in priors}
    errors = {}
    for prior, ref in refs.items():
        try:
            ray.get(ref)
        except (ray.exceptions.RayError, SceneFormatError, OSError, ValueError) as exc:
            errors[prior] = _error_text(exc)
    return errors


AUTO_CHUNK_FRAMES = 500
"""Frames per chunk of a scene :func:`split_frames` splits."""


def split_frames(size: int, total: int, cpus: float) -> int:
    """Frames per chunk of a scene of ``size`` (:func:`_scene_size`) among jobs of
    ``total`` on ``cpus``: :data:`AUTO_CHUNK_FRAMES` when the scene alone is more than
    an even share of the work (a long scene beside short ones, or fewer scenes than
    CPUs: unsplit, it would be the last to finish while cores idle), else 0, one task:
    the chunks' inputs, join and intermediate objects cost ~30 % more CPU per scene
    (``bench/bench_batch.py --frames 750``), for nothing when the scenes keep every core
    busy anyway."""
    return AUTO_CHUNK_FRAMES if cpus > 1 and size * cpus > total else 0


def _scene_size(scene: Scene) -> int:
    """Work of a scene, roughly: its detections (each frame's people in every view)."""
    return len(scene.detections)
