"""Body measures of 3D joints by joint *name*: the horizontal left axes and facing
direction, how far the face and feet are ahead of the torso, knee and elbow flexion,
bone lengths. Works for any :class:`~pipeline.data.joint_sets.JointSet`; a measure whose
joints the set lacks is left out. Used by :mod:`pipeline.evaluation.label_check`.

Conventions: world millimetres, z up; degrees. NaN marks a missing joint.
"""

from __future__ import annotations

import numpy as np

from pipeline.data.joint_sets import JointSet

SIDES = ("left", "right")

# Limbs whose left and right lengths should agree: name -> (proximal, distal) joint
# names without the side prefix.
LIMBS: dict[str, tuple[str, str]] = {
    "upper_arm": ("shoulder", "elbow"),
    "forearm": ("elbow", "wrist"),
    "thigh": ("hip", "knee"),
    "shin": ("knee", "ankle"),
    "flank": ("shoulder", "hip"),
    "foot": ("heel", "big_toe"),
}


def _joint(joints: np.ndarray, js: JointSet, name: str) -> np.ndarray | None:
    """(..., 3) the joint called ``name``, or None if the set lacks it."""
    i = js.index.get(name)
    return None if i is None else joints[..., i, :]


def joint_pair(joints: np.ndarray, js: JointSet, name: str) -> tuple[np.ndarray, np.ndarray] | None:
    """(left, right) (..., 3) of ``left_<name>`` / ``right_<name>``, or None."""
    a, b = _joint(joints, js, f"left_{name}"), _joint(joints, js, f"right_{name}")
    return None if a is None or b is None else (a, b)


def _unit(v: np.ndarray) -> np.ndarray:
    with np.errstate(invalid="ignore", divide="ignore"):
        return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _horizontal_unit(v: np.ndarray, *, min_share: float = 0.5) -> np.ndarray:
    """(..., 3) -> (..., 3) unit horizontal part (z = 0); NaN where the vector is
    mostly vertical (a body lying down or a degenerate pair)."""
    h = v.copy()
    h[..., 2] = 0.0
    with np.errstate(invalid="ignore"):
        keep = np.linalg.norm(h, axis=-1) >= min_share * np.linalg.norm(v, axis=-1)
    return np.where(keep[..., None], _unit(h), np.nan)


def dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(..., 3), (..., 3) -> (...,) dot product over the last axis."""
    return np.einsum("...c,...c->...", a, b)


def body_axes(joints: np.ndarray, joint_set: JointSet) -> dict[str, np.ndarray]:
    """The body's horizontal left axes and facing direction.

    Args:
        joints: (..., num_joints, 3) world mm, z up.
    Returns:
        ``"shoulders"``, ``"hips"``: (..., 3) unit horizontal left-pointing axes
        (``left_x - right_x``), NaN where the set lacks the pair or it is mostly
        vertical; ``"left"``: their normalised sum (either alone where the other is
        missing); ``"forward"``: (..., 3) ``left x up``, the direction the torso faces.
    """
    nan = np.full(joints.shape[:-2] + (3,), np.nan)
    out = {}
    for name, joint in (("shoulders", "shoulder"), ("hips", "hip")):
        pair = joint_pair(joints, joint_set, joint)
        out[name] = nan if pair is None else _horizontal_unit(pair[0] - pair[1])
    s, h = out["shoulders"], out["hips"]
    both = np.where(np.isfinite(s), s, 0.0) + np.where(np.isfinite(h), h, 0.0)
    left = _unit(both)
    left[~(np.isfinite(s).all(-1) | np.isfinite(h).all(-1))] = np.nan
    out["left"] = left
    out["forward"] = np.cross(left, np.array([0.0, 0.0, 1.0]))
    return out


def facing_offsets(joints: np.ndarray, joint_set: JointSet) -> dict[str, np.ndarray]:
    """Signed distances (mm) ahead of the torso of the cues the set has.

    ``"nose"``: nose minus the shoulders' midpoint; ``"eyes"``: the eyes' midpoint
    minus the ears' midpoint; ``"toes"``: big toes minus heels (mean of both feet,
    either alone); each along :func:`body_axes`' ``forward``. Positive = ahead.

    Args:
        joints: (..., num_joints, 3) world mm, z up.
    Returns:
        cue name -> (...,) mm, NaN where a joint is missing.
    """
    fwd = body_axes(joints, joint_set)["forward"]
    out = {}
    nose, sh = _joint(joints, joint_set, "nose"), joint_pair(joints, joint_set, "shoulder")
    if nose is not None and sh is not None:
        out["nose"] = dot(nose - 0.5 * (sh[0] + sh[1]), fwd)
    eyes, ears = joint_pair(joints, joint_set, "eye"), joint_pair(joints, joint_set, "ear")
    if eyes is not None and ears is not None:
        out["eyes"] = dot(0.5 * (eyes[0] + eyes[1]) - 0.5 * (ears[0] + ears[1]), fwd)
    toes, heels = joint_pair(joints, joint_set, "big_toe"), joint_pair(joints, joint_set, "heel")
    if toes is not None and heels is not None:
        per_foot = np.stack([dot(toes[i] - heels[i], fwd) for i in range(2)], -1)
        out["toes"] = nanmean_last(per_foot)
    return out


def nanmean_last(x: np.ndarray) -> np.ndarray:
    """Mean over the last axis ignoring NaN (NaN where all are)."""
    ok = np.isfinite(x)
    n = ok.sum(-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(n > 0, np.where(ok, x, 0.0).sum(-1) / n, np.nan)


def hinge_angles(joints: np.ndarray, joint_set: JointSet) -> dict[str, np.ndarray]:
    """Signed knee and elbow flexion in the body's sagittal plane, degrees.

    Positive = the anatomical direction: a knee's shank goes behind its thigh's line, an
    elbow's forearm ahead of its upper arm's line (both judged by rotation about the
    hips' / shoulders' left axis, in 3D). A straight limb is 0; a knee bent backwards or
    an elbow bent backwards is negative. A bend sideways of the body (out of the
    sagittal plane) reads near 0.

    Args:
        joints: (..., num_joints, 3) world mm, z up.
    Returns:
        ``"left_knee"``, ``"right_knee"``, ``"left_elbow"``, ``"right_elbow"`` (those
        the set has) -> (...,) degrees, NaN where a joint is missing.
    """
    out = {}
    for hinge, (a, b, c), axis, sign in (
        ("knee", ("hip", "knee", "ankle"), "hip", 1.0),
        ("elbow", ("shoulder", "elbow", "wrist"), "shoulder", -1.0),
    ):
        pair = joint_pair(joints, joint_set, axis)
        if pair is None:
            continue
        left = _unit(pair[0] - pair[1])
        for side in SIDES:
            p = [_joint(joints, joint_set, f"{side}_{n}") for n in (a, b, c)]
            if any(x is None for x in p):
                continue
            upper, lower = p[1] - p[0], p[2] - p[1]
            s = dot(np.cross(upper, lower), left)
            out[f"{side}_{hinge}"] = sign * np.rad2deg(np.arctan2(s, dot(upper, lower)))
    return out


def bone_lengths(joints: np.ndarray, joint_set: JointSet) -> dict[str, np.ndarray]:
    """Lengths of the named bones the set has, mm.

    Args:
        joints: (..., num_joints, 3).
    Returns:
        ``"left_<limb>"`` / ``"right_<limb>"`` for each limb of :data:`LIMBS`, and
        ``"shoulder_width"`` / ``"hip_width"`` -> (...,) mm, NaN where a joint is missing.
    """
    out = {}
    for limb, (a, b) in LIMBS.items():
        for side in SIDES:
            pa = _joint(joints, joint_set, f"{side}_{a}")
            pb = _joint(joints, joint_set, f"{side}_{b}")
            if pa is not None and pb is not None:
                out[f"{side}_{limb}"] = np.linalg.norm(pb - pa, axis=-1)
    for width, joint in (("shoulder_width", "shoulder"), ("hip_width", "hip")):
        pair = joint_pair(joints, joint_set, joint)
        if pair is not None:
            out[width] = np.linalg.norm(pair[0] - pair[1], axis=-1)
    return out
