"""The jobs of :mod:`pipeline.batch.jobs` as Ray tasks: embedded local Ray or a cluster.

What travels: the driver loads each scene once and puts it in Ray's object store
(``ray.put``), with the body model; the tasks take them from there, so a worker needs
the same mvviz installed, not the scene files (no shared storage needed). Per scene:
one inputs task, one task per frame chunk, one join task (sequence stages, SMPL fit,
the report's summary) whose results come back to the driver, which writes them
atomically (:func:`pipeline.results.save_results`) beside the scene or under ``--out``.

Failures: every task is retried ``retries`` times, after a Python exception
(``retry_exceptions``) and after its worker or node died (``max_retries``; lost chunk
results are rebuilt from their lineage); a scene that still fails is reported with its
error while the others finish.

Bit for bit: the SMPL fit's float sums depend on torch's thread count, and Ray starts
its workers with ``OMP_NUM_THREADS=1``; the tasks use the driver's thread count, the
one ``mvviz run`` uses on that machine, so the numbers are the same as ``mvviz run``'s.
"""

from __future__ import annotations

import json
import logging
import os
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import ray
import torch

from pipeline.batch.jobs import (
    SceneJob,
    chunk_bounds,
    join_chunks,
    run_chunk,
    scene_inputs,
    stored_key,
    summarize,
)
from pipeline.body_model import BodyModel
from pipeline.files import SceneFormatError, atomic_write
from pipeline.progress import Progress, StageBar
from pipeline.results import load_results, save_results
from pipeline.scene import Scene

RAY_TEMP_DIR = Path(tempfile.gettempdir()) / "mvviz-ray"  # embedded Ray's sessions and logs
SUMMARY_SUFFIX = ".summary.json"  # beside a results file: its report figures and key


def start_ray(address: str | None = None, *, num_cpus: int | None = None) -> dict:
    """Connect to Ray: ``address`` None starts an embedded local Ray on this machine's
    cores (``num_cpus``, default all) bound to 127.0.0.1, no dashboard, quiet, its
    files under the system temp; ``"auto"`` or ``"HOST:PORT"`` joins a running cluster.
    Returns ``ray.cluster_resources()``."""
    # Ray's usage statistics would be sent over the network: never (no network at run time).
    os.environ["RAY_USAGE_STATS_ENABLED"] = "0"
    if ray.is_initialized():
        return ray.cluster_resources()
    quiet = dict(logging_level=logging.ERROR, log_to_driver=False, namespace="mvviz")
    if address is None:
        RAY_TEMP_DIR.mkdir(parents=True, exist_ok=True)
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


def stop_ray() -> None:
    if ray.is_initialized():
        ray.shutdown()


# ------------------------------------------------------------------------- the tasks


def _inputs_task(scene, config, model, threads):
    torch.set_num_threads(threads)
    return scene_inputs(scene, config, model)


def _chunk_task(scene, config, inputs, start, stop, threads):
    torch.set_num_threads(threads)
    return run_chunk(scene, config, inputs, start, stop)


def _join_task(scene, config, model, inputs, key, threads, *chunks):
    torch.set_num_threads(threads)
    results = join_chunks(scene, config, model, inputs, chunks, key)
    return results, summarize(scene, results)


def _summary_task(scene, results, threads):
    torch.set_num_threads(threads)
    return summarize(scene, results)


@dataclass
class Outcome:
    """How one job ended: ``status`` "computed", "cached" or "failed" (``error`` says
    why); ``summary`` the figures of :func:`pipeline.batch.jobs.summarize`."""

    job: SceneJob
    status: str
    summary: dict | None = None
    error: str | None = None
    seconds: float = 0.0


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


def run_jobs(  # long: one scheduling loop (submit, then collect as tasks end)
    jobs: Sequence[SceneJob],
    scenes: dict[Path, Scene],
    model: BodyModel,
    *,
    chunk_frames: int = 0,
    retries: int = 2,
    force: bool = False,
    progress: Progress = True,
) -> list[Outcome]:
    """Run every job whose results are not current (``force``: all) on the connected
    Ray; ``scenes`` maps each job's ``scene_dir`` to its loaded scene. Outcomes in the
    order of ``jobs``. Progress: stage "scenes" (jobs done, cached ones counted at
    once) and stage "chunks" (frame chunks done)."""
    threads = torch.get_num_threads()
    opts = dict(max_retries=retries, retry_exceptions=True)
    inputs_fn = ray.remote(_inputs_task).options(**opts)
    chunk_fn = ray.remote(_chunk_task).options(**opts)
    join_fn = ray.remote(_join_task).options(**opts)
    summary_fn = ray.remote(_summary_task).options(**opts)

    outcomes: list[Outcome | None] = [None] * len(jobs)
    pending: dict[ray.ObjectRef, tuple[str, int]] = {}
    started: dict[int, float] = {}
    scene_refs: dict[Path, ray.ObjectRef] = {}
    model_ref = None
    num_chunks = 0
    for i, job in enumerate(jobs):
        current, summary = cached_summary(job) if not force else (False, None)
        if current and summary is not None:
            outcomes[i] = Outcome(job, "cached", summary)
            continue
        scene = scenes[job.scene_dir]
        if job.scene_dir not in scene_refs:
            scene_refs[job.scene_dir] = ray.put(scene)
        sref = scene_refs[job.scene_dir]
        started[i] = time.perf_counter()
        if current:  # results of mvviz run: only the report's figures are missing
            results = load_results(job.results_path, model=model)
            pending[summary_fn.remote(sref, results, threads)] = ("summary", i)
            continue
        if model_ref is None:
            model_ref = ray.put(model)
        inputs = inputs_fn.remote(sref, job.config, model_ref, threads)
        chunks = [
            chunk_fn.remote(sref, job.config, inputs, a, b, threads)
            for a, b in chunk_bounds(scene.num_frames, chunk_frames)
        ]
        num_chunks += len(chunks)
        pending.update({c: ("chunk", i) for c in chunks})
        join = join_fn.remote(sref, job.config, model_ref, inputs, job.key, threads, *chunks)
        pending[join] = ("join", i)

    done_jobs = sum(o is not None for o in outcomes)
    with (
        StageBar("scenes", len(jobs), progress, unit="scene", initial=done_jobs) as scene_bar,
        StageBar("chunks", num_chunks, progress, unit="chunk") as chunk_bar,
    ):
        while pending:
            ready, _ = ray.wait(list(pending), num_returns=1)
            kind, i = pending.pop(ready[0])
            if kind == "chunk":
                chunk_bar.update()
                continue
            job = jobs[i]
            took = time.perf_counter() - started[i]
            try:
                value = ray.get(ready[0])
            except (ray.exceptions.RayError, SceneFormatError, ValueError) as exc:
                outcomes[i] = Outcome(job, "failed", error=_error_text(exc), seconds=took)
            else:
                if kind == "join":
                    results, summary = value
                    save_results(results, job.results_path)
                    status = "computed"
                else:
                    summary, status = value, "cached"
                _write_summary(job, summary)
                outcomes[i] = Outcome(job, status, summary, seconds=took)
            scene_bar.update()
    return [o for o in outcomes if o is not None]
