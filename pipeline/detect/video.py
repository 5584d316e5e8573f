"""Videos in, detections out: reading videos, matching them to a scene's cameras, and
resumable multi-person BlazePose detection over a scene (``mvviz detect``).

Scene frame ``k`` is video frame ``k * every`` of every camera (``every`` = 1 unless
asked), so the written scene's fps is the videos' fps / ``every`` and the videos copied
into ``SCENE/videos/`` are re-encoded to match when ``every`` > 1.

Resumable: each camera's rows are cached in ``SCENE/.mvviz/detect/<camera>.npz`` every
:data:`CACHE_EVERY` frames (atomically), keyed by the settings, the models and the
video; a rerun skips the frames done. ``detections.npz`` and ``scene.json`` are written
only at the end, atomically.

Pixels: OpenCV convention; keypoints are stored in the calibration's pixels: a video
that is a uniformly scaled copy of the calibrated image is scaled back, one that an
encoder cropped or padded by a few pixels at the right/bottom edge, or whose crop the
user states (``--video-crop``), is mapped by :mod:`pipeline.detect.video_crop`; the crop is
recorded in ``scene.json`` (``video_crop``) for the viewer.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import shutil
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np

from pipeline.core.files import (
    CACHE_DIR,
    SceneFormatError,
    atomic_write,
    load_npz,
    save_npz_atomic,
)
from pipeline.core.progress import StageBar
from pipeline.data.cameras import CameraRig, load_cameras
from pipeline.data.joint_sets import BLAZEPOSE33, COCO17, convert_keypoints
from pipeline.data.scene import check_detections
from pipeline.detect.blazepose import (
    DETECTOR_FILE,
    LANDMARK_FILE,
    MODEL_DIR,
    NUM_LANDMARKS,
    BlazePose,
    Rois,
    mono_joints_smpl24,
    square_bbox,
)
from pipeline.detect.video_crop import VideoCrop, resolve_video_crop
from pipeline.stages.restore import fit_weak_perspective

VIDEO_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv", ".m4v", ".webm")
CACHE_EVERY = 50
CACHE_VERSION = 1


# --------------------------------------------------------------------------- videos


@dataclass(frozen=True)
class VideoInfo:
    """A readable video: frame count as the container reports it, fps, and the size of
    its decoded frames (after any rotation metadata OpenCV applies)."""

    path: Path
    num_frames: int
    fps: float
    width: int
    height: int


def probe_video(path: str | os.PathLike) -> VideoInfo:
    """Open ``path``, decode its first frame, and read its frame count and fps."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"video {path} not found")
    cap = cv2.VideoCapture(str(path))
    try:
        ok, frame = cap.read() if cap.isOpened() else (False, None)
        if not ok:
            raise SceneFormatError(path, None, "cannot decode a frame (not a video OpenCV reads?)")
        n = int(round(cap.get(cv2.CAP_PROP_FRAME_COUNT)))
        fps = float(cap.get(cv2.CAP_PROP_FPS) or 0.0)
    finally:
        cap.release()
    return VideoInfo(
        path=path,
        num_frames=max(n, 1),
        fps=fps if fps > 0 else 25.0,
        width=frame.shape[1],
        height=frame.shape[0],
    )


def iter_frames(
    path: str | os.PathLike, *, start: int = 0, stop: int | None = None, step: int = 1
) -> Iterator[tuple[int, np.ndarray]]:
    """Yield ``(video frame index, RGB uint8 (H, W, 3) image)`` for frames ``start``,
    ``start + step``, ... before ``stop``, reading sequentially (skipped frames are
    grabbed, not converted). Stops early, silently, where the video ends."""
    cap = cv2.VideoCapture(str(path))
    if not cap.isOpened():
        raise SceneFormatError(path, None, "cannot open the video")
    try:
        index = 0
        while stop is None or index < stop:
            wanted = index >= start and (index - start) % step == 0
            if wanted:
                ok, bgr = cap.read()
                if not ok:
                    return
                yield index, cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
            elif not cap.grab():
                return
            index += 1
    finally:
        cap.release()


