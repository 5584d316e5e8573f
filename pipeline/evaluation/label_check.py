"""Label check: do the triangulated bodies say their keypoint labels are right?

A joint order read in the wrong layout (OpenPose BODY_25B read as BODY_25: same
keypoint count, another order) or one camera's (one detector's) left and right swapped
still triangulates to *something*; nothing else in the pipeline complains. Bodies do:
their left shoulder and left hip are on the same side, the nose is ahead of the torso,
the left and right thigh are as long, a thigh is about as long as a shin, knees bend
backwards. Every check here is a pure function of the 3D joints (and, for cameras, of
the 2D they were triangulated from), by joint *name*, so it works for any
:class:`~pipeline.data.joint_sets.JointSet` that has the joints a check needs (a check whose
joints a set lacks is skipped and not listed in :attr:`LabelCheck.checked`).
The measures themselves (body axes, facing offsets, hinge angles, bone lengths) are
in :mod:`pipeline.body.measures`.

Checks (kinds of :class:`LabelFinding`), per track and pooled over the scene:

=================  ===========================================================  ========
kind               measured value                                               flagged
=================  ===========================================================  ========
``left_right``     fraction of frames whose shoulders' and hips' left-right     > 0.2
                   axes (horizontal parts) point to opposite sides
``facing``         fraction of frames whose head (nose ahead of the shoulders,  > 0.3
                   eyes ahead of the ears) and feet (toes ahead of the heels)
                   say the body faces the other way than its torso
``symmetry``       worst relative left/right difference of a limb's median      > 0.25
                   length (upper arm, forearm, thigh, shin, flank, foot)
``proportion``     a ratio of median lengths outside anatomical bounds          bounds
                   (:data:`RATIOS`: thigh/shin, upper arm/forearm, shoulder/hip
                   width, leg/arm)
``stability``      worst robust spread of a bone's length over frames           > 0.25
                   (1.4826 MAD / median)
``knee_hinge``     fraction of knee-frames bent backwards (shank ahead of the   > 0.15
                   thigh line) by more than 25 deg
``elbow_hinge``    fraction of elbow-frames bent backwards (forearm behind the  > 0.35
                   upper arm) by more than 45 deg
``camera_mirror``  per camera: fraction of its associated people whose 2D fits  > 0.5
                   the reprojection of the mirrored 3D joints better
=================  ===========================================================  ========

The thresholds (:class:`LabelCheckParams`) come from anatomy and sit well above what
the shipped correct scenes measure (raw tracks of sample_data/shelf_synth,
shelf_synth_noisy and the real-video pose2sim_demo; the worst track of the three,
asserted by ``tests/pipeline/test_label_check.py``): ``left_right`` 0.064,
``facing`` 0.043, ``symmetry`` 0.083, ``stability`` 0.17 (noisy synthetic 2D),
``knee_hinge`` 0.021, ``elbow_hinge`` 0.037, ``camera_mirror`` 0.066 (pose2sim cam03);
ratios thigh/shin 0.96-1.04, upper arm/forearm 1.03-1.11, shoulder/hip width
1.41-1.88, leg/arm 1.36-1.59. What breaks them: a whole track mirrored reads
``facing`` 1.0 and ``knee_hinge`` 0.3-0.35; BODY_25B read as BODY_25 reads
``left_right`` 0.8-0.97, ``facing`` 0.95-0.98, forearm ``symmetry`` ~1, shoulder/hip
width 0.5-0.8; one of five cameras mirrored reads ``camera_mirror`` 0.8-0.9 there.

A track is judged once it has :attr:`LabelCheckParams.min_frames` scored frames (short
ghost tracks are not); a scene-level finding (``track is None``) is the measure pooled
over the judged tracks (fractions: over all their frames; lengths: the median over
tracks), which is what a joint-order mix-up breaks for everyone at once.

Conventions: world millimetres, z up; pixels; degrees. NaN marks a missing joint.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from pipeline.body.measures import (
    LIMBS,
    SIDES,
    body_axes,
    bone_lengths,
    dot,
    facing_offsets,
    hinge_angles,
    joint_pair,
    nanmean_last,
)
from pipeline.data.cameras import Camera
from pipeline.data.joint_sets import JointSet, get_joint_set
from pipeline.results.store import PipelineResults

KINDS = (
    "left_right",
    "facing",
    "symmetry",
    "proportion",
    "stability",
    "knee_hinge",
    "elbow_hinge",
    "camera_mirror",
)
# Scene-wide findings of these kinds point at the joint order, not at one body.
ORDER_KINDS = ("left_right", "symmetry", "proportion")
# Plausible ratios of median lengths: (name, numerator parts, denominator parts, low,
# high). A part is a limb of LIMBS (mean of both sides) or a width ("shoulder_width",
# "hip_width"). Anthropometry (Drillis & Contini; Winter's segment table) gives thigh
# ~0.245 H, shin ~0.246 H, upper arm ~0.186 H, forearm ~0.146 H, biacromial width
# ~0.26 H, keypoint hip width ~0.16-0.19 H: ratios ~1.0, ~1.3, ~1.5 and ~1.5; the
# bounds leave a factor of ~1.6 either way for keypoint placement and body types.
RATIOS: tuple[tuple[str, tuple[str, ...], tuple[str, ...], float, float], ...] = (
    ("thigh/shin", ("thigh",), ("shin",), 0.6, 1.7),
    ("upper_arm/forearm", ("upper_arm",), ("forearm",), 0.75, 2.0),
    ("shoulder_width/hip_width", ("shoulder_width",), ("hip_width",), 0.9, 3.0),
    ("leg/arm", ("thigh", "shin"), ("upper_arm", "forearm"), 0.9, 2.4),
)


@dataclass(frozen=True)
class LabelCheckParams:
    """Thresholds of every check (see the module docstring for where they come from).

    Attributes:
        min_frames: scored frames a track needs before it is judged.
        axis_contradiction: ``left_right`` fraction above which a track is flagged.
        facing_contradiction: ``facing`` fraction above which a track is flagged.
        facing_min_mm: a facing cue nearer than this to the torso's plane does not vote.
        symmetry: relative left/right length difference above which a limb is flagged.
        stability: robust relative spread of a bone's length above which it is flagged.
        knee_backward_deg / knee_fraction: a knee bent backwards by more than this many
            degrees counts; flagged when more than this fraction of knee-frames do.
        elbow_backward_deg / elbow_fraction: the same for elbows (looser: a twisted
            upper arm puts the forearm behind the body, e.g. hands on the back).
        camera_mirror: fraction of a camera's people fitting the mirror better above
            which the camera is flagged.
        camera_min_people: people a camera needs before it is judged.
        min_separation_px: a left/right pair whose reprojections are closer than this
            cannot tell the labels apart and is not compared.
        min_confidence: 2D joints below this confidence are not compared.
        min_views: joints triangulated from fewer views are not judged by the track
            checks of :func:`check_results`.
    """

    min_frames: int = 20
    axis_contradiction: float = 0.2
    facing_contradiction: float = 0.3
    facing_min_mm: float = 20.0
    symmetry: float = 0.25
    stability: float = 0.25
    knee_backward_deg: float = 25.0
    knee_fraction: float = 0.15
    elbow_backward_deg: float = 45.0
    elbow_fraction: float = 0.35
    camera_mirror: float = 0.5
    camera_min_people: int = 20
    min_separation_px: float = 10.0
    min_confidence: float = 0.3
    min_views: int = 3


@dataclass(frozen=True)
class LabelFinding:
    """One suspicious measurement.

    Attributes:
        kind: one of :data:`KINDS`.
        track: the track it concerns, None for a scene-wide or camera finding.
        camera: the camera (view index) it concerns, or None.
        frames: frames that show it, ascending (the first is where to look).
        value: the measured value (a fraction, a relative difference or a ratio).
        threshold: the bound it crossed.
        message: one human-readable line.
    """

    kind: str
    track: int | None
    camera: int | None
    frames: tuple[int, ...]
    value: float
    threshold: float
    message: str


@dataclass(frozen=True)
class LabelCheck:
    """What :func:`check_labels` measured and found.

    Attributes:
        joint_set: name of the joint set checked.
        checked: the kinds this joint set and input allowed.
        scene: measure name -> value pooled over the judged tracks (and, for
            ``camera_mirror``, the worst camera).
        tracks: judged track -> (measure name -> value).
        cameras: camera name -> fraction of its people fitting the mirror better.
        findings: every finding; scene-wide ones (``track is None``) first.
    """

    joint_set: str
    checked: tuple[str, ...]
    scene: dict[str, float]
    tracks: dict[int, dict[str, float]]
    cameras: dict[str, float]
    findings: tuple[LabelFinding, ...]

    @property
    def ok(self) -> bool:
        return not self.findings

    def summary(self) -> str:
        """One line: ``"OK (...)"`` or what is suspicious and where."""
        if self.ok:
            cams = sum(np.isfinite(x) for x in self.cameras.values())
            seen = f"{len(self.tracks)} tracks" + (f", {cams} cameras" if cams else "")
            if not self.tracks:
                seen = "no track long enough to judge" + (f"; {cams} cameras" if cams else "")
            return f"OK ({seen}; checked {', '.join(self.checked) or 'nothing'})"
        shown = [f.message for f in self.findings[:4]]
        more = len(self.findings) - len(shown)
        head = "SUSPICIOUS: "
        if {f.kind for f in self.findings if f.track is None and f.camera is None} & set(
            ORDER_KINDS
        ):
            head += f"the keypoint order does not look like {self.joint_set} (wrong layout?): "
        return head + "; ".join(shown) + (f"; and {more} more" if more > 0 else "")

    def to_json(self) -> dict:
        return {
            "ok": self.ok,
            "joint_set": self.joint_set,
            "checked": list(self.checked),
            "scene": self.scene,
            "tracks": {str(k): v for k, v in self.tracks.items()},
            "cameras": self.cameras,
            "findings": [
                {
                    "kind": f.kind,
                    "track": f.track,
                    "camera": f.camera,
                    "num_frames": len(f.frames),
                    "frames": list(f.frames[:50]),
                    "value": f.value,
                    "threshold": f.threshold,
                    "message": f.message,
                }
                for f in self.findings
            ],
        }


@dataclass(frozen=True, eq=False)
class ViewObservations:
    """The per-frame people as the cameras saw them: what :func:`camera_mirror_fractions`
    compares.

    Attributes:
        joints2d: (num_people, num_views, num_joints, 3) x px, y px, confidence of the
            detection associated to each person in each view; confidence 0 (x, y may
            be NaN) where a view has none. None when the 2D is read per view from the
            run's detections (:meth:`from_members`).
        joints3d: (num_people, num_joints, 3) the person's triangulated joints, world mm.
        frame: (num_people,) frame of each person.
        track: (num_people,) track of each person, -1 if untracked.
        members: with ``joints2d`` None, (num_people, num_views) detection row of each
            person in each view, -1 where none; ``detections`` (N, J, 3) their 2D, and
            ``mirrored`` (N,) bool or None, the rows to read through ``flip_index``.
    """

    joints2d: np.ndarray | None
    joints3d: np.ndarray
    frame: np.ndarray
    track: np.ndarray
    members: np.ndarray | None = None
    detections: np.ndarray | None = None
    mirrored: np.ndarray | None = None
    flip_index: np.ndarray | None = None

    def __post_init__(self) -> None:
        P = self.joints3d.shape[0]
        if self.joints3d.ndim != 3 or self.joints3d.shape[-1] != 3:
            raise ValueError(f"joints3d: expected (num_people, J, 3), got {self.joints3d.shape}")
        J = self.joints3d.shape[1]
        if self.joints2d is None:
            if self.members is None or self.detections is None:
                raise ValueError("joints2d: None needs members and detections")
            if self.members.ndim != 2 or self.members.shape[0] != P:
                raise ValueError(f"members: expected ({P}, num_views), got {self.members.shape}")
            if self.detections.ndim != 3 or self.detections.shape[1:] != (J, 3):
                raise ValueError(f"detections: expected (N, {J}, 3), got {self.detections.shape}")
        elif (
            self.joints2d.ndim != 4
            or self.joints2d.shape[0] != P
            or self.joints2d.shape[2:] != (J, 3)
        ):
            raise ValueError(
                f"joints2d: expected ({P}, num_views, {J}, 3), got {self.joints2d.shape}"
            )
        if self.frame.shape != (P,) or self.track.shape != (P,):
            raise ValueError(f"frame and track: expected ({P},), got {self.frame.shape}")

    @classmethod
    def from_members(
        cls,
        members: np.ndarray,
        detections: np.ndarray,
        joints3d: np.ndarray,
        frame: np.ndarray,
        track: np.ndarray,
        *,
        mirrored: np.ndarray | None = None,
        flip_index: np.ndarray | None = None,
    ) -> ViewObservations:
        """The 2D of each view gathered when it is read (:meth:`view_joints2d`): the whole
        (P, V, J, 3) array at once was 2.5 GB at 10,000 frames x 31 cameras x 20
        people, one view's is 1/31 of it."""
        return cls(None, joints3d, frame, track, np.asarray(members), detections,
                   mirrored, flip_index)  # fmt: skip

    @property
    def num_views(self) -> int:
        src = self.members if self.joints2d is None else self.joints2d
        return int(src.shape[1])

    def view_joints2d(self, v: int) -> np.ndarray:
        """(num_people, num_joints, 3) the 2D of view ``v``: confidence 0 where the view
        has none, a mirrored detection read back as its detector gave it."""
        if self.joints2d is not None:
            return self.joints2d[:, v]
        rows = self.members[:, v]
        kp = self.detections[np.maximum(rows, 0)]  # a new array (the gather copies)
        if self.mirrored is not None and self.flip_index is not None and len(kp):
            back = np.asarray(self.mirrored)[np.maximum(rows, 0)] & (rows >= 0)
            if back.any():
                kp[back] = kp[back][:, self.flip_index]
        kp[rows < 0, :, 2] = 0.0
        return kp


