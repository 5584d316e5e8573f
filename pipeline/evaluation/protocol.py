"""The Shelf / Campus protocol: PCP of the benchmarks' 14 joints against their own truth.

The benchmarks (Belagiannis et al., CVPR 2014) annotate 14 joints per actor in their own
order (:data:`PROTOCOL_JOINTS`, plus the pelvis where the truth has it); MVPose,
VoxelPose, 4D Association and the methods after them report PCP on it. A limb is correct
when the mean of its two end points' errors is at most ``alpha`` (0.5) times the limb's
true length; for each annotated actor and frame the estimate nearest to it (mean error
over the 14 joints) is scored, a frame with no estimate counts every limb wrong. PCP of
an actor is its share of correct limbs over its annotated frames; the average is over
actors 1-3 (indices 0-2; those annotated in the frames scored).

Limbs (:data:`PROTOCOL_LIMBS`): upper and lower arms, upper and lower legs of each side,
the head (bottom to top of the head) and the torso (bottom of the head to the pelvis).

Our joints -> the protocol's, one rule for every stage (:func:`protocol_joints`): ankles,
knees, hips, wrists, elbows and shoulders by name; pelvis = mid-hips; the two head points,
which no detector gives, by 4D Association's rule: bottom of the head = halfway from the
mid-shoulders to the mid-ears, top of the head = that point + 0.125 m along the face
direction (the cross product of neck-minus-pelvis and right-minus-left shoulder,
normalised) + 0.145 m straight up (+z). This rule is chosen because it is the one the
published 4D Association figures use and it scores every row (ours and a peer's) the
same way; a nose-based rule (VoxelPose's evaluation code) scores the same estimates
about a point lower, all of it on the head limb.

Truth files (:func:`read_protocol_gt`): the datasets' ``actorsGT.mat`` (``actor3D``: one
cell per actor, one cell per frame, each a 14 x 3 array in metres or empty where the
actor is not annotated), or an ``.npz`` with ``frame`` (N,), ``person_id`` (N,) and
``joints3d`` (N, 14 or 15, 3) in mm in :data:`PROTOCOL_JOINTS` order.

Units: mm; world z up.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.core.files import SceneFormatError, save_npz_atomic
from pipeline.data.joint_sets import JointSet

PROTOCOLS = ("shelf", "campus")
PROTOCOL_JOINTS = (
    "right_ankle", "right_knee", "right_hip", "left_hip", "left_knee", "left_ankle",
    "right_wrist", "right_elbow", "right_shoulder", "left_shoulder", "left_elbow",
    "left_wrist", "head_bottom", "head_top", "pelvis",
)  # fmt: skip
"""The protocol's 14 joints in the datasets' order, then the pelvis (index 14)."""
_P = {n: i for i, n in enumerate(PROTOCOL_JOINTS)}
PROTOCOL_LIMBS: dict[str, tuple[int, int]] = {
    "right_lower_leg": (_P["right_ankle"], _P["right_knee"]),
    "right_upper_leg": (_P["right_knee"], _P["right_hip"]),
    "left_upper_leg": (_P["left_hip"], _P["left_knee"]),
    "left_lower_leg": (_P["left_knee"], _P["left_ankle"]),
    "right_lower_arm": (_P["right_wrist"], _P["right_elbow"]),
    "right_upper_arm": (_P["right_elbow"], _P["right_shoulder"]),
    "left_upper_arm": (_P["left_shoulder"], _P["left_elbow"]),
    "left_lower_arm": (_P["left_elbow"], _P["left_wrist"]),
    "head": (_P["head_bottom"], _P["head_top"]),
    "torso": (_P["head_bottom"], _P["pelvis"]),
}
LIMB_JOINTS = np.arange(14)
"""The 14 annotated joints (the pelvis is derived): the MPJPE and the nearest estimate."""
PROTOCOL_TRUTH_FILE = "protocol_gt.npz"
"""A scene's stored protocol truth (``mvviz convert --protocol-gt``): read by ``mvviz eval
--protocol`` without ``--gt`` and by the viewer's failure review."""
DEFAULT_ACTORS = (0, 1, 2)
"""The protocol's actors 1-3: the average is over these."""
HEAD_FORWARD_MM = 125.0
HEAD_UP_MM = 145.0
_BY_NAME = (
    "right_ankle", "right_knee", "right_hip", "left_hip", "left_knee", "left_ankle",
    "right_wrist", "right_elbow", "right_shoulder", "left_shoulder", "left_elbow",
    "left_wrist",
)  # fmt: skip
_HEAD_NEEDS = ("left_shoulder", "right_shoulder", "left_ear", "right_ear", "left_hip", "right_hip")