def find_videos(specs: list[str | os.PathLike]) -> list[Path]:
    """Video files named by ``specs``: files as given, directories by their video files
    (``VIDEO_SUFFIXES``)."""
    out: list[Path] = []
    for spec in specs:
        p = Path(spec)
        if p.is_dir():
            out += sorted(q for q in p.iterdir() if q.suffix.lower() in VIDEO_SUFFIXES)
        elif p.is_file():
            out.append(p)
        else:
            raise FileNotFoundError(f"--videos: {p} is neither a file nor a directory")
    if not out:
        raise FileNotFoundError(f"no video files ({', '.join(VIDEO_SUFFIXES)}) in {specs}")
    return out


@dataclass(frozen=True)
class VideoMatch:
    """Videos matched to cameras by name (file stem == camera name)."""

    videos: dict[str, Path]
    missing_cameras: list[str]
    unmatched_videos: list[Path]


def match_videos(camera_names: list[str], paths: list[Path]) -> VideoMatch:
    stems: dict[str, Path] = {}
    for p in paths:
        if p.stem in stems:
            raise ValueError(f"two videos for camera {p.stem!r}: {stems[p.stem]} and {p}")
        stems[p.stem] = p
    return VideoMatch(
        videos={c: stems[c] for c in camera_names if c in stems},
        missing_cameras=[c for c in camera_names if c not in stems],
        unmatched_videos=[p for s, p in stems.items() if s not in camera_names],
    )


def image_scale(video: VideoInfo, width: int, height: int) -> float:
    """Factor from video pixels to calibration pixels; a ValueError unless the video is the
    calibrated image uniformly scaled (to within a pixel). :func:`video_crop` also takes
    encoders' crops and stated ones."""
    size = (video.width, video.height)
    return resolve_video_crop(
        video.path.stem, size, (width, height), max_px=0, max_fraction=0
    ).scale


def video_crop(camera: str, video: VideoInfo, width: int, height: int, crop=None) -> VideoCrop:
    """How ``camera``'s video maps onto its calibrated ``width`` x ``height`` pixels
    (:func:`pipeline.detect.video_crop.resolve_video_crop`; ``crop`` = the user's LEFT, TOP,
    RIGHT, BOTTOM); the VideoSizeError (a ValueError) also names the video file."""
    try:
        return resolve_video_crop(camera, (video.width, video.height), (width, height), crop=crop)
    except ValueError as exc:
        raise type(exc)(f"{video.path.name}: {exc}") from None


# --------------------------------------------------------------------------- detection


@dataclass(frozen=True)
class DetectSettings:
    """What ``mvviz detect`` runs; everything but ``max_frames`` keys the cache."""

    every: int = 1
    max_people: int | None = None
    max_frames: int | None = None
    min_score: float = 0.5
    min_presence: float = 0.5
    tiles: int = 2
    num_threads: int | None = None

    def make_detector(self, model_dir: Path = MODEL_DIR) -> BlazePose:
        return BlazePose(
            model_dir,
            num_threads=self.num_threads,
            min_score=self.min_score,
            min_presence=self.min_presence,
            max_people=self.max_people,
            tiles=self.tiles,
        )


def model_digest(model_dir: Path = MODEL_DIR) -> str:
    """sha256 of the two model files, short."""
    h = hashlib.sha256()
    for name in (DETECTOR_FILE, LANDMARK_FILE):
        h.update((Path(model_dir) / name).read_bytes())
    return h.hexdigest()[:16]


def cache_key(settings: DetectSettings, video: VideoInfo, models: str) -> str:
    """What a camera's cached rows depend on, as a JSON string."""
    s = asdict(settings)
    s.pop("max_frames")
    s.pop("num_threads")
    s.update(
        cache_version=CACHE_VERSION,
        models=models,
        video=video.path.name,
        video_bytes=video.path.stat().st_size,
        video_frames=video.num_frames,
    )
    return json.dumps(s, sort_keys=True)


@dataclass(frozen=True, eq=False)
class CameraPoses:
    """BlazePose rows of one camera, in the video's pixels.

    Attributes:
        frame: (R,) scene frame of each row.
        keypoints: (R, 33, 3) x px, y px, confidence; world: (R, 33, 3) metres, camera axes.
        score: (R,) detector score; presence: (R,) landmark pose presence.
        rois: (R, 4) crop centre x, y, side, angle (see ``blazepose.Rois``).
        done: (D,) scene frames processed (with or without people).
    """

    frame: np.ndarray
    keypoints: np.ndarray
    world: np.ndarray
    score: np.ndarray
    presence: np.ndarray
    rois: np.ndarray
    done: np.ndarray

    @staticmethod
    def empty() -> CameraPoses:
        z = np.zeros(0)
        return CameraPoses(
            frame=np.zeros(0, np.int64),
            keypoints=np.zeros((0, NUM_LANDMARKS, 3)),
            world=np.zeros((0, NUM_LANDMARKS, 3)),
            score=z,
            presence=z,
            rois=np.zeros((0, 4)),
            done=np.zeros(0, np.int64),
        )

    def arrays(self) -> dict[str, np.ndarray]:
        return {k: getattr(self, k) for k in self.__dataclass_fields__}


