"""Joint sets: names, order and bone connections of every skeleton the project reads.

One place for all of them, so that importers, stages, metrics and the viewer agree.
Names follow COCO's lower-case ``left_*`` / ``right_*`` style in every set, which is
what lets :func:`convert_keypoints` map sets onto each other by name.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np


@dataclass(frozen=True)
class JointSet:
    """A named skeleton.

    Attributes:
        name: registry key, e.g. ``"coco17"``.
        names: joint names in storage order, length ``num_joints``.
        bones: (parent, child) index pairs to draw.
        parents: kinematic parent of each joint (-1 for a root), where the set is a tree.
    """

    name: str
    names: tuple[str, ...]
    bones: tuple[tuple[int, int], ...]
    parents: tuple[int, ...] | None = None
    index: dict[str, int] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "index", {n: i for i, n in enumerate(self.names)})
        for a, b in self.bones:
            if not (0 <= a < len(self.names) and 0 <= b < len(self.names)):
                raise ValueError(f"joint set {self.name}: bone ({a}, {b}) out of range")

    @property
    def num_joints(self) -> int:
        return len(self.names)

    @cached_property
    def flip_index(self) -> np.ndarray:
        """(num_joints,) index of each joint's left/right mirror (itself if unpaired).
        Made once per set (the association asks every frame; ~0.1 ms a time), read-only."""
        out = np.arange(self.num_joints)
        for i, n in enumerate(self.names):
            for a, b in (("left_", "right_"), ("right_", "left_")):
                if n.startswith(a) and n.replace(a, b, 1) in self.index:
                    out[i] = self.index[n.replace(a, b, 1)]
        out.flags.writeable = False
        return out


def _bones(names: tuple[str, ...], pairs: list[tuple[str, str]]) -> tuple[tuple[int, int], ...]:
    idx = {n: i for i, n in enumerate(names)}
    return tuple((idx[a], idx[b]) for a, b in pairs)


# SMPL's 24 joints, in SMPL's order; parents are SMPL's kinematic tree.
SMPL24_NAMES = (
    "pelvis", "left_hip", "right_hip", "spine1", "left_knee", "right_knee", "spine2",
    "left_ankle", "right_ankle", "spine3", "left_foot", "right_foot", "neck",
    "left_collar", "right_collar", "head", "left_shoulder", "right_shoulder",
    "left_elbow", "right_elbow", "left_wrist", "right_wrist", "left_hand", "right_hand",
)  # fmt: skip
SMPL24_PARENTS = (
    -1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 20, 21,
)  # fmt: skip
SMPL24 = JointSet(
    name="smpl24",
    names=SMPL24_NAMES,
    bones=tuple((p, c) for c, p in enumerate(SMPL24_PARENTS) if p >= 0),
    parents=SMPL24_PARENTS,
)

COCO17_NAMES = (
    "nose", "left_eye", "right_eye", "left_ear", "right_ear", "left_shoulder",
    "right_shoulder", "left_elbow", "right_elbow", "left_wrist", "right_wrist",
    "left_hip", "right_hip", "left_knee", "right_knee", "left_ankle", "right_ankle",
)  # fmt: skip
COCO17 = JointSet(
    name="coco17",
    names=COCO17_NAMES,
    bones=_bones(
        COCO17_NAMES,
        [
            ("nose", "left_eye"), ("nose", "right_eye"), ("left_eye", "left_ear"),
            ("right_eye", "right_ear"), ("left_shoulder", "right_shoulder"),
            ("left_shoulder", "left_elbow"), ("left_elbow", "left_wrist"),
            ("right_shoulder", "right_elbow"), ("right_elbow", "right_wrist"),
            ("left_shoulder", "left_hip"), ("right_shoulder", "right_hip"),
            ("left_hip", "right_hip"), ("left_hip", "left_knee"), ("left_knee", "left_ankle"),
            ("right_hip", "right_knee"), ("right_knee", "right_ankle"),
        ],
    ),
)  # fmt: skip

# OpenPose BODY_25 (OpenPose's own order).
BODY25_NAMES = (
    "nose", "neck", "right_shoulder", "right_elbow", "right_wrist", "left_shoulder",
    "left_elbow", "left_wrist", "mid_hip", "right_hip", "right_knee", "right_ankle",
    "left_hip", "left_knee", "left_ankle", "right_eye", "left_eye", "right_ear", "left_ear",
    "left_big_toe", "left_small_toe", "left_heel", "right_big_toe", "right_small_toe",
    "right_heel",
)  # fmt: skip
BODY25 = JointSet(
    name="body25",
    names=BODY25_NAMES,
    bones=_bones(
        BODY25_NAMES,
        [
            ("nose", "neck"), ("neck", "right_shoulder"), ("right_shoulder", "right_elbow"),
            ("right_elbow", "right_wrist"), ("neck", "left_shoulder"),
            ("left_shoulder", "left_elbow"), ("left_elbow", "left_wrist"), ("neck", "mid_hip"),
            ("mid_hip", "right_hip"), ("right_hip", "right_knee"), ("right_knee", "right_ankle"),
            ("mid_hip", "left_hip"), ("left_hip", "left_knee"), ("left_knee", "left_ankle"),
            ("nose", "right_eye"), ("right_eye", "right_ear"), ("nose", "left_eye"),
            ("left_eye", "left_ear"), ("left_ankle", "left_big_toe"),
            ("left_big_toe", "left_small_toe"), ("left_ankle", "left_heel"),
            ("right_ankle", "right_big_toe"), ("right_big_toe", "right_small_toe"),
            ("right_ankle", "right_heel"),
        ],
    ),
)  # fmt: skip

# Halpe-26 (AlphaPose, also RTMPose's body7/halpe26 models): COCO-17 first, then the
# top of the head, the neck, the hip centre and the feet. Halpe's "head" is the top of
# the skull, not SMPL's head joint (inside the skull): it is named ``head_top`` here.
HALPE26_NAMES = COCO17_NAMES + (
    "head_top", "neck", "mid_hip", "left_big_toe", "right_big_toe", "left_small_toe",
    "right_small_toe", "left_heel", "right_heel",
)  # fmt: skip
HALPE26 = JointSet(
    name="halpe26",
    names=HALPE26_NAMES,
    bones=COCO17.bones
    + _bones(
        HALPE26_NAMES,
        [
            ("head_top", "neck"), ("neck", "mid_hip"), ("left_ankle", "left_big_toe"),
            ("left_ankle", "left_small_toe"), ("left_ankle", "left_heel"),
            ("right_ankle", "right_big_toe"), ("right_ankle", "right_small_toe"),
            ("right_ankle", "right_heel"),
        ],
    ),
)  # fmt: skip

# OpenPose BODY_25B (the experimental model of openpose_train, Pose2Sim's default): same
# count as BODY_25, another order: COCO-17 first, then the upper neck (the throat, well
# above BODY_25's shoulder-level neck), the top of the head and the feet.
BODY25B_NAMES = COCO17_NAMES + (
    "upper_neck", "head_top", "left_big_toe", "left_small_toe", "left_heel",
    "right_big_toe", "right_small_toe", "right_heel",
)  # fmt: skip
BODY25B = JointSet(
    name="body25b",
    names=BODY25B_NAMES,
    bones=COCO17.bones
    + _bones(
        BODY25B_NAMES,
        [
            ("upper_neck", "head_top"), ("upper_neck", "left_shoulder"),
            ("upper_neck", "right_shoulder"), ("left_ankle", "left_big_toe"),
            ("left_big_toe", "left_small_toe"), ("left_ankle", "left_heel"),
            ("right_ankle", "right_big_toe"), ("right_big_toe", "right_small_toe"),
            ("right_ankle", "right_heel"),
        ],
    ),
)  # fmt: skip

# OpenPose's "COCO" model: the 17 COCO keypoints plus a neck (mid-shoulders), in
# OpenPose's own order (POSE_COCO_BODY_PARTS in openpose/pose/poseParameters.cpp).
OPENPOSE_COCO18_NAMES = (
    "nose", "neck", "right_shoulder", "right_elbow", "right_wrist", "left_shoulder",
    "left_elbow", "left_wrist", "right_hip", "right_knee", "right_ankle", "left_hip",
    "left_knee", "left_ankle", "right_eye", "left_eye", "right_ear", "left_ear",
)  # fmt: skip
OPENPOSE_COCO18 = JointSet(
    name="coco18",
    names=OPENPOSE_COCO18_NAMES,
    bones=_bones(
        OPENPOSE_COCO18_NAMES,
        [
            ("nose", "neck"), ("neck", "right_shoulder"), ("right_shoulder", "right_elbow"),
            ("right_elbow", "right_wrist"), ("neck", "left_shoulder"),
            ("left_shoulder", "left_elbow"), ("left_elbow", "left_wrist"), ("neck", "right_hip"),
            ("right_hip", "right_knee"), ("right_knee", "right_ankle"), ("neck", "left_hip"),
            ("left_hip", "left_knee"), ("left_knee", "left_ankle"), ("nose", "right_eye"),
            ("right_eye", "right_ear"), ("nose", "left_eye"), ("left_eye", "left_ear"),
        ],
    ),
)  # fmt: skip

# Human3.6M's 17 joints (MMPose's ``h36m`` layout, the input and output of 2D-to-3D
# lifters such as VideoPose3D and MotionBERT): the same count as COCO-17, other points.
# Its "head" is the top of the head; its "neck" sits at the chin (MMPose: "neck_base /
# nose"); "thorax" is the base of the neck.
H36M17_NAMES = (
    "mid_hip", "right_hip", "right_knee", "right_ankle", "left_hip", "left_knee",
    "left_ankle", "spine", "thorax", "chin", "head_top", "left_shoulder", "left_elbow",
    "left_wrist", "right_shoulder", "right_elbow", "right_wrist",
)  # fmt: skip
H36M17 = JointSet(
    name="h36m17",
    names=H36M17_NAMES,
    bones=_bones(
        H36M17_NAMES,
        [
            ("mid_hip", "right_hip"), ("right_hip", "right_knee"), ("right_knee", "right_ankle"),
            ("mid_hip", "left_hip"), ("left_hip", "left_knee"), ("left_knee", "left_ankle"),
            ("mid_hip", "spine"), ("spine", "thorax"), ("thorax", "chin"), ("chin", "head_top"),
            ("thorax", "left_shoulder"), ("left_shoulder", "left_elbow"),
            ("left_elbow", "left_wrist"), ("thorax", "right_shoulder"),
            ("right_shoulder", "right_elbow"), ("right_elbow", "right_wrist"),
        ],
    ),
)  # fmt: skip

# COCO-WholeBody's body and feet (its keypoints 0-22): COCO-17 then the six foot points.
# The body part of RTMPose / rtmlib / MMPose wholebody output, what the pipeline
# triangulates of it by default (``coco_wholebody133`` keeps face and hands too).
COCO23_NAMES = COCO17_NAMES + (
    "left_big_toe", "left_small_toe", "left_heel", "right_big_toe", "right_small_toe",
    "right_heel",
)  # fmt: skip
_FEET_BONES = [
    ("left_ankle", "left_big_toe"), ("left_big_toe", "left_small_toe"),
    ("left_ankle", "left_heel"), ("right_ankle", "right_big_toe"),
    ("right_big_toe", "right_small_toe"), ("right_ankle", "right_heel"),
]  # fmt: skip
COCO23 = JointSet(
    name="coco23", names=COCO23_NAMES, bones=COCO17.bones + _bones(COCO23_NAMES, _FEET_BONES)
)

# COCO-WholeBody-133 (Jin et al. 2020; the default of RTMPose / rtmlib / MMPose
# wholebody models): body and feet (0-22), 68 face points (23-90, the 300-W / iBUG
# order), 21 points per hand (91-111 left, 112-132 right: wrist, then thumb, index,
# middle, ring, little, four points each from the palm out).
_HAND_POINTS = ("wrist",) + tuple(
    f"{finger}{k}" for finger in ("thumb", "index", "middle", "ring", "pinky") for k in range(1, 5)
)
COCO_WHOLEBODY133_NAMES = (
    COCO23_NAMES
    + tuple(f"face_{k}" for k in range(68))
    + tuple(f"left_hand_{p}" for p in _HAND_POINTS)
    + tuple(f"right_hand_{p}" for p in _HAND_POINTS)
)


def _hand_bones(side: str) -> list[tuple[str, str]]:
    h = f"{side}_hand_"
    out = [(f"{side}_wrist", h + "wrist")]
    for finger in ("thumb", "index", "middle", "ring", "pinky"):
        chain = [h + "wrist"] + [f"{h}{finger}{k}" for k in range(1, 5)]
        out += list(zip(chain[:-1], chain[1:], strict=True))
    return out


COCO_WHOLEBODY133 = JointSet(
    name="coco_wholebody133",
    names=COCO_WHOLEBODY133_NAMES,
    bones=COCO23.bones
    + _bones(
        COCO_WHOLEBODY133_NAMES,
        [(f"face_{k}", f"face_{k + 1}") for k in range(16)]  # the jaw line
        + _hand_bones("left")
        + _hand_bones("right"),
    ),
)

# BlazePose's 33 landmarks (Google MediaPipe's pose_landmark models), in the models'
# order; "left" is the person's left, as in every set here.
BLAZEPOSE33_NAMES = (
    "nose", "left_eye_inner", "left_eye", "left_eye_outer", "right_eye_inner", "right_eye",
    "right_eye_outer", "left_ear", "right_ear", "left_mouth", "right_mouth", "left_shoulder",
    "right_shoulder", "left_elbow", "right_elbow", "left_wrist", "right_wrist", "left_pinky",
    "right_pinky", "left_index", "right_index", "left_thumb", "right_thumb", "left_hip",
    "right_hip", "left_knee", "right_knee", "left_ankle", "right_ankle", "left_heel",
    "right_heel", "left_foot_index", "right_foot_index",
)  # fmt: skip
BLAZEPOSE33 = JointSet(
    name="blazepose33",
    names=BLAZEPOSE33_NAMES,
    bones=_bones(
        BLAZEPOSE33_NAMES,
        [
            ("nose", "left_eye_inner"), ("left_eye_inner", "left_eye"),
            ("left_eye", "left_eye_outer"), ("left_eye_outer", "left_ear"),
            ("nose", "right_eye_inner"), ("right_eye_inner", "right_eye"),
            ("right_eye", "right_eye_outer"), ("right_eye_outer", "right_ear"),
            ("left_mouth", "right_mouth"), ("left_shoulder", "right_shoulder"),
            ("left_shoulder", "left_elbow"), ("left_elbow", "left_wrist"),
            ("left_wrist", "left_pinky"), ("left_wrist", "left_index"),
            ("left_pinky", "left_index"), ("left_wrist", "left_thumb"),
            ("right_shoulder", "right_elbow"), ("right_elbow", "right_wrist"),
            ("right_wrist", "right_pinky"), ("right_wrist", "right_index"),
            ("right_pinky", "right_index"), ("right_wrist", "right_thumb"),
            ("left_shoulder", "left_hip"), ("right_shoulder", "right_hip"),
            ("left_hip", "right_hip"), ("left_hip", "left_knee"), ("left_knee", "left_ankle"),
            ("left_ankle", "left_heel"), ("left_heel", "left_foot_index"),
            ("left_ankle", "left_foot_index"), ("right_hip", "right_knee"),
            ("right_knee", "right_ankle"), ("right_ankle", "right_heel"),
            ("right_heel", "right_foot_index"), ("right_ankle", "right_foot_index"),
        ],
    ),
)  # fmt: skip

JOINT_SETS: dict[str, JointSet] = {
    js.name: js
    for js in (
        SMPL24, COCO17, BODY25, BODY25B, OPENPOSE_COCO18, H36M17, HALPE26, COCO23,
        COCO_WHOLEBODY133, BLAZEPOSE33,
    )
}  # fmt: skip

# COCO-17 joints that have an SMPL-24 counterpart (same anatomical joint, modulo the
# usual offset of COCO hips, which sit a little higher and wider than SMPL's).
COCO17_TO_SMPL24: dict[str, str] = {
    n: n
    for n in (
        "left_shoulder", "right_shoulder", "left_elbow", "right_elbow", "left_wrist",
        "right_wrist", "left_hip", "right_hip", "left_knee", "right_knee", "left_ankle",
        "right_ankle",
    )
}  # fmt: skip


# BlazePose-33 -> COCO-17: every COCO joint is a BlazePose landmark of the same name
# (COCO's eyes are BlazePose's eye centres, ``left_eye`` / ``right_eye``), so
# ``convert_keypoints(kp, BLAZEPOSE33, COCO17)`` maps by name.
BLAZEPOSE33_TO_COCO17: dict[str, str] = {n: n for n in COCO17_NAMES}

# BlazePose-33 -> SMPL-24: each SMPL joint that BlazePose locates, as the mean of these
# landmarks. BlazePose's hips sit a little higher and wider than SMPL's (as COCO's);
# SMPL's head joint is inside the skull, here the mean of nose and ears; SMPL's foot
# joint is at the ball of the foot, here the toe tip (``foot_index``); SMPL's hand joint
# is at the knuckles, here the mean of the index and pinky knuckles. spine1-3, neck and
# the collars have no BlazePose counterpart (NaN).
BLAZEPOSE33_TO_SMPL24: dict[str, tuple[str, ...]] = {
    "pelvis": ("left_hip", "right_hip"),
    **{
        n: (n,)
        for n in (
            "left_hip", "right_hip", "left_knee", "right_knee", "left_ankle", "right_ankle",
            "left_shoulder", "right_shoulder", "left_elbow", "right_elbow", "left_wrist",
            "right_wrist",
        )
    },
    "left_foot": ("left_foot_index",),
    "right_foot": ("right_foot_index",),
    "head": ("nose", "left_ear", "right_ear"),
    "left_hand": ("left_index", "left_pinky"),
    "right_hand": ("right_index", "right_pinky"),
}  # fmt: skip


def get_joint_set(name: str) -> JointSet:
    """The joint set registered as ``name``; a ValueError lists the known ones."""
    try:
        return JOINT_SETS[name.lower()]
    except KeyError:
        raise ValueError(
            f"unknown joint set {name!r}; expected one of {sorted(JOINT_SETS)}"
        ) from None


def mapping_indices(src: JointSet, dst: JointSet) -> tuple[np.ndarray, np.ndarray]:
    """Indices ``(src_idx, dst_idx)`` of the joints both sets name alike.

    Between SMPL-24 and a keypoint set only the joints of :data:`COCO17_TO_SMPL24` map:
    a keypoint set's ``neck`` (OpenPose: mid-shoulders) or ``head_top`` is not SMPL's
    neck or head joint, so comparing them would measure a definition, not an error.
    """
    names = set(src.names) & set(dst.names)
    if (src.name == SMPL24.name) != (dst.name == SMPL24.name):
        names &= set(COCO17_TO_SMPL24)
    pairs = [(src.index[n], i) for i, n in enumerate(dst.names) if n in names]
    if not pairs:
        return np.zeros(0, int), np.zeros(0, int)
    s, d = zip(*pairs, strict=True)
    return np.asarray(s), np.asarray(d)


def convert_keypoints(keypoints: np.ndarray, src: JointSet, dst: JointSet) -> np.ndarray:
    """Re-order keypoints from ``src`` to ``dst`` by joint name.

    Args:
        keypoints: (..., src.num_joints, C) array, e.g. C=3 for (x, y, confidence).
    Returns:
        (..., dst.num_joints, C); joints ``dst`` has and ``src`` lacks are NaN
        (confidence 0 when C == 3).
    """
    keypoints = np.asarray(keypoints, dtype=float)
    if keypoints.shape[-2] != src.num_joints:
        raise ValueError(
            f"keypoints have {keypoints.shape[-2]} joints, expected {src.num_joints} ({src.name})"
        )
    out = np.full(keypoints.shape[:-2] + (dst.num_joints, keypoints.shape[-1]), np.nan)
    s, d = mapping_indices(src, dst)
    out[..., d, :] = keypoints[..., s, :]
    if keypoints.shape[-1] == 3:
        missing = np.setdiff1d(np.arange(dst.num_joints), d)
        out[..., missing, 2] = 0.0
    return out


def coco17_smpl24_pairs() -> tuple[np.ndarray, np.ndarray]:
    """(coco_idx, smpl_idx) index arrays of the COCO-17 joints with an SMPL-24 counterpart."""
    c = np.array([COCO17.index[k] for k in COCO17_TO_SMPL24])
    s = np.array([SMPL24.index[v] for v in COCO17_TO_SMPL24.values()])
    return c, s


def blazepose33_to_smpl24_matrix() -> np.ndarray:
    """(24, 33) averaging matrix of :data:`BLAZEPOSE33_TO_SMPL24`: ``M @ landmarks`` gives
    the SMPL-24 joints; rows of SMPL joints BlazePose lacks are NaN."""
    m = np.full((SMPL24.num_joints, BLAZEPOSE33.num_joints), np.nan)
    for smpl_name, sources in BLAZEPOSE33_TO_SMPL24.items():
        row = m[SMPL24.index[smpl_name]]
        row[:] = 0.0
        row[[BLAZEPOSE33.index[s] for s in sources]] = 1.0 / len(sources)
    return m