# --------------------------------------------------------------------------- checks


def _frames(mask: np.ndarray) -> tuple[int, ...]:
    """(num_frames,) bool -> ascending frame indices."""
    return tuple(int(f) for f in np.flatnonzero(mask))


def _pct(x: float) -> str:
    return f"{100 * x:.0f}%"


_FRACTION_TEXT = {
    "left_right": ("shoulders and hips point to opposite sides", "frames"),
    "facing": ("head/feet face the other way than the torso", "frames"),
    "knee_hinge": ("knees bend the wrong way", "knee-frames"),
    "elbow_hinge": ("elbows bend the wrong way", "elbow-frames"),
}


def _fraction_signals(
    joints: np.ndarray, js: JointSet, p: LabelCheckParams
) -> dict[str, tuple[np.ndarray, np.ndarray, float]]:
    """kind -> (bad (K, F, n), scored (K, F, n), threshold) for the fraction checks the
    set allows; n counts the samples per frame (e.g. two knees)."""
    out = {}
    axes = body_axes(joints, js)
    s, h = axes["shoulders"], axes["hips"]
    if joint_pair(joints, js, "shoulder") is not None and joint_pair(joints, js, "hip") is not None:
        scored = np.isfinite(s).all(-1) & np.isfinite(h).all(-1)
        with np.errstate(invalid="ignore"):
            bad = scored & (dot(s, h) < 0)
        out["left_right"] = (bad[..., None], scored[..., None], p.axis_contradiction)
    cues = facing_offsets(joints, js)
    if cues:
        c = np.stack(list(cues.values()), -1)
        total = np.where(np.isfinite(c), c, 0.0).sum(-1)
        with np.errstate(invalid="ignore"):
            scored = np.isfinite(c).any(-1) & (np.abs(total) >= p.facing_min_mm)
            bad = scored & (total < 0)
        out["facing"] = (bad[..., None], scored[..., None], p.facing_contradiction)
    angles = hinge_angles(joints, js)
    for hinge, limit, frac in (
        ("knee", p.knee_backward_deg, p.knee_fraction),
        ("elbow", p.elbow_backward_deg, p.elbow_fraction),
    ):
        a = [angles[f"{side}_{hinge}"] for side in SIDES if f"{side}_{hinge}" in angles]
        if a:
            a = np.stack(a, -1)
            scored = np.isfinite(a)
            with np.errstate(invalid="ignore"):
                bad = scored & (a < -limit)
            out[f"{hinge}_hinge"] = (bad, scored, frac)
    return out


