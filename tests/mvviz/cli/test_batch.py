"""`mvviz batch` on embedded Ray: the same results as `mvviz run`, skips, a failing scene,
a sweep, and the report as a person sees it in headless chromium."""

from __future__ import annotations

import html
import ipaddress
import json
import os
import shutil
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
import ray

from mvviz.cli import main
from pipeline.batch import ray_run
from pipeline.batch.ray_run import EMBEDDED_RAY_CONFIG, start_ray, stop_ray
from pipeline.batch.report import load_report
from pipeline.body.model import load_body_model
from pipeline.config import PipelineConfig
from pipeline.core.files import SceneFormatError
from pipeline.data.scene import load_scene
from pipeline.results.store import load_results
from pipeline.run.pipeline import run_pipeline
from pipeline.synth.scene_gen import SynthConfig, write_synth_scene
from tests.pipeline.helpers import campus_rig
from tools.chromium import CHROMIUM, launch_chromium

# One Ray session per batch command; the source "smpl" makes the keypoint-only copy fail
# inside a task (no monocular SMPL to restore), after its retries.
SMPL = ["--set", "source=smpl"]


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    """root/{a, b_keypoints_only}: a tiny scene, and a copy with only 2D keypoints;
    ref/a: a copy of a for mvviz run."""
    base = tmp_path_factory.mktemp("batch")
    a = base / "root" / "a"
    cfg = SynthConfig(num_people=2, num_frames=12, seed=7, render_video=False)
    write_synth_scene(a, campus_rig(), load_body_model(), cfg, progress=False)
    bad = base / "root" / "b_keypoints_only"
    shutil.copytree(a, bad)
    with np.load(a / "detections.npz") as z:
        keep = {k: z[k] for k in ("frame", "view", "keypoints", "gt_person_id")}
    np.savez(bad / "detections.npz", **keep)
    shutil.copytree(a, base / "ref" / "a")
    return base


@pytest.fixture(scope="module")
def first_batch(dataset):
    """``mvviz batch --root`` (source smpl, 5-frame chunks): its exit code and report."""
    report = dataset / "report1"
    code = main(
        ["batch", "--root", str(dataset / "root"), *SMPL, "--chunk-frames", "5",
         "--retries", "1", "--report", str(report)]
    )  # fmt: skip
    return code, load_report(report)


@pytest.fixture(scope="module")
def reference(dataset):
    """``mvviz run`` on the copy of scene a: its results file."""
    assert main(["run", str(dataset / "ref" / "a"), *SMPL]) == 0
    return dataset / "ref" / "a" / ".mvviz" / "results.npz"


def assert_same_files(batch_file, run_file) -> None:
    """Every array of the two results files bit for bit (NaN where NaN), and the meta."""
    with np.load(batch_file) as batch, np.load(run_file) as run:
        assert sorted(batch.files) == sorted(run.files)
        assert any(k.startswith("smplvae_") for k in run.files)  # the fit is compared too
        for k in run.files:
            assert batch[k].dtype == run[k].dtype, k
            assert np.array_equal(batch[k], run[k], equal_nan=batch[k].dtype.kind == "f"), k
        assert json.loads(str(batch["meta"])) == json.loads(str(run["meta"]))


@pytest.mark.slow
def test_results_equal_mvviz_run_bit_for_bit(dataset, first_batch, reference):
    """Scene a in 5-frame chunks (inputs, chunk and join tasks)."""
    code, report = first_batch
    assert code == 1  # one scene failed
    ok = next(r for r in report["rows"] if r["label"] == "a")
    assert ok["status"] == "computed"
    assert_same_files(dataset / "root" / "a" / ".mvviz" / "results.npz", reference)
    with np.load(reference) as run:
        assert ok["key"] == json.loads(str(run["meta"]))["cache_key"]


@pytest.mark.slow
@pytest.mark.parametrize("ship", [False, True], ids=["files", "objects"])
def test_one_task_scene_equals_mvviz_run(dataset, reference, tmp_path, ship):
    """Scene a in one task (12 frames <= --chunk-frames): on the embedded Ray the worker
    reads the scene and writes the results itself; joining a running Ray with --address
    (no --shared-storage) the scene and the model travel as objects and the driver
    writes the results."""
    out = tmp_path / "out"
    args = ["batch", str(dataset / "ref" / "a"), *SMPL, "--out", str(out), "--force"]
    if ship:
        start_ray()  # the command joins it (and shuts it down when done)
        args += ["--address", "auto"]
    try:
        assert main(args) == 0
    finally:
        stop_ray()
    row = load_report(out)["rows"][0]
    parts = row["task_seconds"]
    assert row["status"] == "computed" and parts["sequence_fit_s"] > 0
    # the batch's timeline: when and on which worker (a Ray worker, not this process)
    assert parts["started_at"] + parts["sequence_fit_s"] <= parts["ended_at"]
    assert parts["pid"] != os.getpid()
    assert_same_files(out / "a" / "results.npz", reference)


