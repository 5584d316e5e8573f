"""Evaluation of a run against ground truth: the method's Table 1 and the extras a
researcher needs to trust it.

Rows (stages): ``raw`` triangulation, ``kalman`` (forward filter), ``rts``
(smoothed), ``smpl`` (SMPL fit to the filtered tracks, step I) and ``smpl_vae`` (that
fit corrected by the VAE pose prior), when the results carry fits. Each row: MPJPE
(mm) and PCK@160 mm over the evaluated joints, the same over the COCO-mappable
subset, PCP (Shelf/Campus convention, limbs of SMPL-24), the acceleration error and
jitter (mm/frame^2); and local plausibility per stage (joint-limit violations, bone
length spread, foot and wrist jitter). Plus association precision/recall,
ID switches and per-view, per-joint reprojection errors. Without ground truth too: the
label check of :mod:`pipeline.evaluation.label_check` (are the keypoint labels plausible?).

Which ground truth: SMPL-24 sources are scored against ``gt.joints3d``; a COCO-17
keypoint source against ``gt.keypoints3d`` (the truth in the detector's own joint
set) when the scene has it, else against the SMPL-24 joints of the COCO-mappable
subset (biased: COCO hips are not SMPL hips). Either way poses are laid out in
SMPL-24 slots (joints a set lacks are NaN), so one code path scores them all.
Predicted people are matched to ground truth per frame by Hungarian on MPJPE.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import numpy as np

from pipeline.body import pose_limits
from pipeline.data.joint_sets import SMPL24, get_joint_set, mapping_indices
from pipeline.data.scene import GroundTruth, Scene
from pipeline.evaluation import metrics
from pipeline.evaluation.label_check import LabelCheck, check_results
from pipeline.fit.types import plausibility
from pipeline.results.store import PipelineResults
from pipeline.run.frames import row_frames


@dataclass(frozen=True, eq=False)
class Evaluation:
    """Everything :func:`evaluate` measured. ``stages`` maps a row name to its figures."""

    stages: dict[str, dict[str, float]]
    association: dict[str, float]
    id_switch_events: list[tuple[int, int, int, int]]
    reprojection_view_mean: np.ndarray  # (V,) px
    reprojection_view_joint_mean: np.ndarray  # (V, J) px
    gt_source: str
    plausibility: dict[str, dict[str, float]]  # per stage: limit violations, bone std, jitter
    smpl24: dict[str, dict[str, float]]  # SMPL fits scored on all 24 SMPL joints vs joints3d
    # pipeline.evaluation.label_check on the raw tracks (no GT needed)
    labels: LabelCheck | None = None
    # per track (and "all"): median over frames of each fit's mean distance to its input
    # (the RTS tracks) and of the constant-bone-length floor's (fit_distances)
    fit_distance: dict[str, dict[str, float]] = field(default_factory=dict)

    def to_json(self) -> dict:
        return {
            "stages": {
                k: {
                    "mpjpe_mm": v["mpjpe"],
                    "pck160": v["pck"],
                    "pcp": v["pcp"],
                    "accel_mm": v["accel"],
                    "mpjpe_coco_mm": v["mpjpe_coco"],
                    "pck160_coco": v["pck_coco"],
                    "jitter_mm": v["jitter"],
                    "recall": v["recall"],
                    "precision": v["precision"],
                }
                for k, v in self.stages.items()
            },
            "association": self.association,
            "reprojection_px": {
                "per_view_mean": [float(x) for x in self.reprojection_view_mean],
                "per_view_joint_mean": self.reprojection_view_joint_mean.tolist(),
            },
            "gt_source": self.gt_source,
            "plausibility": self.plausibility,
            "smpl24_joints": {
                k: {"mpjpe_mm": v["mpjpe"], "pck160": v["pck"], "pcp": v["pcp"]}
                for k, v in self.smpl24.items()
            },
            "labels": self.labels.to_json() if self.labels is not None else None,
            "fit_distance_mm": self.fit_distance,
        }


def to_smpl_slots(joints: np.ndarray, joint_set: str) -> np.ndarray:
    """(..., J, 3) in ``joint_set`` -> (..., 24, 3) SMPL-24 slots (NaN where absent)."""
    js = get_joint_set(joint_set)
    if js.name == SMPL24.name:
        return joints
    src, dst = mapping_indices(js, SMPL24)
    out = np.full(joints.shape[:-2] + (SMPL24.num_joints, 3), np.nan)
    out[..., dst, :] = joints[..., src, :]
    return out


def ground_truth_slots(gt: GroundTruth, joint_set: str) -> tuple[np.ndarray, str]:
    """(M, 24, 3) ground truth in SMPL-24 slots for a prediction in ``joint_set``."""
    if joint_set == SMPL24.name:
        return gt.joints3d, "joints3d"
    if gt.keypoints3d is not None:
        return to_smpl_slots(gt.keypoints3d, joint_set), "keypoints3d"
    return to_smpl_slots(to_coco_like(gt.joints3d, joint_set), joint_set), "joints3d (mapped)"


def to_coco_like(smpl_joints: np.ndarray, joint_set: str) -> np.ndarray:
    """SMPL-24 joints re-expressed in ``joint_set`` by name (NaN where no counterpart)."""
    js = get_joint_set(joint_set)
    src, dst = mapping_indices(SMPL24, js)
    out = np.full(smpl_joints.shape[:-2] + (js.num_joints, 3), np.nan)
    out[..., dst, :] = smpl_joints[..., src, :]
    return out


def gt_per_frame(
    gt: GroundTruth, gt_slots: np.ndarray, num_frames: int
) -> tuple[np.ndarray, np.ndarray]:
    """Ground truth laid out by frame and person, as :func:`stage_metrics` takes it.

    Args:
        gt: the scene's ground truth (M rows, one per person and frame).
        gt_slots: (M, 24, 3) mm, each row's joints in SMPL-24 slots
            (:func:`ground_truth_slots`, or ``gt.joints3d``).
        num_frames: F; rows of later frames are left out.
    Returns:
        ``(dense, person_ids)``: (F, G, 24, 3) mm, NaN where a person is absent, and the
        (G,) sorted person ids of its second axis.
    """
    ids = np.unique(gt.person_id)
    dense = np.full((num_frames, len(ids), SMPL24.num_joints, 3), np.nan)
    col = np.searchsorted(ids, gt.person_id)
    keep = gt.frame < num_frames
    dense[gt.frame[keep], col[keep]] = gt_slots[keep]
    return dense, ids


def stage_metrics(
    tracks: np.ndarray, gt_dense: np.ndarray, *, max_mpjpe: float = metrics.MATCH_GATE_MM
) -> tuple[dict[str, float], metrics.SequenceMatch]:
    """Score one stage.

    Args:
        tracks: (K, F, 24, 3) predicted trajectories in SMPL-24 slots.
        gt_dense: (F, G, 24, 3) ground truth per frame and person.
    """
    F = gt_dense.shape[0]
    preds = [tracks[:, f] for f in range(F)]
    match = metrics.match_sequence(preds, list(gt_dense), max_mpjpe=max_mpjpe)
    out = metrics.pose_metrics(match)
    # Acceleration error per GT person along its matched trajectory (a frame where the
    # person is unmatched breaks the run: those samples are NaN).
    accel, jit = [], []
    for g in range(gt_dense.shape[1]):
        rows = match.gt_index == g
        seq_pred = np.full((F, SMPL24.num_joints, 3), np.nan)
        seq_gt = np.full((F, SMPL24.num_joints, 3), np.nan)
        seq_pred[match.frame[rows]] = match.pred[rows]
        seq_gt[match.frame[rows]] = match.gt[rows]
        a_err = metrics.acceleration(seq_pred) - metrics.acceleration(seq_gt)
        accel.append(np.linalg.norm(a_err, axis=-1).ravel())
        jit.append(np.linalg.norm(metrics.acceleration(seq_pred), axis=-1).ravel())
    a = np.concatenate(accel) if accel else np.zeros(0)
    j = np.concatenate(jit) if jit else np.zeros(0)
    out["accel"] = float(np.nanmean(a)) if np.isfinite(a).any() else float("nan")
    out["jitter"] = float(np.nanmean(j)) if np.isfinite(j).any() else float("nan")
    return out, match


def evaluate(scene: Scene, results: PipelineResults) -> Evaluation:
    """Score ``results`` against the scene's ground truth (association needs
    ``gt_person_id`` in the detections; pose rows need ``gt.npz``)."""
    det = scene.detections
    if det.gt_person_id is not None:
        # Pairs are counted per frame the stages used each row at (re-timed cameras moved).
        frames = row_frames(scene, results.config)
        association = metrics.association_scores(results.det_person, det.gt_person_id, frames)
    else:
        association = {}
    # Reprojection error of the views each joint was triangulated from (a rejected view
    # is an outlier by definition; its error is in the results, not in this mean).
    reproj = np.where(results.person_used, results.person_reproj, np.nan)  # (Q, J, V)
    with np.errstate(invalid="ignore"):
        vj = np.array(
            [
                [_nanmean(reproj[:, j, v]) for j in range(reproj.shape[1])]
                for v in range(reproj.shape[2])
            ]
        ).reshape(reproj.shape[2], reproj.shape[1])
        vm = np.array([_nanmean(reproj[:, :, v]) for v in range(reproj.shape[2])])
    stages: dict[str, dict[str, float]] = {}
    smpl24: dict[str, dict[str, float]] = {}
    events: list = []
    gt_source = "none"
    if scene.gt is not None:
        gt_slots, gt_source = ground_truth_slots(scene.gt, results.joint_set)
        gt_dense, gt_ids = gt_per_frame(scene.gt, gt_slots, results.num_frames)
        # Filters are scored where the raw triangulation has the joint, so every row is
        # measured on the same samples (coasting through gaps is not scored here).
        measured = np.isfinite(results.track_raw).all(-1, keepdims=True)
        for name, arr in stage_tracks(results).items():
            arr = np.where(measured, arr, np.nan) if name != "raw" else arr
            stages[name], match = stage_metrics(to_smpl_slots(arr, results.joint_set), gt_dense)
            if name == "raw":
                m = match.matched
                events = metrics.id_switch_events(
                    match.frame[m], gt_ids[match.gt_index[m]], match.pred_index[m]
                )
        association = dict(association, id_switches=len(events))
        if scene.gt.joints3d is not None:
            dense24, _ = gt_per_frame(scene.gt, scene.gt.joints3d, results.num_frames)
            for name in ("smpl", "smpl_vae"):
                fit = getattr(results, name)
                if fit is not None:
                    smpl24[name], _ = stage_metrics(fit.joints, dense24)
    plaus = {}
    measured = np.isfinite(results.track_raw).all(-1, keepdims=True)
    for name, arr in stage_tracks(results).items():
        if name in ("smpl", "smpl_vae"):
            plaus[name] = plausibility(getattr(results, name))
        else:  # like the pose rows: where the raw triangulation has the joint
            arr = np.where(measured, arr, np.nan)
            plaus[name] = dict(
                limit_violations_per_1000=float("nan"),
                **pose_limits.skeleton_plausibility(to_smpl_slots(arr, results.joint_set)),
            )
    return Evaluation(
        stages=stages,
        association=association,
        id_switch_events=[tuple(int(x) for x in e) for e in events],
        reprojection_view_mean=vm,
        reprojection_view_joint_mean=vj,
        gt_source=gt_source,
        plausibility=plaus,
        smpl24=smpl24,
        labels=check_results(results, scene.rig),
        fit_distance=fit_distances(results),
    )


def fit_distances(results: PipelineResults) -> dict[str, dict[str, float]]:
    """How near each body fit comes to its input, next to the best skeleton of constant
    bone lengths: per track (``"0"``, ``"1"``, ...) and over all person-frames
    (``"all"``), the median over frames of the mean joint distance (mm) of ``floor``
    (:mod:`pipeline.fit.floor`, from ``results.fit_floor``), ``smpl`` and ``smpl_vae``
    to the RTS tracks the fits were given. Empty without fits."""
    if results.smpl is None and results.smpl_vae is None:
        return {}
    per_frame = [fit_distance_frames(results, k) for k in range(results.num_tracks)]
    out = {str(k): {n: _median(v) for n, v in d.items()} for k, d in enumerate(per_frame)}
    out = {k: row for k, row in out.items() if np.isfinite(list(row.values())).any()}
    names = per_frame[0].keys() if per_frame else ()
    out["all"] = {n: _median(np.concatenate([d[n] for d in per_frame])) for n in names}
    return out


def fit_distance_frames(results: PipelineResults, track: int) -> dict[str, np.ndarray]:
    """(F,) per frame of ``track``: the mean joint distance (mm) of ``floor``, ``smpl``
    and ``smpl_vae`` (those the results hold) to the RTS joints the fits were given."""
    out: dict[str, np.ndarray] = {}
    if results.fit_floor is not None:
        out["floor"] = np.asarray(results.fit_floor[track], float)
    target = np.asarray(results.track_smoothed[track])
    for name in ("smpl", "smpl_vae"):
        fit = getattr(results, name)
        if fit is None:
            continue
        d = np.linalg.norm(np.asarray(fit.keypoints[track]) - target, axis=-1)  # (F, T)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # frames without the track
            out[name] = np.nanmean(d, -1)
    return out


def _median(x: np.ndarray) -> float:
    x = x[np.isfinite(x)]
    return float(np.median(x)) if x.size else float("nan")


def stage_tracks(results: PipelineResults) -> dict[str, np.ndarray]:
    """(K, F, J, 3) trajectories of every stage the results carry, in the source joint set."""
    out = {"raw": results.track_raw, "kalman": results.track_forward, "rts": results.track_smoothed}
    for name in ("smpl", "smpl_vae"):
        fit = getattr(results, name)
        if fit is not None:
            out[name] = fit.keypoints
    return out


def _nanmean(x: np.ndarray) -> float:
    x = x[np.isfinite(x)]
    return float(x.mean()) if x.size else float("nan")


def format_table(ev: Evaluation, *, view_names: list[str] | None = None) -> str:
    """The evaluation as a plain-text table."""
    lines = []
    if ev.stages:
        lines.append(f"pose (ground truth: {ev.gt_source})")
        head = (
            f"{'stage':<8} {'MPJPE mm':>9} {'PCK@160':>8} {'PCP':>6} {'accel':>7} "
            f"{'jitter':>7} {'MPJPE12':>8} {'recall':>7}"
        )
        lines.append(head)
        lines.append("-" * len(head))
        for name, v in ev.stages.items():
            lines.append(
                f"{name:<8} {v['mpjpe']:9.1f} {v['pck']:8.3f} {v['pcp']:6.3f} {v['accel']:7.2f} "
                f"{v['jitter']:7.2f} {v['mpjpe_coco']:8.1f} {v['recall']:7.3f}"
            )
        lines.append("(accel = acceleration error, jitter = mean |acceleration|, mm/frame^2;")
        lines.append(" MPJPE12 = over the 12 COCO-mappable joints; recall = GT people matched;")
        lines.append(" filters and fits scored where the raw triangulation has the joint)")
        for name, v in ev.smpl24.items():
            lines.append(
                f"{name} on all 24 SMPL joints (vs joints3d): MPJPE {v['mpjpe']:.1f} mm, "
                f"PCK@160 {v['pck']:.3f}, PCP {v['pcp']:.3f}"
            )
    if ev.plausibility:
        lines.append("")
        lines.append("local plausibility")
        head = (
            f"{'stage':<8} {'limit viol/1000':>15} {'hinge viol/1000':>15} "
            f"{'bone std mm':>11} {'foot jit':>8} {'wrist jit':>9}"
        )
        lines.append(head)
        lines.append("-" * len(head))
        for name, v in ev.plausibility.items():
            lines.append(
                f"{name:<8} {v['limit_violations_per_1000']:15.1f} "
                f"{v['hinge_violations_per_1000']:15.1f} {v['bone_length_std_mm']:11.1f} "
                f"{v['foot_jitter']:8.1f} {v['wrist_jitter']:9.1f}"
            )
        lines.append("(limit violations need joint rotations: SMPL rows only; jitter mm/frame^2)")
    a = ev.association
    if "precision" in a:
        lines.append("")
        lines.append(
            f"association: precision {a['precision']:.4f}  recall {a['recall']:.4f}  "
            f"false positives assigned {a['false_positives_assigned']}  "
            f"unassigned {a['detections_unassigned']}"
            + (f"  ID switches {a['id_switches']}" if "id_switches" in a else "")
        )
    elif "id_switches" in a:
        lines.append("")
        lines.append(
            f"ID switches {a['id_switches']} (no per-detection truth to score association)"
        )
    names = view_names or [str(i) for i in range(len(ev.reprojection_view_mean))]
    lines.append("")
    lines.append(
        "reprojection error per view (px): "
        + "  ".join(f"{n}: {x:.2f}" for n, x in zip(names, ev.reprojection_view_mean, strict=True))
    )
    if ev.labels is not None:
        lines.append(f"labels: {ev.labels.summary()}")
    if ev.fit_distance:
        lines.append("")
        lines.append(
            "body fits vs their input (RTS), median over frames of the mean joint distance"
        )
        names = [n for n in ("floor", "smpl", "smpl_vae") if n in ev.fit_distance["all"]]
        head = f"{'track':<8}" + "".join(f"{n + ' mm':>13}" for n in names)
        lines.append(head)
        lines.append("-" * len(head))
        for k, row in ev.fit_distance.items():
            lines.append(f"{k:<8}" + "".join(f"{row.get(n, float('nan')):13.1f}" for n in names))
        lines.append("(floor = the best skeleton of constant bone lengths: how far the input")
        lines.append(" itself is from rigid)")
    return "\n".join(lines)
