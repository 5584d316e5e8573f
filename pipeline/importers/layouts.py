"""Which keypoint layout a detection file is in, decided from the data.

Keypoint counts collide: BODY_25 and BODY_25B both have 25 points in different orders,
COCO-17 and Human3.6M-17 both 17. Reading one as the other gives plausible-looking
numbers that are wrong (on Pose2Sim's balancing trial, BODY_25B read as BODY_25 put the
"joints" ~420 mm from the truth). So every candidate layout of a count is scored on
what all the 2D detections say about anatomy, and the layout is taken only when the
evidence is clear.

The tests are written in terms of joint *names*, so they apply to every layout:

* **vertical order** (people mostly stand): a point of a higher body level lies higher
  in the image than a point clearly lower on the body (head points above shoulders,
  shoulders above hips, hips above knees, knees above feet; the top of the head above
  the eyes, an upper neck below the nose). Arms are left out: they move freely.
* **mid-points**: a neck that is OpenPose's mid-shoulder point, a mid-hip or pelvis lies
  near the middle of its pair (within half the pair's spread).
* **left/right pairs agree**: the left-right direction of the shoulders, the hips, the
  knees, the eyes and the ears point the same way along the image x axis (a body is
  not twisted by more than 90 degrees between them). This holds for front- and
  back-facing people alike and for mirrored images.

A layout's score is the fraction of these tests that hold over all detections with the
points visible, averaged over the three families. The best candidate is taken if it scores at least
:data:`MIN_SCORE` and beats the runner-up by :data:`MIN_MARGIN`, on at least
:data:`MIN_TESTS` tests; otherwise the file is refused (``--layout`` overrides).

Left and right themselves (is the layout's "left" the person's left?) are told by the
people who face the camera (nose and both eyes seen well): for them the left shoulder
is on the image's right. That is reported as evidence; swapped labels (or mirrored
videos) are refused unless the layout is forced.

Image pixels, y down.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.core.files import SceneFormatError
from pipeline.data.joint_sets import JOINT_SETS, JointSet

# Layouts a detection file may be in, by name. The scene may keep a file's layout or be
# converted by joint name into another (``convert_keypoints``).
SOURCE_LAYOUTS: dict[str, JointSet] = {
    name: JOINT_SETS[name]
    for name in (
        "body25", "body25b", "coco18", "coco17", "h36m17", "halpe26", "coco23",
        "coco_wholebody133", "blazepose33", "smpl24",
    )
}  # fmt: skip
CANDIDATES_BY_COUNT: dict[int, tuple[JointSet, ...]] = {}
for _js in SOURCE_LAYOUTS.values():
    CANDIDATES_BY_COUNT.setdefault(_js.num_joints, ())
    CANDIDATES_BY_COUNT[_js.num_joints] += (_js,)

MIN_SCORE = 0.75
"""The chosen layout's tests must hold this often. Correct layouts score 0.96-0.99 on
synthesised scenes in every layout and on Pose2Sim's real BODY_25B trial; the wrong
reading of a 25- or 17-point file scores 0.21-0.66 (BODY_25B read as BODY_25: 0.54 on
the real trial)."""
MIN_MARGIN = 0.15
"""...and beat the second-best candidate by this much."""
MIN_TESTS = 40
"""Fewer tests than this is not evidence."""
MIN_DETECTIONS = 5
"""...nor fewer detections than this (one person in one view is one pose: it may be
lying, bending or cartwheeling)."""
MIN_FAMILY_TESTS = 20
"""A family of tests with fewer than this does not count towards the score."""
MIN_CONFIDENCE = 0.3
"""Points below this detector confidence are not used as evidence."""
FRONT_CONFIDENCE = 0.5
"""A person faces the camera when the nose and both eyes are seen this well."""

# Body level of each point name that takes part in the vertical test (0 = top of the
# head, 4 = feet). Pairs whose levels differ by 0.5 or more are tested.
_LEVELS: dict[str, float] = {
    "head_top": -0.5,
    **{n: 0.0 for n in ("nose", "left_eye", "right_eye", "left_ear", "right_ear")},
    **{
        n: 0.0
        for n in (
            "left_eye_inner", "left_eye_outer", "right_eye_inner", "right_eye_outer",
        )
    },
    **{n: 0.25 for n in ("left_mouth", "right_mouth")},
    "chin": 0.5,
    "upper_neck": 0.6,
    **{n: 1.0 for n in ("left_shoulder", "right_shoulder", "neck", "thorax")},
    "spine": 1.5,
    **{n: 2.0 for n in ("left_hip", "right_hip", "mid_hip", "pelvis")},
    **{n: 3.0 for n in ("left_knee", "right_knee")},
    **{
        n: 4.0
        for n in (
            "left_ankle", "right_ankle", "left_heel", "right_heel", "left_big_toe",
            "right_big_toe", "left_small_toe", "right_small_toe", "left_foot_index",
            "right_foot_index",
        )
    },
}  # fmt: skip
# Points that lie at the middle of a pair (OpenPose's neck is computed that way in its
# training data; Human3.6M's thorax and pelvis nearly so).
_MIDPOINTS: dict[str, tuple[str, str]] = {
    "neck": ("left_shoulder", "right_shoulder"),
    "thorax": ("left_shoulder", "right_shoulder"),
    "mid_hip": ("left_hip", "right_hip"),
    "pelvis": ("left_hip", "right_hip"),
}
# Left/right pairs whose image-x direction must agree with the shoulders'.
_PAIRS = ("hip", "knee", "eye", "ear", "ankle")


@dataclass(frozen=True)
class LayoutDecision:
    """What was decided about a file's keypoint layout, and on what evidence.

    Attributes:
        layout: the joint set name taken (e.g. ``"body25b"``).
        forced: True if the user named it (``--layout``); the scores are then informative.
        candidates: the layouts with this keypoint count.
        scores: per candidate, the fraction of anatomical tests that held.
        num_tests: per candidate, how many tests were made.
        num_detections: how many detections (people in views) were examined.
        front_facing: detections that face the camera (nose and eyes seen well).
        left_on_image_right: of those, how many have the layout's left shoulder on the
            image's right (the person's left, as it should be).
        evidence: the decision in sentences, for the convert output and scene.json.
    """

    layout: str
    forced: bool
    candidates: tuple[str, ...]
    scores: dict[str, float]
    num_tests: dict[str, int]
    num_detections: int
    front_facing: int
    left_on_image_right: int
    evidence: tuple[str, ...]

    def to_json(self) -> dict:
        return {
            "layout": self.layout,
            "forced": self.forced,
            "candidates": list(self.candidates),
            "scores": {k: round(v, 4) for k, v in self.scores.items()},
            "num_tests": dict(self.num_tests),
            "num_detections": self.num_detections,
            "front_facing": self.front_facing,
            "left_on_image_right": self.left_on_image_right,
            "evidence": list(self.evidence),
        }


def _points(keypoints: np.ndarray, js: JointSet, name: str) -> np.ndarray:
    """(N, 2) image points of ``name`` (NaN where unseen or the set lacks it)."""
    if name not in js.index:
        return np.full((keypoints.shape[0], 2), np.nan)
    kp = keypoints[:, js.index[name]]
    out = kp[:, :2].copy()
    out[~(kp[:, 2] >= MIN_CONFIDENCE)] = np.nan
    return out


def anatomy_tests(keypoints: np.ndarray, js: JointSet) -> dict[str, tuple[int, int]]:
    """Per family of tests of the module docstring (``vertical``, ``midpoints``,
    ``pairs``), (held, made) for ``keypoints`` read as layout ``js``.

    Args:
        keypoints: (N, js.num_joints, 3) x, y (pixels, y down), confidence.
    """
    names = [n for n in js.names if n in _LEVELS]
    pts = {n: _points(keypoints, js, n) for n in names}
    held = made = 0
    for i, a in enumerate(names):
        for b in names[i + 1 :]:
            if abs(_LEVELS[a] - _LEVELS[b]) < 0.5:
                continue
            upper, lower = (a, b) if _LEVELS[a] < _LEVELS[b] else (b, a)
            ok = np.isfinite(pts[upper][:, 1]) & np.isfinite(pts[lower][:, 1])
            made += int(ok.sum())
            held += int((pts[upper][ok, 1] < pts[lower][ok, 1]).sum())
    out = {"vertical": (held, made)}
    held = made = 0
    for mid, (a, b) in _MIDPOINTS.items():
        if mid not in js.index or a not in js.index or b not in js.index:
            continue
        m = _points(keypoints, js, mid)
        pa, pb = _points(keypoints, js, a), _points(keypoints, js, b)
        spread = np.linalg.norm(pa - pb, axis=1)
        ok = np.isfinite(m).all(1) & np.isfinite(spread) & (spread > 1.0)
        dist = np.linalg.norm(m - 0.5 * (pa + pb), axis=1)
        made += int(ok.sum())
        held += int((dist[ok] < 0.5 * spread[ok]).sum())
    out["midpoints"] = (held, made)
    held = made = 0
    ls, rs = _points(keypoints, js, "left_shoulder"), _points(keypoints, js, "right_shoulder")
    dx_sh = ls[:, 0] - rs[:, 0]
    for part in _PAIRS:
        lp, rp = _points(keypoints, js, f"left_{part}"), _points(keypoints, js, f"right_{part}")
        dx = lp[:, 0] - rp[:, 0]
        # Only people seen well from the front or back: a side view has no x direction.
        scale = np.abs(dx_sh)
        ok = np.isfinite(dx) & np.isfinite(dx_sh) & (scale > 5.0) & (np.abs(dx) > 0.2 * scale)
        made += int(ok.sum())
        held += int((np.sign(dx[ok]) == np.sign(dx_sh[ok])).sum())
    out["pairs"] = (held, made)
    return out


def layout_score(tests: dict[str, tuple[int, int]]) -> float:
    """The mean, over the families with at least :data:`MIN_FAMILY_TESTS` tests, of the
    fraction that held (families weigh alike: the vertical family has ~50x the tests of
    the others, and a wrong reading of a 25-point file still gets ~80% of those right)."""
    fractions = [h / m for h, m in tests.values() if m >= MIN_FAMILY_TESTS]
    return float(np.mean(fractions)) if fractions else 0.0


def facing_evidence(keypoints: np.ndarray, js: JointSet) -> tuple[int, int]:
    """(front_facing, left_on_image_right) for ``keypoints`` read as ``js`` (see
    :class:`LayoutDecision`); (0, 0) when the layout has no nose, eyes or shoulders."""
    need = ("nose", "left_eye", "right_eye", "left_shoulder", "right_shoulder")
    if not all(n in js.index for n in need):
        return 0, 0
    conf = keypoints[:, [js.index[n] for n in need], 2]
    front = (conf[:, :3] >= FRONT_CONFIDENCE).all(1) & (conf[:, 3:] >= MIN_CONFIDENCE).all(1)
    ls = keypoints[front, js.index["left_shoulder"], 0]
    rs = keypoints[front, js.index["right_shoulder"], 0]
    return int(front.sum()), int((ls > rs).sum())


def _candidates(count: int, *, source, field: str, forced: str | None) -> tuple[JointSet, ...]:
    """The layouts of ``count`` keypoints to score (``forced`` must be one of them)."""
    if forced is not None:
        js = SOURCE_LAYOUTS.get(forced.lower())
        if js is None:
            raise SceneFormatError(
                source,
                "layout",
                f"unknown layout {forced!r}; expected one of {sorted(SOURCE_LAYOUTS)}",
            )
        if js.num_joints != count:
            raise SceneFormatError(
                source,
                field,
                f"expected {js.num_joints} keypoints ({js.name}, forced), got {count}",
            )
        return CANDIDATES_BY_COUNT[count]
    candidates = CANDIDATES_BY_COUNT.get(count, ())
    if not candidates:
        raise SceneFormatError(
            source,
            field,
            f"cannot tell the layout of {count} keypoints; known layouts: "
            + ", ".join(f"{js.name} ({js.num_joints})" for js in SOURCE_LAYOUTS.values())
            + "; name one with --layout",
        )
    return candidates


def _weak_evidence(
    num_detections: int,
    best: JointSet,
    second: JointSet | None,
    scores: dict[str, float],
    tests: dict[str, int],
) -> list[str]:
    """Why the evidence does not single out ``best`` (empty: it does)."""
    weak = []
    if num_detections < MIN_DETECTIONS:
        weak.append(f"only {num_detections} detections (need {MIN_DETECTIONS})")
    if tests[best.name] < MIN_TESTS:
        weak.append(f"only {tests[best.name]} tests could be made (need {MIN_TESTS})")
    if scores[best.name] < MIN_SCORE:
        weak.append(
            f"the best, {best.name}, holds in {scores[best.name]:.0%} (need {MIN_SCORE:.0%})"
        )
    if second is not None and scores[best.name] - scores[second.name] < MIN_MARGIN:
        weak.append(
            f"{best.name} ({scores[best.name]:.0%}) and {second.name} "
            f"({scores[second.name]:.0%}) are too close (need {MIN_MARGIN:.0%} apart)"
        )
    return weak


def identify_layout(
    keypoints: np.ndarray, *, source, field: str = "keypoints", forced: str | None = None
) -> LayoutDecision:
    """Decide the layout of ``keypoints`` (all detections of a file tree, one count).

    Args:
        keypoints: (N, K, 3) x, y pixels, confidence (0 = missing).
        source: the file or directory, for errors.
        field: the field that held the keypoints, for errors.
        forced: a layout name that overrides the decision (must have K points).
    Raises:
        SceneFormatError naming ``source``, the count and ``--layout`` when no layout has
        K points, or the evidence does not single one out.
    """
    keypoints = np.asarray(keypoints, float)
    if keypoints.ndim != 3 or keypoints.shape[2] != 3:
        raise SceneFormatError(
            source, field, f"expected (N, K, 3) keypoints, got {keypoints.shape}"
        )
    count = keypoints.shape[1]
    candidates = _candidates(count, source=source, field=field, forced=forced)
    scores, tests = {}, {}
    for js in candidates:
        families = anatomy_tests(keypoints, js)
        scores[js.name] = layout_score(families)
        tests[js.name] = sum(m for _, m in families.values())
    ranked = sorted(candidates, key=lambda js: -scores[js.name])
    best = ranked[0] if forced is None else SOURCE_LAYOUTS[forced.lower()]
    second = next((js for js in ranked if js is not best), None)
    front, left_right = facing_evidence(keypoints, best)
    evidence = [
        f"{len(keypoints)} detections of {count} keypoints; candidates "
        + ", ".join(f"{js.name} {scores[js.name]:.1%} of {tests[js.name]} tests" for js in ranked)
        + " (vertical body order, mid-points, left/right pairs agreeing)"
    ]
    if front:
        evidence.append(
            f"{front} detections face the camera; in {left_right} of them the left shoulder "
            "is on the image's right (the person's left)"
        )
    decision = LayoutDecision(
        layout=best.name,
        forced=forced is not None,
        candidates=tuple(js.name for js in candidates),
        scores=scores,
        num_tests=tests,
        num_detections=len(keypoints),
        front_facing=front,
        left_on_image_right=left_right,
        evidence=tuple(evidence),
    )
    if forced is not None:
        return _with(decision, f"layout {best.name} forced by --layout")
    weak = _weak_evidence(len(keypoints), best, second, scores, tests)
    if weak:
        raise SceneFormatError(
            source,
            field,
            f"cannot tell the layout of these {count}-keypoint detections: "
            + "; ".join(weak)
            + f"; name it with --layout ({', '.join(js.name for js in candidates)})",
        )
    if front >= 10 and left_right < 0.3 * front:
        raise SceneFormatError(
            source,
            field,
            f"read as {best.name}, left and right look swapped: in {front - left_right} of "
            f"{front} detections facing the camera the 'left' shoulder is on the person's "
            "right (mirrored videos, or a detector that labels image sides); pass "
            f"--layout {best.name} to read the labels as they are",
        )
    return _with(decision, f"layout {best.name} taken from the data")


def _with(decision: LayoutDecision, line: str) -> LayoutDecision:
    return LayoutDecision(**{**decision.__dict__, "evidence": (line,) + decision.evidence})