@pytest.mark.slow
def test_embedded_ray_listens_on_loopback_only():
    """Every server of the embedded Ray (GCS, raylet, agents, workers, the driver's own)
    on 127.0.0.1: without mvviz's loopback node Ray listens on every interface."""
    import psutil

    start_ray(num_cpus=1)
    try:
        assert ray.get(ray.remote(lambda: 1).remote()) == 1  # a worker is up and serving
        pids = {os.getpid(), *(p.pid for p in psutil.Process().children(recursive=True))}
        listening = [
            (c.laddr.ip, c.pid) for c in psutil.net_connections(kind="inet")
            if c.status == psutil.CONN_LISTEN and c.pid in pids
        ]  # fmt: skip
    finally:
        stop_ray()
    assert len({pid for _, pid in listening}) >= 4, listening  # driver, GCS, raylet, worker
    outside = [(ip, pid) for ip, pid in listening if not _is_loopback(ip)]
    assert not outside, outside


@pytest.mark.slow
def test_embedded_ray_starts_a_lean_head_and_restores_ray():
    """The embedded head runs without the autoscaler monitor, the log monitor and the
    dashboard's API server (ray_run.LEAN_HEAD_SKIPS), still runs tasks and returns their
    errors, and Ray's classes are as before once it is up (a cluster keeps its head)."""
    from ray._private import node as ray_node
    from ray._private import parameter

    params_cls, api = parameter.RayParams, ray_node.Node.__dict__["start_api_server"]
    start_ray(num_cpus=1)
    try:
        started = set(ray._private.worker._global_node.all_processes)

        def fails():
            raise ValueError("no such scene")

        with pytest.raises(ray.exceptions.RayTaskError, match="no such scene"):
            ray.get(ray.remote(fails).options(max_retries=0).remote())
        assert ray.get(ray.remote(lambda: 2).remote()) == 2
    finally:
        stop_ray()
    assert {"gcs_server", "raylet"} <= started, started
    assert not started & set(ray_run.LEAN_HEAD_SKIPS), started
    assert parameter.RayParams is params_cls
    assert ray_node.Node.__dict__["start_api_server"] is api


@pytest.mark.slow
def test_embedded_ray_config_reaches_its_processes(monkeypatch):
    """The embedded node's processes get EMBEDDED_RAY_CONFIG (10 ms socket retries, the
    same 10 s bound; workers prestarted with the raylet) unless the user set a value,
    which is kept; this process's environment is as before once the node is up."""
    import psutil

    user = "RAY_raylet_client_num_connect_attempts"
    monkeypatch.setenv(user, "700")
    before = dict(os.environ)
    start_ray(num_cpus=1)
    try:
        raylets = [
            p for p in psutil.Process().children(recursive=True) if p.name() == "raylet"
        ]  # fmt: skip
        env = raylets[0].environ()
    finally:
        stop_ray()
    assert len(raylets) == 1
    assert env["RAY_raylet_client_connect_timeout_milliseconds"] == "10"
    assert env["RAY_enable_worker_prestart"] == "1"
    assert env[user] == "700"  # the user's, not ours
    # Ray's own init sets a few variables for good (its auth mode, the breakpoint hook),
    # and start_ray turns usage statistics off: the config's are the ones restored.
    assert {k: os.environ.get(k) for k in EMBEDDED_RAY_CONFIG} == {
        k: before.get(k) for k in EMBEDDED_RAY_CONFIG
    }


def _worker_priority() -> int:
    return os.getpriority(os.PRIO_PROCESS, 0)


@pytest.mark.slow
def test_embedded_ray_workers_run_at_the_normal_priority(monkeypatch):
    """A task runs at the priority ``mvviz run`` gets (nice 0), not at Ray's default 15,
    under which any other runnable thread takes the core first; a user's value is kept."""
    import ray

    monkeypatch.delenv("RAY_worker_niceness", raising=False)
    start_ray(num_cpus=1)
    try:
        ours = ray.get(ray.remote(_worker_priority).remote())
    finally:
        stop_ray()
    monkeypatch.setenv("RAY_worker_niceness", "7")
    start_ray(num_cpus=1)
    try:
        users = ray.get(ray.remote(_worker_priority).remote())
    finally:
        stop_ray()
    assert (ours, users) == (os.getpriority(os.PRIO_PROCESS, 0), 7)


