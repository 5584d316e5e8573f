"""``mvviz view``: the interactive 3D debugger in the browser (see mvviz/app.py).

The viser server starts first, with a "loading" line, so a browser gets a page within
~2 s of the command (``bench/bench_startup.py``); the viewer (torch, scipy, trimesh,
OpenCV through the pipeline) is imported and built on that server after it.

The viewer has no authentication. Bound to anything but loopback (``--host``) it warns
on stderr and starts read-only unless ``--allow-writes`` (:mod:`mvviz.safe_paths`);
what a page asks it to write goes into ``--export-dir`` or the scene folder only.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

import viser

from mvviz.safe_paths import WritePolicy, is_loopback
from pipeline.core.files import SceneFormatError, scene_cache_dir
from pipeline.core.units import REPO_ROOT, SAMPLE_DATA
from pipeline.data.calibration_views import CALIBRATION_VIEWS

if TYPE_CHECKING:
    from mvviz.app import FirstTab, ViewerApp

DEFAULT_SCENE = SAMPLE_DATA / "shelf_synth"


def add_view_options(p: argparse.ArgumentParser, *, scene_optional: bool = False) -> None:
    if scene_optional:
        p.add_argument(
            "scene", type=Path, nargs="?", default=DEFAULT_SCENE,
            help=f"scene directory (default: {DEFAULT_SCENE.relative_to(REPO_ROOT)})",
        )  # fmt: skip
        p.add_argument(
            "--batch", type=Path, default=None, metavar="DIR",
            help="the scenes of a mvviz batch report (DIR/batch_report.json): a Dataset tab "
            "lists them, worst first; a click opens one at its worst moment",
        )  # fmt: skip
    else:
        p.add_argument(
            "scene", type=Path,
            help="scene directory (see sample_data/README.md), or a mvviz calibrate output "
            "folder (the calibration view)",
        )  # fmt: skip
    p.add_argument("--port", type=int, default=8080, help="HTTP/websocket port (default 8080)")
    p.add_argument(
        "--host", default="127.0.0.1",
        help="address to bind (default 127.0.0.1; 0.0.0.0 = all). The viewer has no "
        "authentication: on any other than 127.0.0.1 / localhost / ::1 it is read-only "
        "unless --allow-writes",
    )  # fmt: skip
    p.add_argument(
        "--allow-writes", action="store_true",
        help="let pages export and save even when --host is not loopback",
    )  # fmt: skip
    p.add_argument(
        "--export-dir", type=Path, default=None, metavar="DIR",
        help="folder of the files the Export tab and the .rrd export write (a name typed in "
        "the page is a file inside it; default SCENE/.mvviz/export)",
    )  # fmt: skip
    p.add_argument("--smpl-model", default=None, help="body model file (.npz/.pkl)")
    p.add_argument("--config", type=Path, default=None, help="pipeline config JSON")
    p.add_argument(
        "--set", action="append", default=[], metavar="SECTION.FIELD=VALUE",
        help="override a pipeline config value (repeatable)",
    )  # fmt: skip
    p.add_argument(
        "--out",
        type=Path,
        default=None,
        help="results file (default SCENE/.mvviz/results.npz); a path not ending in .npz is "
        "a directory of memory-mapped arrays the viewer reads frame by frame (long scenes)",
    )
    p.add_argument("--force", action="store_true", help="re-run the pipeline, ignore the cache")
    p.add_argument("--frame", type=int, default=None, help="open at this frame")
    p.add_argument("--track", type=int, default=None, help="open with this track selected")
    p.add_argument(
        "--rerun", action="store_true",
        help="also serve rerun's web viewer and log into it live (mvviz/export/rerun_live.py)",
    )  # fmt: skip
    p.add_argument(
        "--rerun-port", type=int, default=9090,
        help="port of rerun's web viewer, its gRPC server on the next one (default 9090)",
    )  # fmt: skip
    p.add_argument(
        "--rerun-save", type=Path, default=None, metavar="RRD",
        help="with --rerun: also write the live stream to this .rrd file",
    )  # fmt: skip


def is_calibration_folder(folder: Path) -> bool:
    """A ``mvviz calibrate`` output that is not (yet) a scene: the calibration view."""
    folder = Path(folder)
    return (folder / CALIBRATION_VIEWS).is_file() and not (folder / "scene.json").is_file()


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "view",
        help="open the interactive 3D debugger for a scene in the browser",
        description=(
            "Loads SCENE, runs the pipeline (or reuses cached results) and serves a viser "
            "viewer: timeline, cameras with their video, 2D detections, rays, raw / filtered "
            "/ ground-truth skeletons, trails, ground-truth and fitted meshes, and the pipeline, "
            "filter A/B and failure panels. On a mvviz calibrate output folder (not yet a "
            "scene): the calibration (cameras, board poses, reprojection error per camera "
            "over the frames, each view's detected and reprojected corners). Blocks until "
            "Ctrl-C."
        ),
    )
    add_view_options(p)
    p.set_defaults(func=run)


def start(
    args: argparse.Namespace, *, progress: bool = True, first_tab: FirstTab | None = None
) -> ViewerApp:
    """Start the server, load the scene, run or load results, build the viewer on the
    server (``first_tab``: see :class:`mvviz.app.ViewerApp`); returns the running app
    (the server stops if any of it fails)."""
    t0 = time.perf_counter()
    allow_writes = getattr(args, "allow_writes", False)
    if not is_loopback(args.host):
        writes = "writes allowed (--allow-writes)" if allow_writes else "read-only"
        print(
            f"warning: serving on {args.host or 'every address'}: the viewer has no "
            f"authentication, anyone who reaches this port can use it ({writes})",
            file=sys.stderr, flush=True,
        )  # fmt: skip
    server = viser.ViserServer(host=args.host, port=args.port, verbose=False)
    loading = server.gui.add_markdown(f"**Loading** `{Path(args.scene).name}` …")
    print(f"serving http://{args.host}:{server.get_port()} (loading the scene)", flush=True)
    try:
        if is_calibration_folder(args.scene):
            from mvviz.calibration_view import CalibrationApp

            loading.remove()
            app = CalibrationApp(args.scene, server)
            print(f"calibration {Path(args.scene).name}: what mvviz calibrate saw")
        else:
            app = _build_viewer(args, server, loading, progress=progress, first_tab=first_tab)
    except BaseException:
        server.stop()
        raise
    print(f"ready in {time.perf_counter() - t0:.1f} s: {app.url}")
    if app.frames is not None and app.frames.sources and not app.frames.ready:
        print("(decoding videos in the background; frames appear as they are ready)")
    return app


def _build_viewer(
    args: argparse.Namespace,
    server: viser.ViserServer,
    loading: viser.GuiMarkdownHandle,
    *,
    progress: bool,
    first_tab: FirstTab | None = None,
) -> ViewerApp:
    # The heavy imports (torch, scipy, trimesh, OpenCV) come after the server is up.
    from mvviz.app import ViewerApp
    from mvviz.cli.run import prepare  # shares --config/--set
    from mvviz.scene.images import FrameStore
    from mvviz.state import ViewerState
    from pipeline.run.pipeline import run_or_load

    scene, config, model = prepare(args, read_prior=False)
    print(f"scene {scene.name}: {len(scene.rig)} cameras, {scene.num_frames} frames")
    results, cached = run_or_load(
        scene, config, model, out=args.out, progress=progress, force=args.force
    )
    print(f"{'cached' if cached else 'computed'} results: {results.num_tracks} tracks")
    cache = scene_cache_dir(scene.root)  # SCENE/.mvviz, elsewhere if read-only
    frames = FrameStore(scene, cache_dir=cache / "frames").start()
    state = ViewerState.create(scene, results, model)
    loading.remove()
    writes = WritePolicy.for_host(
        args.host, getattr(args, "export_dir", None) or cache / "export",
        allow_writes=getattr(args, "allow_writes", False),
    )  # fmt: skip
    app = ViewerApp(
        state, server=server, frames=frames, model=model, first_tab=first_tab, writes=writes
    )
    app.wait_idle(30)
    _open_at(app, args, results.num_frames, results.num_tracks)
    if app.server.get_port() != args.port:  # viser moves to the next free port
        print(f"port {args.port} is taken: serving on port {app.server.get_port()} instead")
    app.rerun_live = None
    if getattr(args, "rerun", False):
        # rerun (~0.3 s to import) loads only with --rerun
        from mvviz.export.rerun_live import LiveRerun, RerunWebServer

        rerun_server = RerunWebServer(host=args.host, web_port=args.rerun_port)
        app.rerun_live = LiveRerun(app, server=rerun_server, save=args.rerun_save)
        print(f"rerun web viewer: {rerun_server.url}")
    return app


def _open_at(app: ViewerApp, args: argparse.Namespace, num_frames: int, num_tracks: int) -> None:
    """``--frame`` / ``--track`` (what ``mvviz compare`` prints to open a difference)."""
    frame, track = getattr(args, "frame", None), getattr(args, "track", None)
    if frame is not None and not 0 <= frame < num_frames:
        raise SceneFormatError("--frame", None, f"expected 0..{num_frames - 1}, got {frame}")
    if track is not None and not 0 <= track < num_tracks:
        raise SceneFormatError("--track", None, f"expected 0..{num_tracks - 1}, got {track}")
    if frame is not None or track is not None:
        app.jump_to(frame=frame, track=track)


def serve_until_interrupted(stop_serving) -> int:
    """Keep the process alive for the server threads until Ctrl-C, then ``stop_serving()``."""
    try:
        while True:
            time.sleep(3600)
    except KeyboardInterrupt:
        print("\nstopping")
    finally:
        stop_serving()
    return 0


def run(args: argparse.Namespace) -> int:
    app = start(args)
    return serve_until_interrupted(lambda: stop(app))


def stop(app: ViewerApp) -> None:
    """Stop the viewer and, with --rerun, the live logging and rerun's server."""
    live = getattr(app, "rerun_live", None)
    app.stop()
    if live is not None:
        live.close()
        if live.server is not None:
            live.server.stop()
