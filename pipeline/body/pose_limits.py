"""Local plausibility of poses: joint-angle limits per SMPL joint, bone-length constancy,
hinge angles read off skeletons, and end-effector jitter.

Angles: every limited joint has an anatomical frame (three axes in SMPL's canonical
frame: y up, facing +z, the person's left on +x; at the rest T-pose every joint frame is
parallel to it). A local rotation is split into *swing* (about the two axes
perpendicular to the bone) and *twist* (about the bone axis), the swing-twist
decomposition ``R = R_swing @ R_twist``; the limits are boxes on
``(swing_a, swing_b, twist)``, the swing given as the two components of its rotation
vector. Limits are written for the left and centre joints; a right joint is mirrored
(``(x, y, z) -> (x, -y, -z)`` for a rotation vector) onto its left twin, so centre
joints need limits symmetric on their b and twist axes. The ranges follow textbook
ranges of motion, widened where :data:`pipeline.synth.motion.PARAM_LIMITS` moves a
joint further (so synthetic ground truth never violates them; see the tests).

Positions: millimetres; accelerations mm/frame^2. Joints are SMPL-24 slots
(``(..., 24, 3)``, NaN where a joint set lacks the joint), so the same functions score a
COCO-17 triangulation and an SMPL fit.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.data.joint_sets import SMPL24

NUM_JOINTS = SMPL24.num_joints
J = SMPL24.index
DEFAULT_TOL_DEG = 5.0
"""A joint counts as violating when it is more than this far outside its box."""


@dataclass(frozen=True)
class JointLimit:
    """Limits of one joint in its anatomical frame, degrees.

    Attributes:
        axes: (3, 3) rows = swing axis a, swing axis b, twist (bone) axis, canonical
            frame, right-handed (a x b = twist).
        low, high: (3,) bounds of (swing_a, swing_b, twist), degrees.
        names: what a positive angle means, for messages and docs.
    """

    axes: tuple[tuple[float, float, float], ...]
    low: tuple[float, float, float]
    high: tuple[float, float, float]
    names: tuple[str, str, str]


_X, _Y, _Z = (1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)


def _neg(v):
    return tuple(-c for c in v)


# Left and centre joints. Bone axes: legs point down (-y), the foot forward (+z), the spine
# and head up (+y), the left arm chain along +x.
LIMITS: dict[str, JointLimit] = {
    # hip: Rx(-flex) swings the leg forward, Rz(+abd) the left leg outward. The box also
    # holds every pose of motion.py's PARAM_LIMITS (its Euler composition of 120 deg
    # flexion with 40 deg abduction reads as 79 deg swing_b and -65 deg twist).
    "left_hip": JointLimit((_X, _Z, _neg(_Y)), (-125, -45, -70), (40, 85, 35),
                           ("extension", "abduction", "axial rotation")),
    "left_knee": JointLimit((_X, _Z, _neg(_Y)), (0, -10, -25), (150, 10, 25),
                            ("flexion", "valgus", "tibial rotation")),
    "left_ankle": JointLimit((_X, _Y, _Z), (-40, -30, -30), (55, 30, 30),
                             ("plantarflexion", "abduction", "inversion")),
    "left_foot": JointLimit((_X, _Y, _Z), (-60, -15, -15), (40, 15, 15),
                            ("toe flexion", "toe abduction", "toe twist")),
    "spine1": JointLimit((_X, _neg(_Z), _Y), (-25, -25, -30), (35, 25, 30),
                         ("forward bend", "side bend", "twist")),
    "spine2": JointLimit((_X, _neg(_Z), _Y), (-25, -25, -30), (35, 25, 30),
                         ("forward bend", "side bend", "twist")),
    "spine3": JointLimit((_X, _neg(_Z), _Y), (-25, -25, -30), (35, 25, 30),
                         ("forward bend", "side bend", "twist")),
    "neck": JointLimit((_X, _neg(_Z), _Y), (-35, -30, -45), (40, 30, 45),
                       ("flexion", "side bend", "rotation")),
    "head": JointLimit((_X, _neg(_Z), _Y), (-35, -30, -45), (40, 30, 45),
                       ("flexion", "side bend", "rotation")),
    "left_collar": JointLimit((_Y, _Z, _X), (-30, -20, -35), (30, 40, 35),
                              ("retraction", "elevation", "axial rotation")),
    # shoulder swing: about y (- = arm forward / flexion), about z (-90 = arm down,
    # +90 = arm overhead); twist = humeral rotation.
    "left_shoulder": JointLimit((_Y, _Z, _X), (-180, -110, -90), (80, 100, 90),
                                ("extension", "elevation", "humeral rotation")),
    "left_elbow": JointLimit((_neg(_Y), _neg(_Z), _X), (0, -10, -90), (150, 10, 90),
                             ("flexion", "hyperabduction", "pronation")),
    "left_wrist": JointLimit((_Z, _neg(_Y), _X), (-80, -35, -45), (70, 25, 45),
                             ("extension", "radial deviation", "twist")),
    "left_hand": JointLimit((_Z, _neg(_Y), _X), (-30, -20, -20), (30, 20, 20),
                            ("extension", "radial deviation", "twist")),
}  # fmt: skip


def _limit_tables() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per SMPL joint: axes (24, 3, 3), low/high (24, 3) radians, mirror flag, limited flag."""
    axes = np.tile(np.eye(3), (NUM_JOINTS, 1, 1))
    low = np.full((NUM_JOINTS, 3), -np.inf)
    high = np.full((NUM_JOINTS, 3), np.inf)
    mirror = np.zeros(NUM_JOINTS, bool)
    limited = np.zeros(NUM_JOINTS, bool)
    for j, name in enumerate(SMPL24.names):
        src = name.replace("right_", "left_", 1)
        if src not in LIMITS:
            continue  # the root: global orientation, unlimited
        lim = LIMITS[src]
        axes[j] = np.asarray(lim.axes, float)
        low[j], high[j] = np.deg2rad(lim.low), np.deg2rad(lim.high)
        mirror[j] = name.startswith("right_")
        limited[j] = True
    return axes, low, high, mirror, limited