def _ended_pid() -> int:
    """The id of a process that has ended (a Ray session's driver gone)."""
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def test_ended_ray_sessions_are_pruned_beyond_the_newest(tmp_path):
    """Ray leaves a session directory per embedded start: those whose driver has ended
    go, but the newest ``keep`` and any still running (its driver alive) stay, and
    nothing else in the directory is touched."""
    ended = _ended_pid()
    names = [
        f"session_2026-01-01_00-00-00_000001_{ended}",
        f"session_2026-01-02_00-00-00_000001_{os.getpid()}",  # running: this process
        f"session_2026-01-03_09-30-00_123456_{ended}",
        f"session_2026-01-04_00-00-00_000001_{ended}",
        f"session_2026-01-05_00-00-00_000001_{ended}",
    ]
    for name in names:
        (tmp_path / name / "logs").mkdir(parents=True)
        (tmp_path / name / "logs" / "raylet.out").write_text("log")
    (tmp_path / "session_latest").symlink_to(tmp_path / names[-1])
    (tmp_path / "session_notes").mkdir()  # not a session's name
    removed = ray_run.prune_ray_sessions(tmp_path, keep=2)
    assert sorted(p.name for p in removed) == [names[0], names[2]]
    left = sorted(p.name for p in tmp_path.iterdir())
    assert left == sorted([names[1], names[3], names[4], "session_latest", "session_notes"])
    # a backlog goes a few at a time, the oldest first
    assert ray_run.prune_ray_sessions(tmp_path, keep=0, limit=1) == [tmp_path / names[3]]
    assert ray_run.prune_ray_sessions(tmp_path, keep=0) == [tmp_path / names[4]]
    assert ray_run.prune_ray_sessions(tmp_path / "absent") == []


@pytest.mark.slow
def test_idle_cpu_hook_and_automatic_split(dataset, reference, tmp_path, monkeypatch):
    """3 equal scenes on 2 CPUs: each runs as one task (none is more than an even share
    of the work), and the driver's closing work (``on_idle_cpu``) runs once, as soon as
    fewer scenes are left than CPUs: after the second is done, before the last. One
    scene alone on 2 CPUs is split into frame chunks (auto chunks of 5 frames here),
    with mvviz run's results bit for bit."""
    from mvviz.cli import build_parser
    from mvviz.cli.batch import plan

    dirs = []
    for name in ("s1", "s2", "s3"):
        skip = shutil.ignore_patterns(".mvviz")
        shutil.copytree(dataset / "ref" / "a", tmp_path / name, ignore=skip)
        dirs.append(str(tmp_path / name))

    def planned(scene_dirs, out):
        argv = ["batch", *scene_dirs, *SMPL, "--force", "--out", str(tmp_path / out)]
        jobs, scenes, model, bad = plan(build_parser(argv).parse_args(argv))
        assert len(jobs) == len(scene_dirs) and not bad
        return jobs, scenes, model

    events: list[str] = []
    finish = ray_run._finish

    def recorded_finish(*args):
        events.append("done")
        return finish(*args)

    monkeypatch.setattr(ray_run, "_finish", recorded_finish)
    monkeypatch.setattr(ray_run, "AUTO_CHUNK_FRAMES", 5)
    start_ray(num_cpus=2)
    try:
        three = ray_run.run_jobs(
            *planned(dirs, "three"), chunk_frames=None, force=True, progress=False,
            shared_files=True, on_idle_cpu=lambda: events.append("idle"),
        )  # fmt: skip
        one = ray_run.run_jobs(
            *planned(dirs[:1], "one"), chunk_frames=None, force=True, progress=False,
            shared_files=True,
        )  # fmt: skip
    finally:
        stop_ray()
    assert [o.status for o in three] == ["computed"] * 3
    assert all(o.parts and o.parts["sequence_fit_s"] > 0 for o in three)  # one task each
    assert events[:4] == ["done", "done", "idle", "done"]
    assert one[0].status == "computed" and one[0].parts is None  # inputs, chunks, join
    assert_same_files(tmp_path / "one" / "s1" / "results.npz", reference)