@dataclass(frozen=True, eq=False)
class ProtocolTruth:
    """The annotated actors of the frames.

    Attributes:
        frame: (N,) frame index (the scene's).
        actor: (N,) actor index (0-based: the protocol's actor 1 is 0).
        joints: (N, 15, 3) mm in :data:`PROTOCOL_JOINTS` order; a 14-joint truth gets
            the pelvis as mid-hips.
        source: the file read.
    """

    frame: np.ndarray
    actor: np.ndarray
    joints: np.ndarray
    source: str = ""


@dataclass(frozen=True, eq=False)
class ProtocolScore:
    """PCP of one stage.

    Attributes:
        per_actor: actor -> PCP (fraction).
        per_limb: limb -> PCP over the scored actors' frames.
        per_actor_limb: actor -> limb -> PCP.
        average: mean of ``per_actor`` over the protocol's actors present.
        mpjpe_mm: mean error of the 14 joints of the matched estimates (frames with an
            estimate), mm.
        scored: annotated actor-frames scored; missed: of them, those with no estimate.
        wrong: (frame, actor, limb) of every wrong limb, in frame order.
    """

    per_actor: dict[int, float]
    per_limb: dict[str, float]
    per_actor_limb: dict[int, dict[str, float]]
    average: float
    mpjpe_mm: float
    scored: int
    missed: int
    wrong: tuple[tuple[int, int, str], ...]

    def as_dict(self) -> dict:
        return {
            "average": self.average,
            "per_actor": {str(k): v for k, v in self.per_actor.items()},
            "per_limb": self.per_limb,
            "per_actor_limb": {str(k): v for k, v in self.per_actor_limb.items()},
            "mpjpe_mm": self.mpjpe_mm,
            "scored": self.scored,
            "missed": self.missed,
            "wrong_limbs": len(self.wrong),
        }


def _with_pelvis(joints: np.ndarray) -> np.ndarray:
    """(..., 14 or 15, 3) -> (..., 15, 3): a 14-joint pose gets the pelvis as mid-hips."""
    if joints.shape[-2] == 15:
        return joints
    hips = 0.5 * (joints[..., _P["right_hip"], :] + joints[..., _P["left_hip"], :])
    return np.concatenate([joints, hips[..., None, :]], axis=-2)