def _load_cache(path: Path, key: str, log: Callable[[str], None]) -> CameraPoses:
    if not path.is_file():
        return CameraPoses.empty()
    try:
        arrays = load_npz(path)
        if str(arrays.pop("key")) != key:
            log(f"  {path.name}: cached rows were made with other settings or video; starting over")
            return CameraPoses.empty()
        return CameraPoses(**arrays)
    except (SceneFormatError, KeyError, TypeError) as exc:
        log(f"  {path.name}: unreadable cache ({exc}); starting over")
        return CameraPoses.empty()


def _save_cache(path: Path, key: str, rows: list[dict], done: list[int]) -> None:
    cp = _stack_rows(rows, done)
    save_npz_atomic(path, key=np.array(key), **cp.arrays())


def _stack_rows(rows: list[dict], done: list[int]) -> CameraPoses:
    if not rows:
        rows = [CameraPoses.empty().arrays()]
    return CameraPoses(
        frame=np.concatenate([r["frame"] for r in rows]).astype(np.int64),
        keypoints=np.concatenate([r["keypoints"] for r in rows]),
        world=np.concatenate([r["world"] for r in rows]),
        score=np.concatenate([r["score"] for r in rows]),
        presence=np.concatenate([r["presence"] for r in rows]),
        rois=np.concatenate([r["rois"] for r in rows]),
        done=np.asarray(sorted(done), np.int64),
    )


def detect_camera(
    detector: BlazePose,
    video: VideoInfo,
    *,
    num_frames: int,
    every: int,
    cache_path: Path,
    key: str,
    progress: bool = True,
    desc: str = "",
    log: Callable[[str], None] = print,
) -> CameraPoses:
    """Run ``detector`` on scene frames ``0 .. num_frames - 1`` (video frame ``k * every``)
    of one video, resuming from and updating the cache at ``cache_path``."""
    cached = _load_cache(cache_path, key, log)
    done = set(int(f) for f in cached.done)
    rows = [] if len(cached.done) == 0 else [cached.arrays()]
    todo = [k for k in range(num_frames) if k not in done]
    if done and todo:
        log(f"  {desc}: resuming, {len(done & set(range(num_frames)))} frames cached")
    since_save = 0
    with StageBar(desc, num_frames, progress, unit="frame", initial=num_frames - len(todo)) as bar:
        if todo:
            start = todo[0] * every
            for index, image in iter_frames(
                video.path, start=start, stop=num_frames * every, step=every
            ):
                k = index // every
                if k in done:
                    continue
                poses = detector(image)
                rows.append(
                    {
                        "frame": np.full(len(poses), k),
                        "keypoints": poses.keypoints,
                        "world": poses.world,
                        "score": poses.score,
                        "presence": poses.presence,
                        "rois": poses.rois.array(),
                    }
                )
                done.add(k)
                bar.update(1)
                since_save += 1
                if since_save >= CACHE_EVERY:
                    _save_cache(cache_path, key, rows, sorted(done))
                    since_save = 0
        _save_cache(cache_path, key, rows, sorted(done))
    out = _stack_rows(rows, sorted(done))
    keep = out.frame < num_frames
    return CameraPoses(
        frame=out.frame[keep],
        keypoints=out.keypoints[keep],
        world=out.world[keep],
        score=out.score[keep],
        presence=out.presence[keep],
        rois=out.rois[keep],
        done=out.done[out.done < num_frames],
    )