def test_split_frames_splits_a_scene_beyond_an_even_share():
    split = ray_run.split_frames
    assert split(100, 800, 2) == 0  # 8 equal scenes on 2 CPUs: one task each
    assert split(100, 100, 2) == ray_run.AUTO_CHUNK_FRAMES  # one scene, 2 CPUs
    assert split(600, 800, 2) == ray_run.AUTO_CHUNK_FRAMES  # a long one beside short ones
    assert split(100, 800, 2) == split(400, 800, 2) == 0  # exactly an even share: no
    assert split(100, 100, 1) == 0  # one CPU: nothing to gain


def _is_loopback(ip: str) -> bool:
    addr = ipaddress.ip_address(ip)
    return (getattr(addr, "ipv4_mapped", None) or addr).is_loopback


@pytest.mark.slow
def test_failing_scene_is_reported_while_the_others_finish(first_batch):
    _, report = first_batch
    bad = next(r for r in report["rows"] if r["label"] == "b_keypoints_only")
    assert bad["status"] == "failed" and bad["summary"] is None
    assert "source 'smpl' needs" in bad["error"]
    assert report["counts"] == {"computed": 1, "cached": 0, "failed": 1}


@pytest.mark.slow
def test_report_figures(dataset, first_batch):
    _, report = first_batch
    row = next(r for r in report["rows"] if r["label"] == "a")
    s = row["summary"]
    assert s["num_frames"] == 12 and s["num_tracks"] >= 2
    assert 0 < s["mpjpe_mm"] < 100 and 0.5 < s["pck160"] <= 1 and 0 <= s["pcp"] <= 1
    assert 0 < s["smpl_mpjpe_mm"] < 150
    assert s["assoc_precision"] > 0.8 and s["assoc_recall"] > 0.8
    assert set(s["reprojection_px"]) == set(load_scene(dataset / "root" / "a").rig.names)
    m = report["worst_moments"][0]
    assert m["label"] == "a" and m["metric"] == "mpjpe_mm" and m["value"] >= s["mpjpe_mm"]
    assert f"--frame {m['frame']}" in m["command"] and "source=smpl" in m["command"]
    assert report["worst_scenes"] == {"metric": "mpjpe_mm", "labels": ["a"]}


@pytest.mark.slow
def test_rerun_skips_current_results(dataset, first_batch):
    results = dataset / "root" / "a" / ".mvviz" / "results.npz"
    before = results.stat().st_mtime_ns
    report = dataset / "report2"
    code = main(["batch", str(dataset / "root" / "a"), *SMPL, "--report", str(report)])
    assert code == 0
    rows = load_report(report)["rows"]
    assert [r["status"] for r in rows] == ["cached"]
    assert (
        rows[0]["summary"]
        == next(r for r in first_batch[1]["rows"] if r["label"] == "a")["summary"]
    )
    assert results.stat().st_mtime_ns == before  # not rewritten


@pytest.mark.slow
def test_sweep_runs_the_grid(dataset, tmp_path):
    scene = dataset / "root" / "a"
    out = tmp_path / "out"
    # ended sessions older than any: whatever else is there, the oldest is beyond the
    # newest KEPT_RAY_SESSIONS, and the batch's end deletes it
    ended = _ended_pid()
    old = [
        ray_run.RAY_TEMP_DIR / f"session_2000-01-01_00-00-{i:02d}_000000_{ended}"
        for i in range(ray_run.KEPT_RAY_SESSIONS + 1)
    ]
    for d in old:
        (d / "logs").mkdir(parents=True)
    try:
        code = main(
            ["batch", str(scene), "--set", "fit_smpl=false", "--sweep", "kalman.q=1,2000",
             "--out", str(out)]
        )  # fmt: skip
        assert not old[0].exists()
    finally:
        for d in old:
            shutil.rmtree(d, ignore_errors=True)
    assert code == 0
    report = load_report(out)
    assert [r["setting"] for r in report["rows"]] == [["kalman.q=1"], ["kalman.q=2000"]]
    assert [s["setting"] for s in report["settings"]] == [["kalman.q=1"], ["kalman.q=2000"]]
    accel = [s["accel_mm"] for s in report["settings"]]
    assert accel[0] != accel[1]  # q changes the filtered motion
    # each setting's file holds that configuration's run
    model = load_body_model()
    cfg = PipelineConfig().with_overrides(["fit_smpl=false", "kalman.q=2000"])
    fresh = run_pipeline(load_scene(scene), cfg, model, progress=False)
    stored = load_results(out / "a" / "kalman.q-2000.npz")
    assert np.array_equal(stored.track_forward, fresh.track_forward, equal_nan=True)
    assert (out / "batch_report.html").is_file()


