"""2D keypoint detections of other tools, read into native :class:`Detections`.

Layouts on disk (one folder per camera, named like the camera in the calibration, one
file per frame, the frame index being the trailing digits of the file name):

* **OpenPose** ``--write_json``: ``<anything>_000000000012_keypoints.json`` holding
  ``{"people": [{"pose_keypoints_2d": [x0, y0, c0, x1, y1, c1, ...]}, ...]}``; BODY_25
  (25 joints) or OpenPose's COCO (18 joints, neck at index 1: :data:`OPENPOSE_COCO18`).
* **EasyMocap** ``annots/<cam>/000012.json`` holding ``{"annots": [{"personID": 0,
  "bbox": [x0, y0, x1, y1, c], "keypoints": [[x, y, c], ...]}, ...]}`` (usually BODY_25).

Keypoints are image pixels; a joint with confidence 0 is missing and gets NaN x, y.
The source layout is detected from the keypoint count (17 COCO, 18 OpenPose COCO,
25 BODY_25, 26 Halpe) unless forced, and the result is re-ordered by joint name into
the scene's joint set with :func:`~pipeline.joint_sets.convert_keypoints`.

Every problem raises :class:`~pipeline.files.SceneFormatError` naming the file and the
field (``people[2].pose_keypoints_2d``, ``annots[0].keypoints``).
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

from pipeline.files import SceneFormatError
from pipeline.joint_sets import (
    BODY25,
    COCO17,
    HALPE26,
    OPENPOSE_COCO18,
    JointSet,
    convert_keypoints,
    get_joint_set,
)
from pipeline.scene import Detections, check_detections

# Layouts a file may be in, by name (for forcing one) and by keypoint count (to detect one).
SOURCE_LAYOUTS: dict[str, JointSet] = {
    "body25": BODY25,
    "coco18": OPENPOSE_COCO18,
    "coco17": COCO17,
    "halpe26": HALPE26,
}
_LAYOUT_BY_COUNT: dict[int, JointSet] = {js.num_joints: js for js in SOURCE_LAYOUTS.values()}

# Confidences a little above 1 are float round-off in the writer; clip them.
_CONFIDENCE_SLACK = 1e-4
_TRAILING_DIGITS = re.compile(r"(\d+)\D*$")


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
    """

    detections: Detections
    view_names: tuple[str, ...]
    joint_set: JointSet
    source_layout: str | None
    num_frames: int
    missing_views: tuple[str, ...]


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
        return SOURCE_LAYOUTS[layout.lower()]
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

    Confidence must be finite and in [0, 1] (values up to 1.0001 are clipped to 1);
    x, y must be finite where the confidence is > 0; x, y become NaN where it is 0.
    """
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
    if np.isnan(conf).any():
        j = int(np.flatnonzero(np.isnan(conf))[0])
        raise SceneFormatError(path, field, f"confidence of keypoint {j} is NaN")
    bad = (conf < 0) | (conf > 1 + _CONFIDENCE_SLACK)
    if bad.any():
        j = int(np.flatnonzero(bad)[0])
        raise SceneFormatError(
            path, field, f"confidence of keypoint {j} is {conf[j]!r}, expected a value in [0, 1]"
        )
    kp[:, 2] = np.minimum(conf, 1.0)
    seen = kp[:, 2] > 0
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


# A per-file parser: path -> [(field, (J, 3) keypoints)], one entry per person.
FileParser = Callable[[Path], list[tuple[str, np.ndarray]]]


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


def _read_folders(
    root: str | os.PathLike,
    camera_names: Sequence[str],
    joint_set: str | JointSet,
    layout: str | None,
    parse: FileParser,
) -> ImportedDetections:
    root = Path(root)
    dst = resolve_joint_set(joint_set, root)
    forced = _resolve_layout(layout, root)
    if not root.is_dir():
        raise SceneFormatError(root, None, "directory not found")
    names = [str(n) for n in camera_names]
    folders = sorted(p for p in root.iterdir() if p.is_dir() and not p.name.startswith("."))
    for folder in folders:
        if folder.name not in names:
            raise SceneFormatError(
                folder,
                "camera",
                f"folder {folder.name!r} is not a camera of the calibration {names}",
            )
    present = {f.name for f in folders}
    if not present:
        raise SceneFormatError(root, None, f"no camera folders found (expected folders {names})")
    missing = tuple(n for n in names if n not in present)
    if missing:
        warnings.warn(
            f"{root}: no folder for camera(s) {list(missing)}; they get no detections",
            stacklevel=3,
        )

    src = forced
    frames, views, rows = [], [], []
    num_frames = 0
    for v, name in enumerate(names):
        if name not in present:
            continue
        seen: dict[int, Path] = {}
        files = (p for p in (root / name).glob("*.json") if not p.name.startswith("."))
        for path in sorted(files):
            f = frame_index(path)
            if f in seen:
                raise SceneFormatError(
                    path, "file name", f"frame {f} is also read from {seen[f].name}"
                )
            seen[f] = path
            num_frames = max(num_frames, f + 1)
            for field, kp in parse(path):
                if src is None:  # the first person fixes the layout of all files
                    src = _LAYOUT_BY_COUNT.get(kp.shape[0])
                    if src is None:
                        raise SceneFormatError(
                            path,
                            field,
                            f"cannot tell the layout of {kp.shape[0]} keypoints; known: "
                            + ", ".join(
                                f"{k} ({js.num_joints})" for k, js in SOURCE_LAYOUTS.items()
                            )
                            + "; force one with layout=...",
                        )
                if kp.shape[0] != src.num_joints:
                    raise SceneFormatError(
                        path,
                        field,
                        f"expected {src.num_joints} keypoints ({_layout_name(src)}"
                        f"{', forced' if forced else ', as in the first file'}), got {kp.shape[0]}",
                    )
                frames.append(f)
                views.append(v)
                rows.append(kp)

    num_joints = dst.num_joints
    if rows:
        keypoints = convert_keypoints(np.stack(rows), src, dst)
        frame, view = np.asarray(frames, np.int64), np.asarray(views, np.int64)
        order = np.lexsort((view, frame))
        frame, view, keypoints = frame[order], view[order], keypoints[order]
    else:
        frame = view = np.zeros(0, np.int64)
        keypoints = np.zeros((0, num_joints, 3))
    detections = check_detections(
        {"frame": frame, "view": view, "keypoints": keypoints},
        source=root,
        num_joints=num_joints,
        num_views=len(names),
    )
    return ImportedDetections(
        detections=detections,
        view_names=tuple(names),
        joint_set=dst,
        source_layout=None if src is None else _layout_name(src),
        num_frames=num_frames,
        missing_views=missing,
    )


def _layout_name(js: JointSet) -> str:
    return next(k for k, v in SOURCE_LAYOUTS.items() if v is js)


def read_openpose_folders(
    root: str | os.PathLike,
    camera_names: Sequence[str],
    joint_set: str | JointSet = "coco17",
    *,
    layout: str | None = None,
) -> ImportedDetections:
    """Read OpenPose JSON output, one folder per camera under ``root``.

    Args:
        root: directory holding ``<camera name>/*.json``.
        camera_names: the calibration's camera names, in rig order (``view`` indexes them).
        joint_set: the joint set to convert to (the scene's; default COCO-17).
        layout: force the files' layout (``"body25"``, ``"coco18"``, ...) instead of
            detecting it from the keypoint count.
    """
    return _read_folders(root, camera_names, joint_set, layout, _openpose_people)


def read_easymocap_annots(
    root: str | os.PathLike,
    camera_names: Sequence[str],
    joint_set: str | JointSet = "coco17",
    *,
    layout: str | None = None,
) -> ImportedDetections:
    """Read EasyMocap ``annots/<camera>/<frame:06d>.json`` files; arguments as
    :func:`read_openpose_folders` (``root`` is the ``annots`` directory)."""
    return _read_folders(root, camera_names, joint_set, layout, _easymocap_people)
