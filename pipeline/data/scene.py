"""The native scene format: a directory with scene.json, cameras.json, detections.npz,
optional gt.npz and optional videos/images. Documented in sample_data/README.md.

Units: world millimetres (z up), image pixels. Every reader checks shapes and values
where the data enters and raises :class:`~pipeline.core.files.SceneFormatError` naming the
file and the field; :func:`write_scene` writes a whole scene atomically.
"""

from __future__ import annotations

import json
import os
import shutil
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pipeline.core.files import (
    SceneFormatError,
    atomic_directory,
    atomic_write,
    load_npz,
    recover,
    save_npz_atomic,
)
from pipeline.core.npy_stream import is_mapped, release_pages
from pipeline.core.schema import Int, Number, Str, check_object
from pipeline.data.cameras import CameraRig, load_cameras, save_cameras
from pipeline.data.joint_sets import JOINT_SETS, SMPL24, JointSet, get_joint_set
from pipeline.data.references import (
    REFERENCES_DIR,
    ReferenceTrack,
    check_joints,
    check_name,
    fit_frames,
    load_references,
    reference_entry,
    save_reference,
)

SMPL_FIELDS = ("smpl_pose", "smpl_betas", "cam_weak", "bbox")
SMPL_FIELD_WIDTH = {"smpl_pose": 72, "smpl_betas": 10, "cam_weak": 3, "bbox": 4}
# Monocular 3D joints instead of (or beside) SMPL parameters: they share cam_weak/bbox.
MONO_FIELDS = ("mono_joints3d", "cam_weak", "bbox")

CHECK_ROWS = 1 << 16
"""Detection rows checked at a time (a long scene's columns stay memory-mapped)."""

MAX_FRAMES = 1_000_000
"""Frames per scene at most (4.6 hours at 60 fps): memory follows the frame count."""

SCENE_JSON = {
    "name": Str(optional=True),
    "fps": Number(gt=0, optional=True, default=25.0, doc="frames per second"),
    "units": Str(choices=("mm",), optional=True, default="mm"),
    "joint_set": Str(choices=tuple(JOINT_SETS)),
    "num_frames": Int(min=0, max=MAX_FRAMES, optional=True),
    "cameras": Str(optional=True, default="cameras.json", doc="path in the scene"),
    "detections": Str(optional=True, default="detections.npz", doc="path in the scene"),
    "gt": Str(optional=True, doc="path in the scene"),
    "videos": Str(optional=True, doc="folder in the scene"),
    "images": Str(optional=True, doc="folder in the scene"),
}
"""The declared fields of scene.json (pipeline/core/schema.py); others are kept and ignored.
``references`` is checked by :func:`~pipeline.data.references.load_references`."""