@pytest.mark.slow
def test_bad_prior_fails_its_jobs_before_any_scene_runs(dataset, tmp_path):
    """The checkpoint is read on a worker (the driver never imports torch): a file that is
    no checkpoint fails the job with an error naming it, and no results are written."""
    bad = tmp_path / "prior.pt"
    bad.write_bytes(b"not a checkpoint")
    out = tmp_path / "out"
    scene = str(dataset / "ref" / "a")
    assert main(["batch", scene, "--set", f"pose_prior={bad}", "--force", "--out", str(out)]) == 1
    row = load_report(out)["rows"][0]
    assert row["status"] == "failed" and row["task_seconds"] is None
    assert "SceneFormatError" in row["error"] and "not a readable checkpoint" in row["error"]
    assert str(bad) in row["error"]
    assert not (out / "a" / "results.npz").exists()


DRIVER = """
import sys
from mvviz.cli import build_parser
from mvviz.cli.batch import plan
import pipeline.batch.ray_run
argv = ["batch", sys.argv[1], "--force"]
jobs, scenes, model, bad = plan(build_parser(argv).parse_args(argv))
assert len(jobs) == 1 and not bad
print(sorted(m for m in sys.modules if m.partition(".")[0] in ("torch", "scipy", "cv2")))
"""


@pytest.mark.slow
def test_the_driver_plans_without_torch(dataset):
    """Importing the batch command and Ray's side and planning (scene, config, body
    model, cache key) load no torch (~1.3 s of a batch's fixed cost), and no SciPy or
    OpenCV (~0.4 s before Ray can start): the stages import those where they run."""
    done = subprocess.run([sys.executable, "-c", DRIVER, str(dataset / "ref" / "a")],
                          capture_output=True, text=True, check=True)  # fmt: skip
    assert done.stdout.strip() == "[]"


def test_no_scenes_is_an_input_error(tmp_path, capsys):
    assert main(["batch", "--root", str(tmp_path)]) == 2
    assert "no scenes" in capsys.readouterr().err
    with pytest.raises(SceneFormatError):
        load_report(tmp_path)


@pytest.mark.slow
def test_report_in_chromium(dataset, first_batch, tmp_path):
    """The HTML as a person sees it: tables, the plot, the viewer commands."""
    if not CHROMIUM.exists():
        pytest.skip(f"{CHROMIUM} is absent")
    sync_api = pytest.importorskip("playwright.sync_api")
    out = tmp_path / "sweep"
    main(["batch", str(dataset / "root" / "a"), "--set", "fit_smpl=false", "--sweep",
          "kalman.q=1,100,2000", "--out", str(out)])  # fmt: skip
    shots = {}
    # Playwright's sync API refuses a thread where an asyncio loop is marked running
    # (an earlier test in the session can leave one); a fresh thread has none.
    with ThreadPoolExecutor(1) as pool:
        pool.submit(_browse_reports, sync_api, dataset, out, shots, tmp_path).result()
    page_text = html.unescape((dataset / "report1" / "batch_report.html").read_text())
    assert "source 'smpl' needs" in page_text
    assert all(p.stat().st_size > 20_000 for p in shots.values())
    print("screenshots:", *shots.values())


def _browse_reports(sync_api, dataset, out, shots, tmp_path):
    with sync_api.sync_playwright() as pw:
        browser = launch_chromium(pw)
        for name, d in (("report", dataset / "report1"), ("sweep", out)):
            page = browser.new_page(viewport={"width": 1400, "height": 1000})
            page.goto((d / "batch_report.html").as_uri())
            text = page.inner_text("body")
            assert "Worst moments across the dataset" in text and "MPJPE mm" in text
            assert "python app.py" in text and "--frame" in text
            if name == "sweep":  # one task per setting: the batch's timeline is drawn
                assert "Where the time went" in text and "3 tasks on" in text
            # The viewer commands wrap inside their cells (one click selects a whole
            # command): the page is no wider than the window, every command in view.
            assert page.evaluate("document.documentElement.scrollWidth") <= 1400
            boxes = [c.bounding_box() for c in page.locator("td code").all()]
            assert boxes and max(b["x"] + b["width"] for b in boxes) <= 1400
            assert page.locator("td code").first.evaluate(
                "e => getComputedStyle(e).userSelect") == "all"  # fmt: skip
            images = page.locator("img")
            widths = [images.nth(i).evaluate("e => e.naturalWidth") for i in range(images.count())]
            assert widths and all(w > 100 for w in widths)  # the inline PNGs decoded
            shots[name] = tmp_path / f"batch_{name}.png"
            page.screenshot(path=str(shots[name]), full_page=True)
            page.close()
        browser.close()
