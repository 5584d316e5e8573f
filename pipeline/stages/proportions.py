"""A person's own proportions as evidence: joints whose bones contradict the rest of
their track are re-solved from the views that agree with the body, or flagged.

Triangulation judges each joint alone: with two views, or three of which one is
another person's arm, it cannot tell a wrong point from a right one (a 2-view joint
reprojects well wherever the two rays cross). The track knows more: over its frames
a person's bones keep their lengths, so an upper arm of 456 mm on a person whose
upper arm is 303 mm in every other frame is a wrong elbow, not a long arm. On the
real Shelf sequence (OpenPose detections) such joints are a wrist or elbow taken from
the wrong view pair for a few frames, 300 mm off while the other pair of views
placed it within 35 mm.

For every person-frame of a track (after stitching, so that the track is the
person's whole run):

1. Each bone's length is compared with its median over the track (a track needs
   ``min_track_frames`` frames with the bone to have a median). A bone more than
   ``tolerance`` (relative) off is *off*.
2. Off bones are taken from the body's centre outwards (the skeleton rooted at its
   joint of most bones: the neck, or the pelvis), the bone's outer end ``c`` and
   everything beyond it (the limb from ``c`` on) being the suspect. An end seen by
   ``trusted_views`` or more agreeing views is kept as measured: views that many do
   not agree by chance.
3. The suspect limb is triangulated from every pair of the person's views, and the
   pair whose limb fits the track's bones best is taken if all its bones are within
   ``tolerance``; the views that agree with it (reprojection within the
   triangulation's outlier threshold) join it in a last solve. Those joints are
   *re-solved*.
4. Where no pair fits, the suspect joints (those not trusted) are *contradicted*:
   they stay in the track's measurements, for the viewer to show, but the Kalman
   filter does not take them (it coasts there, as through a gap).

Units: mm; the 2D joints are distorted pixels with a confidence.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from itertools import combinations

import numpy as np

from pipeline.data.cameras import CameraRig
from pipeline.stages.track import bone_lengths
from pipeline.stages.triangulate import triangulate_people


@dataclass(frozen=True)
class ProportionParams:
    enabled: bool = True
    """Judge joints by their track's bone lengths (re-solve or flag those that contradict)."""
    tolerance: float = 0.25
    """A bone whose length differs from its track's median by more than this fraction is
    off (bones vary 5-10 % in a triangulated track from 2D noise and joint centres that
    move; a joint from the wrong view is off by 30-50 %)."""
    trusted_views: int = 3
    """A joint solved from this many agreeing views is kept as measured."""
    min_track_frames: int = 10
    """Frames with a bone that its track needs before the bone's median is trusted."""


@dataclass(frozen=True, eq=False)
class PersonEvidence:
    """What the per-frame stages saw of each person-frame, for re-solving its joints.

    Attributes:
        rig: the V cameras.
        joints2d: (N, J, 3) every detection row's 2D joints (u, v px, confidence).
        members: (Q, V) the detection row of each person-frame in each view, -1 if none.
        used: (Q, J, V) bool, the views each joint was triangulated from.
        min_confidence: 2D joints below this are not used (the triangulation's).
        outlier_threshold_px: a view agrees with a point within this reprojection error.
    """

    rig: CameraRig
    joints2d: np.ndarray
    members: np.ndarray
    used: np.ndarray
    min_confidence: float = 0.1
    outlier_threshold_px: float = 20.0


@dataclass(frozen=True, eq=False)
class ProportionCheck:
    """The person-frames' joints after the check.

    Attributes:
        joints: (Q, J, 3) mm, re-solved joints replaced, the rest as given.
        resolved: (Q, J) bool, re-solved from the views that fit the track's bones.
        contradicted: (Q, J) bool, kept as measured but contradicting the track's bones.
        bone_median: (K, B) each track's median bone lengths, mm (NaN: too few frames).
    """

    joints: np.ndarray
    resolved: np.ndarray
    contradicted: np.ndarray
    bone_median: np.ndarray


def skeleton_tree(bones: np.ndarray, num_joints: int) -> tuple[np.ndarray, list[int]]:
    """The skeleton rooted at its joint of most bones: (J,) parent of each joint (-1 at
    the root and at joints no bone reaches) and the joints in breadth-first order."""
    bones = np.asarray(bones, int).reshape(-1, 2)
    neighbours: list[list[int]] = [[] for _ in range(num_joints)]
    for a, b in bones:
        neighbours[a].append(b)
        neighbours[b].append(a)
    parent = np.full(num_joints, -1)
    if len(bones) == 0:
        return parent, []
    root = int(np.argmax([len(n) for n in neighbours]))
    order, seen, todo = [], {root}, deque([root])
    while todo:
        j = todo.popleft()
        order.append(j)
        for n in neighbours[j]:
            if n not in seen:
                seen.add(n)
                parent[n] = j
                todo.append(n)
    return parent, order


