"""Videos whose frames are not exactly the calibrated image: the mapping from a video's
pixels to its camera's calibrated pixels, and the rule that decides it.

Pixels: OpenCV's (u, v) = (column, row). A video pixel maps to a calibrated pixel as::

    x = scale * u + left,    y = scale * v + top

where ``crop = (left, top, right, bottom)`` are the calibrated pixels the video does not
show at each edge (negative: the video shows that many more, e.g. an encoder's padding)
and ``scale`` = calibrated pixels per video pixel. (No half-pixel term, as everywhere
else in the project where a uniformly scaled video is mapped back: at scale s the
convention differs from pixel-centre alignment by (s - 1) / 2 px.)

The rule (:func:`resolve_video_crop`), for a video of w x h and a calibration of W x H:

1. a crop stated by the user (``mvviz detect --video-crop CAM=LEFT,TOP,RIGHT,BOTTOM``,
   calibrated pixels) is used if what it leaves is a uniform scale of the video;
2. a uniform scale (to within a pixel, ``max(1, s)`` calibrated px) needs no crop;
3. otherwise, when one dimension matches exactly, or at a simple ratio (a resized copy:
   2, 3/2, 4/3..., denominator at most 4), and the other is off by at most
   ``max(16 px, 1 %)`` of the video's size along it (at that scale), the
   difference is taken as an encoder's crop (video smaller) or padding (video larger) at
   the **right or bottom edge**: H.264 codes whole 16 px macroblocks, and its
   frame-cropping (and most re-encoders) cut or pad at the right and bottom. The video's
   top-left pixel is then the calibrated top-left pixel and the principal point does not
   move (0 px shift); this is an assumption, stated in the warning, and a video cut on
   another edge needs rule 1;
4. anything else is a :class:`VideoSizeError` naming the camera, both sizes and the flag.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from fractions import Fraction

import cv2
import numpy as np

MAX_ENCODER_PX = 16  # an H.264 macroblock: the most an encoder pads or crops
MAX_ENCODER_FRACTION = 0.01
MAX_SCALE_DENOMINATOR = 4  # scales of a resized copy: 1, 2, 3/2, 4/3, 5/4 ... not 192/191
FILL = 48  # grey of the calibrated image's area a cropped video does not show (RGB/BGR)


class VideoSizeError(ValueError):
    """A video that is no known mapping of its camera's calibrated image."""


@dataclass(frozen=True)
class VideoCrop:
    """How one camera's video pixels map onto its calibrated pixels (module docstring).

    Attributes:
        camera: camera name.
        video_size: (w, h) video pixels.
        calib_size: (W, H) calibrated pixels.
        scale: calibrated pixels per video pixel.
        crop: (left, top, right, bottom) calibrated pixels not shown at each edge
            (negative = extra pixels shown, padding).
        rule: ``"exact"``, ``"scale"``, ``"encoder"`` (rule 3) or ``"stated"`` (rule 1).
    """

    camera: str
    video_size: tuple[int, int]
    calib_size: tuple[int, int]
    scale: float
    crop: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)
    rule: str = "exact"

    @property
    def offset(self) -> np.ndarray:
        """(2,) calibrated pixels of video pixel (0, 0): (left, top)."""
        return np.array(self.crop[:2], float)

    def to_calibrated(self, uv: np.ndarray) -> np.ndarray:
        """(..., 2) video pixels -> (..., 2) calibrated pixels."""
        return np.asarray(uv, float) * self.scale + self.offset

    def to_video(self, xy: np.ndarray) -> np.ndarray:
        """(..., 2) calibrated pixels -> (..., 2) video pixels."""
        return (np.asarray(xy, float) - self.offset) / self.scale

    def describe(self) -> str:
        """One line: the sizes, the rule and the principal point's shift in video px."""
        (w, h), (W, H) = self.video_size, self.calib_size
        head = f"camera {self.camera}: video {w}x{h}, calibration {W}x{H}"
        if self.rule == "exact":
            return f"{head}: the same"
        if self.rule == "scale":
            return f"{head}: scaled {1 / self.scale:.4g}x, keypoints scaled back"
        shift = -self.offset / self.scale + 0.0  # the principal point's move, video px
        edges = [
            f"{'cropped' if c > 0 else 'padded'} {abs(c):g} px at the {e}"
            for c, e in zip(self.crop, ("left", "top", "right", "bottom"), strict=True)
            if c
        ]
        how = (
            "taken as an encoder's crop/padding at the right/bottom edge (what encoders do)"
            if self.rule == "encoder"
            else "the crop stated with --video-crop"
        )
        text = (
            f"{head}: {how}: {', '.join(edges)} (calibrated px); scale {self.scale:.4g}; "
            f"principal point shift ({shift[0]:+g}, {shift[1]:+g}) px"
        )
        if self.rule == "encoder":
            text += (
                f"; if the video was cut elsewhere, pass "
                f"--video-crop {self.camera}=LEFT,TOP,RIGHT,BOTTOM"
            )
        return text


