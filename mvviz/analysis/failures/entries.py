"""A failure entry (:class:`Failure`), how entries name where they apply, and the
thresholds of the criteria (millimetres and pixels, as in the results)."""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import numpy as np

from pipeline.data.joint_sets import get_joint_set
from pipeline.evaluation.metrics import MATCH_GATE_MM  # noqa: F401  (re-exported)
from pipeline.results.store import PipelineResults

CRITERIA = (
    "reprojection", "mpjpe", "association", "id", "kalman", "proportions", "smpl", "labels",
    "protocol",
)  # fmt: skip
MAHALANOBIS_THRESHOLD = 3.0
# "close to two": a detection whose mean affinity to another person's detections reaches
# AFFINITY_THRESHOLD and comes within CLOSE_MARGIN of its mean affinity to its own person's
# (one pair alone says little: two rays from different cameras pass near each other without
# their people being near, which on a 31-camera dome made ~190 such pairs a frame).
AFFINITY_THRESHOLD = 0.5
CLOSE_MARGIN = 0.2
UNASSIGNED_CONFIDENCE = 0.3  # mean joint confidence of an unassigned detection worth a look
LIMIT_SCALE_DEG = 10.0
SWITCH_SCORE = 3.0
# A measure this many times its usual level (the run's median for that joint and camera)
# is a problem worth listing; entries rank by the ratio, so no list fills up at a limit.
RELATIVE_LEVEL = 2.0
USUAL_FLOOR_PX = 1.0  # usual reprojection errors below this count as 1 px
RESIDUAL_FLOOR_MM = 10.0
MERGE_GAP = 2  # entries of one problem this many frames apart (or fewer) merge
# What one problem is, beyond its kind and track: these criteria merge frames whichever
# joint (Kalman, MPJPE: the track is off) or camera (reprojection: the 3D joint is off,
# so every view shows it) is worst frame by frame, and name the worst frame's.
MERGE_IGNORES = {"kalman": ("joint",), "mpjpe": ("joint",), "reprojection": ("view",)}


@dataclass(frozen=True)
class Failure:
    """One problem to look at, over a span of frames ``first..last`` (inclusive) of which
    ``frames`` show it; ``frame`` is the worst of them (where a jump goes). ``joint``
    indexes the results' joint set, ``view`` the rig. ``score`` ranks entries within a
    criterion; ``value`` is the measure itself at ``frame`` (px, mm, Mahalanobis ...).
    ``where`` names track, joint and camera (``"track 2 · left_wrist · cam03"``),
    ``detail`` the measure; ``kind`` groups entries within a criterion for the counts.
    """

    criterion: str
    score: float
    frame: int
    track: int | None
    joint: int | None
    view: int | None
    where: str = ""
    detail: str = ""
    kind: str = ""
    first: int = -1  # -1: ``frame``
    last: int = -1
    frames: int = 1
    value: float = math.nan

    def __post_init__(self) -> None:
        if self.first < 0:
            object.__setattr__(self, "first", self.frame)
        if self.last < 0:
            object.__setattr__(self, "last", self.frame)

    @property
    def span(self) -> str:
        """``"f 12"`` or ``"f 140–172"``."""
        return f"f {self.first}" if self.first == self.last else f"f {self.first}–{self.last}"

    @property
    def head(self) -> str:
        """Short enough for a button: the span and the track (else the camera)."""
        who = f"track {self.track}" if self.track is not None else ""
        if not who and self.view is not None:
            who = self.where.split(" · ")[-1] if self.where else ""
        return f"{self.span} · {who}" if who else self.span

    @property
    def text(self) -> str:
        """The whole entry on one line, e.g.
        ``"f 140–152 · track 2 · left_wrist · cam03 · 19.5 px, 4.1× its usual 4.8 px
        (13 frames, worst f 147)"``."""
        parts = [self.span] + [p for p in (self.where, self.detail) if p]
        out = " · ".join(parts)
        if self.first != self.last:
            n = f"{self.frames} frames" if self.frames != self.last - self.first + 1 else ""
            n = n or f"{self.last - self.first + 1} frames"
            out += f" ({n}, worst f {self.frame})"
        return out


def camera_label(name: str) -> str:
    """A camera as the lists name it: ``"cam03"`` as it is, ``"3"`` as ``"cam 3"``."""
    return name if name.lower().startswith(("cam", "view")) else f"cam {name}"


def where_label(track: int | None = None, joint: str | None = None, view: str | None = None) -> str:
    """``"track 2 · left_wrist · cam03"``, leaving out what is None (``view``: a camera name)."""
    parts = [] if track is None else [f"track {track}"]
    parts += [] if joint is None else [joint]
    parts += [] if view is None else [camera_label(view)]
    return " · ".join(parts)


def label(
    frame: int,
    track: int | None = None,
    joint: str | None = None,
    view: str | None = None,
    detail: str = "",
) -> str:
    """``"f 12 · track 2 · left_wrist · cam03 · detail"``, leaving out what is None."""
    return " · ".join(p for p in (f"f {frame}", where_label(track, joint, view), detail) if p)


def usual_level(values: np.ndarray, axis: int = 0, *, floor: float) -> np.ndarray:
    """The median of ``values`` along ``axis`` (NaN ignored), at least ``floor``; where a
    slice has no finite value, the median of all of them."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN slices
        med = np.nanmedian(values, axis=axis)
        overall = np.nanmedian(values) if np.isfinite(values).any() else floor
    return np.maximum(np.where(np.isfinite(med), med, overall), floor)


# --------------------------------------------------------------------------- criteria


def track_or_none(track: int) -> int | None:
    return int(track) if track >= 0 else None


def joint_names(results: PipelineResults) -> tuple[str, ...]:
    return get_joint_set(results.joint_set).names


def present(results: PipelineResults) -> np.ndarray:
    """(K, F) bool: the track has a raw triangulated joint in the frame."""
    return np.isfinite(results.track_raw).all(-1).any(-1)