@dataclass(frozen=True, eq=False)
class Detections:
    """Per-view detections, one row per detected person in one view and frame.

    Attributes:
        frame: (N,) int frame index.
        view: (N,) int index into the scene's camera rig.
        keypoints: (N, J, 3) x px, y px, confidence >= 0 (the detector's score; it may
            exceed 1); a missed joint has confidence 0 (its x, y may be NaN).
        smpl_pose: (N, 72) axis-angle, SPIN-style, root orientation in the camera frame
            (x right, y down, z forward); a NaN row means "no regressor output".
        smpl_betas: (N, 10); cam_weak: (N, 3) weak-perspective (s, tx, ty);
        bbox: (N, 4) x0, y0, x1, y1 pixels of the crop cam_weak refers to.
        mono_joints3d: (N, 24, 3) optional monocular 3D joints in metres, SMPL-24 order,
            camera axes (x right, y down, z forward), projected by cam_weak/bbox like the
            SMPL joints (e.g. BlazePose's world landmarks); NaN for joints it lacks. Rows
            with smpl_pose use SMPL; the others use these.
        gt_person_id: (N,) optional ground truth of synthetic scenes: the person a row
            shows, -1 for a false positive (used to score association).
    """

    frame: np.ndarray
    view: np.ndarray
    keypoints: np.ndarray
    smpl_pose: np.ndarray | None = None
    smpl_betas: np.ndarray | None = None
    cam_weak: np.ndarray | None = None
    bbox: np.ndarray | None = None
    gt_person_id: np.ndarray | None = None
    mono_joints3d: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.frame.shape[0])

    @property
    def has_smpl(self) -> bool:
        return self.smpl_pose is not None

    @property
    def smpl_valid(self) -> np.ndarray:
        """(N,) bool: rows that carry monocular SMPL regressor output."""
        if self.smpl_pose is None:
            return np.zeros(len(self), bool)
        return np.isfinite(self.smpl_pose).all(1) & np.isfinite(self.cam_weak).all(1)

    @property
    def has_mono3d(self) -> bool:
        """Whether any monocular 3D (SMPL parameters or 3D joints) is present."""
        return self.has_smpl or self.mono_joints3d is not None

    @property
    def mono_valid(self) -> np.ndarray:
        """(N,) bool: rows without SMPL output that carry monocular 3D joints."""
        if self.mono_joints3d is None:
            return np.zeros(len(self), bool)
        has = np.isfinite(self.mono_joints3d).all(-1).any(-1) & np.isfinite(self.cam_weak).all(1)
        return has & ~self.smpl_valid

    def take(self, rows: np.ndarray) -> Detections:
        """The subset of rows ``rows`` (index or boolean mask)."""
        kw = {
            k: (None if getattr(self, k) is None else getattr(self, k)[rows])
            for k in ("frame", "view", "keypoints", "gt_person_id", "mono_joints3d") + SMPL_FIELDS
        }
        return Detections(**kw)

    def arrays(self) -> dict[str, np.ndarray]:
        out = {"frame": self.frame, "view": self.view, "keypoints": self.keypoints}
        for k in SMPL_FIELDS + ("mono_joints3d",):
            if getattr(self, k) is not None:
                out[k] = getattr(self, k)
        if self.gt_person_id is not None:
            out["gt_person_id"] = self.gt_person_id
        return out


@dataclass(frozen=True, eq=False)
class GroundTruth:
    """Ground-truth people.

    Attributes:
        frame: (M,) int; person_id: (M,) int, stable over time.
        joints3d: (M, 24, 3) world mm, SMPL-24 order.
        smpl_pose: (M, 72) axis-angle; smpl_betas: (M, 10); transl: (M, 3) world mm.
            The body is ``1000 * body_model(pose, betas) + transl`` (the model is in metres).
        keypoints3d: (M, K, 3) optional, world mm: the truth in the detections' joint set
            (e.g. COCO-17 read off the true mesh), to score keypoint triangulation.
    """

    frame: np.ndarray
    person_id: np.ndarray
    joints3d: np.ndarray
    smpl_pose: np.ndarray | None = None
    smpl_betas: np.ndarray | None = None
    transl: np.ndarray | None = None
    keypoints3d: np.ndarray | None = None

    def arrays(self) -> dict[str, np.ndarray]:
        out = {"frame": self.frame, "person_id": self.person_id, "joints3d": self.joints3d}
        for k in ("smpl_pose", "smpl_betas", "transl", "keypoints3d"):
            if getattr(self, k) is not None:
                out[k] = getattr(self, k)
        return out


@dataclass(frozen=True, eq=False)
class Scene:
    """A loaded scene directory."""

    root: Path
    name: str
    fps: float
    num_frames: int
    joint_set: JointSet
    rig: CameraRig
    detections: Detections
    gt: GroundTruth | None = None
    videos: dict[str, Path] = field(default_factory=dict)
    image_dirs: dict[str, Path] = field(default_factory=dict)
    meta: dict = field(default_factory=dict)
    # other tools' 3D results by name (pipeline/data/references.py), drawn beside ours
    references: dict[str, ReferenceTrack] = field(default_factory=dict)


# --------------------------------------------------------------------------- checks