def track_bone_medians(
    joints: np.ndarray, track_of: np.ndarray, bones: np.ndarray, num_tracks: int, min_frames: int
) -> np.ndarray:
    """(Q, J, 3) person-frames, (Q,) their tracks -> (K, B) median bone lengths per track,
    NaN where a track has the bone in fewer than ``min_frames`` frames."""
    lengths = bone_lengths(joints, bones)  # (Q, B)
    out = np.full((num_tracks, len(bones)), np.nan)
    for k in range(num_tracks):
        rows = lengths[track_of == k]
        count = np.isfinite(rows).sum(0)
        enough = count >= max(min_frames, 1)
        if enough.any():
            out[k, enough] = np.nanmedian(rows[:, enough], axis=0)
    return out


def _deviation(pose: np.ndarray, bones: np.ndarray, median: np.ndarray) -> np.ndarray:
    """(..., J, 3) poses -> (..., B) |length / median - 1| (NaN where unknown)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.abs(bone_lengths(pose, bones) / median - 1.0)


def _views_of(evidence: PersonEvidence, q: int) -> np.ndarray:
    """(V, J, 3) person-frame ``q``'s 2D joints in every view (NaN where it has none)."""
    V, J = len(evidence.rig), evidence.joints2d.shape[1]
    obs = np.full((V, J, 3), np.nan)
    rows = evidence.members[q]
    seen = rows >= 0
    obs[seen] = evidence.joints2d[rows[seen]]
    return obs


def _pair_solutions(rig: CameraRig, obs: np.ndarray, limb: np.ndarray, min_conf: float):
    """The limb's joints triangulated from every view pair that sees its first joint:
    ((C, J, 3) points, NaN outside the limb, list of the C pairs)."""
    visible = np.isfinite(obs[:, limb[0], :2]).all(-1) & (obs[:, limb[0], 2] >= min_conf)
    pairs = list(combinations(np.flatnonzero(visible).tolist(), 2))
    if not pairs:
        return np.zeros((0,) + obs.shape[1:2] + (3,)), pairs
    kp = np.full((len(pairs),) + obs.shape, np.nan)  # (C, V, J, 3)
    for i, (a, b) in enumerate(pairs):
        kp[i, [a, b]] = obs[[a, b]]
    outside = np.ones(obs.shape[1], bool)
    outside[limb] = False
    kp[:, :, outside] = np.nan  # only the limb is solved
    tri = triangulate_people(
        rig, kp, min_confidence=min_conf, outlier_threshold_px=np.inf, min_views=2
    )
    return tri.points, pairs


def _with_agreeing_views(
    evidence: PersonEvidence, obs: np.ndarray, points: np.ndarray, limb: np.ndarray
) -> np.ndarray:
    """The limb re-solved from every view whose 2D joint lies within the outlier
    threshold of ``points``' projection (the pair's own views always do)."""
    proj = evidence.rig.project(points[limb])  # (V, L, 2)
    err = np.linalg.norm(proj - obs[:, limb, :2], axis=-1)  # (V, L), NaN where unseen
    agree = np.zeros(obs.shape[:2], bool)
    with np.errstate(invalid="ignore"):
        agree[:, limb] = err <= evidence.outlier_threshold_px
    kp = np.where(agree[..., None], obs, np.nan)[None]  # (1, V, J, 3)
    tri = triangulate_people(
        evidence.rig, kp, min_confidence=evidence.min_confidence,
        outlier_threshold_px=np.inf, min_views=2,
    )  # fmt: skip
    out = points.copy()
    solved = np.isfinite(tri.points[0, limb]).all(-1)
    out[limb[solved]] = tri.points[0, limb[solved]]
    return out


def _limbs(bones: np.ndarray, num_joints: int) -> tuple[np.ndarray, np.ndarray, list[np.ndarray]]:
    """The skeleton seen from its centre (:func:`skeleton_tree`): (B,) each bone's outer
    end, (B,) the bones from the centre outwards, and per joint its limb (the joint and
    every joint beyond it)."""
    parent, order = skeleton_tree(bones, num_joints)
    depth = np.zeros(num_joints, int)
    children: list[list[int]] = [[] for _ in range(num_joints)]
    for j in order:
        if parent[j] >= 0:
            depth[j] = depth[parent[j]] + 1
            children[parent[j]].append(j)
    limbs = []
    for c in range(num_joints):
        out, todo = [], [c]
        while todo:
            j = todo.pop()
            out.append(j)
            todo.extend(children[j])
        limbs.append(np.array(out))
    outer = np.where(depth[bones[:, 0]] > depth[bones[:, 1]], bones[:, 0], bones[:, 1])
    return outer, np.argsort(depth[outer], kind="stable"), limbs


