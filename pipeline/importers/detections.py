"""2D keypoint detections of other tools, read into native :class:`Detections`.

Layouts on disk (one folder per camera, named like the camera in the calibration, one
file per frame, the frame index being the trailing digits of the file name):

* **OpenPose** ``--write_json``: ``<anything>_000000000012_keypoints.json`` holding
  ``{"people": [{"pose_keypoints_2d": [x0, y0, c0, x1, y1, c1, ...]}, ...]}``; BODY_25
  (25 joints) or OpenPose's COCO (18 joints, neck at index 1: :data:`OPENPOSE_COCO18`).
* **EasyMocap** ``annots/<cam>/000012.json`` holding ``{"annots": [{"personID": 0,
  "bbox": [x0, y0, x1, y1, c], "keypoints": [[x, y, c], ...]}, ...]}`` (usually BODY_25).
* **MMPose** (RTMPose, rtmlib, MMPose's inferencer and demos): per frame a list of
  ``{"keypoints": [[x, y], ...], "keypoint_scores": [...]}`` instances, or one
  ``instance_info`` file per camera (:func:`read_mmpose_predictions`).

Keypoints are image pixels; confidences are the detector's scores as written (they may
exceed 1); a joint scored 0, below 0 or NaN is missing and gets NaN x, y.
The layout (BODY_25, BODY_25B, OpenPose COCO-18, COCO-17, Human3.6M-17, Halpe-26,
COCO-WholeBody-133, BlazePose-33, SMPL-24) is identified from the data unless forced
(:mod:`pipeline.importers.layouts`: counts collide, so the anatomy decides), and the
result is kept in that layout or re-ordered by joint name into the asked joint set with
:func:`~pipeline.data.joint_sets.convert_keypoints`.

Every problem raises :class:`~pipeline.core.files.SceneFormatError` naming the file and the
field (``people[2].pose_keypoints_2d``, ``annots[0].keypoints``). Keypoint values must be
JSON numbers (a string or ``true`` is an error, not 1.0).

Frame numbers (file names, MMPose ``frame_id``) are scene frames as they are: frame k of
every camera is the same instant, and videos stay aligned. They are bounded by what was
read: a frame number above ``10 x (frames read) + 10000`` (:func:`frame_limit`) is
refused, so a stray ``999999999999`` in a file name is an error, not a 7 TiB scene;
renumber such files from 0.
"""

from __future__ import annotations

import json
import os
import re
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.core.files import SceneFormatError
from pipeline.core.schema import check_numbers
from pipeline.data.joint_sets import COCO17, JointSet, convert_keypoints, get_joint_set
from pipeline.data.scene import Detections, check_detections
from pipeline.importers.layouts import (
    CANDIDATES_BY_COUNT,
    SOURCE_LAYOUTS,
    LayoutDecision,
    identify_layout,
)

# The joint set a scene keeps of a layout when none is asked for: the layout itself,
# except COCO-WholeBody, whose 110 face and hand points are dropped (the body model and
# the viewer use body and feet; ``joint_set="coco_wholebody133"`` keeps them).
DEFAULT_SCENE_JOINT_SET: dict[str, str] = {"coco_wholebody133": "coco23"}

_TRAILING_DIGITS = re.compile(r"(\d+)\D*$")


def frame_limit(frames_read: int) -> int:
    """The largest frame number accepted when ``frames_read`` frames were read (see the
    module docstring): a leading offset of up to 10000 frames, or gaps up to 10x."""
    return 10 * frames_read + 10_000


@dataclass(frozen=True, eq=False)
class ImportedDetections:
    """Detections read from a folder tree, with where they came from.

    Attributes:
        detections: rows in frame order; ``view`` indexes ``view_names``; keypoints are
            (N, joint_set.num_joints, 3) pixels + confidence.
        view_names: the camera names given to the reader (the calibration's order).
        joint_set: the joint set of ``detections.keypoints``.
        source_layout: the layout found in the files (``"body25"``, ``"coco18"``, ...), or
            None if no file held a person.
        num_frames: 1 + the largest frame index of any file (0 if there were none); frames
            whose file lists nobody are valid and simply have no rows.
        missing_views: cameras that had no folder (they have no detections).
        layout_decision: what was decided about the files' layout and on what evidence
            (None if no file held a person).
    """

    detections: Detections
    view_names: tuple[str, ...]
    joint_set: JointSet
    source_layout: str | None
    num_frames: int
    missing_views: tuple[str, ...]
    layout_decision: LayoutDecision | None = None