def _fraction_findings(
    kind: str, bad: np.ndarray, scored: np.ndarray, threshold: float, judged: np.ndarray
) -> tuple[dict[int, float], float, list[LabelFinding]]:
    """Per judged track and pooled: fraction of scored samples that are bad."""
    n_bad, n_scored = bad.sum((1, 2)), scored.sum((1, 2))
    what, unit = _FRACTION_TEXT[kind]
    per_track, findings = {}, []
    for k in np.flatnonzero(judged & (n_scored > 0)):
        value = float(n_bad[k] / n_scored[k])
        per_track[int(k)] = value
        if value > threshold:
            text = (
                f"track {k}: {what} in {_pct(value)} of {int(n_scored[k])} {unit} "
                f"(threshold {_pct(threshold)})"
            )
            frames = _frames(bad[k].any(-1))
            findings.append(LabelFinding(kind, int(k), None, frames, value, threshold, text))
    total = int(n_scored[judged].sum())
    pooled = float(n_bad[judged].sum() / total) if total else float("nan")
    if total and pooled > threshold and _most(len(findings), len(per_track)):
        text = (
            f"scene: {what} in {_pct(pooled)} of {total} {unit} of {len(per_track)} tracks "
            f"(threshold {_pct(threshold)})"
        )
        frames = _frames(bad[judged].any(-1).any(0))
        findings.insert(0, LabelFinding(kind, None, None, frames, pooled, threshold, text))
    return per_track, pooled, findings