def _check_array(
    source, name: str, a: np.ndarray, *, ndim_shape: tuple, kind: str = "f"
) -> np.ndarray:
    """Check ``a`` against ``ndim_shape`` (None = any size) and numeric kind."""
    if a.dtype.kind not in ("f", "i", "u", "b"):
        raise SceneFormatError(source, name, f"expected a numeric array, got dtype {a.dtype}")
    if a.ndim != len(ndim_shape) or any(
        s is not None and s != d for s, d in zip(ndim_shape, a.shape, strict=True)
    ):
        want = "(" + ", ".join("N" if s is None else str(s) for s in ndim_shape)
        want += ",)" if len(ndim_shape) == 1 else ")"
        raise SceneFormatError(source, name, f"expected shape {want}, got {a.shape}")
    if kind == "i":
        if a.dtype.kind == "f":
            if not (np.isfinite(a).all() and (a == np.round(a)).all()):
                raise SceneFormatError(source, name, "expected integers")
        return a.astype(np.int64)
    if a.dtype == np.float64 and is_mapped(a):
        return a  # a column of a detections directory stays mapped (read as indexed)
    return a.astype(np.float64)


def _check_keypoint_values(source, kp: np.ndarray) -> None:
    """Confidences finite and >= 0 (a detector's score, which may exceed 1), coordinates
    finite where confidence > 0; in blocks
    of rows, a mapped array's pages released after each (a long scene's keypoints are
    not held in memory for the check)."""
    step = CHECK_ROWS
    for i in range(0, len(kp), step):
        block = kp[i : i + step]
        conf = block[..., 2]
        # reductions first (NaN propagates through min / max / sum: 1.9 GB of keypoints
        # check in ~1 s where element-wise masks took 3), the details only on failure
        if not (conf.min(initial=0.0) >= 0 and np.isfinite(conf.max(initial=0.0))):
            if not np.isfinite(conf).all():
                raise SceneFormatError(source, "keypoints[..., 2]", "confidence is NaN or infinite")
            raise SceneFormatError(
                source,
                "keypoints[..., 2]",
                f"expected confidence >= 0 (0 = missing), got minimum {conf.min():.3g}"
                + (f" in rows {i}..{i + len(block) - 1}" if len(kp) > step else ""),
            )
        xy = np.where(conf > 0, block[..., 0] + block[..., 1], 0.0).sum()
        if not np.isfinite(xy) and not (np.isfinite(block[..., :2]).all(-1) | (conf <= 0)).all():
            raise SceneFormatError(
                source, "keypoints[..., :2]", "NaN coordinates on a joint with confidence > 0"
            )
        release_pages(kp)


def check_detections(
    arrays: dict[str, np.ndarray], *, source, num_joints: int, num_views: int
) -> Detections:
    """Validate detection columns (see :class:`Detections`) and build the dataclass."""
    for k in ("frame", "view", "keypoints"):
        if k not in arrays:
            raise SceneFormatError(source, k, "missing (required column)")
    frame = _check_array(source, "frame", np.asarray(arrays["frame"]), ndim_shape=(None,), kind="i")
    n = frame.shape[0]
    view = _check_array(source, "view", np.asarray(arrays["view"]), ndim_shape=(n,), kind="i")
    kp = _check_array(source, "keypoints", np.asarray(arrays["keypoints"]), ndim_shape=(n, None, 3))
    if kp.shape[1] != num_joints:
        raise SceneFormatError(
            source, "keypoints", f"expected {num_joints} joints per row, got {kp.shape[1]}"
        )
    if (frame < 0).any():
        raise SceneFormatError(source, "frame", "expected non-negative frame indices")
    if ((view < 0) | (view >= num_views)).any():
        bad = np.unique(view[(view < 0) | (view >= num_views)])
        raise SceneFormatError(
            source, "view", f"expected view indices in [0, {num_views}), got {bad.tolist()}"
        )
    _check_keypoint_values(source, kp)
    smpl = _check_monocular(arrays, source=source, n=n)
    gt_person = None
    if "gt_person_id" in arrays:
        gt_person = _check_array(
            source, "gt_person_id", np.asarray(arrays["gt_person_id"]), ndim_shape=(n,), kind="i"
        )
    return Detections(frame=frame, view=view, keypoints=kp, gt_person_id=gt_person, **smpl)


