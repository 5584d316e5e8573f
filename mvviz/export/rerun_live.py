"""Rerun live beside viser: ``python app.py --rerun [--rerun-port P]``.

:class:`RerunWebServer` starts rerun's own web viewer and gRPC server from the
rerun-sdk package (``python -m rerun --serve-web``, nothing downloaded), bound to
127.0.0.1 like viser: the web viewer on port P, the gRPC proxy on P + 1.
:class:`LiveRerun` logs the viewer's state into it with the layout of :mod:`mvviz.export.rerun`:

- at start the static context (cameras as Pinhole + Transform3D, the skeleton
  AnnotationContext, the blueprint) and the time series of the results;
- each frame the timeline visits: images (the viewer's stored JPEGs, not re-encoded),
  2D joints, rays, raw / filtered / GT skeletons, GT meshes, the fitted SMPL bodies
  (step I and SMPL + VAE, decimated), filter B's skeletons;
- every re-run of the Pipeline panel (new results) as a branch ``_run<n>`` and every
  filter B change as a branch ``_b<n>`` of the time series (see :mod:`mvviz.export.rerun`).

The logging runs on its own thread through a "latest wins" slot: the render thread only
stores the newest frame (a ``subscribe`` callback, microseconds), frames visited while
one is being logged are dropped, never queued; and the logger waits while the viewer
renders, so it does not hold the GIL against a frame change; it and rerun's server run
at a lower CPU priority (nice 10) than the viewer.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Protocol
from urllib.parse import quote

import numpy as np
import rerun as rr
import torch

from mvviz.analysis.filter_runs import FilterRun
from mvviz.export.rerun import APP_ID, SceneLogger, make_blueprint
from mvviz.scene.images import FrameStore, video_frame
from mvviz.state import ViewerState
from pipeline.body.arrays import BodyModelData
from pipeline.body.model import BodyModel, torch_body_model

DEFAULT_WEB_PORT = 9090
POLL_S = 0.25  # how often the logger looks at filter B and the stop flag
NICE = 10  # the logging thread and rerun's server yield the CPU to the viewer
SERVER_MEMORY_LIMIT = "1GiB"  # the gRPC server's buffer for late viewers (oldest dropped)


class LiveHost(Protocol):
    """What :class:`LiveRerun` reads of the viewer: a part of the panel contract
    (:class:`mvviz.panels.contract.PanelHost`, documented there), so any panel host,
    the app included, is one. Declared here because export code sits below the panels.
    """

    @property
    def state(self) -> ViewerState: ...
    @property
    def model(self) -> BodyModel | BodyModelData | None: ...
    @property
    def frames(self) -> FrameStore | None: ...
    @property
    def stopped(self) -> threading.Event: ...
    @property
    def rendering(self) -> bool: ...
    def subscribe(self, callback: Callable[[ViewerState, str], None]) -> Callable[[], None]: ...
    def filter_runs(self) -> tuple[FilterRun, FilterRun | None] | None: ...


def _lower_priority() -> None:
    os.nice(NICE)  # the viewer's frame changes first


def port_is_free(host: str, port: int) -> bool:
    with socket.socket() as s:
        try:
            s.bind((host, port))
        except OSError:
            return False
    return True


def free_port(host: str = "127.0.0.1") -> int:
    with socket.socket() as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


class RerunWebServer:
    """rerun's web viewer (``web_port``) and gRPC server (``web_port + 1``) in a child
    process (``python -m rerun --serve-web --bind HOST``); a taken port moves both to
    free ones. :meth:`stop` ends the child."""

    def __init__(self, *, host: str = "127.0.0.1", web_port: int = DEFAULT_WEB_PORT) -> None:
        self.host = host
        if not (port_is_free(host, web_port) and port_is_free(host, web_port + 1)):
            web_port, grpc_port = free_port(host), free_port(host)
        else:
            grpc_port = web_port + 1
        self.web_port, self.grpc_port = web_port, grpc_port
        cmd = [
            sys.executable, "-m", "rerun", "--serve-web", "--bind", host,
            "--web-viewer-port", str(web_port), "--port", str(grpc_port),
            "--server-memory-limit", SERVER_MEMORY_LIMIT, "--hide-welcome-screen",
        ]  # fmt: skip
        # ``python -m rerun`` runs rerun's binary as its child: a session of its own lets
        # stop() end both (ending the Python wrapper alone left the server running)
        self.process = subprocess.Popen(
            cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, stdin=subprocess.DEVNULL,
            preexec_fn=_lower_priority if os.name == "posix" else None,
            start_new_session=os.name == "posix",
        )  # fmt: skip
        self._wait_listening(30.0)

    def _wait_listening(self, timeout: float) -> None:
        end = time.monotonic() + timeout
        for port in (self.grpc_port, self.web_port):
            while True:
                if self.process.poll() is not None:
                    raise RuntimeError(f"rerun server exited with code {self.process.returncode}")
                try:
                    with socket.create_connection((self._connect_host, port), timeout=0.5):
                        break
                except OSError:
                    if time.monotonic() > end:
                        self.stop()
                        raise TimeoutError(f"rerun server not listening on port {port}") from None
                    time.sleep(0.1)

    @property
    def _connect_host(self) -> str:
        return "127.0.0.1" if self.host in ("0.0.0.0", "::", "") else self.host

    @property
    def grpc_uri(self) -> str:
        return f"rerun+http://{self._connect_host}:{self.grpc_port}/proxy"

    @property
    def url(self) -> str:
        """The web viewer, connected to the gRPC server."""
        return f"http://{self._connect_host}:{self.web_port}/?url={quote(self.grpc_uri, safe='')}"

    def stop(self) -> None:
        """End the server: the wrapper and rerun's binary (the wrapper's session)."""
        if os.name != "posix":
            if self.process.poll() is None:
                self.process.terminate()
            self.process.wait(5)
            return
        for sig in (signal.SIGTERM, signal.SIGKILL):
            try:
                os.killpg(self.process.pid, sig)
            except ProcessLookupError:
                break  # the session has ended
            if self._session_ended(within_s=5.0):
                break
        try:
            self.process.wait(5)  # the wrapper, reaped
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait(5)

    def _session_ended(self, within_s: float) -> bool:
        """Wait up to ``within_s`` for every process of the server's session to end."""
        end = time.monotonic() + within_s
        while _session_alive(self.process.pid):
            self.process.poll()  # reaps the wrapper
            if time.monotonic() > end:
                return False
            time.sleep(0.05)
        return True