def read_protocol_gt(path: str | os.PathLike) -> ProtocolTruth:
    """The truth of ``path`` (see the module docstring); a SceneFormatError naming the file
    and the field otherwise."""
    path = Path(path)
    if not path.is_file():
        raise SceneFormatError(path, None, "ground truth file not found")
    if path.suffix.lower() == ".mat":
        return _read_actors_mat(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except (ValueError, OSError, EOFError) as exc:
        msg = f"expected an .npz or actorsGT.mat ({exc})"
        raise SceneFormatError(path, None, msg) from None
    for name in ("frame", "person_id", "joints3d"):
        if name not in arrays:
            raise SceneFormatError(path, name, "missing (required array)")
    joints = np.asarray(arrays["joints3d"], dtype=float)
    n = len(joints)
    if joints.ndim != 3 or joints.shape[1:] not in ((14, 3), (15, 3)):
        msg = f"expected (N, 14 or 15, 3) mm, got {joints.shape}"
        raise SceneFormatError(path, "joints3d", msg)
    for name in ("frame", "person_id"):
        a = np.asarray(arrays[name])
        if a.shape != (n,) or a.dtype.kind not in "iu" or (n and a.min() < 0):
            raise SceneFormatError(
                path, name, f"expected ({n},) integers >= 0, got {a.dtype} {a.shape}"
            )
    if not np.isfinite(joints).all():
        raise SceneFormatError(path, "joints3d", "expected finite coordinates")
    return ProtocolTruth(
        frame=np.asarray(arrays["frame"], np.int64),
        actor=np.asarray(arrays["person_id"], np.int64),
        joints=_with_pelvis(joints),
        source=str(path),
    )


def _read_actors_mat(path: Path) -> ProtocolTruth:
    from scipy.io import loadmat  # scipy.io only where a .mat is read

    try:
        mat = loadmat(path)
    except (ValueError, OSError, TypeError, NotImplementedError) as exc:
        raise SceneFormatError(path, None, f"not a readable .mat file ({exc})") from None
    if "actor3D" not in mat:
        raise SceneFormatError(path, "actor3D", "missing (expected the datasets' actorsGT.mat)")
    actors = np.asarray(mat["actor3D"]).reshape(-1)
    frames, ids, poses = [], [], []
    for a, cells in enumerate(actors):
        cells = np.asarray(cells).reshape(-1)
        for f, cell in enumerate(cells):
            pose = np.asarray(cell, dtype=float)
            while pose.dtype == object or (pose.ndim == 3 and pose.shape[0] == 1):
                pose = np.asarray(pose.reshape(-1)[0] if pose.dtype == object else pose[0], float)
            if pose.size == 0:
                continue  # not annotated in this frame
            if pose.shape != (14, 3) or not np.isfinite(pose).all():
                field = f"actor3D{{{a + 1}}}{{{f + 1}}}"
                msg = f"expected 14 x 3 metres, got {pose.shape}"
                raise SceneFormatError(path, field, msg)
            frames.append(f)
            ids.append(a)
            poses.append(pose * 1000.0)
    joints = np.stack(poses) if poses else np.zeros((0, 14, 3))
    return ProtocolTruth(
        frame=np.asarray(frames, np.int64), actor=np.asarray(ids, np.int64),
        joints=_with_pelvis(joints), source=str(path),
    )  # fmt: skip


def protocol_joints(joints: np.ndarray, joint_set: JointSet) -> np.ndarray:
    """(..., J, 3) poses of ``joint_set`` -> (..., 15, 3) in :data:`PROTOCOL_JOINTS` order
    (mm, z up), the head points by 4D Association's rule (module docstring).

    Raises ValueError naming the joints ``joint_set`` lacks (shoulders, elbows, wrists,
    hips, knees, ankles and ears are needed)."""
    missing = [n for n in _BY_NAME + _HEAD_NEEDS if n not in joint_set.index]
    if missing:
        raise ValueError(f"joint set {joint_set.name} lacks {missing} (the protocol needs them)")
    joints = np.asarray(joints, dtype=float)
    out = np.full(joints.shape[:-2] + (15, 3), np.nan)

    def j(name: str) -> np.ndarray:
        return joints[..., joint_set.index[name], :]

    for name in _BY_NAME:
        out[..., _P[name], :] = j(name)
    mid_shoulders = 0.5 * (j("left_shoulder") + j("right_shoulder"))
    mid_ears = 0.5 * (j("left_ear") + j("right_ear"))
    pelvis = 0.5 * (j("left_hip") + j("right_hip"))
    bottom = 0.5 * (mid_shoulders + mid_ears)
    face = np.cross(mid_shoulders - pelvis, j("right_shoulder") - j("left_shoulder"))
    with np.errstate(invalid="ignore", divide="ignore"):
        face = face / np.linalg.norm(face, axis=-1, keepdims=True)
    top = bottom + HEAD_FORWARD_MM * face
    top[..., 2] += HEAD_UP_MM
    out[..., _P["head_bottom"], :] = bottom
    out[..., _P["head_top"], :] = top
    out[..., _P["pelvis"], :] = pelvis
    return out


def nearest_estimate(estimates: np.ndarray, truth: np.ndarray) -> tuple[int, float]:
    """Index of the estimate nearest to ``truth`` by mean error over the 14 joints (NaN
    joints ignored; an estimate with none finite never chosen) and that error, or
    (-1, inf) when there is none.

    Args:
        estimates: (P, 15, 3); truth: (15, 3); mm.
    """
    if len(estimates) == 0:
        return -1, float("inf")
    err = np.linalg.norm(estimates[:, LIMB_JOINTS] - truth[LIMB_JOINTS], axis=-1)  # (P, 14)
    finite = np.isfinite(err)
    with np.errstate(invalid="ignore"):
        mean = np.where(finite.any(1), np.where(finite, err, 0).sum(1) / finite.sum(1), np.inf)
    best = int(np.argmin(mean))
    return (best, float(mean[best])) if np.isfinite(mean[best]) else (-1, float("inf"))


@dataclass(frozen=True, eq=False)
class _ScoredRow:
    """One annotated actor-frame scored: the estimate used (-1: none), each limb's
    correctness, end-point mean error and limit (10,), the 14 joints' errors (or None)."""

    frame: int
    actor: int
    estimate: int
    correct: np.ndarray
    limb_error: np.ndarray
    limit: np.ndarray
    joint_error: np.ndarray | None


_LIMB_ENDS = np.array(list(PROTOCOL_LIMBS.values()))  # (10, 2)


def _scored_rows(
    estimates: dict[int, np.ndarray], truth: ProtocolTruth, actors: tuple[int, ...], alpha: float
) -> list[_ScoredRow]:
    """Every annotated actor-frame of ``actors``, matched to its nearest estimate and
    scored limb by limb (the one place the protocol's rules are applied)."""
    rows = []
    for f, a, gt in zip(truth.frame, truth.actor, truth.joints, strict=True):
        if int(a) not in actors:
            continue
        est = estimates.get(int(f), np.zeros((0, 15, 3)))
        k, _ = nearest_estimate(est, gt)
        limit = alpha * np.linalg.norm(gt[_LIMB_ENDS[:, 0]] - gt[_LIMB_ENDS[:, 1]], axis=-1)
        if k < 0:
            n = len(_LIMB_ENDS)
            rows.append(_ScoredRow(int(f), int(a), -1, np.zeros(n, bool), np.full(n, np.inf),
                                   limit, None))  # fmt: skip
            continue
        e = np.linalg.norm(est[k] - gt, axis=-1)  # (15,)
        limb_error = 0.5 * (e[_LIMB_ENDS[:, 0]] + e[_LIMB_ENDS[:, 1]])
        with np.errstate(invalid="ignore"):
            correct = limb_error <= limit  # NaN compares False: wrong
        rows.append(_ScoredRow(int(f), int(a), k, correct, limb_error, limit, e[LIMB_JOINTS]))
    return rows


def score_protocol(
    estimates: dict[int, np.ndarray],
    truth: ProtocolTruth,
    *,
    actors: tuple[int, ...] = DEFAULT_ACTORS,
    alpha: float = 0.5,
) -> ProtocolScore:
    """PCP of ``estimates`` against ``truth`` by the protocol (module docstring).

    Args:
        estimates: frame -> (P, 15, 3) the estimated people of that frame, mm
            (:func:`protocol_joints` of a stage); a frame absent or empty has none.
        truth: the annotated actors; only ``actors`` are scored.
    """
    names = tuple(PROTOCOL_LIMBS)
    rows = _scored_rows(estimates, truth, actors, alpha)
    per_actor: dict[int, float] = {}
    per_actor_limb: dict[int, dict[str, float]] = {}
    for a in sorted({r.actor for r in rows}):
        table = np.array([r.correct for r in rows if r.actor == a], float)  # (frames, 10)
        per_actor[a] = float(table.mean())
        per_actor_limb[a] = {n: float(table[:, i].mean()) for i, n in enumerate(names)}
    table = np.array([r.correct for r in rows], float).reshape(-1, len(names))
    per_limb = {n: float(table[:, i].mean()) if len(table) else float("nan")
                for i, n in enumerate(names)}  # fmt: skip
    scored = [per_actor[a] for a in actors if a in per_actor]
    errors = [r.joint_error for r in rows if r.joint_error is not None]
    err = np.concatenate(errors) if errors else np.zeros(0)
    finite = err[np.isfinite(err)]
    wrong = tuple((r.frame, r.actor, names[i]) for r in rows for i in np.flatnonzero(~r.correct))
    return ProtocolScore(
        per_actor=per_actor,
        per_limb=per_limb,
        per_actor_limb=per_actor_limb,
        average=float(np.mean(scored)) if scored else float("nan"),
        mpjpe_mm=float(finite.mean()) if finite.size else float("nan"),
        scored=len(rows),
        missed=sum(r.estimate < 0 for r in rows),
        wrong=wrong,
    )


def estimates_by_frame(
    tracks: np.ndarray, joint_set: JointSet, *, with_tracks: bool = False
) -> dict[int, np.ndarray] | tuple[dict[int, np.ndarray], dict[int, np.ndarray]]:
    """frame -> (P, 15, 3) the protocol joints of every track present in the frame (any
    finite joint); ``with_tracks``: also frame -> (P,) those tracks' indices.

    Args:
        tracks: (K, F, J, 3) a stage's trajectories in ``joint_set``, mm.
    """
    poses = protocol_joints(tracks, joint_set)  # (K, F, 15, 3)
    present = np.isfinite(tracks).all(-1).any(-1)  # (K, F)
    ids = {f: np.flatnonzero(present[:, f]) for f in range(tracks.shape[1]) if present[:, f].any()}
    estimates = {f: poses[k, f] for f, k in ids.items()}
    return (estimates, ids) if with_tracks else estimates


def format_protocol_table(scores: dict[str, ProtocolScore]) -> str:
    """The protocol's tables as text: per stage the PCP of each actor (1-based, as the
    papers number them), the average and the MPJPE of the 14 joints; then PCP per limb."""
    actors = sorted({a for s in scores.values() for a in s.per_actor})
    head = "| stage | " + " | ".join(f"actor {a + 1}" for a in actors) + " | average | MPJPE mm |"
    lines = [head, "|---" * (len(actors) + 3) + "|"]
    for name, s in scores.items():
        cells = [f"{100 * s.per_actor[a]:.1f}" for a in actors]
        lines.append(
            f"| {name} | " + " | ".join(cells) + f" | {100 * s.average:.1f} | {s.mpjpe_mm:.1f} |"
        )
    limbs = tuple(PROTOCOL_LIMBS)
    lines += ["", "| stage | " + " | ".join(limbs) + " |", "|---" * (len(limbs) + 1) + "|"]
    for name, s in scores.items():
        cells = [f"{100 * s.per_limb[n]:.1f}" for n in limbs]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    missed = {name: s.missed for name, s in scores.items() if s.missed}
    if missed:
        lines.append(f"actor-frames with no estimate (all limbs wrong): {missed}")
    return "\n".join(lines)


def save_scene_protocol(scene_dir: str | os.PathLike, protocol: str, truth: ProtocolTruth) -> Path:
    """Store ``truth`` in the scene as :data:`PROTOCOL_TRUTH_FILE` (atomically)."""
    if protocol not in PROTOCOLS:
        raise ValueError(f"protocol must be one of {PROTOCOLS}, got {protocol!r}")
    path = Path(scene_dir) / PROTOCOL_TRUTH_FILE
    save_npz_atomic(
        path, frame=truth.frame, person_id=truth.actor, joints3d=truth.joints,
        protocol=np.array(protocol),
    )  # fmt: skip
    return path


def load_scene_protocol(scene_dir: str | os.PathLike) -> tuple[str, ProtocolTruth] | None:
    """(protocol, truth) stored in the scene, or None if it has none."""
    path = Path(scene_dir) / PROTOCOL_TRUTH_FILE
    if not path.is_file():
        return None
    truth = read_protocol_gt(path)
    with np.load(path, allow_pickle=False) as z:
        protocol = str(z["protocol"]) if "protocol" in z.files else "shelf"
    if protocol not in PROTOCOLS:
        raise SceneFormatError(path, "protocol", f"expected one of {PROTOCOLS}, got {protocol!r}")
    return protocol, truth


@dataclass(frozen=True)
class WrongLimb:
    """A limb the protocol counts wrong: of ``actor`` in ``frame``, on the estimate of
    ``track`` (-1: no estimate), its end points' mean error and the limit (half its true
    length), mm."""

    frame: int
    actor: int
    track: int
    limb: str
    error_mm: float
    limit_mm: float


def wrong_limbs(
    tracks: np.ndarray, joint_set: JointSet, truth: ProtocolTruth, *, alpha: float = 0.5,
    actors: tuple[int, ...] = DEFAULT_ACTORS,
) -> list[WrongLimb]:
    """Every wrong limb of ``tracks`` (K, F, J, 3) by the protocol, naming the track whose
    estimate was scored (the nearest to the actor), in frame order."""
    estimates, track_ids = estimates_by_frame(tracks, joint_set, with_tracks=True)
    names = tuple(PROTOCOL_LIMBS)
    return [
        WrongLimb(r.frame, r.actor, int(track_ids[r.frame][r.estimate]) if r.estimate >= 0
                  else -1, names[i], float(r.limb_error[i]), float(r.limit[i]))
        for r in _scored_rows(estimates, truth, actors, alpha)
        for i in np.flatnonzero(~r.correct)
    ]  # fmt: skip