def _most(flagged: int, judged: int) -> bool:
    """A scene-wide finding needs more than half of the judged tracks flagged."""
    return judged > 0 and 2 * flagged > judged


def _median_lengths(lengths: dict[str, np.ndarray], min_frames: int) -> dict[str, np.ndarray]:
    """bone -> (K,) median length over frames (NaN with fewer than ``min_frames``)."""
    out = {}
    for name, x in lengths.items():
        n = np.isfinite(x).sum(1)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN rows -> NaN
            med = np.nanmedian(x, axis=1)
        out[name] = np.where(n >= min_frames, med, np.nan)
    return out


def _part(medians: dict[str, np.ndarray], part: str) -> np.ndarray | None:
    """(K,) a width, or a limb's mean of both sides (either alone), or None."""
    if part in medians:
        return medians[part]
    sides = [medians[f"{s}_{part}"] for s in SIDES if f"{s}_{part}" in medians]
    return nanmean_last(np.stack(sides, -1)) if sides else None


def _flag_measure(
    findings: list[LabelFinding],
    kind: str,
    values: np.ndarray,
    joints: np.ndarray,
    tracks: np.ndarray,
    threshold: Callable[[float], float],
    worse: Callable[[float], bool],
    describe: Callable[[float], str],
) -> tuple[dict[int, float], float]:
    """Per-track measure ``values`` (K,) of the judged ``tracks``, and its scene value
    (the median over them); a finding (appended to ``findings``, a scene one in front)
    where ``worse(value)``, ``threshold(value)`` the bound it crossed."""
    per = {int(k): float(values[k]) for k in tracks if np.isfinite(values[k])}
    vals = np.array(list(per.values()))
    scene = float(np.median(vals)) if vals.size else float("nan")
    flagged = 0
    for k, v in per.items():
        if worse(v):
            flagged += 1
            frames = _frames(np.isfinite(joints[k]).all(-1).any(-1))
            text = f"track {k}: {describe(v)}"
            findings.append(LabelFinding(kind, k, None, frames, v, threshold(v), text))
    if vals.size and worse(scene) and _most(flagged, vals.size):
        frames = _frames(np.isfinite(joints[tracks]).all(-1).any(-1).any(0))
        text = f"scene: {describe(scene)} (median over {vals.size} tracks)"
        findings.insert(0, LabelFinding(kind, None, None, frames, scene, threshold(scene), text))
    return per, scene