def resolve_joint_set(joint_set: str | JointSet, source, field: str = "joint_set") -> JointSet:
    """A joint set by name, or a SceneFormatError naming ``source`` and ``field``."""
    if isinstance(joint_set, JointSet):
        return joint_set
    try:
        return get_joint_set(str(joint_set))
    except ValueError as exc:
        raise SceneFormatError(source, field, str(exc)) from None


def _resolve_layout(layout: str | None, source) -> JointSet | None:
    if layout is None:
        return None
    try:
        return SOURCE_LAYOUTS[str(layout).lower()]
    except KeyError:
        raise SceneFormatError(
            source, "layout", f"unknown layout {layout!r}; expected one of {sorted(SOURCE_LAYOUTS)}"
        ) from None


def frame_index(path: Path) -> int:
    """The frame index in a file name: its last run of digits (``cam0_000000000012_keypoints``
    -> 12, ``000012.json`` -> 12)."""
    m = _TRAILING_DIGITS.search(path.stem)
    if m is None:
        raise SceneFormatError(path, "file name", "expected a frame number in the file name")
    return int(m.group(1))


def check_keypoints(value, path, field: str) -> np.ndarray:
    """One person's keypoints as (J, 3) x, y, confidence, validated.

    A confidence is the detector's score, not a probability, and is kept as written:
    OpenPose's heatmap peaks and MMPose's top-down scores exceed 1. A score of zero or
    below, or NaN, marks a missing joint (OpenPose writes ``0 0 0``): its confidence
    becomes 0 and its x, y NaN. An infinite score is refused, as are x, y that are not
    finite where the score is > 0.
    """
    check_numbers(value, path, field)
    try:
        kp = np.asarray(value, dtype=float)
    except (TypeError, ValueError) as exc:
        raise SceneFormatError(path, field, f"expected numbers ({exc})") from None
    if kp.ndim == 1:
        if kp.size % 3:
            raise SceneFormatError(
                path, field, f"expected x, y, c triples; got {kp.size} values (not a multiple of 3)"
            )
        kp = kp.reshape(-1, 3)
    if kp.ndim != 2 or kp.shape[1] != 3:
        raise SceneFormatError(path, field, f"expected (num_joints, 3) x, y, c; got {kp.shape}")
    conf = kp[:, 2]
    if np.isinf(conf).any():
        j = int(np.flatnonzero(np.isinf(conf))[0])
        raise SceneFormatError(
            path, field, f"confidence of keypoint {j} is {conf[j]!r}, expected a finite score"
        )
    seen = conf > 0  # NaN compares False: missing
    kp[~seen, 2] = 0.0
    if not np.isfinite(kp[seen, :2]).all():
        j = int(np.flatnonzero(seen & ~np.isfinite(kp[:, :2]).all(1))[0])
        raise SceneFormatError(path, field, f"keypoint {j} has confidence > 0 but x, y not finite")
    kp[~seen, :2] = np.nan
    return kp


def _read_json(path: Path):
    try:
        return json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise SceneFormatError(path, None, f"not valid JSON ({exc})") from exc


# A per-file parser: path -> (frames the file covers, [(frame, field, (K, 3) keypoints)]
# one entry per person). A file of a frame where nobody was seen covers that frame.
FileParser = Callable[[Path], tuple[list[int], list[tuple[int, str, np.ndarray]]]]


def _per_frame(people_of: Callable[[Path], list[tuple[str, np.ndarray]]]) -> FileParser:
    """A parser for formats with one file per frame, numbered in the file name."""

    def parse(path: Path) -> tuple[list[int], list[tuple[int, str, np.ndarray]]]:
        f = frame_index(path)
        return [f], [(f, field, kp) for field, kp in people_of(path)]

    return parse


def _openpose_people(path: Path) -> list[tuple[str, np.ndarray]]:
    data = _read_json(path)
    if not isinstance(data, dict) or "people" not in data:
        raise SceneFormatError(path, "people", "missing (expected an OpenPose JSON file)")
    people = data["people"]
    if not isinstance(people, list):
        raise SceneFormatError(path, "people", "expected a list")
    out = []
    for i, person in enumerate(people):
        field = f"people[{i}].pose_keypoints_2d"
        if not isinstance(person, dict) or "pose_keypoints_2d" not in person:
            raise SceneFormatError(path, field, "missing")
        values = person["pose_keypoints_2d"]
        if not isinstance(values, list):
            raise SceneFormatError(path, field, "expected a flat list [x0, y0, c0, x1, ...]")
        if not values:  # OpenPose writes [] when only hands / faces were run
            continue
        out.append((field, check_keypoints(values, path, field)))
    return out