def _refit_limb(
    evidence: PersonEvidence,
    obs: np.ndarray,
    pose: np.ndarray,
    limb: np.ndarray,
    bones: np.ndarray,
    median: np.ndarray,
    tolerance: float,
) -> np.ndarray | None:
    """``pose`` (J, 3) with ``limb`` re-solved from the view pair whose limb fits the
    track's bones best (then joined by the views that agree with it), or None when no
    pair keeps every bone of the limb within ``tolerance`` of ``median`` (B,)."""
    points, pairs = _pair_solutions(evidence.rig, obs, limb, evidence.min_confidence)
    if not pairs:
        return None
    limb_bones = np.flatnonzero(np.isin(bones, limb).any(1))
    cand = np.repeat(pose[None], len(pairs), 0)  # (C, J, 3)
    solved = np.isfinite(points[:, limb]).all(-1)  # (C, L)
    for i in range(len(pairs)):
        cand[i, limb[solved[i]]] = points[i, limb[solved[i]]]
    d = _deviation(cand, bones, median)[:, limb_bones]  # (C, bl)
    worst = np.where(np.isfinite(d), d, 0.0).max(1)
    worst[~solved[:, 0]] = np.inf  # the pair must place the joint itself
    best = int(np.argmin(worst))
    if worst[best] > tolerance:
        return None
    fixed = _with_agreeing_views(evidence, obs, cand[best], limb)
    d = _deviation(fixed, bones, median)[limb_bones]
    if (np.where(np.isfinite(d), d, 0.0) > tolerance).any():
        return cand[best]  # the extra views pulled it off again
    return fixed


def check_proportions(
    person_joints: np.ndarray,
    person_track: np.ndarray,
    num_tracks: int,
    bones: np.ndarray,
    evidence: PersonEvidence | None,
    params: ProportionParams | None = None,
) -> ProportionCheck:
    """Judge every tracked person-frame's joints by its track's bone lengths (module
    docstring); without ``evidence`` (no 2D at hand) nothing is re-solved, only flagged.

    Args:
        person_joints: (Q, J, 3) triangulated joints, mm, NaN where absent.
        person_track: (Q,) track of each person-frame, -1 untracked.
        num_tracks: K.
        bones: (B, 2) joint index pairs of the skeleton.
    """
    params = ProportionParams() if params is None else params
    person_joints = np.asarray(person_joints, float)
    Q, J = person_joints.shape[:2]
    bones = np.asarray(bones, int).reshape(-1, 2)
    joints = person_joints.copy()
    resolved = np.zeros((Q, J), bool)
    contradicted = np.zeros((Q, J), bool)
    median = track_bone_medians(
        person_joints, person_track, bones, num_tracks, params.min_track_frames
    )
    if not params.enabled or Q == 0 or len(bones) == 0 or num_tracks == 0:
        return ProportionCheck(joints, resolved, contradicted, median)
    outer, bone_order, limbs = _limbs(bones, J)
    tracked = person_track >= 0
    ref = np.full((Q, len(bones)), np.nan)
    ref[tracked] = median[person_track[tracked]]
    off_any = (_deviation(person_joints, bones, ref) > params.tolerance).any(1)
    used_views = evidence.used.sum(-1) if evidence is not None else None
    for q in np.flatnonzero(off_any & tracked):
        handled = np.zeros(J, bool)  # joints of a limb already re-solved or flagged
        trusted = (
            used_views[q] >= params.trusted_views if used_views is not None else np.zeros(J, bool)
        )
        obs = _views_of(evidence, q) if evidence is not None else None
        for b in bone_order:
            dev = _deviation(joints[q], bones, ref[q])
            if not dev[b] > params.tolerance:
                continue
            c = int(outer[b])
            if trusted[c] or handled[c]:
                continue  # the outer end is seen alike by many views: the fault is inward
            limb = limbs[c]
            handled[limb] = True
            fixed = None
            if obs is not None:
                fixed = _refit_limb(evidence, obs, joints[q], limb, bones, ref[q], params.tolerance)
            if fixed is not None:
                moved = np.linalg.norm(fixed[limb] - joints[q, limb], axis=-1) > 1.0
                moved |= np.isfinite(fixed[limb]).all(-1) & ~np.isfinite(joints[q, limb]).all(-1)
                joints[q, limb] = fixed[limb]
                resolved[q, limb[moved]] = True
                contradicted[q, limb] = False
            else:
                suspect = limb[~trusted[limb] & np.isfinite(joints[q, limb]).all(-1)]
                contradicted[q, suspect] = True
    resolved &= ~contradicted
    return ProportionCheck(joints, resolved, contradicted, median)
