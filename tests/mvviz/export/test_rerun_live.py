"""mvviz.export.rerun_live and mvviz.export.rerun: the viewer with --rerun logs what it shows into
rerun's own web viewer, live; a script logs a scene into its own recording.

The live stream is read back from the same recording saved alongside (``--rerun-save``,
a second sink of the one stream) with rerun's own reader; rerun's web viewer, served from
the rerun-sdk package on 127.0.0.1, is screenshotted in headless chromium."""

from __future__ import annotations

import argparse
import os
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest
import rerun as rr

from mvviz.cli import view as cli_view
from mvviz.export.rerun import SceneLogger, display_mesh, log_scene
from mvviz.export.rrd import export_rrd, read_rrd_summary
from tests.mvviz.conftest import free_port, wait_until
from tests.mvviz.export.test_rrd import rerun_cli, rows_of

SHOTS = Path(os.environ.get("MVVIZ_SHOTS", "/tmp/mvviz_shots"))
VISITED = (3, 7, 12, 5)


def start_app(scene, tmp_path):
    p = argparse.ArgumentParser()
    cli_view.add_view_options(p, scene_optional=True)
    web = free_port()
    args = p.parse_args([
        str(scene.root), "--port", str(free_port()), "--rerun", "--rerun-port", str(web),
        "--rerun-save", str(tmp_path / "live.rrd"),
    ])  # fmt: skip
    return cli_view.start(args, progress=False)


@pytest.fixture(scope="module")
def live_run(viewer_scene, tmp_path_factory):
    """The app with --rerun after frame changes, a re-run and a filter B change; yields
    (app, live, saved path) while it still runs."""
    scene, results, _ = viewer_scene
    tmp = tmp_path_factory.mktemp("live")
    app = start_app(scene, tmp)
    live = app.rerun_live
    try:
        assert live is not None and live.wait_idle(60)
        for f in VISITED:
            app.set_frame(f)
            assert app.wait_idle(30) and live.wait_idle(30)
        # a re-run of the Pipeline panel: camera 0 off
        cam = scene.rig.names[0]
        app.pipeline_panel.gui.cameras[cam].value = False
        assert app.pipeline_panel.wait_idle(120) and live.wait_idle(60)
        # a filter B change
        fp = app.filter_panel
        fp.gui.q.value = float(fp.gui.q.value) * 4
        assert fp.wait_idle(60)
        # the logger looks at B every 0.25 s: polled, not slept (a busy machine)
        wait_until(lambda: any(b.startswith("_b") for b in live.branches), 60, "filter B logged")
        assert live.wait_idle(30)
        app.set_frame(9)
        assert app.wait_idle(30) and live.wait_idle(30)
        yield app, live, tmp / "live.rrd"
    finally:
        cli_view.stop(app)


@pytest.mark.slow
def test_live_stream_holds_the_visited_frames_and_the_branches(viewer_scene, live_run):
    scene, results, _ = viewer_scene
    app, live, path = live_run
    assert not live.errors, live.errors
    assert live.branches[0] == "base" and "_run1" in live.branches and "_b1" in live.branches
    live.rec.flush()
    time.sleep(0.5)
    summary = read_rrd_summary(path)  # the file is still being written: read what is there
    assert set(VISITED) | {0, 9} <= set(summary.frames.tolist())
    comp = summary.components
    for cam in scene.rig.names:
        base = f"/world/cameras/{cam}"
        assert base in summary.static_entities
        assert {"Pinhole:image_from_camera", "Transform3D:translation"} <= comp[base]
        assert "EncodedImage:blob" in comp[f"{base}/image"]
        assert "Points2D:keypoint_ids" in comp[f"{base}/detections"]
    assert {"AnnotationContext:context", "ViewCoordinates:xyz"} <= comp["/world"]
    for stage in ("raw", "filtered"):
        assert "Points3D:positions" in comp[f"/world/skeletons/{stage}/0"]
    assert "Points3D:positions" in comp["/world/skeletons/filter_b/0"]
    assert "Mesh3D:vertex_positions" in comp["/world/meshes/gt/0"]
    # the fitted bodies of every visited frame, decimated as the GT meshes
    for stage in ("smpl", "smpl_vae"):
        fit = getattr(results, stage)
        if fit is None:
            continue
        keep, _ = display_mesh(fit.model, 25.0)
        ent = f"/world/bodies/{stage}/0"
        assert "Mesh3D:triangle_indices" in comp[ent] and ent in summary.static_entities
        meshes = dict(rows_of(path, ent, "Mesh3D:vertex_positions"))
        for f in VISITED:
            if fit.present[0, f]:
                assert len(meshes[f]) == len(keep), (stage, f)
    # A, the re-run and filter B side by side: one series each, every frame of the scene
    for stage in ("filtered", "raw_run1", "filtered_run1", "filtered_b1"):
        ent = f"/plots/joints/0/pelvis/{stage}/x"
        assert "Scalars:scalars" in comp[ent], ent
    assert "Scalars:scalars" in comp["/plots/metrics/mahalanobis_b1/0"]
    assert np.isfinite(live.log_ms) and live.logged >= len(VISITED) + 2