def _session_alive(sid: int) -> bool:
    """A process of session ``sid`` still runs (not a zombie waiting to be reaped)."""
    proc = Path("/proc")
    if not proc.is_dir():
        try:
            os.killpg(sid, 0)
        except ProcessLookupError:
            return False
        return True
    for stat in proc.glob("[0-9]*/stat"):
        try:
            state, _ppid, _pgrp, session = stat.read_text().rsplit(")", 1)[1].split()[:4]
        except (OSError, ValueError):
            continue  # ended meanwhile
        if int(session) == sid and state != "Z":
            return True
    return False


class LiveRerun:
    """Logs what a running viewer shows into a rerun recording, live.

    Args:
        app: the running viewer (any :class:`LiveHost`: the app, or a panel host).
        server: where the recording streams (None: no gRPC sink).
        save: also write the same stream to this ``.rrd`` file.
        recording: log into this stream instead of a new one (its sinks are kept when
            neither ``server`` nor ``save`` is given).

    Attributes (for tests and the benchmark): ``logged`` frames logged, ``dropped``
    frames visited but skipped, ``last_frame`` the last one logged, ``branches`` the
    branch names logged, ``log_ms`` the last frame's logging time, ``errors``.
    """

    def __init__(
        self,
        app: LiveHost,
        *,
        server: RerunWebServer | None = None,
        save: str | Path | None = None,
        recording: rr.RecordingStream | None = None,
    ) -> None:
        self.app, self.server = app, server
        self._sink_args = (recording, save)
        self.rec: rr.RecordingStream | None = None
        self._ready = threading.Event()
        self.logged = self.dropped = 0
        self.branches: list[str] = []
        self.log_ms = 0.0
        self.last_frame: int | None = None
        self.errors: list[str] = []
        self._cv = threading.Condition()
        self._want: tuple[int, object] | None = None  # (frame, ViewerData) to log next
        self._new_results = False
        self._busy = False
        self._closed = threading.Event()
        self._logger: SceneLogger | None = None
        self._results = None
        self._runs = self._b_runs = 0
        self._b_seen = None
        self._b_shown: np.ndarray | None = None
        st = app.state
        self._want = (st.frame, st.data)
        self._thread = threading.Thread(target=self._loop, name="mvviz-rerun", daemon=True)
        self._thread.start()
        self._ready.wait(30)
        self._unsubscribe: Callable[[], None] | None = app.subscribe(self._on_state_changed)

    # ------------------------------------------------------------------ public

    def wait_idle(self, timeout: float = 30.0) -> bool:
        """Block until the newest visited frame and results are logged."""
        end = time.monotonic() + timeout
        with self._cv:
            while self._want is not None or self._busy or self._new_results:
                left = end - time.monotonic()
                if left <= 0 or self._closed.is_set():
                    return False
                self._cv.wait(min(left, 0.05))
        return True

    def close(self) -> None:
        """Stop logging, flush and close the sinks (the file gets its footer)."""
        if self._unsubscribe is not None:
            self._unsubscribe()
            self._unsubscribe = None
        self._closed.set()
        with self._cv:
            self._cv.notify_all()
        self._thread.join(timeout=10)
        if self.rec is not None:
            self.rec.flush()
            self.rec.disconnect()

    @property
    def on_state_changed_attached(self) -> bool:
        """Still following the viewer (until :meth:`close`)."""
        return self._unsubscribe is not None

    # ------------------------------------------------------------------ render thread

    def _on_state_changed(self, st, reason: str) -> None:
        """Render thread: remember the newest frame (and new results); nothing else."""
        with self._cv:
            if self._want is not None:
                self.dropped += 1
            self._want = (st.frame, st.data)
            if "results" in reason.split(","):
                self._new_results = True
            self._cv.notify_all()

    # ------------------------------------------------------------------ logging thread

    def _pause(self) -> None:
        """Wait while the viewer renders a frame (its render lock is held)."""
        t0 = time.monotonic()
        while self.app.rendering and time.monotonic() - t0 < 0.5:
            time.sleep(0.001)

    def _open(self) -> None:
        """On the logging thread, at a lower CPU priority (Linux nice is per thread): so
        are the encoder and sink threads rerun starts here, which inherit it."""
        try:
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), NICE)
        except (AttributeError, OSError):
            pass
        # One intra-op thread for this thread's skinning (GT meshes, fitted bodies): on 2
        # busy cores two spinning threads made a frame's bodies up to ~30x slower (230 vs
        # 8 ms). With torch's OpenMP backend the setting is mostly per thread; where it
        # is not, the viewer's other torch work (skinning on load, the Pipeline panel's
        # re-runs, whose fits set their own threads) runs on one thread as well.
        torch.set_num_threads(1)
        recording, save = self._sink_args
        try:
            self.rec = recording if recording is not None else rr.RecordingStream(APP_ID)
            sinks = []
            if self.server is not None:
                sinks.append(rr.GrpcSink(self.server.grpc_uri))
            if save is not None:
                sinks.append(rr.FileSink(str(save)))
            if sinks:
                self.rec.set_sinks(*sinks)
        finally:
            self._ready.set()

    def _loop(self) -> None:
        self._open()
        try:
            self.rec.send_blueprint(make_blueprint(self.app.state.scene.rig.names))
        except Exception as exc:
            self.errors.append(f"blueprint: {exc}")
        while not self._closed.is_set() and not self.app.stopped.is_set():
            with self._cv:
                if self._want is None and not self._new_results:
                    self._cv.wait(POLL_S)
                want, self._want = self._want, None
                new_results, self._new_results = self._new_results, False
                self._busy = True
            try:
                if want is not None:
                    self._log(want[0], want[1], new_results)
                self._check_filter_b()
            except Exception as exc:  # keep logging the next frames
                self.errors.append(f"{type(exc).__name__}: {exc}")
                print(f"mvviz view: rerun logging failed: {self.errors[-1]}")
            finally:
                with self._cv:
                    self._busy = False
                    self._cv.notify_all()

    def _log(self, frame: int, data, new_results: bool) -> None:
        results = data.results
        if results is not self._results:
            first = self._results is None
            model = self.app.model if data.bodies is not None else None
            model = None if model is None else torch_body_model(model)  # the GT meshes skin
            self._logger = SceneLogger(
                data.scene, results, self.rec, body_model=model,
                image_width=self._image_width(), sparse=True, pause=self._pause,
            )  # fmt: skip
            self._logger.log_static()
            self._results = results
            if first or new_results:
                branch = "" if first else f"_run{self._runs + 1}"
                self._runs += 0 if first else 1
                self._logger.send_plots(branch=branch)
                self.branches.append(branch or "base")
            self._b_seen = None  # B re-filters on the new results
            self._b_shown = None
        t0 = time.perf_counter()
        frames = self.app.frames
        images = {}
        if frames is not None:
            for cam in data.scene.rig.names:
                shown = video_frame(data, cam, frame)  # follows sync.offsets, as the viewer
                jpeg = frames.jpeg(cam, shown)
                if jpeg is None:
                    rgb = frames.frame(cam, shown)
                    jpeg = None if rgb is None else np.ascontiguousarray(rgb[..., ::-1])
                images[cam] = jpeg
        self._logger.log_frame(frame, images=images, filter_b=self._b_shown)
        self.log_ms = (time.perf_counter() - t0) * 1e3
        self.logged += 1
        self.last_frame = frame

    def _image_width(self) -> int:
        frames = self.app.frames
        return frames.width if frames is not None else 640

    def _check_filter_b(self) -> None:
        """A new filter B run (not equal to A): its filtered tracks as a branch."""
        runs, logger = self.app.filter_runs(), self._logger
        if runs is None or logger is None:
            return
        run_a, run_b = runs
        if run_b is None or run_b is self._b_seen:
            return
        self._b_seen = run_b
        if run_b.params == run_a.params or run_b.shown.shape != self._results.track_raw.shape:
            self._b_shown = None
            return
        self._b_runs += 1
        branch = f"_b{self._b_runs}"
        logger.send_plots(branch=branch, filtered=run_b.shown, mahalanobis=run_b.mahalanobis)
        self._b_shown = run_b.shown
        self.branches.append(branch)
        with self._cv:  # redraw the current frame with B's skeletons
            if self._want is None:
                st = self.app.state
                self._want = (st.frame, st.data)