AXES, LOW, HIGH, MIRROR, LIMITED = _limit_tables()


# --------------------------------------------------------------------------- angles


def _rotvec_to_quat(r: np.ndarray) -> np.ndarray:
    """(..., 3) rotation vectors -> (..., 4) unit quaternions (w, x, y, z), w >= 0."""
    angle = np.linalg.norm(r, axis=-1, keepdims=True)
    half = 0.5 * angle
    with np.errstate(invalid="ignore", divide="ignore"):
        k = np.where(angle > 1e-8, np.sin(half) / angle, 0.5 - angle**2 / 48)
    q = np.concatenate([np.cos(half), k * r], -1)
    return np.where(q[..., :1] < 0, -q, q)


def swing_twist(pose_rotvecs: np.ndarray) -> np.ndarray:
    """Swing-twist angles of every joint in its anatomical frame.

    Args:
        pose_rotvecs: (..., 24, 3) local axis-angle rotations (SMPL pose).
    Returns:
        (..., 24, 3) radians: (swing_a, swing_b, twist) per joint, see :data:`LIMITS`;
        right joints are mirrored onto their left twins first; the root row is its
        plain rotation vector.
    """
    r = np.asarray(pose_rotvecs, float)
    if r.shape[-2:] != (NUM_JOINTS, 3):
        raise ValueError(f"expected pose_rotvecs (..., 24, 3), got {r.shape}")
    r = np.where(MIRROR[:, None], r * np.array([1.0, -1.0, -1.0]), r)
    local = np.einsum("jab,...jb->...ja", AXES, r)  # rotation vector in the joint frame
    q = _rotvec_to_quat(local)
    w, x, y, z = np.moveaxis(q, -1, 0)
    twist = 2.0 * np.arctan2(z, w)  # in [-pi, pi] since w >= 0
    ct, st = np.cos(0.5 * twist), np.sin(0.5 * twist)
    # swing = q * conj(twist), twist = (ct, 0, 0, st); its z component vanishes.
    sw = ct * w + st * z
    sx = ct * x - st * y
    sy = ct * y + st * x
    sign = np.where(sw < 0, -1.0, 1.0)
    sw, sx, sy = sw * sign, sx * sign, sy * sign
    vnorm = np.hypot(sx, sy)
    angle = 2.0 * np.arctan2(vnorm, sw)
    with np.errstate(invalid="ignore", divide="ignore"):
        k = np.where(vnorm > 1e-9, angle / vnorm, 2.0)
    out = np.stack([k * sx, k * sy, twist], -1)
    return np.where(LIMITED[:, None], out, r)