def detection_columns(
    poses: CameraPoses, view: int, scale: float, *, offset: tuple[float, float] = (0.0, 0.0)
) -> dict[str, np.ndarray]:
    """One camera's rows as ``detections.npz`` columns, in calibration pixels: video pixel
    ``uv`` is ``scale * uv + offset`` (a :class:`~pipeline.detect.video_crop.VideoCrop`).

    ``keypoints`` are COCO-17; ``blazepose_keypoints`` / ``blazepose_world`` keep all 33
    landmarks; ``mono_joints3d`` (SMPL-24, metres, camera axes) with ``cam_weak`` fitted
    by least squares so that the world landmarks project onto the 2D landmarks (weights:
    their confidence) in ``bbox``, the ROI's axis-aligned square.
    """
    kp33 = poses.keypoints.copy()
    kp33[..., :2] = kp33[..., :2] * scale + np.asarray(offset, float)
    rois = Rois.from_array(poses.rois)
    centre = rois.centre * scale + np.asarray(offset, float)
    rois = Rois(centre=centre, size=rois.size * scale, angle=rois.angle)
    bbox = square_bbox(rois)
    if len(poses.frame):
        cam = fit_weak_perspective(poses.world, kp33[..., :2], bbox, kp33[..., 2])
    else:
        cam = np.zeros((0, 3))
    return {
        "frame": poses.frame.astype(np.int64),
        "view": np.full(len(poses.frame), view, np.int64),
        "keypoints": convert_keypoints(kp33, BLAZEPOSE33, COCO17),
        "mono_joints3d": mono_joints_smpl24(poses.world),
        "cam_weak": cam,
        "bbox": bbox,
        "blazepose_keypoints": kp33,
        "blazepose_world": poses.world,
        "person_score": poses.score,
    }


# --------------------------------------------------------------------------- scene


@dataclass(frozen=True)
class DetectReport:
    """What :func:`detect_scene` did."""

    scene_dir: Path
    num_frames: int
    fps: float
    rows_per_camera: dict[str, int]
    frames_with_people: dict[str, int]