def _symmetry_measures(med: dict[str, np.ndarray], p: LabelCheckParams) -> list[tuple]:
    """(key, values (K,), threshold, worse, describe) of each limb's left/right difference."""
    out = []
    for limb in [x for x in LIMBS if f"left_{x}" in med and f"right_{x}" in med]:
        a, b = med[f"left_{limb}"], med[f"right_{limb}"]
        with np.errstate(invalid="ignore"):
            rel = np.abs(a - b) / (0.5 * (a + b))
        out.append((
            f"symmetry:{limb}",
            rel,
            lambda v: p.symmetry,
            lambda v: v > p.symmetry,
            lambda v, limb=limb: (
                f"left and right {limb} lengths differ by {_pct(v)} (threshold {_pct(p.symmetry)})"
            ),
        ))  # fmt: skip
    return out


def _proportion_measures(med: dict[str, np.ndarray]) -> list[tuple]:
    """(key, values (K,), threshold, worse, describe) of each ratio of :data:`RATIOS`."""
    out = []
    for name, num, den, lo, hi in RATIOS:
        parts_n = [_part(med, x) for x in num]
        parts_d = [_part(med, x) for x in den]
        if any(x is None for x in parts_n + parts_d):
            continue
        with np.errstate(invalid="ignore", divide="ignore"):
            ratio = np.sum(parts_n, 0) / np.sum(parts_d, 0)
        out.append((
            f"ratio:{name}",
            ratio,
            lambda v, lo=lo, hi=hi: lo if v < lo else hi,
            lambda v, lo=lo, hi=hi: not lo <= v <= hi,
            lambda v, name=name, lo=lo, hi=hi: f"{name} = {v:.2f} (plausible {lo}-{hi})",
        ))  # fmt: skip
    return out