def from_swing_twist(angles: np.ndarray) -> np.ndarray:
    """Inverse of :func:`swing_twist`: (..., 24, 3) (swing_a, swing_b, twist) radians ->
    (..., 24, 3) local axis-angle (the root row is taken as its rotation vector)."""
    ang = np.asarray(angles, float)
    if ang.shape[-2:] != (NUM_JOINTS, 3):
        raise ValueError(f"expected angles (..., 24, 3), got {ang.shape}")
    sa, sb, tw = np.moveaxis(ang, -1, 0)
    s_angle = np.hypot(sa, sb)
    with np.errstate(invalid="ignore", divide="ignore"):
        k = np.where(s_angle > 1e-9, np.sin(0.5 * s_angle) / s_angle, 0.5)
    sw, sx, sy = np.cos(0.5 * s_angle), k * sa, k * sb
    ct, st = np.cos(0.5 * tw), np.sin(0.5 * tw)
    # q = swing * twist with twist = (ct, 0, 0, st)
    q = np.stack([sw * ct, sx * ct + sy * st, sy * ct - sx * st, sw * st], -1)
    w = np.clip(q[..., 0], -1.0, 1.0)
    v = q[..., 1:]
    vnorm = np.linalg.norm(v, axis=-1, keepdims=True)
    angle = 2.0 * np.arctan2(vnorm, w[..., None])
    with np.errstate(invalid="ignore", divide="ignore"):
        local = np.where(vnorm > 1e-12, v * angle / vnorm, 2.0 * v)
    r = np.einsum("jba,...jb->...ja", AXES, local)  # back to the canonical frame
    r = np.where(MIRROR[:, None], r * np.array([1.0, -1.0, -1.0]), r)
    return np.where(LIMITED[:, None], r, ang)


def limit_excess(pose_rotvecs: np.ndarray) -> np.ndarray:
    """How far each joint is outside its limits.

    Args:
        pose_rotvecs: (..., 24, 3) axis-angle.
    Returns:
        (..., 24) degrees: the norm of the per-axis excess of (swing_a, swing_b, twist)
        over :data:`LIMITS` (0 inside the box; 0 for the unlimited root; NaN where the
        pose is NaN).
    """
    ang = swing_twist(pose_rotvecs)
    over = np.maximum(ang - HIGH, 0.0) + np.maximum(LOW - ang, 0.0)
    over = np.where(LIMITED[:, None], over, 0.0)
    return np.rad2deg(np.linalg.norm(over, axis=-1))


def limit_violations(pose_rotvecs: np.ndarray, *, tol_deg: float = DEFAULT_TOL_DEG) -> np.ndarray:
    """(..., 24, 3) axis-angle -> (..., 24) bool: joint more than ``tol_deg`` outside."""
    with np.errstate(invalid="ignore"):
        return limit_excess(pose_rotvecs) > tol_deg


def violations_per_1000(pose_rotvecs: np.ndarray, *, tol_deg: float = DEFAULT_TOL_DEG) -> float:
    """Joint-limit violations per 1000 bodies.

    Args:
        pose_rotvecs: (..., 24, 3); bodies with any NaN are skipped.
    Returns:
        1000 * (violating joints) / (bodies); NaN when there is no body.
    """
    r = np.asarray(pose_rotvecs, float).reshape(-1, NUM_JOINTS, 3)
    r = r[np.isfinite(r).all((1, 2))]
    if len(r) == 0:
        return float("nan")
    return 1000.0 * float(limit_violations(r, tol_deg=tol_deg).sum()) / len(r)


# --------------------------------------------------------------------------- skeletons

# Limb bones of SMPL-24 that a COCO-17 skeleton has too (both endpoints in both sets).
LIMB_BONES: tuple[tuple[int, int], ...] = tuple(
    (J[a], J[b])
    for a, b in (
        ("left_hip", "left_knee"), ("right_hip", "right_knee"),
        ("left_knee", "left_ankle"), ("right_knee", "right_ankle"),
        ("left_shoulder", "left_elbow"), ("right_shoulder", "right_elbow"),
        ("left_elbow", "left_wrist"), ("right_elbow", "right_wrist"),
    )
)  # fmt: skip
FOOT_JOINTS = (J["left_ankle"], J["right_ankle"])
WRIST_JOINTS = (J["left_wrist"], J["right_wrist"])
KNEE_FLEXION_DEG = (0.0, 150.0)
ELBOW_FLEXION_MAX_DEG = 150.0


def _check_tracks(joints: np.ndarray) -> np.ndarray:
    joints = np.asarray(joints, float)
    if joints.ndim != 4 or joints.shape[-2:] != (NUM_JOINTS, 3):
        raise ValueError(
            f"expected (num_tracks, num_frames, 24, 3) SMPL-24 slots, got {joints.shape}"
        )
    return joints


def bone_length_std(
    joints: np.ndarray, *, bones: tuple[tuple[int, int], ...] = LIMB_BONES
) -> np.ndarray:
    """Per track, the mean over bones of the standard deviation of the bone's length.

    Args:
        joints: (num_tracks, num_frames, 24, 3) SMPL-24 slots, mm; NaN where absent.
        bones: (parent, child) index pairs; default :data:`LIMB_BONES`.
    Returns:
        (num_tracks,) mm; NaN for a track without two measured frames of any bone.
    """
    joints = _check_tracks(joints)
    b = np.asarray(bones)
    length = np.linalg.norm(joints[:, :, b[:, 0]] - joints[:, :, b[:, 1]], axis=-1)  # (K, F, B)
    out = np.full(joints.shape[0], np.nan)
    for k in range(joints.shape[0]):
        stds = [np.std(col[np.isfinite(col)]) for col in length[k].T if np.isfinite(col).sum() >= 2]
        if stds:
            out[k] = float(np.mean(stds))
    return out