def _easymocap_people(path: Path) -> list[tuple[str, np.ndarray]]:
    data = _read_json(path)
    if isinstance(data, dict):
        if "annots" not in data:
            raise SceneFormatError(path, "annots", "missing (expected an EasyMocap annots file)")
        annots = data["annots"]
    else:
        annots = data  # older EasyMocap files are a bare list of people
    if not isinstance(annots, list):
        raise SceneFormatError(path, "annots", "expected a list of people")
    out = []
    for i, person in enumerate(annots):
        field = f"annots[{i}].keypoints"
        if not isinstance(person, dict) or "keypoints" not in person:
            raise SceneFormatError(path, field, "missing")
        out.append((field, check_keypoints(person["keypoints"], path, field)))
    return out


def _mmpose_instance(person, path: Path, field: str) -> np.ndarray:
    """One MMPose instance ``{"keypoints": [[x, y], ...], "keypoint_scores": [...]}``."""
    if not isinstance(person, dict) or "keypoints" not in person:
        raise SceneFormatError(path, field + ".keypoints", "missing")
    check_numbers(person["keypoints"], path, field + ".keypoints")
    check_numbers(person.get("keypoint_scores", []), path, field + ".keypoint_scores")
    try:
        xy = np.asarray(person["keypoints"], dtype=float)
        scores = np.asarray(person.get("keypoint_scores", np.ones(len(xy))), dtype=float)
    except (TypeError, ValueError) as exc:
        raise SceneFormatError(path, field + ".keypoints", f"expected numbers ({exc})") from None
    if xy.ndim != 2 or xy.shape[1] not in (2, 3):
        raise SceneFormatError(
            path, field + ".keypoints", f"expected [[x, y], ...] per keypoint, got shape {xy.shape}"
        )
    if scores.shape != (len(xy),):
        raise SceneFormatError(
            path,
            field + ".keypoint_scores",
            f"expected {len(xy)} scores (one per keypoint), got shape {scores.shape}",
        )
    if np.isinf(scores).any():
        j = int(np.flatnonzero(np.isinf(scores))[0])
        raise SceneFormatError(
            path,
            field + ".keypoint_scores",
            f"score of keypoint {j} is {scores[j]!r}, expected a finite score",
        )
    # RTMPose's SimCC scores reach ~1.2 and heatmap maxima exceed 1: kept as scores
    kp = np.concatenate([xy[:, :2], scores[:, None]], 1)
    return check_keypoints(kp, path, field + ".keypoints")


def _mmpose_file(path: Path) -> tuple[list[int], list[tuple[int, str, np.ndarray]]]:
    """An MMPose prediction file: either one frame (a list of instances, or a dict with
    ``instances``; the frame number in the file name), or a whole video as written by
    MMPose's demos with ``--save-predictions``: ``{"meta_info": ..., "instance_info":
    [{"frame_id": k, "instances": [...]}, ...]}`` (frame k of the file is frame k of the
    scene: write the first frame as 0, or renumber in one place for every camera)."""
    data = _read_json(path)
    if isinstance(data, dict) and "instance_info" in data:
        info = data["instance_info"]
        if not isinstance(info, list):
            raise SceneFormatError(path, "instance_info", "expected a list of frames")
        covered, people = [], []
        for i, entry in enumerate(info):
            field = f"instance_info[{i}]"
            if not isinstance(entry, dict) or "frame_id" not in entry:
                raise SceneFormatError(path, field + ".frame_id", "missing")
            f = entry["frame_id"]
            if isinstance(f, bool) or not isinstance(f, int) or f < 0:
                raise SceneFormatError(
                    path, field + ".frame_id", f"expected a frame number >= 0, got {f!r}"
                )
            instances = entry.get("instances", [])
            if not isinstance(instances, list):
                raise SceneFormatError(path, field + ".instances", "expected a list")
            covered.append(f)
            for k, person in enumerate(instances):
                fk = f"{field}.instances[{k}]"
                people.append((f, fk + ".keypoints", _mmpose_instance(person, path, fk)))
        return covered, people
    if isinstance(data, dict) and "instances" in data:
        data = data["instances"]
    if not isinstance(data, list):
        raise SceneFormatError(
            path, "instances", "expected a list of instances or an MMPose instance_info file"
        )
    f = frame_index(path)
    return [f], [
        (f, f"[{k}].keypoints", _mmpose_instance(person, path, f"[{k}]"))
        for k, person in enumerate(data)
    ]