def _check_monocular(arrays: dict[str, np.ndarray], *, source, n: int) -> dict:
    """The optional monocular columns: the SMPL group (smpl_pose, smpl_betas, cam_weak,
    bbox: all or none) and/or mono_joints3d (with cam_weak and bbox)."""
    out: dict[str, np.ndarray | None] = dict.fromkeys(SMPL_FIELDS + ("mono_joints3d",))
    has_smpl = any(k in arrays for k in ("smpl_pose", "smpl_betas"))
    has_mono = "mono_joints3d" in arrays
    group = SMPL_FIELDS if has_smpl else MONO_FIELDS if has_mono else ()
    if not group:
        if "cam_weak" in arrays or "bbox" in arrays:
            raise SceneFormatError(
                source, "cam_weak", "cam_weak/bbox need smpl_pose + smpl_betas or mono_joints3d"
            )
        return out
    missing = sorted(set(group) - set(arrays))
    if missing:
        raise SceneFormatError(
            source, missing[0], f"monocular fields {list(group)} come together; missing {missing}"
        )
    for k in SMPL_FIELDS:
        if k in arrays:
            out[k] = _check_array(
                source, k, np.asarray(arrays[k]), ndim_shape=(n, SMPL_FIELD_WIDTH[k])
            )
    if has_mono:
        out["mono_joints3d"] = _check_array(
            source, "mono_joints3d", np.asarray(arrays["mono_joints3d"]), ndim_shape=(n, 24, 3)
        )
    # in blocks of rows: a long scene's columns stay mapped (4.6 M rows of SMPL columns
    # checked whole made ~1 GB of temporaries)
    step = CHECK_ROWS
    for i in range(0, n, step):
        valid = np.zeros(min(step, n - i), bool)
        if has_smpl:
            valid |= np.isfinite(out["smpl_pose"][i : i + step]).all(1)
        if has_mono:
            mono = out["mono_joints3d"][i : i + step]
            if np.isinf(mono).any():
                raise SceneFormatError(source, "mono_joints3d", "infinite values (NaN marks a gap)")
            valid |= np.isfinite(mono).all(-1).any(-1)
        for k in ("smpl_betas", "cam_weak", "bbox"):
            if out[k] is not None and not np.isfinite(out[k][i : i + step][valid]).all():
                raise SceneFormatError(
                    source, k, "NaN in a row whose smpl_pose or mono_joints3d is given"
                )
        bb = out["bbox"][i : i + step][valid]
        if ((bb[:, 2] <= bb[:, 0]) | (bb[:, 3] <= bb[:, 1])).any():
            raise SceneFormatError(source, "bbox", "expected x1 > x0 and y1 > y0")
        for col in out.values():  # a mapped column's pages read so far go back
            if col is not None:
                release_pages(col)
    return out


def check_ground_truth(arrays: dict[str, np.ndarray], *, source) -> GroundTruth:
    for k in ("frame", "person_id", "joints3d"):
        if k not in arrays:
            raise SceneFormatError(source, k, "missing (required column)")
    frame = _check_array(source, "frame", np.asarray(arrays["frame"]), ndim_shape=(None,), kind="i")
    m = frame.shape[0]
    pid = _check_array(
        source, "person_id", np.asarray(arrays["person_id"]), ndim_shape=(m,), kind="i"
    )
    j3 = _check_array(
        source, "joints3d", np.asarray(arrays["joints3d"]), ndim_shape=(m, SMPL24.num_joints, 3)
    )
    opt = {}
    for k, w in (("smpl_pose", 72), ("smpl_betas", 10), ("transl", 3)):
        opt[k] = (
            _check_array(source, k, np.asarray(arrays[k]), ndim_shape=(m, w))
            if k in arrays
            else None
        )
    if "keypoints3d" in arrays:
        opt["keypoints3d"] = _check_array(
            source, "keypoints3d", np.asarray(arrays["keypoints3d"]), ndim_shape=(m, None, 3)
        )
    if (frame < 0).any():
        raise SceneFormatError(source, "frame", "expected non-negative frame indices")
    if (pid < 0).any():
        raise SceneFormatError(
            source, "person_id", f"expected person ids >= 0, got {int(pid.min())}"
        )
    pairs = frame * (pid.max(initial=0) + 1) + pid
    if np.unique(pairs).size != m:
        raise SceneFormatError(source, "person_id", "a person appears twice in one frame")
    return GroundTruth(frame=frame, person_id=pid, joints3d=j3, **opt)


