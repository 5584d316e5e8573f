"""Evaluation metrics: pure, NaN-aware functions over arrays.

Units: 3D positions and their errors in millimetres; accelerations in mm/frame^2
(per frame, not per second); reprojection errors in pixels. NaN (or any non-finite
value) marks a missing joint, person or sample: metrics skip it, never raise on it,
and return NaN where nothing finite is left to average.

Conventions, with their sources:

* Person matching (:func:`match_people`): per frame, Hungarian assignment
  (``scipy.optimize.linear_sum_assignment``) on the MPJPE between every
  (prediction, ground truth) pair, gated at ``max_mpjpe`` (a pair above it is a miss
  plus a false positive). VoxelPose / MvP / Faster-VoxelPose's Shelf/Campus
  ``evaluate`` instead take, for each GT person, the prediction of least MPJPE
  (``argmin``, not exclusive, no gate) and count a GT as recalled when that MPJPE is
  ``< 500`` mm ("Recall@500mm"). We gate at ``<= max_mpjpe`` and keep matches
  one-to-one; with well-separated people both give the same pairs.
  :func:`match_sequence` runs it per frame and lays the result out per GT instance
  (:class:`SequenceMatch`); :func:`pose_metrics` summarises that.
* PCP (:func:`limb_correct`, :func:`pcp`, :func:`pcp_per_person`): a limb is correct
  when the *mean* of its two endpoint errors is ``<= alpha * |GT limb|`` with
  alpha = 0.5, as in ``Shelf.evaluate`` / ``Campus.evaluate`` of
  microsoft/voxelpose-pytorch, sail-sg/mvp and AlvinYH/Faster-VoxelPose
  (``(error_s + error_e) / 2.0 <= alpha * limb_length``). Their ten limbs: lower legs,
  upper legs, lower arms, upper arms (left and right), head (Bottom-Head to Top-Head)
  and torso (mid-point of the two hips to Bottom-Head). Ours are the SMPL-24
  counterparts in :data:`PCP_LIMBS`; two differ: torso is SMPL ``pelvis`` to ``neck``
  (SMPL's pelvis sits near, not at, the hip mid-point) and head is ``neck`` to
  ``head`` (SMPL's head joint is mid-skull, not the top), so those two are not
  numerically comparable with published Shelf/Campus tables. Per-person PCP pools
  all limbs of all frames where the GT person exists (``correct_parts /
  total_parts``) and the reported average is the mean over persons (the papers
  average actors 0-2); a GT person with no matched prediction counts all its limbs
  wrong (NaN prediction).
* MPJPE / PCK (:func:`mpjpe`, :func:`pck`): pooled over all finite joint errors of
  matched pairs; PCK@160 mm counts an error as correct when ``< threshold``.
* Acceleration error (:func:`acceleration_error`): second differences
  ``x[t-1] - 2 x[t] + x[t+1]`` as HMR / VIBE ``compute_error_accel``
  (akanazawa/human_dynamics ``eval_util.py``), the norm of the difference averaged
  over joints and frames; their code (like ours) is per frame^2 although the papers
  label it mm/s^2. A joint's acceleration at ``t`` exists only when the joint is
  finite at ``t-1``, ``t`` and ``t+1`` (HMR drops the whole frame on a per-frame
  visibility flag; ours is the same rule per joint).
* ID switches (:func:`id_switches`): CLEAR-MOT (Bernardin & Stiefelhagen 2008) as
  implemented in py-motmetrics ``MOTAccumulator.update``: a switch is a match of a GT
  object to a hypothesis other than the one it was last matched to; the memory
  survives frames where the object is unmatched (default ``max_switch_time = inf``).
  py-motmetrics also prefers, before its Hungarian step, to keep last frame's
  correspondence when still within the gate; :func:`match_people` does not, so in
  ambiguous frames the matched pairs (and hence the count) may differ.
* Association (:func:`association_scores`): pairwise precision / recall within each
  frame (see there).
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from pipeline.core.assignment import gated_assignment
from pipeline.data.joint_sets import SMPL24, coco17_smpl24_pairs

# SMPL-24 indices of the 12 joints COCO-17 also has (shoulders, elbows, wrists, hips,
# knees, ankles): the subset on which a COCO-based method and an SMPL fit compare.
SMPL24_COCO_JOINTS: np.ndarray = coco17_smpl24_pairs()[1]
SMPL24_ALL_JOINTS: np.ndarray = np.arange(SMPL24.num_joints)


MATCH_GATE_MM = 500.0
"""Two people whose MPJPE is above this are different people: the gate of every
person matching (against ground truth, between runs, in the failure review)."""

def _limb(a: str, b: str) -> tuple[int, int]:
    return SMPL24.index[a], SMPL24.index[b]


# The ten Shelf/Campus PCP limbs on SMPL-24 (see module docstring for head and torso).
PCP_LIMBS: dict[str, tuple[int, int]] = {
    "left_upper_arm": _limb("left_shoulder", "left_elbow"),
    "right_upper_arm": _limb("right_shoulder", "right_elbow"),
    "left_lower_arm": _limb("left_elbow", "left_wrist"),
    "right_lower_arm": _limb("right_elbow", "right_wrist"),
    "left_upper_leg": _limb("left_hip", "left_knee"),
    "right_upper_leg": _limb("right_hip", "right_knee"),
    "left_lower_leg": _limb("left_knee", "left_ankle"),
    "right_lower_leg": _limb("right_knee", "right_ankle"),
    "head": _limb("neck", "head"),
    "torso": _limb("pelvis", "neck"),
}
# The rows of the papers' PCP tables.
PCP_LIMB_GROUPS: dict[str, tuple[str, ...]] = {
    "head": ("head",),
    "torso": ("torso",),
    "upper_arms": ("left_upper_arm", "right_upper_arm"),
    "lower_arms": ("left_lower_arm", "right_lower_arm"),
    "upper_legs": ("left_upper_leg", "right_upper_leg"),
    "lower_legs": ("left_lower_leg", "right_lower_leg"),
}
_LIMB_NAMES = tuple(PCP_LIMBS)
_LIMB_IDX = np.array(list(PCP_LIMBS.values()))  # (num_limbs, 2)


# ---------------------------------------------------------------------------
# NaN-aware reductions (no RuntimeWarnings on empty / all-NaN input)
# ---------------------------------------------------------------------------


def _finite_mean(x: np.ndarray, axis: int | tuple[int, ...] | None = None) -> np.ndarray:
    """Mean over the finite entries along ``axis``; NaN where there are none."""
    x = np.asarray(x, dtype=float)
    finite = np.isfinite(x)
    total = np.where(finite, x, 0.0).sum(axis=axis)
    count = finite.sum(axis=axis)
    with np.errstate(invalid="ignore", divide="ignore"):
        return total / count


def _finite_median(x: np.ndarray, axis: int | tuple[int, ...] | None = None) -> np.ndarray:
    x = np.where(np.isfinite(x), x, np.nan)
    if x.size == 0:
        return _finite_mean(x, axis=axis)  # right shape, all NaN
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN slices -> NaN
        return np.nanmedian(x, axis=axis)


def _check_points(name: str, x: np.ndarray, min_ndim: int = 2) -> np.ndarray:
    x = np.asarray(x, dtype=float)
    if x.ndim < min_ndim or x.shape[-1] not in (2, 3):
        raise ValueError(f"{name}: expected (..., num_joints, 3) (or 2), got {x.shape}")
    return x


def _check_same(pred: np.ndarray, gt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    pred, gt = _check_points("pred", pred), _check_points("gt", gt)
    if pred.shape != gt.shape:
        raise ValueError(f"pred shape {pred.shape} != gt shape {gt.shape}")
    return pred, gt


# ---------------------------------------------------------------------------
# Joint errors, MPJPE, PCK
# ---------------------------------------------------------------------------


def joint_errors(pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """Euclidean error of every joint.

    Args:
        pred, gt: (..., num_joints, 3) positions, mm; NaN marks a missing joint.
    Returns:
        (..., num_joints) errors, mm; NaN where either side is missing.
    """
    pred, gt = _check_same(pred, gt)
    err = np.linalg.norm(pred - gt, axis=-1)
    return np.where(np.isfinite(err), err, np.nan)


def mpjpe(pred: np.ndarray, gt: np.ndarray, *, joints: np.ndarray | None = None) -> float:
    """Mean per-joint position error of paired poses, pooled over all finite joint errors.

    Args:
        pred, gt: (..., num_joints, 3) paired poses (e.g. the matched pairs, (K, J, 3)), mm.
        joints: optional joint indices to restrict to, e.g. :data:`SMPL24_COCO_JOINTS`.
    Returns:
        MPJPE in mm; NaN when no joint is finite on both sides.
    """
    err = joint_errors(pred, gt)
    if joints is not None:
        err = err[..., np.asarray(joints, dtype=int)]
    return float(_finite_mean(err))


def pck(errors: np.ndarray, threshold: float = 160.0) -> float:
    """Fraction of finite joint errors strictly below ``threshold`` (PCK@160 mm by default).

    Args:
        errors: any-shaped array of joint errors, mm (NaN ignored).
    Returns:
        fraction in [0, 1]; NaN when no error is finite.
    """
    errors = np.asarray(errors, dtype=float)
    finite = np.isfinite(errors)
    n = int(finite.sum())
    if n == 0:
        return float("nan")
    return float((errors[finite] < threshold).sum() / n)


def mpjpe_matrix(pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """MPJPE of every (prediction, ground truth) pair over the joints both have.

    Args:
        pred: (num_pred, num_joints, 3), mm.
        gt: (num_gt, num_joints, 3), mm.
    Returns:
        (num_pred, num_gt) MPJPE, mm; NaN where the two share no finite joint.
    """
    pred, gt = _check_points("pred", pred, 3), _check_points("gt", gt, 3)
    if pred.ndim != 3 or gt.ndim != 3 or pred.shape[1:] != gt.shape[1:]:
        raise ValueError(
            f"expected pred (num_pred, J, 3) and gt (num_gt, J, 3), got {pred.shape}, {gt.shape}"
        )
    err = np.linalg.norm(pred[:, None] - gt[None], axis=-1)  # (P, G, J)
    return _finite_mean(err, axis=-1)


def match_people(
    pred: np.ndarray, gt: np.ndarray, *, max_mpjpe: float = MATCH_GATE_MM
) -> list[tuple[int, int]]:
    """One frame's one-to-one matching of predicted to ground-truth people.

    Hungarian assignment on :func:`mpjpe_matrix`; a pair whose MPJPE is above
    ``max_mpjpe`` (or undefined, e.g. an all-NaN person) is never a match, so its
    people count as a false positive and a miss. Among assignments the number of
    matches is maximised first, then their total MPJPE minimised.

    Args:
        pred: (num_pred, num_joints, 3), mm.
        gt: (num_gt, num_joints, 3), mm.
        max_mpjpe: gate, mm; pairs with MPJPE ``<= max_mpjpe`` may match.
    Returns:
        ``[(pred_index, gt_index), ...]`` sorted by ``pred_index``.
    """
    cost = mpjpe_matrix(pred, gt)
    rows, cols = gated_assignment(cost, cost <= max_mpjpe)
    return [(int(p), int(g)) for p, g in zip(rows, cols, strict=True)]


# ---------------------------------------------------------------------------
# Matching a whole sequence
# ---------------------------------------------------------------------------


@dataclass(frozen=True)
class SequenceMatch:
    """Per-frame matches of a sequence, one row per ground-truth person instance.

    A GT person is present in a frame when it has a finite joint; a prediction is
    counted when it has a finite joint.

    Attributes:
        frame: (num_instances,) frame index of each GT instance.
        gt_index: (num_instances,) index of the GT person within its frame's array
            (its person id when GT is given as a dense (frames, people, J, 3) array).
        pred_index: (num_instances,) matched prediction within its frame's array, -1 if
            unmatched (its track id when predictions are dense, indexed by track).
        gt: (num_instances, num_joints, 3) GT poses, mm.
        pred: (num_instances, num_joints, 3) matched predictions, mm; NaN where unmatched.
        num_pred: number of predictions over all frames.
    """

    frame: np.ndarray
    gt_index: np.ndarray
    pred_index: np.ndarray
    gt: np.ndarray
    pred: np.ndarray
    num_pred: int

    @property
    def matched(self) -> np.ndarray:
        """(num_instances,) bool."""
        return self.pred_index >= 0


def _present(people: np.ndarray) -> np.ndarray:
    return np.isfinite(people).all(axis=-1).any(axis=-1)


def match_sequence(
    preds: Sequence[np.ndarray] | np.ndarray,
    gts: Sequence[np.ndarray] | np.ndarray,
    *,
    max_mpjpe: float = MATCH_GATE_MM,
) -> SequenceMatch:
    """Run :func:`match_people` on every frame.

    Args:
        preds: per frame a (num_pred_t, num_joints, 3) array, mm (or one NaN-padded
            (num_frames, num_slots, num_joints, 3) array).
        gts: per frame a (num_gt_t, num_joints, 3) array, mm (or a dense NaN-padded array).
        max_mpjpe: gate, mm.
    """
    if len(preds) != len(gts):
        raise ValueError(f"{len(preds)} prediction frames but {len(gts)} ground-truth frames")
    preds = [np.asarray(p, dtype=float) for p in preds]
    gts = [np.asarray(g, dtype=float) for g in gts]
    shapes = {a.shape[-2] for a in preds + gts if a.size > 0 and a.ndim == 3}
    if len(shapes) > 1:
        raise ValueError(f"people have different joint counts across frames: {sorted(shapes)}")
    j = shapes.pop() if shapes else 0
    frames, gt_idx, pred_idx, gt_rows, pred_rows = [], [], [], [], []
    num_pred = 0
    for f, (p, g) in enumerate(zip(preds, gts, strict=True)):
        p = p.reshape(0, j, 3) if p.size == 0 else p
        g = g.reshape(0, j, 3) if g.size == 0 else g
        num_pred += int(_present(p).sum())
        matches = {gi: pi for pi, gi in match_people(p, g, max_mpjpe=max_mpjpe)}
        for gi in np.flatnonzero(_present(g)):
            pi = matches.get(int(gi), -1)
            frames.append(f)
            gt_idx.append(gi)
            pred_idx.append(pi)
            gt_rows.append(g[gi])
            pred_rows.append(p[pi] if pi >= 0 else np.full_like(g[gi], np.nan))
    return SequenceMatch(
        frame=np.asarray(frames, dtype=int),
        gt_index=np.asarray(gt_idx, dtype=int),
        pred_index=np.asarray(pred_idx, dtype=int),
        gt=np.asarray(gt_rows, dtype=float).reshape(len(gt_rows), j, 3),
        pred=np.asarray(pred_rows, dtype=float).reshape(len(pred_rows), j, 3),
        num_pred=num_pred,
    )


def _ratio(num: float, den: float) -> float:
    return float(num / den) if den > 0 else float("nan")


def pose_metrics(
    match: SequenceMatch,
    *,
    pck_threshold: float = 160.0,
    alpha: float = 0.5,
    pcp_persons: Sequence[int] | None = None,
) -> dict[str, float]:
    """Summary of an SMPL-24 sequence match (the numbers of the method's results table).

    Returns:
        ``num_gt``, ``num_pred``, ``num_matched``; ``recall`` (matched / GT instances)
        and ``precision`` (matched / predictions); ``mpjpe`` and ``pck`` over all 24
        joints of the matched pairs and ``mpjpe_coco`` / ``pck_coco`` over
        :data:`SMPL24_COCO_JOINTS`; ``pcp``, the Shelf/Campus average of per-person
        PCP (unmatched GT counts all limbs wrong; ``pcp_persons`` restricts the average,
        e.g. ``[0, 1, 2]`` as the papers do). NaN where undefined.
    """
    m = match.matched
    n_gt, n_matched = int(len(m)), int(m.sum())
    if n_gt > 0 and match.gt.shape[1] != SMPL24.num_joints:
        raise ValueError(f"pose_metrics expects SMPL-24 poses, got {match.gt.shape[1]} joints")
    err = joint_errors(match.pred[m], match.gt[m]) if n_gt else np.zeros((0, 0))
    coco = err[:, SMPL24_COCO_JOINTS] if n_gt else err
    pcp_avg = float("nan")
    if n_gt:
        by_person = pcp_per_person(
            match.pred, match.gt, match.gt_index, alpha=alpha, persons=pcp_persons
        )
        pcp_avg = by_person["average"]
    return {
        "num_gt": n_gt,
        "num_pred": int(match.num_pred),
        "num_matched": n_matched,
        "recall": _ratio(n_matched, n_gt),
        "precision": _ratio(n_matched, match.num_pred),
        "mpjpe": float(_finite_mean(err)),
        "pck": pck(err, pck_threshold),
        "mpjpe_coco": float(_finite_mean(coco)),
        "pck_coco": pck(coco, pck_threshold),
        "pcp": pcp_avg,
    }


# ---------------------------------------------------------------------------
# PCP
# ---------------------------------------------------------------------------


def limb_correct(pred: np.ndarray, gt: np.ndarray, *, alpha: float = 0.5) -> np.ndarray:
    """Shelf/Campus PCP test of every limb of :data:`PCP_LIMBS`.

    Args:
        pred, gt: (..., 24, 3) SMPL-24 poses, mm. A NaN prediction (e.g. an unmatched
            GT person) makes its limbs wrong; a limb with a NaN GT endpoint is not scored.
    Returns:
        (..., num_limbs) 1.0 correct, 0.0 wrong, NaN not scored; correct when
        ``(err_a + err_b) / 2 <= alpha * |gt_a - gt_b|``.
    """
    pred, gt = _check_same(pred, gt)
    if gt.shape[-2] != SMPL24.num_joints:
        raise ValueError(f"PCP expects SMPL-24 poses (..., 24, 3), got {gt.shape}")
    err = np.linalg.norm(pred - gt, axis=-1)  # (..., 24)
    a, b = _LIMB_IDX[:, 0], _LIMB_IDX[:, 1]
    length = np.linalg.norm(gt[..., a, :] - gt[..., b, :], axis=-1)
    mean_err = (err[..., a] + err[..., b]) / 2.0
    with np.errstate(invalid="ignore"):
        correct = (mean_err <= alpha * length).astype(float)  # NaN compares False: wrong
    return np.where(np.isfinite(length), correct, np.nan)


def _pcp_table(correct: np.ndarray) -> tuple[dict[str, float], dict[str, float], float]:
    """(per limb, per table row, pooled) PCP of a (num_rows, num_limbs) correctness table."""
    limbs = {n: float(_finite_mean(correct[:, i])) for i, n in enumerate(_LIMB_NAMES)}
    groups = {
        g: float(_finite_mean(correct[:, [_LIMB_NAMES.index(n) for n in names]]))
        for g, names in PCP_LIMB_GROUPS.items()
    }
    return limbs, groups, float(_finite_mean(correct))


def pcp(pred: np.ndarray, gt: np.ndarray, *, alpha: float = 0.5) -> dict[str, object]:
    """Percentage of correct parts of paired SMPL-24 poses.

    Args:
        pred, gt: (num_poses, 24, 3), mm; a NaN ``pred`` row counts all its limbs wrong.
    Returns:
        ``{"limbs": {limb: pcp}, "groups": {table row: pcp}, "average": pcp}``, each a
        fraction in [0, 1] (pooled over scored limbs: correct / scored, as
        ``correct_parts / total_parts`` in the references); NaN where nothing is scored.
    """
    correct = limb_correct(pred, gt, alpha=alpha).reshape(-1, len(_LIMB_NAMES))
    limbs, groups, average = _pcp_table(correct)
    return {"limbs": limbs, "groups": groups, "average": average}


def pcp_per_person(
    pred: np.ndarray,
    gt: np.ndarray,
    person: np.ndarray,
    *,
    alpha: float = 0.5,
    persons: Sequence[int] | None = None,
) -> dict[str, object]:
    """Shelf/Campus-style PCP: per GT person over the frames it exists, then averaged.

    Args:
        pred, gt: (num_instances, 24, 3), one row per GT person per frame (e.g.
            :class:`SequenceMatch` ``pred`` / ``gt``), mm; unmatched rows NaN in ``pred``.
        person: (num_instances,) GT person id of each row.
        persons: ids to average over (default all present); the papers use actors 0-2.
    Returns:
        ``{"per_person": {id: pcp}, "average": mean over ``persons``,
        "per_person_groups": {id: {table row: pcp}}}``.
    """
    correct = limb_correct(pred, gt, alpha=alpha)
    person = np.asarray(person, dtype=int).reshape(-1)
    if person.shape[0] != correct.shape[0]:
        raise ValueError(f"person has {person.shape[0]} rows, poses have {correct.shape[0]}")
    per_person: dict[int, float] = {}
    per_groups: dict[int, dict[str, float]] = {}
    for pid in np.unique(person):
        _, groups, average = _pcp_table(correct[person == pid])
        per_person[int(pid)] = average
        per_groups[int(pid)] = groups
    ids = list(per_person) if persons is None else [int(p) for p in persons]
    vals = np.array([per_person.get(p, np.nan) for p in ids], dtype=float)
    return {
        "per_person": per_person,
        "average": float(_finite_mean(vals)),
        "per_person_groups": per_groups,
    }


# ---------------------------------------------------------------------------
# Temporal smoothness
# ---------------------------------------------------------------------------


def acceleration(x: np.ndarray) -> np.ndarray:
    """Second differences along time: ``x[t] - 2 x[t+1] + x[t+2]``.

    Args:
        x: (num_frames, ..., 3) positions, mm.
    Returns:
        (num_frames - 2, ..., 3) accelerations, mm/frame^2 (empty when fewer than 3
        frames); NaN where any of the three samples is.
    """
    x = np.asarray(x, dtype=float)
    if x.ndim < 1:
        raise ValueError(f"expected (num_frames, ..., 3), got {x.shape}")
    return x[:-2] - 2.0 * x[1:-1] + x[2:]


def acceleration_error(pred: np.ndarray, gt: np.ndarray) -> float:
    """Mean ``|a_pred - a_gt|`` over joints and frames (HMR/VIBE, but mm/frame^2).

    Args:
        pred, gt: (num_frames, num_joints, 3) one person's trajectory, mm.
    Returns:
        mm/frame^2, over the (t, joint) where both are finite at t-1, t, t+1; NaN if none.
    """
    pred, gt = _check_same(pred, gt)
    diff = np.linalg.norm(acceleration(pred) - acceleration(gt), axis=-1)
    return float(_finite_mean(diff))


def jitter(pred: np.ndarray) -> float:
    """Mean ``|a_pred|`` over joints and frames, mm/frame^2 (NaN-aware as above).

    Args:
        pred: (num_frames, num_joints, 3), mm.
    """
    pred = _check_points("pred", pred)
    return float(_finite_mean(np.linalg.norm(acceleration(pred), axis=-1)))


# ---------------------------------------------------------------------------
# Multi-view association
# ---------------------------------------------------------------------------


def association_scores(
    pred_cluster: np.ndarray, gt_person: np.ndarray, frame: np.ndarray
) -> dict[str, float]:
    """Pairwise precision / recall of a cross-view association.

    Within each frame, two detections form a *predicted pair* when they share a
    cluster id ``>= 0`` and a *true pair* when they share a GT person ``>= 0``; a
    correct pair is both. Precision = correct / predicted pairs, recall = correct /
    true pairs, each defined as 1.0 when its denominator is 0 (nothing claimed,
    nothing missed); F1 is their harmonic mean (0 when both are 0).

    Args:
        pred_cluster: (num_detections,) int cluster id, -1 = unassigned.
        gt_person: (num_detections,) int GT person, -1 = false-positive detection.
        frame: (num_detections,) int frame of each detection.
    Returns:
        precision, recall, f1, true_pairs, pred_pairs, correct_pairs,
        false_positives_assigned (GT -1 detections put in a cluster) and
        detections_unassigned (cluster -1 detections).
    """
    c = np.asarray(pred_cluster, dtype=int).reshape(-1)
    g = np.asarray(gt_person, dtype=int).reshape(-1)
    f = np.asarray(frame, dtype=int).reshape(-1)
    if not (c.shape == g.shape == f.shape):
        raise ValueError(f"length mismatch: {c.shape}, {g.shape}, {f.shape}")
    true_pairs = pred_pairs = correct_pairs = 0
    for fr in np.unique(f):
        cf, gf = c[f == fr], g[f == fr]
        upper = np.triu(np.ones((len(cf), len(cf)), dtype=bool), k=1)
        same_c = (cf[:, None] == cf[None]) & (cf[:, None] >= 0) & upper
        same_g = (gf[:, None] == gf[None]) & (gf[:, None] >= 0) & upper
        pred_pairs += int(same_c.sum())
        true_pairs += int(same_g.sum())
        correct_pairs += int((same_c & same_g).sum())
    precision = correct_pairs / pred_pairs if pred_pairs else 1.0
    recall = correct_pairs / true_pairs if true_pairs else 1.0
    f1 = 2 * precision * recall / (precision + recall) if precision + recall > 0 else 0.0
    return {
        "precision": float(precision),
        "recall": float(recall),
        "f1": float(f1),
        "true_pairs": true_pairs,
        "pred_pairs": pred_pairs,
        "correct_pairs": correct_pairs,
        "false_positives_assigned": int(((g < 0) & (c >= 0)).sum()),
        "detections_unassigned": int((c < 0).sum()),
    }


# ---------------------------------------------------------------------------
# Tracking identity
# ---------------------------------------------------------------------------


def id_switch_events(
    frames: np.ndarray, gt_ids: np.ndarray, track_ids: np.ndarray
) -> list[tuple[int, int, int, int]]:
    """CLEAR-MOT identity switches of matched (frame, GT person, track) triples.

    For each GT person, a switch is a frame where its matched track differs from the
    track it was last matched to; frames where it is unmatched keep that memory (a
    track that vanishes and returns with the same id is no switch).

    Args:
        frames, gt_ids, track_ids: (num_matches,) int, one row per matched pair, any order.
    Returns:
        ``[(frame, gt_id, old_track, new_track), ...]`` in frame order.
    """
    fr = np.asarray(frames, dtype=int).reshape(-1)
    gi = np.asarray(gt_ids, dtype=int).reshape(-1)
    ti = np.asarray(track_ids, dtype=int).reshape(-1)
    if not (fr.shape == gi.shape == ti.shape):
        raise ValueError(f"length mismatch: {fr.shape}, {gi.shape}, {ti.shape}")
    if len(set(zip(fr.tolist(), gi.tolist(), strict=True))) != len(fr):
        raise ValueError("a GT person is matched twice in one frame")
    last: dict[int, int] = {}
    events = []
    for k in np.argsort(fr, kind="stable"):
        f, g, t = int(fr[k]), int(gi[k]), int(ti[k])
        if g in last and last[g] != t:
            events.append((f, g, last[g], t))
        last[g] = t
    return events


def id_switches(frames: np.ndarray, gt_ids: np.ndarray, track_ids: np.ndarray) -> int:
    """Number of CLEAR-MOT identity switches; see :func:`id_switch_events`."""
    return len(id_switch_events(frames, gt_ids, track_ids))


# ---------------------------------------------------------------------------
# Reprojection
# ---------------------------------------------------------------------------


def per_view_joint_reprojection(errors: np.ndarray) -> dict[str, np.ndarray]:
    """Reprojection error statistics per camera and joint.

    Args:
        errors: (num_frames, num_people, num_joints, num_views) pixel errors, NaN
            where a joint is not seen / not detected in a view.
    Returns:
        ``mean``, ``median`` (num_views, num_joints) px and ``count`` (num_views,
        num_joints) of finite values; ``view_mean``, ``view_median`` (num_views,) over
        all joints. NaN where a cell has no finite value.
    """
    e = np.asarray(errors, dtype=float)
    if e.ndim != 4:
        raise ValueError(f"expected (num_frames, num_people, num_joints, num_views), got {e.shape}")
    n_f, n_p, n_j, n_v = e.shape
    per_vj = np.moveaxis(e, -1, 0).reshape(n_v, n_f * n_p, n_j)
    per_v = per_vj.reshape(n_v, n_f * n_p * n_j)
    return {
        "mean": _finite_mean(per_vj, axis=1),
        "median": _finite_median(per_vj, axis=1),
        "count": np.isfinite(per_vj).sum(axis=1),
        "view_mean": _finite_mean(per_v, axis=1),
        "view_median": _finite_median(per_v, axis=1),
    }