def write_viewer_video(
    video: VideoInfo, out: Path, *, num_frames: int, every: int, fps: float, scale: float = 1.0
) -> None:
    """``out`` = frames 0, every, ... of ``video`` (``num_frames`` of them), atomically: a
    plain copy when nothing changes, else re-encoded (mp4v) at ``scale``."""
    out.parent.mkdir(parents=True, exist_ok=True)
    if out.exists() and out.resolve() == video.path.resolve():
        return
    if every == 1 and scale == 1.0 and video.path.suffix.lower() == ".mp4":
        with atomic_write(out) as fh, open(video.path, "rb") as src:
            shutil.copyfileobj(src, fh)
        return
    size = (
        max(2, int(round(video.width * scale)) // 2 * 2),
        max(2, int(round(video.height * scale)) // 2 * 2),
    )
    tmp = out.with_name(f".{out.stem}.tmp{os.getpid()}.mp4")
    writer = cv2.VideoWriter(str(tmp), cv2.VideoWriter_fourcc(*"mp4v"), fps, size)
    if not writer.isOpened():
        raise RuntimeError(f"cannot open a video writer for {out}")
    try:
        for _, rgb in iter_frames(video.path, stop=num_frames * every, step=every):
            bgr = cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)
            if bgr.shape[1::-1] != size:
                bgr = cv2.resize(bgr, size, interpolation=cv2.INTER_AREA)
            writer.write(bgr)
        writer.release()
        os.replace(tmp, out)
    finally:
        writer.release()
        if tmp.exists():
            tmp.unlink()


def _read_meta(scene_dir: Path) -> dict:
    meta_path = scene_dir / "scene.json"
    if not meta_path.is_file():
        return {}
    try:
        meta = json.loads(meta_path.read_text())
    except json.JSONDecodeError as exc:
        raise SceneFormatError(meta_path, None, f"not valid JSON ({exc})") from exc
    if not isinstance(meta, dict):
        raise SceneFormatError(meta_path, None, "expected a JSON object")
    return meta


def _videos_and_crops(
    rig: CameraRig,
    video_specs: list[str | os.PathLike],
    video_crops: dict[str, tuple[float, float, float, float]] | None,
    log: Callable[[str], None],
) -> tuple[dict[str, VideoInfo], dict[str, VideoCrop]]:
    """1a. The videos named after the rig's cameras, probed, and how each maps onto its
    camera's calibrated image."""
    match = match_videos(rig.names, find_videos(list(video_specs)))
    if match.unmatched_videos:
        log(
            "ignored videos with no camera of that name: "
            f"{[p.name for p in match.unmatched_videos]}"
        )
    if not match.videos:
        raise FileNotFoundError(
            f"no video is named after a camera ({rig.names}); name them <camera>.mp4"
        )
    if match.missing_cameras:
        log(f"cameras without a video (no detections in those views): {match.missing_cameras}")
    infos = {c: probe_video(p) for c, p in match.videos.items()}
    video_crops = dict(video_crops or {})
    unknown = sorted(set(video_crops) - set(rig.names))
    if unknown:
        raise ValueError(f"--video-crop names cameras not in the calibration: {unknown}")
    crops = {
        c: video_crop(
            c, v, rig[rig.index_of(c)].width, rig[rig.index_of(c)].height, video_crops.get(c)
        )
        for c, v in infos.items()
    }
    for c, vc in crops.items():
        if vc.rule == "scale":
            log(f"video {infos[c].path.name}: {vc.describe()}")
        elif vc.rule != "exact":
            log(f"warning: video {infos[c].path.name}: {vc.describe()}")
    return infos, crops


def _frame_plan(
    infos: dict[str, VideoInfo], settings: DetectSettings, log: Callable[[str], None]
) -> tuple[int, float, dict[str, int]]:
    """1b. The scene's frame count and rate (the common length, every ``settings.every``-th
    frame, at most ``settings.max_frames``) and each video's frame count."""
    counts = {c: v.num_frames for c, v in infos.items()}
    common = min(counts.values())
    if len(set(counts.values())) > 1:
        log(
            f"frame counts differ between cameras: {counts}; "
            f"using the common length, {common} frames"
        )
    fps_all = {c: round(v.fps, 3) for c, v in infos.items()}
    if len(set(fps_all.values())) > 1:
        log(f"frame rates differ between cameras: {fps_all}; the scene uses the first")
    video_fps = next(iter(infos.values())).fps
    num_frames = math.ceil(common / settings.every)
    if settings.max_frames is not None and settings.max_frames < num_frames:
        num_frames = settings.max_frames
    fps = video_fps / settings.every
    log(
        f"{len(infos)} cameras, {num_frames} frames at {fps:.3g} fps"
        + (f" (every {settings.every}th video frame)" if settings.every > 1 else "")
    )
    return num_frames, fps, counts


def _detect_cameras(
    detector: BlazePose,
    rig: CameraRig,
    infos: dict[str, VideoInfo],
    crops: dict[str, VideoCrop],
    *,
    num_frames: int,
    settings: DetectSettings,
    cache_dir: Path,
    models: str,
    progress: bool,
    log: Callable[[str], None],
) -> tuple[dict[str, np.ndarray], dict[str, int], dict[str, int]]:
    """2. Detection, camera by camera, resumable: the detection columns of all cameras,
    and per camera its rows and frames with people."""
    columns, rows_per, with_people = [], {}, {}
    for cam, info in infos.items():
        poses = detect_camera(
            detector,
            info,
            num_frames=num_frames,
            every=settings.every,
            cache_path=cache_dir / f"{cam}.npz",
            key=cache_key(settings, info, models),
            progress=progress,
            desc=cam,
            log=log,
        )
        short = num_frames - len(poses.done)
        if short:
            log(f"  {cam}: the video ended {short} frames early; those frames have no detections")
        vc = crops[cam]
        columns.append(
            detection_columns(poses, rig.index_of(cam), vc.scale, offset=tuple(vc.offset))
        )
        rows_per[cam] = len(poses.frame)
        with_people[cam] = int(np.unique(poses.frame).size)
    arrays = {k: np.concatenate([c[k] for c in columns]) for k in columns[0]}
    return arrays, rows_per, with_people


def _updated_meta(
    meta: dict,
    scene_dir: Path,
    det_path: Path,
    *,
    num_frames: int,
    fps: float,
    counts: dict[str, int],
    infos: dict[str, VideoInfo],
    crops: dict[str, VideoCrop],
    settings: DetectSettings,
    models: str,
    log: Callable[[str], None],
) -> dict:
    """3. ``scene.json`` updated for the new detections (``meta`` is changed in place)."""
    old_frames = meta.get("num_frames")
    if meta.get("gt") and old_frames not in (None, num_frames):
        log(f"scene.json had num_frames {old_frames} (ground truth kept); now {num_frames}")
    meta.setdefault("name", scene_dir.resolve().name)
    meta.update(
        fps=float(fps),
        units="mm",
        joint_set=COCO17.name,
        num_frames=int(num_frames),
        cameras=meta.get("cameras", "cameras.json"),
        detections=det_path.name,
        videos="videos",
        detect={
            "detector": "blazepose (pose_detection + pose_landmark_full, mediapipe 0.10.21)",
            "models_sha256_16": models,
            "every": settings.every,
            "max_people": settings.max_people,
            "min_score": settings.min_score,
            "min_presence": settings.min_presence,
            "tiles": settings.tiles,
            "source_videos": {c: str(v.path) for c, v in infos.items()},
            "video_frames": counts,
            "video_mapping": {c: vc.describe() for c, vc in crops.items() if vc.rule != "exact"},
        },
    )
    cropped = {c: list(vc.crop) for c, vc in crops.items() if any(vc.crop)}
    meta.pop("video_crop", None)
    if cropped:  # calibrated px each video does not show: the viewer places frames by it
        meta["video_crop"] = cropped
    return meta


def _holds_no_detections(path: Path) -> bool:
    """``path`` is a detections file with no rows (what ``mvviz convert`` of a calibration
    alone writes): room to fill, not results to protect."""
    try:
        with np.load(path) as arrays:
            return "frame" in arrays.files and arrays["frame"].shape == (0,)
    except (OSError, ValueError):
        return False  # unreadable: not ours to replace without --overwrite


def detect_scene(
    scene_dir: str | os.PathLike,
    video_specs: list[str | os.PathLike],
    *,
    settings: DetectSettings = DetectSettings(),
    overwrite: bool = False,
    video_scale: float = 1.0,
    progress: bool = True,
    log: Callable[[str], None] = print,
    detector: BlazePose | None = None,
    video_crops: dict[str, tuple[float, float, float, float]] | None = None,
) -> DetectReport:
    """Detect people in every camera's video and write the scene's detections.

    ``scene_dir`` needs ``cameras.json`` (or the file ``scene.json`` names); ``scene.json``
    is created or updated (joint_set coco17, fps, num_frames, videos), ``detections.npz``
    written, ``videos/<camera>.mp4`` copied or re-encoded; all atomically, at the end.
    ``video_crops`` (camera -> LEFT, TOP, RIGHT, BOTTOM calibrated px) states how a video
    was cut from the calibrated image (see :mod:`pipeline.detect.video_crop`).
    """
    scene_dir = Path(scene_dir)
    meta = _read_meta(scene_dir)
    rig: CameraRig = load_cameras(scene_dir / meta.get("cameras", "cameras.json"))
    det_path = scene_dir / meta.get("detections", "detections.npz")
    if det_path.exists() and not overwrite and not _holds_no_detections(det_path):
        raise FileExistsError(f"{det_path} exists (pass --overwrite to replace it)")
    if settings.every < 1:
        raise ValueError(f"--every must be >= 1, got {settings.every}")
    # 1. videos <-> cameras, sizes and lengths
    infos, crops = _videos_and_crops(rig, video_specs, video_crops, log)
    num_frames, fps, counts = _frame_plan(infos, settings, log)
    # 2. detection, camera by camera, resumable
    detector = detector or settings.make_detector()
    models = model_digest()
    arrays, rows_per, with_people = _detect_cameras(
        detector, rig, infos, crops, num_frames=num_frames,
        settings=settings, cache_dir=scene_dir / CACHE_DIR / "detect", models=models,
        progress=progress, log=log,
    )  # fmt: skip
    check_detections(arrays, source=det_path, num_joints=COCO17.num_joints, num_views=len(rig))
    # 3. the viewer's videos, the detections, then scene.json (which points to both)
    for cam, info in infos.items():
        write_viewer_video(
            info,
            scene_dir / "videos" / f"{cam}.mp4",
            num_frames=num_frames,
            every=settings.every,
            fps=fps,
            scale=video_scale,
        )
    save_npz_atomic(det_path, **arrays)
    meta = _updated_meta(
        meta, scene_dir, det_path, num_frames=num_frames, fps=fps, counts=counts, infos=infos,
        crops=crops, settings=settings, models=models, log=log,
    )  # fmt: skip
    with atomic_write(scene_dir / "scene.json", "w") as fh:
        fh.write(json.dumps(meta, indent=1) + "\n")
    return DetectReport(
        scene_dir=scene_dir,
        num_frames=num_frames,
        fps=fps,
        rows_per_camera=rows_per,
        frames_with_people=with_people,
    )