def camera_key(name: str) -> str:
    """A camera name reduced for matching folder names to calibration names: lower case,
    letters and numbers only, numbers without leading zeros (``cam_01``, ``Cam01`` and
    ``cam1`` are one camera; Pose2Sim names its 2D folders ``cam_01`` while a Qualisys
    calibration calls the camera ``cam01``)."""
    parts = re.findall(r"[a-z]+|\d+", name.lower())
    return "".join(str(int(p)) if p.isdigit() else p for p in parts)


def _match_camera(entry: Path, stem: str, names: list[str]) -> str | None:
    """The calibration camera ``stem`` names: itself, or the one camera whose
    :func:`camera_key` is the same (None if none; an error if several)."""
    if stem in names:
        return stem
    same = [n for n in names if camera_key(n) == camera_key(stem)]
    if len(same) > 1:
        raise SceneFormatError(
            entry, "camera", f"{stem!r} matches several cameras of the calibration: {same}"
        )
    return same[0] if same else None


def _camera_files(root: Path, names: list[str], single_file: bool) -> tuple[dict, tuple]:
    """Per camera name, the JSON files to read (a folder's files, or ``root/<camera>.json``
    where ``single_file`` formats allow one file per camera); and the missing cameras.
    Folder names match camera names exactly or by :func:`camera_key` (a warning says so)."""
    entries = sorted(p for p in root.iterdir() if not p.name.startswith("."))
    files: dict[str, list[Path]] = {}
    renamed = []
    for entry in entries:
        is_file = single_file and entry.is_file() and entry.suffix == ".json"
        if not (entry.is_dir() or is_file):
            continue
        stem = entry.name if entry.is_dir() else entry.stem
        cam = _match_camera(entry, stem, names)
        if cam is None:
            if is_file:
                continue
            raise SceneFormatError(
                entry,
                "camera",
                f"folder {entry.name!r} is not a camera of the calibration {names}",
            )
        if cam in files:
            raise SceneFormatError(entry, "camera", f"a second source for camera {cam!r}")
        if cam != stem:
            renamed.append(f"{entry.name} -> {cam}")
        if entry.is_dir():
            files[cam] = sorted(p for p in entry.glob("*.json") if not p.name.startswith("."))
        else:
            files[cam] = [entry]
    if renamed:
        warnings.warn(
            f"{root}: camera folders matched to the calibration by name: {', '.join(renamed)}",
            stacklevel=4,
        )
    if not files:
        raise SceneFormatError(
            root,
            None,
            f"no camera folders found (expected folders {names}"
            + (" or files <camera>.json)" if single_file else ")"),
        )
    missing = tuple(n for n in names if n not in files)
    return files, missing


def _check_count(
    path: Path,
    field: str,
    count: int,
    forced: JointSet | None,
    first: tuple[Path, int] | None,
) -> tuple[Path, int]:
    """A person's keypoint ``count`` is the forced layout's, or known and the same as in
    the ``first`` file that had people; returns that first (file, count)."""
    if forced is not None and count != forced.num_joints:
        raise SceneFormatError(
            path,
            field,
            f"expected {forced.num_joints} keypoints ({forced.name}, forced), got {count}",
        )
    if first is None:
        if count not in CANDIDATES_BY_COUNT:
            raise SceneFormatError(
                path,
                field,
                f"cannot tell the layout of {count} keypoints; known: "
                + ", ".join(f"{js.name} ({js.num_joints})" for js in SOURCE_LAYOUTS.values())
                + "; name one with --layout",
            )
        return path, count
    if count != first[1]:
        raise SceneFormatError(
            path,
            field,
            f"expected {first[1]} keypoints (as in {first[0].name}), "
            f"got {count}: one layout per scene",
        )
    return first


def _converted(
    rows: list[np.ndarray],
    frames: list[int],
    views: list[int],
    *,
    root: Path,
    layout: str | None,
    forced: JointSet | None,
    dst: JointSet | None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, JointSet, LayoutDecision | None]:
    """The people's keypoints (each (K, 3)) in the identified layout converted to ``dst``
    (default: the scene joint set of that layout), sorted by frame then view: frame,
    view, keypoints, the joint set and the layout decision (None without people)."""
    if not rows:
        if dst is None:
            dst = COCO17 if forced is None else forced
        empty = np.zeros(0, np.int64)
        return empty, empty, np.zeros((0, dst.num_joints, 3)), dst, None
    raw = np.stack(rows)
    decision = identify_layout(raw, source=root, field="keypoints", forced=layout)
    src = SOURCE_LAYOUTS[decision.layout]
    if dst is None:
        dst = get_joint_set(DEFAULT_SCENE_JOINT_SET.get(src.name, src.name))
    keypoints = convert_keypoints(raw, src, dst)
    frame, view = np.asarray(frames, np.int64), np.asarray(views, np.int64)
    order = np.lexsort((view, frame))
    return frame[order], view[order], keypoints[order], dst, decision