def _uniform(w: float, h: float, W: float, H: float) -> float | None:
    """Calibrated px per video px if w x h is W x H uniformly scaled (within a pixel)."""
    s = W / w
    return s if abs(h * s - H) <= max(1.0, s) else None


def resolve_video_crop(
    camera: str,
    video_size: tuple[int, int],
    calib_size: tuple[int, int],
    *,
    crop: Sequence[float] | None = None,
    max_px: float = MAX_ENCODER_PX,
    max_fraction: float = MAX_ENCODER_FRACTION,
) -> VideoCrop:
    """The mapping of ``camera``'s video (w, h) onto its calibrated image (W, H), by the
    rule of the module docstring; ``crop`` = (left, top, right, bottom) calibrated px
    stated by the user. A VideoSizeError when no rule applies."""
    (w, h), (W, H) = (int(v) for v in video_size), (int(c) for c in calib_size)
    head = f"camera {camera}: the video is {w}x{h}, the calibration {W}x{H}"
    if min(w, h, W, H) <= 0:
        raise VideoSizeError(f"{head}: sizes must be positive")
    if crop is not None:  # rule 1
        c = tuple(float(x) for x in crop)
        if len(c) != 4:
            raise VideoSizeError(f"camera {camera}: --video-crop needs LEFT,TOP,RIGHT,BOTTOM")
        vis = (W - c[0] - c[2], H - c[1] - c[3])
        s = _uniform(w, h, *vis) if min(vis) > 0 else None
        if s is None:
            raise VideoSizeError(
                f"{head}: the stated crop {c} leaves {vis[0]:g}x{vis[1]:g} calibrated px, "
                "not a uniform scale of the video"
            )
        rule = "exact" if not any(c) and s == 1 else "scale" if not any(c) else "stated"
        return VideoCrop(camera, (w, h), (W, H), s, c, rule)
    s = _uniform(w, h, W, H)  # rule 2
    if s is not None:
        return VideoCrop(camera, (w, h), (W, H), s, rule="exact" if s == 1 else "scale")
    # rule 3: the scale from one dimension, the other padded or cropped at its far edge
    candidates = []
    for axis, (n, N, m, M) in enumerate(((w, W, h, H), (h, H, w, W))):
        ratio = Fraction(M, m)  # the matching dimension gives the scale: a simple one
        if ratio.denominator > MAX_SCALE_DENOMINATOR:
            continue
        s = float(ratio)
        diff = N / s - n  # video px missing (+) or extra (-) along the other one
        if abs(diff) >= 0.5 and abs(diff) <= max(max_px, max_fraction * n):
            candidates.append((ratio != 1, abs(diff), axis, s, diff * s))
    if not candidates:
        raise VideoSizeError(
            f"{head}: not a uniform scale (rotated or cropped?), nor an encoder's crop or "
            f"padding (one dimension off by at most {max_px:g} px or "
            f"{100 * max_fraction:g} %). If the video shows part of the calibrated image, "
            f"state which: mvviz detect --video-crop {camera}=LEFT,TOP,RIGHT,BOTTOM "
            "(calibrated pixels cut from each edge)"
        )
    _, _, axis, s, cut = min(candidates)
    c = (0.0, 0.0, float(cut), 0.0) if axis == 0 else (0.0, 0.0, 0.0, float(cut))
    return VideoCrop(camera, (w, h), (W, H), s, c, "encoder")