def _check_frames_in_scene(path: Path, frames: np.ndarray, num_frames: int) -> None:
    if frames.size and frames.max() >= num_frames:
        raise SceneFormatError(
            path,
            "frame",
            f"expected frames in [0, {num_frames}) (num_frames in scene.json), "
            f"got {int((frames >= num_frames).sum())} rows up to frame {int(frames.max())}",
        )


# --------------------------------------------------------------------------- load / write


def _read_scene_json(root: Path) -> tuple[dict, dict]:
    """``scene.json`` as read, and checked against :data:`SCENE_JSON` (defaults filled)."""
    meta_path = root / "scene.json"
    if not meta_path.is_file():
        raise SceneFormatError(meta_path, None, "file not found (is this a scene directory?)")
    try:
        meta = json.loads(meta_path.read_text())
    except json.JSONDecodeError as exc:
        raise SceneFormatError(meta_path, None, f"not valid JSON ({exc})") from exc
    if not isinstance(meta, dict):
        raise SceneFormatError(meta_path, None, "expected a JSON object")
    if "detections" in meta and meta["detections"] is None:  # every scene has detections
        raise SceneFormatError(
            meta_path, "detections", "expected a path in the scene, got null (leave the "
            "field out for the default 'detections.npz')"
        )  # fmt: skip
    return meta, check_object(meta, SCENE_JSON, meta_path)


def open_detection_columns(path: Path) -> dict[str, np.ndarray]:
    """A detections directory: one ``COLUMN.npy`` per column of ``detections.npz``,
    memory-mapped (a float64 ``keypoints`` stays mapped: rows are read as the stages
    index them, so a scene of 10,000 frames x 31 cameras need not fit in memory)."""
    arrays = {}
    for p in sorted(path.glob("*.npy")):
        try:
            arrays[p.stem] = np.load(p, mmap_mode="r", allow_pickle=False)
        except (OSError, ValueError) as exc:  # a truncated file, a bad header
            raise SceneFormatError(p, None, f"not a readable .npy file ({exc})") from None
    return arrays


def save_detection_columns(path: Path, arrays: dict[str, np.ndarray]) -> None:
    """``arrays`` as a new detections directory (see :func:`open_detection_columns`)."""
    path.mkdir()
    for name, a in arrays.items():
        np.save(path / f"{name}.npy", np.ascontiguousarray(a), allow_pickle=False)


def _load_detections(det_path: Path, rig: CameraRig, joint_set: JointSet) -> Detections:
    """The detections file (or directory), its views mapped onto the rig's order if it
    names them."""
    det_arrays = open_detection_columns(det_path) if det_path.is_dir() else load_npz(det_path)
    if "view_names" in det_arrays:
        # Detections may name their views; map them onto the rig's order.
        names = [str(s) for s in det_arrays.pop("view_names")]
        unknown = [n for n in names if n not in rig.names]
        if unknown:
            raise SceneFormatError(
                det_path, "view_names", f"cameras {unknown} are not in cameras.json ({rig.names})"
            )
        lut = np.array([rig.index_of(n) for n in names])
        v = np.asarray(det_arrays["view"])
        if v.size and (v.min() < 0 or v.max() >= len(names)):
            raise SceneFormatError(det_path, "view", f"expected indices into view_names ({names})")
        det_arrays["view"] = lut[v.astype(int)] if v.size else v
    return check_detections(
        det_arrays, source=det_path, num_joints=joint_set.num_joints, num_views=len(rig)
    )


