"""Importers: other tools' calibrations and detections -> a native scene directory.

Calibration formats (:data:`CALIBRATION_FORMATS`): ``voxelpose``, ``easymocap``,
``pose2sim``, ``qualisys``, ``caliscope``. Detection formats (:data:`DETECTION_FORMATS`):
``openpose``, ``easymocap``.
:func:`convert_scene` reads one of each and writes a scene with
:func:`pipeline.data.scene.write_scene` (atomic: a failure leaves nothing behind).

Units: the scene is in world millimetres; formats in metres are scaled on the way in.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from pipeline.core.files import SceneFormatError
from pipeline.data.cameras import CameraRig
from pipeline.data.joint_sets import OPENPOSE_COCO18, JointSet
from pipeline.data.references import fit_frames
from pipeline.data.scene import Detections, write_scene
from pipeline.importers.calibration import (
    read_caliscope_calibration,
    read_easymocap_calibration,
    read_pose2sim_calibration,
    read_voxelpose_calibration,
    write_caliscope_calibration,
    write_easymocap_calibration,
    write_pose2sim_calibration,
    write_voxelpose_calibration,
)
from pipeline.importers.detections import (
    ImportedDetections,
    read_easymocap_annots,
    read_mmpose_predictions,
    read_openpose_folders,
    resolve_joint_set,
)
from pipeline.importers.layouts import SOURCE_LAYOUTS, LayoutDecision, identify_layout
from pipeline.importers.qualisys import read_qualisys_calibration, write_qualisys_calibration
from pipeline.importers.trc import reference_from_trc

__all__ = [
    "CALIBRATION_FORMATS",
    "DETECTION_FORMATS",
    "OPENPOSE_COCO18",
    "SOURCE_LAYOUTS",
    "CalibrationFormat",
    "DetectionFormat",
    "ImportedDetections",
    "LayoutDecision",
    "identify_layout",
    "read_mmpose_predictions",
    "read_caliscope_calibration",
    "write_caliscope_calibration",
    "convert_scene",
    "read_calibration",
    "read_detections",
    "read_easymocap_annots",
    "read_easymocap_calibration",
    "read_openpose_folders",
    "read_pose2sim_calibration",
    "read_qualisys_calibration",
    "read_voxelpose_calibration",
    "write_easymocap_calibration",
    "write_pose2sim_calibration",
    "write_qualisys_calibration",
    "write_voxelpose_calibration",
]


@dataclass(frozen=True)
class CalibrationFormat:
    """A calibration format: how to read it from the paths a user gives, and write it.

    Attributes:
        name: registry key, e.g. ``"pose2sim"``.
        files: what the paths are, for help texts.
        read: ``(paths, image_size) -> CameraRig``; image_size is (W, H) or None.
        write: ``(rig, path) -> ...``; ``path`` is a file, or a directory for EasyMocap.
    """

    name: str
    files: str
    read: Callable[[list[Path], tuple[int, int] | None], CameraRig]
    write: Callable[[CameraRig, Path], object]


@dataclass(frozen=True)
class DetectionFormat:
    """A detection format and its reader."""

    name: str
    files: str
    read: Callable[..., ImportedDetections]
    """``read(root, camera_names, joint_set, *, layout=None)``."""


def _one_file(paths: list[Path], fmt: str, suffix: str | None = None) -> Path:
    if len(paths) != 1:
        raise SceneFormatError(
            ", ".join(map(str, paths)) or "<no files>", None, f"{fmt} expects one file"
        )
    path = paths[0]
    if suffix and path.is_dir():
        found = sorted(path.glob(f"*{suffix}"))
        if len(found) != 1:
            raise SceneFormatError(
                path, None, f"expected one {suffix} file in the directory, found {len(found)}"
            )
        path = found[0]
    return path


def _read_voxelpose(paths: list[Path], image_size) -> CameraRig:
    return read_voxelpose_calibration(_one_file(paths, "voxelpose"), image_size=image_size)


def _read_pose2sim(paths: list[Path], image_size) -> CameraRig:
    # The size is in the file; image_size is not needed.
    return read_pose2sim_calibration(_one_file(paths, "pose2sim", ".toml"))


def _read_qualisys(paths: list[Path], image_size) -> CameraRig:
    path = _one_file(paths, "qualisys", ".qca.txt")
    return read_qualisys_calibration(path, image_size=image_size)


def _read_caliscope(paths: list[Path], image_size) -> CameraRig:
    return read_caliscope_calibration(_one_file(paths, "caliscope", ".toml"))


def _read_easymocap(paths: list[Path], image_size) -> CameraRig:
    if len(paths) == 1 and paths[0].is_dir():
        intri, extri = paths[0] / "intri.yml", paths[0] / "extri.yml"
    elif len(paths) == 2:
        intri, extri = paths
        if intri.name.startswith("extri") and extri.name.startswith("intri"):
            intri, extri = extri, intri
    else:
        raise SceneFormatError(
            ", ".join(map(str, paths)) or "<no files>",
            None,
            "easymocap expects intri.yml and extri.yml, or the directory holding them",
        )
    return read_easymocap_calibration(intri, extri, image_size=image_size)


CALIBRATION_FORMATS: dict[str, CalibrationFormat] = {
    f.name: f
    for f in (
        CalibrationFormat(
            "voxelpose",
            "one json {camera: {R, T, fx, fy, cx, cy, k, p}} (T = camera centre, mm)",
            _read_voxelpose,
            write_voxelpose_calibration,
        ),
        CalibrationFormat(
            "easymocap",
            "intri.yml and extri.yml (or their directory); T in metres",
            _read_easymocap,
            write_easymocap_calibration,
        ),
        CalibrationFormat(
            "pose2sim",
            "one Calib.toml (Pose2Sim / aniposelib); translation in metres",
            _read_pose2sim,
            write_pose2sim_calibration,
        ),
        CalibrationFormat(
            "qualisys",
            "one Qualisys QTM .qca.txt (XML; mm, intrinsics in 1/64 px); --image-size W H "
            "if the videos are scaled",
            _read_qualisys,
            write_qualisys_calibration,
        ),
        CalibrationFormat(
            "caliscope",
            "one Caliscope camera_array.toml (cameras cam_<port>); translation in metres",
            _read_caliscope,
            write_caliscope_calibration,
        ),
    )
}

DETECTION_FORMATS: dict[str, DetectionFormat] = {
    f.name: f
    for f in (
        DetectionFormat(
            "openpose",
            "DIR/<camera>/*_<frame>_keypoints.json (BODY_25, BODY_25B, COCO-18, ...)",
            read_openpose_folders,
        ),
        DetectionFormat(
            "mmpose",
            "DIR/<camera>/<frame>.json instance lists, or DIR/<camera>.json instance_info "
            "(MMPose, RTMPose, rtmlib: COCO-17, Halpe-26, COCO-WholeBody-133, ...)",
            read_mmpose_predictions,
        ),
        DetectionFormat(
            "easymocap",
            "DIR/<camera>/<frame:06d>.json (EasyMocap annots)",
            read_easymocap_annots,
        ),
    )
}


def _format(registry: dict, name: str, source, field: str):
    try:
        return registry[name]
    except KeyError:
        raise SceneFormatError(
            source, field, f"unknown format {name!r}; expected one of {sorted(registry)}"
        ) from None


def read_calibration(
    calib_format: str,
    calib_paths: Sequence[str | os.PathLike],
    *,
    image_size: tuple[int, int] | None = None,
) -> CameraRig:
    """Read a calibration in a registered format (see :data:`CALIBRATION_FORMATS`)."""
    paths = [Path(p) for p in calib_paths]
    fmt = _format(CALIBRATION_FORMATS, calib_format, ", ".join(map(str, paths)), "format")
    return fmt.read(paths, image_size)


def read_detections(
    detections_format: str,
    path: str | os.PathLike,
    camera_names: Sequence[str],
    joint_set: str | JointSet | None = None,
    *,
    layout: str | None = None,
) -> ImportedDetections:
    """Read detections in a registered format (see :data:`DETECTION_FORMATS`); None keeps
    the files' layout, which is identified from the data unless ``layout`` names it."""
    fmt = _format(DETECTION_FORMATS, detections_format, path, "format")
    return fmt.read(Path(path), camera_names, joint_set, layout=layout)