def _stability(
    findings: list[LabelFinding],
    lengths: dict[str, np.ndarray],
    med: dict[str, np.ndarray],
    p: LabelCheckParams,
    tracks: np.ndarray,
) -> tuple[dict[int, float], float]:
    """Worst robust relative spread (1.4826 MAD / median) of a bone's length over frames,
    per judged track and its median over them; findings appended to ``findings``."""
    spread = {}
    for bone, x in lengths.items():
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN rows -> NaN
            mad = np.nanmedian(np.abs(x - med[bone][:, None]), axis=1)
        spread[bone] = 1.4826 * mad / med[bone]
    stack = np.stack(list(spread.values()), -1)  # (K, B)
    worst = np.where(np.isfinite(stack), stack, -np.inf).argmax(-1)
    value = np.take_along_axis(stack, worst[:, None], -1)[:, 0]
    bones = list(spread)
    per = {int(k): float(value[k]) for k in tracks if np.isfinite(value[k])}
    vals = np.array(list(per.values()))
    scene = float(np.median(vals)) if vals.size else float("nan")
    flagged = 0
    for k, v in per.items():
        if v > p.stability:
            flagged += 1
            bone = bones[worst[k]]
            with np.errstate(invalid="ignore"):
                off = np.abs(lengths[bone][k] / med[bone][k] - 1) > p.stability
            text = (
                f"track {k}: {bone} length varies by {_pct(v)} over frames "
                f"(threshold {_pct(p.stability)})"
            )
            findings.append(LabelFinding("stability", k, None, _frames(off), v, p.stability, text))
    if vals.size and scene > p.stability and _most(flagged, vals.size):
        text = (
            f"scene: bone lengths vary by {_pct(scene)} over frames "
            f"(median over {vals.size} tracks; threshold {_pct(p.stability)})"
        )
        frames = tuple(sorted({f for x in findings if x.kind == "stability" for f in x.frames}))
        findings.insert(0, LabelFinding("stability", None, None, frames, scene, p.stability, text))
    return per, scene


def _length_findings(
    joints: np.ndarray, js: JointSet, p: LabelCheckParams, judged: np.ndarray
) -> tuple[dict[str, dict[int, float]], dict[str, float], list[LabelFinding], list[str]]:
    """Symmetry, proportion and stability of bone lengths: per-track measures, scene
    measures (median over judged tracks), findings and the kinds checked."""
    lengths = bone_lengths(joints, js)  # name -> (K, F)
    med = _median_lengths(lengths, p.min_frames)
    per: dict[str, dict[int, float]] = {}
    scene: dict[str, float] = {}
    findings: list[LabelFinding] = []
    kinds: list[str] = []
    tracks = np.flatnonzero(judged)
    # 1. left/right symmetry of each limb, 2. anatomical proportions
    for kind, measures in (
        ("symmetry", _symmetry_measures(med, p)),
        ("proportion", _proportion_measures(med)),
    ):
        if measures:
            kinds.append(kind)
        for key, values, threshold, worse, describe in measures:
            per[key], scene[key] = _flag_measure(
                findings, kind, values, joints, tracks, threshold, worse, describe
            )
    # 3. stability over frames: robust relative spread of each bone's length
    if lengths:
        kinds.append("stability")
        per["stability"], scene["stability"] = _stability(findings, lengths, med, p, tracks)
    return per, scene, findings, kinds


