"""Log a scene and its pipeline results into a rerun recording: yours, a file, or live.

The one place of the project's rerun entity layout (this docstring; the package's
modules: ``layout`` constants, class ids and blueprint, ``meshes`` decimation and
skinning, ``frames`` per-frame entities, ``series`` time series, ``logger``
:class:`SceneLogger`), used by ``mvviz export-rrd``
(:func:`mvviz.export.rrd.export_rrd`), by the viewer's live mode (``python app.py
--rerun``, :mod:`mvviz.export.rerun_live`) and by scripts and notebooks::

    import rerun as rr
    from mvviz.export.rerun import log_scene

    rr.init("my_app", spawn=True)              # or rr.save(...), rr.serve_grpc(), ...
    log_scene(scene, results, frames=range(0, 100))   # into the global recording
    log_scene(scene, results, recording=my_rec, body_model=model, images=False)

Every rerun call of the project lives in this package and the two modules above: rerun's API
changes between versions (this is written against rerun-sdk 0.41).

Units: the recording's world is in METRES, z up (the pipeline's millimetres are divided
by 1000 on the way in); plots keep millimetres. Image coordinates follow rerun's
convention, origin at the top-left CORNER of the top-left pixel: an OpenCV pixel
``(u, v)`` (origin at that pixel's centre) is drawn at ``s * (u + 0.5, v + 0.5)`` for an
image downscaled by ``s``, and the pinhole's intrinsics are shifted and scaled to match.

Entity layout (static context is logged once; each frame sets the time and logs under
paths that mirror the data)::

    world                                      ViewCoordinates RIGHT_HAND_Z_UP and the
                                               AnnotationContext (static, see ClassLayout)
    world/cameras/<camera>                     Transform3D (camera pose) + Pinhole, static
    world/cameras/<camera>/image               EncodedImage (JPEG), per frame
    world/cameras/<camera>/detections          Points2D: the 2D joints that fed the stages
    world/skeletons/{raw,filtered}/<track>     Points3D with keypoint ids
    world/skeletons/filter_b/<track>           Points3D: filter B of the viewer (live only)
    world/skeletons/gt/<person>                Points3D, SMPL-24
    world/rays/<track>, world/rays/untracked   LineStrips3D: camera centre -> used 2D joint's
                                               ray, up to the triangulated joint's depth
    world/meshes/gt/<person>                   Mesh3D: faces static, vertex positions per frame
    world/bodies/{smpl,smpl_vae}/<track>       Mesh3D: the fitted SMPL body (step I, and
                                               corrected by the VAE prior), decimated as
                                               the GT meshes; faces static, vertices per
                                               frame; track colour (step I darker)
    world/meshes/<name>                        any extra MeshSequence (e.g. a fit of yours)
    plots/joints/<track>/<joint>/<stage>/{x,y,z}   Scalars, mm; stage raw / filtered
    plots/metrics/mahalanobis<branch>/<track>  mean Mahalanobis distance over joints
    plots/metrics/{people,tracks,gt_people}<branch>   counts per frame

Branches: the first results logged have stages ``raw`` / ``filtered`` and no branch
suffix. In the live viewer every re-run of the Pipeline panel adds a branch ``_run<n>``
(stages ``raw_run<n>``, ``filtered_run<n>``, ``mahalanobis_run<n>``, ...) and every
filter B change a branch ``_b<n>`` (``filtered_b<n>``, ``mahalanobis_b<n>``), so before
and after, A and B are lines of the same time-series views.

Timelines: ``frame`` (sequence = scene frame index) and ``time`` (seconds, frame / fps).
An entity that is absent in a frame after being present is cleared in that frame.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping

import rerun as rr  # the SDK: absolute imports, this package is mvviz.export.rerun

from mvviz.export.rerun.frames import encode_jpeg, resize
from mvviz.export.rerun.layout import (
    APP_ID,
    AXIS_COLORS,
    BODY_STAGES,
    DEFAULT_PLOT_JOINTS,
    GREY_UNASSIGNED,
    GREY_UNTRACKED,
    GT_COLOR,
    JOINT_ALIASES,
    MM_TO_M,
    ClassLayout,
    MeshSequence,
    annotation_context,
    body_color,
    check_inputs,
    make_blueprint,
    ray_segments,
    resolve_plot_joint,
    scaled_intrinsics,
    select_frames,
    track_color,
)
from mvviz.export.rerun.logger import MESH_CHUNK_FRAMES, ImageLike, SceneLogger
from mvviz.export.rerun.meshes import decimate_mesh, display_mesh, skin_subset
from mvviz.export.rerun.sources import scene_frame_sources
from pipeline.body.model import BodyModel
from pipeline.data.scene import Scene
from pipeline.results.store import PipelineResults
from pipeline.stages.retime import picture_frame

__all__ = [
    "APP_ID", "AXIS_COLORS", "BODY_STAGES", "DEFAULT_PLOT_JOINTS", "GREY_UNASSIGNED",
    "GREY_UNTRACKED", "GT_COLOR", "JOINT_ALIASES", "MESH_CHUNK_FRAMES", "MM_TO_M", "ClassLayout",
    "ImageLike",
    "MeshSequence", "SceneLogger", "annotation_context", "body_color", "check_inputs",
    "decimate_mesh", "display_mesh", "encode_jpeg", "log_scene", "make_blueprint",
    "ray_segments", "resize", "resolve_plot_joint", "scaled_intrinsics", "select_frames",
    "skin_subset", "track_color",
]  # fmt: skip


def log_scene(
    scene: Scene,
    results: PipelineResults,
    recording: rr.RecordingStream | None = None,
    frames: slice | range | Iterable[int] | None = None,
    *,
    images: Mapping[str, Callable[[int], ImageLike | None]] | bool = False,
    body_model: BodyModel | None = None,
    blueprint: bool = True,
    progress: Callable[[Iterable[int]], Iterable[int]] | None = None,
    **options,
) -> SceneLogger:
    """Log ``scene`` and its ``results`` into ``recording`` (default: the global one of
    ``rr.init``) with the layout of this module: static context, blueprint, the
    ``frames`` (default all; a slice or range may run past the end), GT meshes, fitted
    bodies and time series as columns.

    Args:
        images: camera name -> ``read(frame)`` returning JPEG bytes or a BGR image (e.g.
            :class:`mvviz.export.rerun.sources.FrameSource`), or True to read the scene's videos
            and image folders, or False (default) for no images.
        body_model: skins the GT meshes (``pipeline.body.model.load_body_model()``).
        progress: wraps the frame loop (e.g. ``tqdm``).
        options: of :class:`SceneLogger` (``image_width``, ``mesh_cell_mm``, ...).
    Returns:
        The :class:`SceneLogger`, to log more frames or branches into the same recording.
    """
    readers: Mapping[str, Callable[[int], ImageLike | None]] = {}
    opened = []
    if images is True:
        opened = list(scene_frame_sources(scene).values())
        readers = {src.camera: src.read for src in opened}
    elif images:
        readers = images
    logger = SceneLogger(
        scene, results, recording, body_model=body_model, images=bool(readers), **options
    )
    frame_ids = select_frames(frames, scene.num_frames)
    try:
        logger.log_static(blueprint=blueprint)
        loop = progress(frame_ids) if progress is not None else frame_ids
        offsets = results.config.sync.by_camera()  # a re-timed camera's picture follows
        for f in loop:
            f = int(f)
            pictures = {n: r(picture_frame(offsets, n, f)) for n, r in readers.items()}
            logger.log_frame(f, images=pictures, gt_meshes=False, bodies=False)
        logger.send_gt_meshes(frame_ids)
        logger.send_bodies(frame_ids)
        logger.send_plots(frame_ids)
    finally:
        for src in opened:
            src.close()
    return logger