def _check_convert_args(
    meta_path: Path,
    fps: float,
    detections_format: str | None,
    detections_path: str | os.PathLike | None,
) -> None:
    """The arguments of :func:`convert_scene` that can be checked before reading anything."""
    if isinstance(fps, bool) or not isinstance(fps, (int, float)) or not math.isfinite(fps):
        raise SceneFormatError(meta_path, "fps", f"expected a positive number, got {fps!r}")
    if fps <= 0:
        raise SceneFormatError(meta_path, "fps", f"expected a positive number, got {fps!r}")
    if (detections_format is None) != (detections_path is None):
        raise SceneFormatError(
            detections_path or meta_path,
            "detections",
            "give both the detections format and the detections path, or neither",
        )


def _detections_source(
    detections_format: str, detections_path: str | os.PathLike, imported: ImportedDetections
) -> dict:
    """What ``scene.json`` records of imported detections (``imported_from.detections``)."""
    decision = imported.layout_decision
    return {
        "format": detections_format,
        "path": str(detections_path),
        "layout": imported.source_layout,
        "layout_decision": None if decision is None else decision.to_json(),
        "missing_views": list(imported.missing_views),
    }


def convert_scene(
    *,
    calib_format: str,
    calib_paths: Sequence[str | os.PathLike],
    out_dir: str | os.PathLike,
    detections_format: str | None = None,
    detections_path: str | os.PathLike | None = None,
    joint_set: str | None = None,
    layout: str | None = None,
    fps: float = 25.0,
    name: str | None = None,
    image_size: tuple[int, int] | None = None,
    overwrite: bool = False,
    references: Mapping[str, str | os.PathLike] | None = None,
) -> Path:
    """Read a calibration (and optionally detections) and write a native scene at ``out_dir``.

    Everything is read and checked before anything is written, and the scene is written
    atomically, so on any error ``out_dir`` is left as it was (absent if it was absent).
    Without detections the scene gets zero detection rows and ``num_frames = 0`` (or the
    longest reference's length). ``references`` (name -> Pose2Sim TRC file) are stored as
    the scene's reference tracks (:mod:`pipeline.data.references`), in its joint set.
    ``joint_set`` None keeps the detections' layout (identified from the data unless
    ``layout`` names it; COCO-17 without detections); the decision and its evidence are
    recorded in ``scene.json`` under ``imported_from.detections.layout_decision``.

    Returns:
        ``out_dir`` as a Path.
    """
    out_dir = Path(out_dir)
    meta_path = out_dir / "scene.json"
    if out_dir.exists() and not overwrite and (not out_dir.is_dir() or any(out_dir.iterdir())):
        raise FileExistsError(f"{out_dir} exists and is not empty (pass overwrite to replace it)")
    js = None if joint_set is None else resolve_joint_set(joint_set, meta_path)
    _check_convert_args(meta_path, fps, detections_format, detections_path)
    rig = read_calibration(calib_format, calib_paths, image_size=image_size)
    source = {
        "calibration": {"format": calib_format, "paths": [str(p) for p in calib_paths]},
    }
    if detections_format is not None:
        imported = read_detections(detections_format, detections_path, rig.names, js, layout=layout)
        detections, num_frames, js = imported.detections, imported.num_frames, imported.joint_set
        source["detections"] = _detections_source(detections_format, detections_path, imported)
    else:
        js = js if js is not None else resolve_joint_set("coco17", meta_path)
        detections = Detections(
            frame=np.zeros(0, np.int64),
            view=np.zeros(0, np.int64),
            keypoints=np.zeros((0, js.num_joints, 3)),
        )
        num_frames = 0
    refs = {n: reference_from_trc(p, n, js, fps=float(fps)) for n, p in (references or {}).items()}
    if detections_format is None and refs:
        num_frames = max(len(r.joints) for r in refs.values())
    refs = {
        n: replace(r, joints=fit_frames(r.joints, num_frames, source=references[n]))
        for n, r in refs.items()
    }
    return write_scene(
        out_dir,
        references=refs,
        name=name if name is not None else out_dir.name,
        fps=float(fps),
        num_frames=num_frames,
        joint_set=js,
        rig=rig,
        detections=detections,
        extra_meta={"imported_from": source},
        overwrite=overwrite,
    )