def parse_video_crops(specs: Sequence[str]) -> dict[str, tuple[float, float, float, float]]:
    """``["CAM=L,T,R,B", ...]`` -> ``{CAM: (L, T, R, B)}``; a ValueError names a bad spec."""
    out = {}
    for spec in specs:
        cam, sep, rest = spec.partition("=")
        try:
            vals = tuple(float(x) for x in rest.split(","))
        except ValueError:
            vals = ()
        if not sep or not cam or len(vals) != 4:
            raise ValueError(f"--video-crop {spec!r}: expected CAM=LEFT,TOP,RIGHT,BOTTOM")
        if cam in out:
            raise ValueError(f"--video-crop: camera {cam!r} given twice")
        out[cam] = vals
    return out


def to_calibrated_frame(image: np.ndarray, vc: VideoCrop, fill: int = FILL) -> np.ndarray:
    """(h, w, 3) video frame -> the calibrated image at the video's scale, about
    (H / scale, W / scale, 3): the video placed where it belongs, the calibrated area it
    does not show filled with ``fill``, video pixels beyond the calibrated image cut.
    A frame that already is a uniform scale is returned as is."""
    if vc.rule in ("exact", "scale"):
        return image
    h, w = image.shape[:2]
    W, H = vc.calib_size
    left, top = (round(c / vc.scale) for c in vc.crop[:2])
    right = round(W / vc.scale) - w - left
    bottom = round(H / vc.scale) - h - top
    img = image[max(0, -top) : h - max(0, -bottom), max(0, -left) : w - max(0, -right)]
    pads = [max(0, v) for v in (top, bottom, left, right)]
    value = (fill,) * (img.shape[2] if img.ndim == 3 else 1)
    return cv2.copyMakeBorder(img, *pads, cv2.BORDER_CONSTANT, value=value)


class CalibratedFrames:
    """Places one camera's frames on its calibrated image (:func:`to_calibrated_frame`),
    the mapping resolved once per frame size. A size that fits no rule is reported once
    through ``note`` and its frames are returned as they are."""

    def __init__(
        self,
        camera: str,
        calib_size: tuple[int, int],
        *,
        crop: Sequence[float] | None = None,
        note: Callable[[str], None] | None = None,
    ) -> None:
        self.camera, self.calib_size, self.crop = camera, calib_size, crop
        self.note = note
        self.mappings: dict[tuple[int, int], VideoCrop | None] = {}

    def mapping(self, width: int, height: int) -> VideoCrop | None:
        """The mapping of a ``width`` x ``height`` frame (None: it fits no rule)."""
        key = (int(width), int(height))
        if key not in self.mappings:
            try:
                vc = resolve_video_crop(self.camera, key, self.calib_size, crop=self.crop)
                if self.note is not None and vc.rule not in ("exact", "scale"):
                    self.note(vc.describe())
            except (ValueError, TypeError) as exc:
                vc = None
                if self.note is not None:
                    self.note(f"{exc}; its frames are shown as they are")
            self.mappings[key] = vc
        return self.mappings[key]

    def __call__(self, image: np.ndarray) -> np.ndarray:
        """(h, w, 3) frame -> the frame on the calibrated image (see the class docstring)."""
        vc = self.mapping(image.shape[1], image.shape[0])
        return image if vc is None else to_calibrated_frame(image, vc)
