"""Video frames for the viewer, and the 2D overlays drawn on them with cv2.

Seeking an mp4 with ``cv2.VideoCapture`` costs tens of milliseconds, so each video is
decoded once, sequentially, in a background thread, into a compact in-memory list of
JPEG-encoded frames downscaled to ``width`` pixels (a few kB each), and cached on disk
under ``SCENE/.mvviz/frames/`` for the next start. A frame request decodes one JPEG
(about a millisecond) through a small LRU cache. ``images/<camera>/<frame:06d>.jpg``
scenes are read lazily instead.

Pixels: OpenCV convention, (u, v) = (column, row); arrays are RGB uint8.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from pipeline.files import save_npz_atomic
from pipeline.scene import Scene

CACHE_VERSION = 1


@dataclass(frozen=True)
class _Source:
    kind: str  # "video" | "images"
    path: Path


class FrameStore:
    """Downscaled RGB frames of every camera of a scene, decoded once.

    Args:
        scene: the scene (its ``videos`` or ``image_dirs``).
        width: stored width in pixels (height keeps the aspect ratio).
        cache_dir: where decoded videos are cached (None: memory only).
        cache_size: decoded frames kept in the LRU.
    """

    def __init__(
        self,
        scene: Scene,
        *,
        width: int = 640,
        cache_dir: Path | None = None,
        cache_size: int = 96,
        jpeg_quality: int = 85,
    ) -> None:
        self.width = int(width)
        self.num_frames = scene.num_frames
        self.cache_dir = cache_dir
        self.jpeg_quality = jpeg_quality
        self.sources: dict[str, _Source] = {}
        for cam in scene.rig.names:
            if cam in scene.videos:
                self.sources[cam] = _Source("video", scene.videos[cam])
            elif cam in scene.image_dirs:
                self.sources[cam] = _Source("images", scene.image_dirs[cam])
        self._jpegs: dict[str, list[bytes | None]] = {}
        self._lru: OrderedDict[tuple, np.ndarray] = OrderedDict()
        self._cache_size = cache_size
        self._lock = threading.Lock()
        self._done = threading.Event()
        self._thread: threading.Thread | None = None
        self.on_camera_ready: list[Callable[[str], None]] = []

    # ------------------------------------------------------------------ decoding

    def start(self) -> FrameStore:
        """Decode every video in a background thread (cached ones load from disk)."""
        videos = [c for c, s in self.sources.items() if s.kind == "video"]
        if not videos:
            self._done.set()
            return self
        self._thread = threading.Thread(
            target=self._decode_all, args=(videos,), name="mvviz-frames", daemon=True
        )
        self._thread.start()
        return self

    def wait(self, timeout: float | None = None) -> bool:
        """Block until every video is decoded; False on timeout."""
        return self._done.wait(timeout)

    @property
    def ready(self) -> bool:
        return self._done.is_set()

    def _decode_all(self, cams: list[str]) -> None:
        try:
            for cam in cams:
                try:
                    frames = self._load_cache(cam)
                    if frames is None:
                        frames = self._decode_video(self.sources[cam].path)
                        self._save_cache(cam, frames)
                except Exception as exc:  # a broken video must not take the viewer down
                    print(f"mvviz view: cannot decode video of camera {cam}: {exc}")
                    frames = []
                with self._lock:
                    self._jpegs[cam] = frames
                for cb in list(self.on_camera_ready):
                    cb(cam)
        finally:
            self._done.set()

    def _decode_video(self, path: Path) -> list[bytes | None]:
        cap = cv2.VideoCapture(str(path))
        if not cap.isOpened():
            raise OSError(f"cannot open {path}")
        out: list[bytes | None] = []
        params = [int(cv2.IMWRITE_JPEG_QUALITY), self.jpeg_quality]
        try:
            while len(out) < self.num_frames:
                ok, bgr = cap.read()
                if not ok:
                    break
                ok, buf = cv2.imencode(".jpg", self._resize(bgr), params)
                out.append(buf.tobytes() if ok else None)
        finally:
            cap.release()
        return out

    def _resize(self, img: np.ndarray) -> np.ndarray:
        h, w = img.shape[:2]
        if w == self.width:
            return img
        size = (self.width, max(1, round(h * self.width / w)))
        return cv2.resize(img, size, interpolation=cv2.INTER_AREA)

    def _cache_path(self, cam: str) -> Path | None:
        return None if self.cache_dir is None else self.cache_dir / f"{cam}_w{self.width}.npz"

    def _stamp(self, cam: str) -> np.ndarray:
        st = self.sources[cam].path.stat()
        return np.array([CACHE_VERSION, st.st_size, st.st_mtime_ns, self.jpeg_quality], np.int64)

    def _load_cache(self, cam: str) -> list[bytes | None] | None:
        path = self._cache_path(cam)
        if path is None or not path.is_file():
            return None
        try:
            with np.load(path) as z:
                if not np.array_equal(z["stamp"], self._stamp(cam)):
                    return None
                data, offsets = z["data"], z["offsets"]
        except (OSError, ValueError, KeyError):
            return None
        blob = data.tobytes()
        return [
            blob[a:b] if b > a else None
            for a, b in zip(offsets[:-1], offsets[1:], strict=True)
        ]

    def _save_cache(self, cam: str, frames: list[bytes | None]) -> None:
        path = self._cache_path(cam)
        if path is None or not frames:
            return
        sizes = [len(f) if f else 0 for f in frames]
        offsets = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
        data = np.frombuffer(b"".join(f or b"" for f in frames), np.uint8)
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            save_npz_atomic(path, data=data, offsets=offsets, stamp=self._stamp(cam))
        except OSError:
            pass  # read-only scene directory: keep the frames in memory only

    # ------------------------------------------------------------------ access

    def frame(self, cam: str, frame: int) -> np.ndarray | None:
        """(h, width, 3) RGB of ``cam`` at ``frame``; None if unavailable (yet)."""
        key = (cam, int(frame))
        with self._lock:
            img = self._lru.get(key)
            if img is not None:
                self._lru.move_to_end(key)
                return img
            src = self.sources.get(cam)
            jpegs = self._jpegs.get(cam)
        if src is None or not 0 <= frame < self.num_frames:
            return None
        if src.kind == "images":
            bgr = cv2.imread(str(src.path / f"{frame:06d}.jpg"), cv2.IMREAD_COLOR)
            if bgr is None:
                return None
            bgr = self._resize(bgr)
        else:
            if jpegs is None or frame >= len(jpegs) or jpegs[frame] is None:
                return None
            bgr = cv2.imdecode(np.frombuffer(jpegs[frame], np.uint8), cv2.IMREAD_COLOR)
        img = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
        with self._lock:
            self._lru[key] = img
            while len(self._lru) > self._cache_size:
                self._lru.popitem(last=False)
        return img

    def thumbnail(self, cam: str, frame: int, width: int = 256) -> np.ndarray | None:
        """The frame downscaled to ``width`` pixels (for a frustum's image plane)."""
        key = (cam, int(frame), width)
        with self._lock:
            img = self._lru.get(key)
        if img is not None:
            return img
        full = self.frame(cam, frame)
        if full is None:
            return None
        h, w = full.shape[:2]
        img = cv2.resize(full, (width, max(1, round(h * width / w))), interpolation=cv2.INTER_AREA)
        with self._lock:
            self._lru[key] = img
            while len(self._lru) > self._cache_size:
                self._lru.popitem(last=False)
        return img

    def available(self, cam: str) -> bool:
        src = self.sources.get(cam)
        if src is None:
            return False
        return src.kind == "images" or bool(self._jpegs.get(cam))


# --------------------------------------------------------------------------- overlays


@dataclass(frozen=True, eq=False)
class Overlay2D:
    """What to draw on one camera's image, in that camera's full-resolution pixels.

    Shapes: n detections, K tracks, P ground-truth people, J / Jg joints.
    """

    camera: str
    image_size: tuple[int, int]  # full-resolution width, height
    detections: np.ndarray  # (n, J, 3) x, y, confidence
    detection_colors: np.ndarray  # (n, 3) uint8
    reprojections: np.ndarray  # (K', J, 2) the filtered tracks of this frame, projected
    reprojection_colors: np.ndarray  # (K', 3) uint8
    gt: np.ndarray  # (P, Jg, 2)
    bones: tuple[tuple[int, int], ...]
    gt_bones: tuple[tuple[int, int], ...]
    label: str


def blank_frame(width: int, height: int) -> np.ndarray:
    """A dark-grey frame for a camera without video."""
    return np.full((height, width, 3), 48, np.uint8)


def _pt(p: np.ndarray) -> tuple[int, int]:
    return int(round(float(p[0]))), int(round(float(p[1])))


def _ok(p: np.ndarray, w: int, h: int) -> bool:
    return bool(np.isfinite(p).all() and -w < p[0] < 2 * w and -h < p[1] < 2 * h)


def draw_overlay(image: np.ndarray, ov: Overlay2D) -> np.ndarray:
    """A copy of ``image`` (any size; overlay pixels are rescaled) with: ground truth
    (thin grey), reprojected filtered joints (hollow circles, track colour), detections
    (filled, person colour, unassigned grey) and the camera name."""
    out = np.ascontiguousarray(image.copy())
    h, w = out.shape[:2]
    s = w / ov.image_size[0]
    aa = cv2.LINE_AA
    r = max(2, round(3 * s * 1.6))
    gt_col = (30, 30, 30)
    for person in ov.gt:
        p = person * s
        for a, b in ov.gt_bones:
            if _ok(p[a], w, h) and _ok(p[b], w, h):
                cv2.line(out, _pt(p[a]), _pt(p[b]), gt_col, 1, aa)
        for q in p:
            if _ok(q, w, h):
                cv2.drawMarker(out, _pt(q), gt_col, cv2.MARKER_CROSS, 2 * r, 1, aa)
    for joints, col in zip(ov.reprojections, ov.reprojection_colors, strict=True):
        p, c = joints * s, tuple(int(x) for x in col)
        for a, b in ov.bones:
            if _ok(p[a], w, h) and _ok(p[b], w, h):
                cv2.line(out, _pt(p[a]), _pt(p[b]), c, 1, aa)
        for q in p:
            if _ok(q, w, h):
                cv2.circle(out, _pt(q), r + 1, c, 1, aa)
    for det, col in zip(ov.detections, ov.detection_colors, strict=True):
        p, c = det[:, :2] * s, tuple(int(x) for x in col)
        vis = det[:, 2] > 0
        for a, b in ov.bones:
            if vis[a] and vis[b] and _ok(p[a], w, h) and _ok(p[b], w, h):
                cv2.line(out, _pt(p[a]), _pt(p[b]), c, 2, aa)
        for j in np.flatnonzero(vis):
            if _ok(p[j], w, h):
                cv2.circle(out, _pt(p[j]), r, c, -1, aa)
    font, scale = cv2.FONT_HERSHEY_SIMPLEX, max(0.4, 0.55 * w / 640)
    (tw, th), _ = cv2.getTextSize(ov.label, font, scale, 1)
    cv2.rectangle(out, (0, 0), (tw + 10, th + 12), (0, 0, 0), -1)
    cv2.putText(out, ov.label, (5, th + 5), font, scale, (255, 255, 255), 1, aa)
    return out