def _read_folders(
    root: str | os.PathLike,
    camera_names: Sequence[str],
    joint_set: str | JointSet | None,
    layout: str | None,
    parse: FileParser,
    *,
    single_file: bool = False,
) -> ImportedDetections:
    root = Path(root)
    dst = None if joint_set is None else resolve_joint_set(joint_set, root)
    forced = _resolve_layout(layout, root)  # an unknown name fails before any file is read
    if not root.is_dir():
        raise SceneFormatError(root, None, "directory not found")
    names = [str(n) for n in camera_names]
    files, missing = _camera_files(root, names, single_file)
    if missing:
        warnings.warn(
            f"{root}: no folder for camera(s) {list(missing)}; they get no detections",
            stacklevel=3,
        )

    frames, views, rows = [], [], []
    first: tuple[Path, int] | None = None  # where the keypoint count was first seen
    num_frames, frames_read = 0, 0
    last: Path | None = None  # the file of the largest frame number
    for v, name in enumerate(names):
        seen: dict[int, Path] = {}
        for path in files.get(name, []):
            covered, people = parse(path)
            for f in covered:
                if f in seen:
                    raise SceneFormatError(
                        path, "file name", f"frame {f} is also read from {seen[f].name}"
                    )
                seen[f] = path
                if f + 1 > num_frames:
                    num_frames, last = f + 1, path
            frames_read += len(covered)
            for f, field, kp in people:
                first = _check_count(path, field, kp.shape[0], forced, first)
                frames.append(f)
                views.append(v)
                rows.append(kp)

    if num_frames - 1 > frame_limit(frames_read):
        raise SceneFormatError(
            last,
            "frame number",
            f"expected frame numbers up to {frame_limit(frames_read)} for {frames_read} frames "
            f"read, got {num_frames - 1}: renumber the files from 0",
        )
    frame, view, keypoints, dst, decision = _converted(
        rows, frames, views, root=root, layout=layout, forced=forced, dst=dst
    )
    detections = check_detections(
        {"frame": frame, "view": view, "keypoints": keypoints},
        source=root,
        num_joints=dst.num_joints,
        num_views=len(names),
    )
    return ImportedDetections(
        detections=detections,
        view_names=tuple(names),
        joint_set=dst,
        source_layout=None if decision is None else decision.layout,
        num_frames=num_frames,
        missing_views=missing,
        layout_decision=decision,
    )


def read_openpose_folders(
    root: str | os.PathLike,
    camera_names: Sequence[str],
    joint_set: str | JointSet | None = None,
    *,
    layout: str | None = None,
) -> ImportedDetections:
    """Read OpenPose JSON output, one folder per camera under ``root``.

    Args:
        root: directory holding ``<camera name>/*.json``.
        camera_names: the calibration's camera names, in rig order (``view`` indexes them).
        joint_set: the joint set to convert to (the scene's); None keeps the files'
            layout (COCO-WholeBody-133: its body and feet, ``coco23``).
        layout: force the files' layout (``"body25"``, ``"body25b"``, ...) instead of
            identifying it from the data (:func:`~pipeline.importers.layouts.identify_layout`).
    """
    return _read_folders(root, camera_names, joint_set, layout, _per_frame(_openpose_people))


def read_easymocap_annots(
    root: str | os.PathLike,
    camera_names: Sequence[str],
    joint_set: str | JointSet | None = None,
    *,
    layout: str | None = None,
) -> ImportedDetections:
    """Read EasyMocap ``annots/<camera>/<frame:06d>.json`` files; arguments as
    :func:`read_openpose_folders` (``root`` is the ``annots`` directory)."""
    return _read_folders(root, camera_names, joint_set, layout, _per_frame(_easymocap_people))


def read_mmpose_predictions(
    root: str | os.PathLike,
    camera_names: Sequence[str],
    joint_set: str | JointSet | None = None,
    *,
    layout: str | None = None,
) -> ImportedDetections:
    """Read MMPose / RTMPose / rtmlib predictions: ``root/<camera>/<frame>.json`` (a list
    of ``{"keypoints", "keypoint_scores"}`` instances per frame, as MMPose's inferencer
    writes with ``--pred-out-dir``), or one ``instance_info`` file per camera
    (``root/<camera>.json`` or ``root/<camera>/<any>.json``, MMPose's demos with
    ``--save-predictions``). Arguments as :func:`read_openpose_folders`."""
    return _read_folders(root, camera_names, joint_set, layout, _mmpose_file, single_file=True)