def camera_mirror_fractions(
    cameras: Sequence[Camera],
    views: ViewObservations,
    joint_set: JointSet,
    *,
    min_confidence: float = LabelCheckParams.min_confidence,
    min_separation_px: float = LabelCheckParams.min_separation_px,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Does each camera's 2D fit the reprojected 3D better under its own labels or the
    mirrored ones?

    Per person and view, each left/right pair (``joint_set.flip_index``) whose 2D joints
    are both confident and whose reprojections are at least ``min_separation_px``
    apart votes "mirror" when ``|x_l - p_r| + |x_r - p_l| < |x_l - p_l| + |x_r - p_r|``
    (x: the view's 2D, p: the reprojection of the person's 3D). A person is mirrored in
    a view when most of at least two voting pairs say so.

    Args:
        cameras: (num_views,) the calibrated cameras, in view order.
        views: the people's 2D per view and 3D.
        joint_set: the set of both.
    Returns:
        fraction: (num_views,) of the compared people that are mirrored (NaN: none).
        compared: (num_views,) people compared.
        mirrored: (num_people, num_views) bool.
    """
    flip = joint_set.flip_index
    left = np.array(
        [i for i, n in enumerate(joint_set.names) if n.startswith("left_") and flip[i] != i], int
    )
    right = flip[left]
    P, V = len(views.joints3d), views.num_views
    if len(cameras) != V:
        raise ValueError(f"{len(cameras)} cameras for 2D of {V} views")
    mirrored = np.zeros((P, V), bool)
    compared = np.zeros((P, V), bool)
    for v, cam in enumerate(cameras):
        if P == 0 or len(left) == 0:
            break
        proj = cam.project(views.joints3d)  # (P, J, 2)
        kp = views.view_joints2d(v)
        x, conf = kp[..., :2], kp[..., 2]
        pl, pr, xl, xr = proj[:, left], proj[:, right], x[:, left], x[:, right]
        with np.errstate(invalid="ignore"):
            ok = (
                (conf[:, left] >= min_confidence)
                & (conf[:, right] >= min_confidence)
                & np.isfinite(pl + pr + xl + xr).all(-1)
                & (np.linalg.norm(pl - pr, axis=-1) >= min_separation_px)
            )
        d = lambda a, b: np.linalg.norm(a - b, axis=-1)  # noqa: E731
        with np.errstate(invalid="ignore"):
            votes = ok & (d(xl, pr) + d(xr, pl) < d(xl, pl) + d(xr, pr))
        n = ok.sum(1)
        compared[:, v] = n >= 2
        mirrored[:, v] = compared[:, v] & (2 * votes.sum(1) > n)
    count = compared.sum(0)
    with np.errstate(invalid="ignore", divide="ignore"):
        fraction = np.where(count > 0, mirrored.sum(0) / np.maximum(count, 1), np.nan)
    return fraction, count, mirrored


def _camera_findings(
    cameras: Sequence[Camera], views: ViewObservations, js: JointSet, params: LabelCheckParams
) -> tuple[dict[str, float], list[LabelFinding]]:
    """``camera_mirror``: the mirrored fraction per camera name, and the findings."""
    fraction, count, mirrored = camera_mirror_fractions(
        cameras,
        views,
        js,
        min_confidence=params.min_confidence,
        min_separation_px=params.min_separation_px,
    )
    cam_fraction: dict[str, float] = {}
    found = []
    for v, cam in enumerate(cameras):
        cam_fraction[cam.name] = float(fraction[v])
        if count[v] >= params.camera_min_people and fraction[v] > params.camera_mirror:
            frames = tuple(sorted({int(x) for x in views.frame[mirrored[:, v]]}))
            text = (
                f"camera {cam.name}: 2D fits the left/right-mirrored 3D better for "
                f"{_pct(fraction[v])} of {int(count[v])} people "
                f"(threshold {_pct(params.camera_mirror)})"
            )
            found.append(
                LabelFinding(
                    "camera_mirror", None, v, frames, float(fraction[v]),
                    params.camera_mirror, text,
                )
            )  # fmt: skip
    return cam_fraction, found


def _finding_order(x: LabelFinding) -> tuple[int, int, int]:
    """Scene-wide findings first, then per track, then per camera; by kind within."""
    scope = 2 if x.camera is not None else 0 if x.track is None else 1
    return scope, -1 if x.track is None else x.track, KINDS.index(x.kind)


def check_labels(
    joints: np.ndarray,
    joint_set: JointSet | str,
    *,
    cameras: Sequence[Camera] | None = None,
    views: ViewObservations | None = None,
    params: LabelCheckParams = LabelCheckParams(),
) -> LabelCheck:
    """Every label check on tracked 3D joints (and, given ``cameras`` and ``views``, per
    camera).

    Args:
        joints: (num_tracks, num_frames, num_joints, 3) world mm, z up, NaN where absent.
        joint_set: the set (or its registry name) the joints are laid out in.
        cameras: (num_views,) calibrated cameras, for ``camera_mirror``.
        views: the per-frame people's 2D per view and 3D, for ``camera_mirror``.
        params: thresholds.
    Returns:
        The measures and findings; ``findings`` lists scene-wide ones first, then per
        track, then per camera.
    """
    js = get_joint_set(joint_set) if isinstance(joint_set, str) else joint_set
    joints = np.asarray(joints, float)
    if joints.ndim != 4 or joints.shape[2:] != (js.num_joints, 3):
        raise ValueError(
            f"joints: expected (num_tracks, num_frames, {js.num_joints}, 3) for joint set "
            f"{js.name}, got {joints.shape}"
        )
    present = np.isfinite(joints).all(-1).sum(-1) >= 4  # (K, F) a body, not a stray joint
    judged = present.sum(1) >= params.min_frames
    kinds: list[str] = []
    scene: dict[str, float] = {}
    tracks: dict[int, dict[str, float]] = {int(k): {} for k in np.flatnonzero(judged)}
    found: list[LabelFinding] = []
    for kind, (bad, scored, threshold) in _fraction_signals(joints, js, params).items():
        kinds.append(kind)
        per, pooled, f = _fraction_findings(kind, bad, scored, threshold, judged)
        scene[kind] = pooled
        for k, v in per.items():
            tracks[k][kind] = v
        found += f
    per_len, scene_len, f, len_kinds = _length_findings(joints, js, params, judged)
    kinds += len_kinds
    scene.update(scene_len)
    for key, per in per_len.items():
        for k, v in per.items():
            tracks[k][key] = v
    found += f
    cam_fraction: dict[str, float] = {}
    if cameras is not None and views is not None:
        kinds.append("camera_mirror")
        cam_fraction, f = _camera_findings(cameras, views, js, params)
        found += f
        finite = [x for x in cam_fraction.values() if np.isfinite(x)]
        scene["camera_mirror"] = max(finite) if finite else float("nan")
    found.sort(key=_finding_order)
    return LabelCheck(
        joint_set=js.name,
        checked=tuple(k for k in KINDS if k in kinds),
        scene=scene,
        tracks=tracks,
        cameras=cam_fraction,
        findings=tuple(found),
    )


def view_observations(results: PipelineResults) -> ViewObservations:
    """The run's per-frame people (raw triangulation) with their associated 2D per view,
    as the cameras' detector gave it: detections the association un-mirrored
    (``results.det_flipped``) are mirrored back, so that a camera whose detector swaps
    left and right is still told, though the 3D no longer suffers from it. Each view's
    2D is gathered when it is read (:meth:`ViewObservations.from_members`)."""
    flipped = results.det_flipped
    return ViewObservations.from_members(
        results.person_members,
        results.det_joints2d,
        results.person_joints,
        results.person_frame,
        results.person_track,
        mirrored=flipped,
        flip_index=None if flipped is None else get_joint_set(results.joint_set).flip_index,
    )


def check_results(
    results: PipelineResults,
    cameras: Sequence[Camera],
    *,
    params: LabelCheckParams = LabelCheckParams(),
) -> LabelCheck:
    """:func:`check_labels` on a run: its raw tracks, and its cameras' associated 2D
    against the per-frame triangulation.

    A joint triangulated from fewer than ``params.min_views`` views is left out of the
    track checks: with two views nothing is redundant (no outlier can be dropped), so
    lengths and hinges of such joints measure the triangulation, not the labels (a
    bystander that two of the balancing trial's cameras see at their edge has forearms
    38% apart)."""
    joints = results.track_raw
    if params.min_views > 2 and results.person_used.size:
        views = np.zeros(joints.shape[:3], int)  # (K, F, J)
        q = np.flatnonzero(results.person_track >= 0)
        views[results.person_track[q], results.person_frame[q]] = results.person_used[q].sum(-1)
        joints = np.where((views >= params.min_views)[..., None], joints, np.nan)
    return check_labels(
        joints,
        results.joint_set,
        cameras=cameras,
        views=view_observations(results),
        params=params,
    )