def _load_gt(gt_path: Path, joint_set: JointSet) -> GroundTruth:
    gt = check_ground_truth(load_npz(gt_path), source=gt_path)
    if gt.keypoints3d is not None and gt.keypoints3d.shape[1] != joint_set.num_joints:
        raise SceneFormatError(
            gt_path,
            "keypoints3d",
            f"expected {joint_set.num_joints} joints ({joint_set.name}), "
            f"got {gt.keypoints3d.shape[1]}",
        )
    return gt


def _num_frames(spec: dict, det_path: Path, detections: Detections, gt: GroundTruth | None) -> int:
    """``num_frames`` of scene.json, else one past the last frame of any row."""
    num_frames = spec["num_frames"]
    if num_frames is None:
        candidates = [detections.frame.max(initial=-1) + 1]
        if gt is not None:
            candidates.append(gt.frame.max(initial=-1) + 1)
        num_frames = int(max(candidates))
        if num_frames > MAX_FRAMES:
            raise SceneFormatError(
                det_path, "frame", f"expected frames below {MAX_FRAMES}, got {num_frames - 1}"
            )
    return int(num_frames)


def _media(root: Path, spec: dict, rig: CameraRig) -> tuple[dict[str, Path], dict[str, Path]]:
    """camera -> video file, camera -> image folder, for the cameras that have them."""
    videos, image_dirs = {}, {}
    if spec["videos"]:
        for cam in rig.names:
            p = root / spec["videos"] / f"{cam}.mp4"
            if p.is_file():
                videos[cam] = p
    if spec["images"]:
        for cam in rig.names:
            p = root / spec["images"] / cam
            if p.is_dir():
                image_dirs[cam] = p
    return videos, image_dirs


def load_scene(root: str | os.PathLike) -> Scene:
    """Load and validate a scene directory."""
    root = Path(root)
    recover(root)  # a replacement of this scene interrupted by a kill is completed first
    meta, spec = _read_scene_json(root)
    joint_set = get_joint_set(spec["joint_set"])
    rig = load_cameras(root / spec["cameras"])
    det_path = root / spec["detections"]
    detections = _load_detections(det_path, rig, joint_set)
    gt_path = root / spec["gt"] if spec["gt"] else None
    gt = _load_gt(gt_path, joint_set) if gt_path is not None else None
    num_frames = _num_frames(spec, det_path, detections, gt)
    # Every row is inside the scene: a row past num_frames is an error, never dropped.
    _check_frames_in_scene(det_path, detections.frame, num_frames)
    if gt is not None:
        _check_frames_in_scene(gt_path, gt.frame, num_frames)
    references = load_references(
        root,
        meta,
        joint_set=joint_set.name,
        num_frames=num_frames,
        num_joints=joint_set.num_joints,
    )
    videos, image_dirs = _media(root, spec, rig)
    return Scene(
        root=root,
        name=spec["name"] or root.name,
        fps=spec["fps"],
        num_frames=num_frames,
        joint_set=joint_set,
        rig=rig,
        detections=detections,
        gt=gt,
        videos=videos,
        image_dirs=image_dirs,
        meta=meta,
        references=references,
    )


