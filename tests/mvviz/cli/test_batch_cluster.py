"""`mvviz batch --address` on a real two-node Ray cluster on this machine (loopback only):
a ``ray start --head`` node and a ``ray start --address`` worker node started by this
test, 4 tiny scenes shipped as Ray objects; the worker node is killed while it runs a
scene's task, and every scene still completes with the results of ``mvviz run``.

Every process this test starts is ended by its id (the ``ray start`` processes, and
every process seen under them: GCS, raylets, agents, task workers), never by name."""

from __future__ import annotations

import json
import os
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from mvviz.cli import main
from pipeline.batch.report import load_report
from pipeline.body.model import load_body_model
from pipeline.synth.scene_gen import SynthConfig, write_synth_scene
from tests.mvviz.conftest import wait_until
from tests.pipeline.helpers import campus_rig

pytestmark = pytest.mark.slow

RAY = shutil.which("ray") or str(Path(sys.executable).with_name("ray"))
NUM_SCENES = 4
TASK_TITLES = ("ray::_scene_task", "ray::_join_task", "ray::_chunk_task", "ray::_inputs_task")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def children(pid: int) -> list[int]:
    """Every live descendant of ``pid`` (from /proc)."""
    kids: dict[int, list[int]] = {}
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                ppid = int(Path(f"/proc/{entry}/stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError):
                continue
            kids.setdefault(ppid, []).append(int(entry))
    out, todo = [], [pid]
    while todo:
        for k in kids.get(todo.pop(), []):
            out.append(k)
            todo.append(k)
    return out


def cmdline(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_text().replace("\0", " ")
    except OSError:
        return ""


class RayNode:
    """One ``ray start --block`` process and the ids of everything seen under it."""

    def __init__(self, args: list[str], temp_dir: Path, env: dict) -> None:
        ports = [free_port() for _ in range(4)]
        cmd = [
            RAY, "start", "--block", "--node-ip-address", "127.0.0.1",
            "--temp-dir", str(temp_dir), "--disable-usage-stats",
            "--dashboard-agent-listen-port", str(ports[0]),
            "--dashboard-agent-grpc-port", str(ports[1]),
            "--runtime-env-agent-port", str(ports[2]), "--metrics-export-port", str(ports[3]),
            *args,
        ]  # fmt: skip
        self.proc = subprocess.Popen(
            cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
            start_new_session=True,
        )  # fmt: skip
        self.seen: set[int] = set()
        self.output: list[str] = []
        self.started = threading.Event()
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        for line in self.proc.stdout:
            self.output.append(line)
            if "Ray runtime started" in line:
                self.started.set()

    def wait_started(self, timeout: float = 120) -> None:
        deadline = time.monotonic() + timeout
        while not self.started.wait(0.2) and time.monotonic() < deadline:
            if self.proc.poll() is not None:
                break
        if not self.started.is_set():
            raise AssertionError("ray start did not come up:\n" + "".join(self.output[-30:]))

    def processes(self) -> list[int]:
        found = children(self.proc.pid)
        self.seen.update(found)
        return found

    def kill(self) -> None:
        """SIGKILL the ``ray start`` process and every process seen under it, by id."""
        pids = [self.proc.pid, *self.processes(), *self.seen]
        try:  # its process group too (start_new_session: the group's id is its pid)
            os.killpg(self.proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        for pid in dict.fromkeys(pids):
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        self.proc.wait(timeout=30)


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    """root/s0..s3 (2 people, 30 frames, campus rig, no videos) and ref/s*: copies,
    each run by ``mvviz run``."""
    base = tmp_path_factory.mktemp("cluster")
    model = load_body_model()
    for i in range(NUM_SCENES):
        d = base / "root" / f"s{i}"
        cfg = SynthConfig(num_people=2, num_frames=30, seed=20 + i, render_video=False)
        write_synth_scene(d, campus_rig(), model, cfg, progress=False)
        shutil.copytree(d, base / "ref" / d.name)
        assert main(["run", str(base / "ref" / d.name)]) == 0
    return base


def test_worker_node_killed_mid_run(scenes, tmp_path):
    # Ray >= 2.5x authenticates with a token; this cluster's own one, given to every
    # process of it (nodes and driver), not the user's ~/.ray/auth_token.
    env = {**os.environ, "RAY_USAGE_STATS_ENABLED": "0", "RAY_AUTH_MODE": "token",
           "RAY_AUTH_TOKEN": secrets.token_hex(32)}  # fmt: skip
    port = free_port()
    # Short temp paths: Ray's socket paths must stay under the 107-byte limit.
    temp = Path(f"/tmp/mvviz-cl-{os.getpid()}")
    head = RayNode(["--head", "--port", str(port), "--num-cpus", "1",
                    "--include-dashboard", "false"], temp / "h", env)  # fmt: skip
    nodes = [head]
    try:
        head.wait_started()
        worker = RayNode(["--address", f"127.0.0.1:{port}", "--num-cpus", "2"], temp / "w", env)
        nodes.append(worker)
        worker.wait_started()
        out = tmp_path / "out"
        driver = subprocess.Popen(
            [sys.executable, "-m", "mvviz.cli", "batch", "--root", str(scenes / "root"),
             "--address", f"127.0.0.1:{port}", "--out", str(out), "--retries", "3"],
            env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
        )  # fmt: skip
        killed_task = None
        deadline = time.monotonic() + 240
        while killed_task is None and time.monotonic() < deadline and driver.poll() is None:
            for pid in worker.processes():
                title = cmdline(pid)
                if title.startswith(TASK_TITLES):
                    killed_task = title.split()[0]
                    break
            else:
                time.sleep(0.05)
        assert killed_task, "no task ran on the worker node"
        worker.kill()  # mid-run: a scene's task is running there now
        head.processes()
        log, _ = driver.communicate(timeout=600)
        head.processes()
        assert driver.returncode == 0, log
    finally:
        for node in reversed(nodes):
            node.kill()
        shutil.rmtree(temp, ignore_errors=True)

    print(f"killed the worker node while it ran {killed_task}")
    report = load_report(out)
    assert [r["status"] for r in report["rows"]] == ["computed"] * NUM_SCENES
    for i in range(NUM_SCENES):
        with (
            np.load(out / f"s{i}" / "results.npz") as batch,
            np.load(scenes / "ref" / f"s{i}" / ".mvviz" / "results.npz") as run,
        ):
            assert sorted(batch.files) == sorted(run.files)
            for k in run.files:
                assert np.array_equal(batch[k], run[k], equal_nan=batch[k].dtype.kind == "f"), k
            assert json.loads(str(batch["meta"])) == json.loads(str(run["meta"]))

    def gone(pid: int) -> bool:
        return not Path(f"/proc/{pid}").exists() or _zombie(pid)

    # every process this test started is gone (one killed may take a moment to exit)
    for node in nodes:
        wait_until(lambda n=node: all(map(gone, n.seen)), 30, f"{node.seen} to exit")


def _zombie(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] == "Z"
    except OSError:
        return True