def hinge_flexion(joints: np.ndarray) -> np.ndarray:
    """Knee and elbow flexion read off a skeleton's positions.

    Args:
        joints: (..., 24, 3) SMPL-24 slots (z up or any frame).
    Returns:
        (..., 4) degrees: left knee, right knee (signed: negative = bent backwards,
        judged against the hips' left-right axis), left elbow, right elbow (unsigned:
        the bending direction of an elbow depends on the upper arm's twist).
    """
    x = np.asarray(joints, float)
    left = x[..., J["left_hip"], :] - x[..., J["right_hip"], :]
    left = left / np.linalg.norm(left, axis=-1, keepdims=True)
    out = []
    for side in ("left", "right"):
        thigh = x[..., J[f"{side}_knee"], :] - x[..., J[f"{side}_hip"], :]
        shank = x[..., J[f"{side}_ankle"], :] - x[..., J[f"{side}_knee"], :]
        s = np.einsum("...c,...c->...", np.cross(thigh, shank), left)
        c = np.einsum("...c,...c->...", thigh, shank)
        out.append(np.rad2deg(np.arctan2(s, c)))
    for side in ("left", "right"):
        upper = x[..., J[f"{side}_elbow"], :] - x[..., J[f"{side}_shoulder"], :]
        fore = x[..., J[f"{side}_wrist"], :] - x[..., J[f"{side}_elbow"], :]
        s = np.linalg.norm(np.cross(upper, fore), axis=-1)
        c = np.einsum("...c,...c->...", upper, fore)
        out.append(np.rad2deg(np.arctan2(s, c)))
    return np.stack(out, -1)


def hinge_violations_per_1000(joints: np.ndarray, *, tol_deg: float = DEFAULT_TOL_DEG) -> float:
    """Knee/elbow flexion outside 0..150 deg (knees) / above 150 deg (elbows), per 1000
    bodies (NaN-aware: a hinge with a missing joint is not scored; the denominator is the
    number of bodies with at least one scored hinge)."""
    f = hinge_flexion(np.asarray(joints, float).reshape(-1, NUM_JOINTS, 3))  # (N, 4)
    lo = np.array([KNEE_FLEXION_DEG[0]] * 2 + [-np.inf] * 2)
    hi = np.array([KNEE_FLEXION_DEG[1]] * 2 + [ELBOW_FLEXION_MAX_DEG] * 2)
    with np.errstate(invalid="ignore"):
        bad = (f < lo - tol_deg) | (f > hi + tol_deg)
    scored = np.isfinite(f)
    bodies = int(scored.any(1).sum())
    return 1000.0 * float((bad & scored).sum()) / bodies if bodies else float("nan")


def joint_jitter(joints: np.ndarray, joint_index: tuple[int, ...]) -> float:
    """Mean |second difference| of the given joints along time, mm/frame^2.

    Args:
        joints: (num_tracks, num_frames, 24, 3) SMPL-24 slots, mm; NaN-aware (a sample
            needs the joint at t-1, t, t+1).
    """
    x = _check_tracks(joints)[:, :, list(joint_index)]
    acc = np.linalg.norm(x[:, :-2] - 2.0 * x[:, 1:-1] + x[:, 2:], axis=-1)
    acc = acc[np.isfinite(acc)]
    return float(acc.mean()) if acc.size else float("nan")


def skeleton_plausibility(joints: np.ndarray, *, tol_deg: float = DEFAULT_TOL_DEG) -> dict:
    """Position-only plausibility of tracks (any stage: raw, Kalman, SMPL).

    Args:
        joints: (num_tracks, num_frames, 24, 3) SMPL-24 slots, mm.
    Returns:
        ``bone_length_std_mm`` (mean over tracks of :func:`bone_length_std`),
        ``hinge_violations_per_1000``, ``foot_jitter`` (ankles) and ``wrist_jitter``,
        mm/frame^2.
    """
    joints = _check_tracks(joints)
    std = bone_length_std(joints)
    return {
        "bone_length_std_mm": float(np.nanmean(std)) if np.isfinite(std).any() else float("nan"),
        "hinge_violations_per_1000": hinge_violations_per_1000(joints, tol_deg=tol_deg),
        "foot_jitter": joint_jitter(joints, FOOT_JOINTS),
        "wrist_jitter": joint_jitter(joints, WRIST_JOINTS),
    }