def write_scene(
    out_dir: str | os.PathLike,
    *,
    name: str,
    fps: float,
    num_frames: int,
    joint_set: JointSet,
    rig: CameraRig,
    detections: Detections | None,
    gt: GroundTruth | None = None,
    videos: dict[str, Path] | None = None,
    extra_meta: dict | None = None,
    overwrite: bool = False,
    references: dict[str, ReferenceTrack] | None = None,
    detections_file: str = "detections.npz",
    detection_columns: Path | None = None,
) -> Path:
    """Write a complete scene directory atomically.

    ``detections_file`` not ending in ``.npz`` writes the detections as a directory of
    ``.npy`` columns (:func:`open_detection_columns`: read lazily; long scenes).
    ``detection_columns`` (with ``detections`` None): such a directory already written,
    e.g. by a synthesis that streams its rows; checked as the reader checks it and moved
    into the scene, not copied (the source directory is gone afterwards).

    ``videos`` (camera name -> mp4 path) are copied into ``videos/<camera>.mp4``;
    ``references`` (each (num_frames, J, 3) mm) into ``references/<name>.npz``.

    The data is validated on the way out with the same checks the reader applies.
    """
    out_dir = Path(out_dir)
    if (detections is None) == (detection_columns is None):
        raise ValueError("write_scene: give detections or detection_columns, not both")
    if detection_columns is not None and detections_file.lower().endswith(".npz"):
        raise ValueError(f"detection_columns needs a directory name, not {detections_file!r}")
    check_detections(
        detections.arrays() if detections is not None
        else open_detection_columns(Path(detection_columns)),
        source=out_dir / detections_file,
        num_joints=joint_set.num_joints,
        num_views=len(rig),
    )  # fmt: skip
    if gt is not None:
        check_ground_truth(gt.arrays(), source=out_dir / "gt.npz")
    for r in (references or {}).values():
        check_name(r.name, out_dir / "scene.json")
        check_joints(
            r.joints, source=r.source or r.name, num_frames=num_frames,
            num_joints=joint_set.num_joints,
        )  # fmt: skip
    meta = {
        "name": name,
        "fps": float(fps),
        "units": "mm",
        "joint_set": joint_set.name,
        "num_frames": int(num_frames),
        "cameras": "cameras.json",
        "detections": detections_file,
        "gt": "gt.npz" if gt is not None else None,
    }
    with atomic_directory(out_dir, overwrite=overwrite) as tmp:
        save_cameras(rig, tmp / "cameras.json")
        _save_detections(tmp / detections_file, detections, detection_columns)
        if gt is not None:
            save_npz_atomic(tmp / "gt.npz", **gt.arrays())
        if videos:
            (tmp / "videos").mkdir()
            for cam, src in videos.items():
                shutil.copyfile(src, tmp / "videos" / f"{cam}.mp4")
        meta["videos"] = "videos" if (tmp / "videos").is_dir() else None
        for r in (references or {}).values():
            save_reference(tmp, r)
        if references:
            meta["references"] = {
                r.name: reference_entry(r, joint_set.name) for r in references.values()
            }
        meta.update(extra_meta or {})
        (tmp / "scene.json").write_text(json.dumps(meta, indent=1) + "\n")
    return out_dir


def _save_detections(path: Path, detections: Detections | None, columns: Path | None) -> None:
    """``detections`` as ``path`` (an ``.npz`` file or a directory of columns), or the
    written ``columns`` directory moved there."""
    if columns is not None:
        shutil.move(str(columns), path)
    elif path.name.lower().endswith(".npz"):
        save_npz_atomic(path, **detections.arrays())
    else:
        save_detection_columns(path, detections.arrays())


def add_reference(scene: Scene, track: ReferenceTrack, *, overwrite: bool = False) -> Path:
    """Attach ``track`` to the scene on disk: its npz, then ``scene.json``, each atomically.

    ``track.joints`` may be shorter than the scene (padded, :func:`fit_frames`). A name
    already present is a FileExistsError unless ``overwrite``. Returns the npz path.
    """
    meta_path = scene.root / "scene.json"
    check_name(track.name, meta_path)
    if track.name in scene.references and not overwrite:
        raise FileExistsError(
            f"{meta_path}: reference {track.name!r} exists (pass overwrite to replace it)"
        )
    joints = fit_frames(track.joints, scene.num_frames, source=track.source or meta_path)
    js = scene.joint_set
    joints = check_joints(
        joints, source=track.source or meta_path, num_frames=scene.num_frames,
        num_joints=js.num_joints,
    )  # fmt: skip
    track = ReferenceTrack(name=track.name, joints=joints, source=track.source)
    # re-read scene.json: keep every key as it is on disk, change only this entry
    meta = json.loads(meta_path.read_text())
    save_reference(scene.root, track)
    refs = dict(meta.get("references") or {})
    refs[track.name] = reference_entry(track, js.name)
    meta["references"] = refs
    with atomic_write(meta_path, "w") as fh:
        fh.write(json.dumps(meta, indent=1) + "\n")
    return scene.root / REFERENCES_DIR / f"{track.name}.npz"
