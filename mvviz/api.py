"""The Python API for scripts and notebooks: a scene in, results out, the viewer on them.

    import mvviz

    scene = mvviz.load_scene("sample_data/shelf_synth")
    results = mvviz.run(scene)                      # cached under SCENE/.mvviz/
    scores = mvviz.evaluate(scene, results)         # against the scene's ground truth
    print(scores.stages["rts"]["mpjpe"])            # mm
    viewer = mvviz.show(scene, results)             # inline in Jupyter, else prints the URL
    viewer.stop()

The same functions the command line uses (``mvviz run``, ``mvviz eval``, ``mvviz view``),
so a notebook's figures are the command line's. Everything else (stages one by one, the
body model, exports) is in :mod:`pipeline`; a rerun recording of a run is
:func:`mvviz.export.rerun.log_scene`.
"""

from __future__ import annotations

import atexit
import os
import sys
from collections.abc import Iterable
from pathlib import Path
from typing import TYPE_CHECKING

from pipeline.core.files import SceneFormatError, scene_cache_dir

if TYPE_CHECKING:
    from mvviz.app import ViewerApp
    from pipeline.config import PipelineConfig
    from pipeline.data.scene import Scene
    from pipeline.evaluation.evaluate import Evaluation
    from pipeline.results.store import PipelineResults

PathLike = str | os.PathLike


def load_scene(path: PathLike) -> Scene:
    """The scene folder at ``path`` (cameras, detections, optional ground truth and
    videos; the format: ``sample_data/README.md``), every field checked as it is read.

    Raises :class:`pipeline.core.files.SceneFormatError` naming the file and field of
    anything malformed."""
    from pipeline.data.scene import load_scene as _load_scene

    return _load_scene(path)


def config_of(
    scene: Scene, config: PipelineConfig | PathLike | None = None, overrides: Iterable[str] = ()
) -> PipelineConfig:
    """The run's settings: ``config`` (a :class:`~pipeline.config.PipelineConfig` or a
    JSON file), else the scene's own ``mvviz_config.json`` if it has one, else the
    defaults; then ``overrides`` (``"kalman.q=50"``, as ``--set`` on the command line).
    Checked against the scene's cameras."""
    from pipeline.config import CONFIG_FILE, PipelineConfig, load_config

    if config is None:
        own = Path(scene.root) / CONFIG_FILE
        config = load_config(own) if own.is_file() else PipelineConfig()
    elif not isinstance(config, PipelineConfig):
        config = load_config(Path(config))
    config = config.with_overrides(list(overrides))
    config.check_cameras(scene.rig.names, source="config")
    return config


def run(
    scene: Scene | PathLike,
    config: PipelineConfig | PathLike | None = None,
    *,
    overrides: Iterable[str] = (),
    cache: bool = True,
    progress: bool = True,
) -> PipelineResults:
    """Every stage on ``scene``: association, triangulation, tracking, filtering and the
    SMPL fit (:func:`pipeline.run.pipeline.run_pipeline`).

    With ``cache`` (the default) the results are stored under ``SCENE/.mvviz/`` and
    reused while the scene, the settings, the body model and the prior are unchanged,
    exactly as ``mvviz run`` and the viewer do; ``cache=False`` runs and writes nothing."""
    from pipeline.body.arrays import load_body_model_data
    from pipeline.run.pipeline import run_or_load, run_pipeline

    if not hasattr(scene, "rig"):
        scene = load_scene(scene)
    settings = config_of(scene, config, overrides)
    model = load_body_model_data()
    if not cache:
        return run_pipeline(scene, settings, model, progress=progress)
    results, _cached = run_or_load(scene, settings, model, progress=progress)
    return results


def evaluate(scene: Scene, results: PipelineResults) -> Evaluation:
    """``results`` scored against the scene's ground truth (MPJPE, PCK, PCP, jitter per
    stage in ``.stages``; association and identity counts; reprojection per view), as
    ``mvviz eval``; ``.to_json()`` is the whole as plain numbers, and
    :func:`pipeline.evaluation.evaluate.format_table` prints ``mvviz eval``'s table."""
    from pipeline.evaluation.evaluate import evaluate as _evaluate

    return _evaluate(scene, results)


def show(
    scene: Scene | PathLike,
    results: PipelineResults | None = None,
    *,
    port: int = 8080,
    host: str = "127.0.0.1",
    frame: int | None = None,
    track: int | None = None,
    inline: bool | None = None,
    height: int = 640,
) -> ViewerApp:
    """Serve the viewer on ``scene`` and ``results`` (run with the defaults if None) and
    return it while it runs in the background; ``.url`` is its address, ``.stop()`` ends
    it. Bound to 127.0.0.1 by default (another ``host`` makes it read-only, as on the
    command line); viser moves to the next free port when ``port`` is taken.

    In Jupyter (``inline`` None: detected) the page is displayed in the cell; elsewhere
    the URL is printed. Writes from the page (exports, notes) go under
    ``SCENE/.mvviz/export``."""
    import viser

    from mvviz.app import ViewerApp
    from mvviz.safe_paths import WritePolicy
    from mvviz.scene.images import FrameStore
    from mvviz.state import ViewerState
    from pipeline.body.arrays import load_body_model_data

    if not hasattr(scene, "rig"):
        scene = load_scene(scene)
    if results is None:
        results = run(scene, progress=False)
    for name, value, count in (("frame", frame, results.num_frames),
                               ("track", track, results.num_tracks)):  # fmt: skip
        if value is not None and not 0 <= value < count:
            raise SceneFormatError(name, None, f"expected 0..{count - 1}, got {value}")
    model = load_body_model_data()
    server = viser.ViserServer(host=host, port=port, verbose=False)
    try:
        cache = scene_cache_dir(scene.root)  # SCENE/.mvviz, elsewhere if read-only
        frames = FrameStore(scene, cache_dir=cache / "frames").start()
        state = ViewerState.create(scene, results, model)
        writes = WritePolicy.for_host(host, cache / "export")
        app = ViewerApp(state, server=server, frames=frames, model=model, writes=writes)
    except BaseException:
        server.stop()
        raise
    app.wait_idle(30)
    # A script's interpreter must not exit while the frames decode on their thread.
    atexit.register(_stop_viewer, app, frames)
    if frame is not None or track is not None:
        app.jump_to(frame=frame, track=track)
    if inline is None:
        inline = in_notebook()
    if inline:
        from IPython.display import IFrame, display

        display(IFrame(app.url, width="100%", height=height))
    else:
        print(f"mvviz viewer: {app.url}", file=sys.stderr)
    return app


def _stop_viewer(app: ViewerApp, frames) -> None:
    if not app.stopped.is_set():
        app.stop()
    frames.stop()


def in_notebook() -> bool:
    """Running in a Jupyter kernel (where a page can be displayed in the cell)."""
    shell = sys.modules.get("IPython")
    if shell is None:
        return False
    ipython = shell.get_ipython()
    return ipython is not None and "IPKernelApp" in getattr(ipython, "config", {})


def log_scene(*args, **kwargs):
    """A run into the current rerun recording: :func:`mvviz.export.rerun.log_scene`
    (in Jupyter, ``rr.notebook_show()`` then shows it in the cell)."""
    from mvviz.export.rerun import log_scene as _log_scene

    return _log_scene(*args, **kwargs)