@pytest.mark.slow
def test_rerun_server_binds_loopback_and_serves_its_web_viewer(live_run, browser):
    from PIL import Image

    app, live, _ = live_run
    server = live.server
    assert server.process.args[server.process.args.index("--bind") + 1] == "127.0.0.1"
    page = browser.new_page(viewport={"width": 1400, "height": 860})
    try:
        page.goto(server.url)
        page.wait_for_selector("canvas", timeout=60_000)
        SHOTS.mkdir(parents=True, exist_ok=True)
        shot = SHOTS / "rerun_live_web_viewer.png"
        # wasm start, connect, first frames: at least 12 s, then until drawn (a deadline)
        time.sleep(12)
        deadline = time.monotonic() + 90
        while True:
            page.screenshot(path=str(shot))
            img = np.asarray(Image.open(shot).convert("RGB"), float)
            if img.std() > 10 or time.monotonic() > deadline:
                break
            time.sleep(2)
    finally:
        page.close()
    assert img.std() > 10, "the web viewer page is blank"


@pytest.mark.slow
def test_log_scene_into_a_users_recording_matches_the_export(viewer_scene, tmp_path):
    scene, results, model = viewer_scene
    rec = rr.RecordingStream("my_notebook")
    rec.save(tmp_path / "mine.rrd")
    logger = log_scene(scene, results, recording=rec, frames=range(2, 5), body_model=model)
    assert isinstance(logger, SceneLogger)
    rec.flush()
    rec.disconnect()
    mine = read_rrd_summary(tmp_path / "mine.rrd")
    export_rrd(scene, results, model, tmp_path / "x.rrd", frames=range(2, 5), images=False,
               progress=False)  # fmt: skip
    theirs = read_rrd_summary(tmp_path / "x.rrd")
    np.testing.assert_array_equal(mine.frames, [2, 3, 4])
    assert mine.entities == theirs.entities
    props = lambda rows: {k: v for k, v in rows.items() if not k.startswith("/__")}  # noqa: E731
    assert props(mine.rows) == props(theirs.rows)  # the export also names the recording
    cli = rerun_cli()
    if cli:
        proc = subprocess.run([cli, "rrd", "verify", str(tmp_path / "mine.rrd")],
                              capture_output=True, text=True, timeout=120)  # fmt: skip
        assert proc.returncode == 0, proc.stderr


def test_log_scene_into_the_global_recording(viewer_scene, tmp_path):
    scene, results, _ = viewer_scene
    rr.init("mvviz_test_global")
    rr.save(tmp_path / "global.rrd")
    try:
        log_scene(scene, results, frames=[1], images=True)
    finally:
        rr.disconnect()
    s = read_rrd_summary(tmp_path / "global.rrd")
    np.testing.assert_array_equal(s.frames, [1])
    assert f"/world/cameras/{scene.rig.names[0]}/image" in s.rows


@pytest.mark.slow
def test_rerun_server_stop_ends_rerun_itself():
    """``python -m rerun`` runs rerun's binary as its child: stop() ends both, and the
    ports are free again (ending the wrapper alone had left the binary serving)."""
    from mvviz.export.rerun_live import RerunWebServer, _session_alive, port_is_free

    server = RerunWebServer(web_port=free_port())
    sid = server.process.pid
    binaries = [
        p for p in Path("/proc").glob("[0-9]*/stat")
        if int(p.read_text().rsplit(")", 1)[1].split()[3]) == sid and int(p.parent.name) != sid
    ]  # fmt: skip
    assert binaries, "rerun's binary is not in the server's session"
    server.stop()
    assert server.process.poll() is not None
    assert not _session_alive(sid), "a process of the rerun server is still running"
    # the kernel frees a listening port a moment after its process ends: on a loaded
    # machine that moment can follow stop()'s return, so the ports are polled
    wait_until(
        lambda: port_is_free("127.0.0.1", server.web_port)
        and port_is_free("127.0.0.1", server.grpc_port),
        10.0, "the rerun server's ports to be free",
    )  # fmt: skip
