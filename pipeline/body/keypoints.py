"""Every keypoint of every joint set, tied to the body model: the one table the SMPL fit,
the synthetic scenes and their simulated detectors read.

A keypoint is tied (:class:`Tie`) to one of

* ``joint``: an SMPL-24 joint (the model's posed joint);
* ``coco``: a row of the model's ``coco_regressor`` (17 rows, the COCO-17 keypoints as
  Anny's ``coco.pth`` places them on the mesh, re-fitted for the open model);
* ``landmark``: a vertex or a small vertex regressor picked by a documented rule
  (:data:`LANDMARK_RULES`: toes, heels, head top, eye and mouth corners, knuckles, ...);
* ``mean``: the mean of other ties (``mid_hip`` = mean of the COCO hips, OpenPose's
  ``neck`` = mean of the COCO shoulders, ...);
* ``none``: not fitted (face contour, finger joints: a 24-joint body has no such parts).
  The fit gives such keypoints weight 0; the synthetic scenes leave them NaN.

Every tie is linear in the mesh and the joints, so a layout's keypoints are
``vertex_weights @ vertices + joint_weights @ joints`` (:class:`KeypointRegressor`),
which the fit folds into the skinning weights ("virtual vertices", see
:mod:`pipeline.fit.smpl`). A tie may also name its ``anchor``: the SMPL-24 joint the
keypoint *is* anatomically (COCO's knee is SMPL's knee, modulo surface offset); anchors
decide which joint rotations the layout constrains (:func:`free_joints`), which points
align the torso (:func:`torso_points`) and where the analytic initialisation reads
limbs.

Landmark vertices of the open model (13,348 vertices, y up, facing +z, the person's
left on +x, T-pose with the palms down) are picked at load time from the rest mesh and
the skinning weights (dominant joint = segment): deterministic, a few milliseconds, and
nothing beside the model file that could fall out of step with it when the model is
rebuilt. A licensed 6,890-vertex SMPL file uses SMPL's well-known vertex ids where they
exist (:data:`SMPL_VERTEX_IDS`, those of smplx's ``vertex_ids`` for the OpenPose feet,
and the common head-top vertex 411) and the same rules elsewhere.

Units: metres (the body model's).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from pipeline.data.joint_sets import (
    _HAND_POINTS,
    COCO17_NAMES,
    COCO17_TO_SMPL24,
    JOINT_SETS,
    SMPL24,
    get_joint_set,
)

if TYPE_CHECKING:
    import torch

    from pipeline.body.model import BodyModel

# torch is imported by the functions that build or apply regressors (the fit's): the
# table (layout_ties, FITTABLE_JOINT_SETS) is read by code that never fits, e.g. the
# viewer loading cached results.

_J = SMPL24.index
SIDES = (("left", 1.0), ("right", -1.0))  # side name, sign of its x


# --------------------------------------------------------------------------- the table


@dataclass(frozen=True)
class Tie:
    """How one keypoint is read off the body model.

    Attributes:
        kind: ``"joint"``, ``"coco"``, ``"landmark"``, ``"mean"`` or ``"none"``.
        source: the SMPL-24 joint, COCO-17 row or landmark name (empty for mean/none).
        parts: for ``mean``, the ties averaged.
        anchor: the SMPL-24 joint this keypoint is anatomically, if any.
        why: the reason for the choice.
    """

    kind: str
    source: str = ""
    parts: tuple[Tie, ...] = ()
    anchor: str | None = None
    why: str = ""

    @property
    def fitted(self) -> bool:
        return self.kind != "none"


def joint(name: str, why: str) -> Tie:
    return Tie("joint", name, anchor=name, why=why)


def coco(name: str, why: str = "") -> Tie:
    anchor = COCO17_TO_SMPL24.get(name)
    return Tie("coco", name, anchor=anchor, why=why or f"COCO-17 {name}: the model's regressor")


def landmark(name: str, why: str) -> Tie:
    return Tie("landmark", name, why=why)


def mean(*parts: Tie, why: str, anchor: str | None = None) -> Tie:
    return Tie("mean", parts=parts, anchor=anchor, why=why)


def not_fitted(why: str) -> Tie:
    return Tie("none", why=why)


def _sided(name: str, make: Callable[[str], Tie]) -> dict[str, Tie]:
    return {f"{s}_{name}": make(s) for s, _ in SIDES}


# The vocabulary: one tie per keypoint name, shared by every layout that uses the name
# (the sets name joints alike, see pipeline.data.joint_sets).
DEFAULT_TIES: dict[str, Tie] = {
    **{n: coco(n) for n in COCO17_NAMES},
    "neck": mean(
        coco("left_shoulder"), coco("right_shoulder"),
        why="OpenPose/Halpe neck: the midpoint of the shoulders (OpenPose's own definition)",
    ),
    "mid_hip": mean(
        coco("left_hip"), coco("right_hip"),
        why="OpenPose/Halpe mid hip: the midpoint of the (COCO) hips",
    ),
    "head_top": landmark("head_top", "top of the skull: the head_top landmark"),
    "upper_neck": mean(
        joint("neck", ""), joint("head", ""),
        why="BODY_25B's upper neck (MPII's, the throat below the chin): midway between "
        "SMPL's neck joint (base of the neck) and head joint (base of the skull)",
    ),
    **_sided("big_toe", lambda s: landmark(f"{s}_big_toe", "tip of the big toe")),
    **_sided("small_toe", lambda s: landmark(f"{s}_small_toe", "tip of the little toe")),
    **_sided("heel", lambda s: landmark(f"{s}_heel", "back of the heel")),
    **_sided("foot_index", lambda s: landmark(f"{s}_toe_tip", "BlazePose: tip of the toes")),
    **_sided("eye_inner", lambda s: landmark(f"{s}_eye_inner", "inner eye corner")),
    **_sided("eye_outer", lambda s: landmark(f"{s}_eye_outer", "outer eye corner")),
    **_sided("mouth", lambda s: landmark(f"{s}_mouth", "BlazePose: corner of the mouth")),
    **_sided("index", lambda s: landmark(f"{s}_index_knuckle", "BlazePose: index #1 knuckle")),
    **_sided("pinky", lambda s: landmark(f"{s}_pinky_knuckle", "BlazePose: pinky #1 knuckle")),
    **_sided(
        "thumb",
        lambda s: landmark(
            f"{s}_thumb", "BlazePose: thumb #2 knuckle; rigid with the wrist in a 24-joint model"
        ),
    ),
}  # fmt: skip

# COCO-WholeBody's face (iBUG 300-W order, 0-based): the points the model can give; the
# contour, brows, nose bridge and lips are not fitted (no stable vertex, and real faces
# move them: expression, jaw).
_FACE_TIES = {
    30: coco("nose", "nose tip = COCO's nose"),
    36: landmark("right_eye_outer", "300-W 37: right eye, outer corner"),
    39: landmark("right_eye_inner", "300-W 40: right eye, inner corner"),
    42: landmark("left_eye_inner", "300-W 43: left eye, inner corner"),
    45: landmark("left_eye_outer", "300-W 46: left eye, outer corner"),
    48: landmark("right_mouth", "300-W 49: right mouth corner"),
    54: landmark("left_mouth", "300-W 55: left mouth corner"),
}


def _wholebody_ties() -> dict[str, Tie]:
    out = {
        f"face_{k}": _FACE_TIES.get(k, not_fitted("face point the body model cannot give"))
        for k in range(68)
    }
    knuckle = {"index1": "index", "middle1": "middle", "ring1": "ring", "pinky1": "pinky"}
    for s, _ in SIDES:
        for p in _HAND_POINTS:
            name = f"{s}_hand_{p}"
            if p == "wrist":
                out[name] = coco(f"{s}_wrist", "the hand's wrist point is COCO's wrist")
            elif p in knuckle:
                out[name] = landmark(f"{s}_{knuckle[p]}_knuckle", f"{p}: MCP knuckle")
            else:
                out[name] = not_fitted("finger joint: SMPL-24 has no fingers")
    return out


# Where a layout means something else by a name, or has names of its own.
LAYOUT_TIES: dict[str, dict[str, Tie]] = {
    "smpl24": {n: joint(n, "SMPL-24 joint") for n in SMPL24.names},
    "h36m17": {
        **{
            n: joint(n, "Human3.6M joints are mocap joint centres, like SMPL's")
            for n in COCO17_TO_SMPL24
        },
        "mid_hip": joint("pelvis", "Human3.6M's root is the pelvis centre"),
        "thorax": joint("neck", "Human3.6M's thorax: the base of the neck, SMPL's neck"),
        "spine": not_fitted("mid-spine: no SMPL joint at that height"),
        "chin": not_fitted("MMPose 'neck_base/nose' point: ill-defined on the body model"),
    },
    "coco_wholebody133": _wholebody_ties(),
}


def layout_ties(joint_set: str) -> tuple[Tie, ...]:
    """The ties of a joint set, in its storage order (ValueError if a name has none)."""
    js = get_joint_set(joint_set)
    own = LAYOUT_TIES.get(js.name, {})
    missing = [n for n in js.names if n not in own and n not in DEFAULT_TIES]
    if missing:
        raise ValueError(f"joint set {js.name}: no body-model tie for {missing}")
    return tuple(own.get(n, DEFAULT_TIES.get(n)) for n in js.names)


# The sets whose fit is meaningful: the table anchors both ends of every limb (hips,
# knees, ankles, shoulders, elbows, wrists), which pins the body.
LIMB_ANCHORS = tuple(COCO17_TO_SMPL24)
FITTABLE_JOINT_SETS = tuple(
    name
    for name in JOINT_SETS
    if set(LIMB_ANCHORS) <= {t.anchor for t in layout_ties(name) if t.fitted}
)


# --------------------------------------------------------------------------- landmarks

Landmark = tuple[np.ndarray, np.ndarray]  # vertex ids (n,), weights (n,) summing to 1

# SMPL's (6,890 vertices) well-known ids: smplx.vertex_ids["smplh"] for OpenPose's feet,
# 411 for the top of the head (used by many SMPL marker sets).
SMPL_VERTEX_IDS: dict[str, int] = {
    "head_top": 411,
    "left_big_toe": 3216, "left_small_toe": 3226, "left_heel": 3387,
    "right_big_toe": 6617, "right_small_toe": 6624, "right_heel": 6787,
}  # fmt: skip
SMPL_NUM_VERTICES = 6890

LANDMARK_RULES: dict[str, str] = {
    "head_top": "highest vertex (max y) of the head segment",
    "heel": "of the foot's vertices (ankle and foot segments) within 3 cm of its sole "
    "(lowest vertex), the most posterior (min z)",
    "big_toe": "toes = foot vertices anterior to SMPL's foot joint (the ball); their width "
    "split in 5 equal bands, medial to lateral: the most anterior vertex of the medial band",
    "small_toe": "the most anterior vertex of the lateral band of the toes (see big_toe)",
    "toe_tip": "the most anterior vertex (max z) of the foot",
    "knuckles": "the hand segment's vertices within 1 cm of the plane through SMPL's hand "
    "joint (the MCP line, across the forearm axis x), split by z in 4 equal bands, anterior "
    "(index: palms down, the thumb points forward) to posterior (pinky): each knuckle is the "
    "mean of its band, both sides of the hand, so a point inside it",
    "thumb": "the wrist and hand vertices distal to the wrist joint: the most anterior is "
    "the thumb tip; the thumb's MCP is the vertex nearest to 55 % of the way from the wrist "
    "joint to it",
    "eye_inner": "with E = COCO's eye: the most anterior head vertex within 4 mm (x, y) of "
    "(0.5 E.x, E.y): the inner canthus sits half-way to the midline",
    "eye_outer": "the most anterior head vertex within 4 mm (x, y) of (1.5 E.x, E.y)",
    "mouth": "with N = COCO's nose: the most anterior head vertex within 4 mm (x, y) of "
    "(0.8 E.x, N.y - (E.y - N.y)): the mouth line as far below the nose as the eyes are "
    "above it, the corners below the inner irises",
}


@dataclass(frozen=True, eq=False)
class _RestBody:
    v: np.ndarray  # (V, 3) rest vertices (mean shape)
    seg: np.ndarray  # (V,) dominant joint
    J: np.ndarray  # (24, 3) rest joints
    coco: np.ndarray | None  # (17, 3) COCO keypoints, or None without a regressor

    def segment(self, *names: str) -> np.ndarray:
        return np.flatnonzero(np.isin(self.seg, [_J[n] for n in names]))


def _one(v: int) -> Landmark:
    return np.array([int(v)]), np.array([1.0])


def _argbest(ids: np.ndarray, score: np.ndarray) -> Landmark | None:
    return None if len(ids) == 0 else _one(ids[int(np.argmax(score))])


def _front_vertex(b: _RestBody, ids: np.ndarray, xy: np.ndarray, tol: float = 0.004):
    """Most anterior vertex of ``ids`` within ``tol`` (x, y) of ``xy``, what a frontal
    camera sees there; the nearest in (x, y) if none is that close."""
    d = np.abs(b.v[ids, :2] - xy).max(1)
    near = ids[d <= tol]
    if len(near):
        return _one(near[int(np.argmax(b.v[near, 2]))])
    return _argbest(ids, -d)


def _foot_landmarks(b: _RestBody, side: str, sign: float) -> dict[str, Landmark]:
    foot = b.segment(f"{side}_ankle", f"{side}_foot")
    if len(foot) == 0:
        return {}
    v = b.v[foot]
    out = {f"{side}_toe_tip": _one(foot[int(np.argmax(v[:, 2]))])}
    low = v[:, 1] <= v[:, 1].min() + 0.03
    out[f"{side}_heel"] = _one(foot[low][int(np.argmin(v[low, 2]))])
    toes = v[:, 2] > b.J[_J[f"{side}_foot"], 2]
    if toes.any():
        lateral = sign * v[toes, 0]
        edges = np.linspace(lateral.min(), lateral.max(), 6)
        band = np.clip(np.searchsorted(edges, lateral, side="right") - 1, 0, 4)
        ids, z = foot[toes], v[toes, 2]
        for name, k in (("big_toe", 0), ("small_toe", 4)):
            sel = band == k
            out[f"{side}_{name}"] = _one(ids[sel][int(np.argmax(z[sel]))])
    return out


def _hand_landmarks(b: _RestBody, side: str, sign: float) -> dict[str, Landmark]:
    out: dict[str, Landmark] = {}
    hand = b.segment(f"{side}_hand")
    x_hand = b.J[_J[f"{side}_hand"], 0]
    ring = hand[np.abs(b.v[hand, 0] - x_hand) < 0.01]
    if len(ring) >= 4:
        z = b.v[ring, 2]
        edges = np.linspace(z.max(), z.min(), 5)  # anterior to posterior
        band = np.clip(np.searchsorted(-edges, -z, side="right") - 1, 0, 3)
        for k, finger in enumerate(("index", "middle", "ring", "pinky")):
            ids = ring[band == k]
            if len(ids):
                out[f"{side}_{finger}_knuckle"] = (ids, np.full(len(ids), 1.0 / len(ids)))
    wrist = b.J[_J[f"{side}_wrist"]]
    distal = b.segment(f"{side}_wrist", f"{side}_hand")
    distal = distal[sign * (b.v[distal, 0] - wrist[0]) > 0]
    if len(distal):
        tip = b.v[distal[int(np.argmax(b.v[distal, 2]))]]
        target = wrist + 0.55 * (tip - wrist)
        out[f"{side}_thumb"] = _argbest(distal, -np.linalg.norm(b.v[distal] - target, axis=1))
    return out


def _face_landmarks(b: _RestBody) -> dict[str, Landmark]:
    if b.coco is None:
        return {}
    head = b.segment("head")
    if len(head) == 0:
        return {}
    c = {n: b.coco[i] for i, n in enumerate(COCO17_NAMES)}
    nose = c["nose"]
    out = {}
    for side, _ in SIDES:
        eye = c[f"{side}_eye"]
        out[f"{side}_eye_inner"] = _front_vertex(b, head, np.array([0.5 * eye[0], eye[1]]))
        out[f"{side}_eye_outer"] = _front_vertex(b, head, np.array([1.5 * eye[0], eye[1]]))
        y_mouth = nose[1] - (eye[1] - nose[1])
        out[f"{side}_mouth"] = _front_vertex(b, head, np.array([0.8 * eye[0], y_mouth]))
    return out


def landmark_regressors(model: BodyModel) -> dict[str, Landmark]:
    """Every landmark the model gives: name -> (vertex ids, weights); see :data:`LANDMARK_RULES`.

    Rules run on the rest mesh of the mean shape; on a 6,890-vertex (SMPL) mesh the ids
    of :data:`SMPL_VERTEX_IDS` replace the rules' picks. A landmark a rule cannot place
    (e.g. a model without a segment) is absent, and the keypoints tied to it are not fitted.
    """
    import torch

    with torch.no_grad():
        v = model.v_template.double().numpy()
        J = model.J_template.double().numpy()
        co = None
        if model.coco_regressor is not None:
            co = model.coco_regressor.double().numpy() @ v
    b = _RestBody(v=v, seg=model.weights.numpy().argmax(1), J=J, coco=co)
    out: dict[str, Landmark] = {}
    head = b.segment("head")
    if len(head):
        out["head_top"] = _one(head[int(np.argmax(v[head, 1]))])
    for side, sign in SIDES:
        out.update(_foot_landmarks(b, side, sign))
        out.update(_hand_landmarks(b, side, sign))
    out.update(_face_landmarks(b))
    if model.num_vertices == SMPL_NUM_VERTICES:
        out.update({k: _one(i) for k, i in SMPL_VERTEX_IDS.items()})
    return {k: x for k, x in out.items() if x is not None}


# --------------------------------------------------------------------------- regressors


@dataclass(frozen=True, eq=False)
class KeypointRegressor:
    """A layout's keypoints as a linear map of the mesh and the joints.

    ``keypoints = vertex_weights @ vertices + joint_weights @ joints`` per body; rows of
    keypoints the model cannot give (``fitted`` False) are zero. T keypoints, V vertices.

    Attributes:
        joint_set: the layout.
        vertex_weights: (T, V) float32.
        joint_weights: (T, 24) float32.
        fitted: (T,) bool.
        anchor: (T,) the SMPL-24 joint each keypoint is anatomically, or None.
        ties: (T,) the table's entries.
    """

    joint_set: str
    vertex_weights: torch.Tensor
    joint_weights: torch.Tensor
    fitted: np.ndarray
    anchor: tuple[str | None, ...]
    ties: tuple[Tie, ...] = field(repr=False)

    @property
    def anchors(self) -> dict[str, int]:
        """SMPL-24 joint name -> index of the first fitted keypoint anchored there."""
        out: dict[str, int] = {}
        for i, a in enumerate(self.anchor):
            if a is not None and self.fitted[i]:
                out.setdefault(a, i)
        return out

    @property
    def is_joints(self) -> bool:
        """Every keypoint is the SMPL-24 joint of the same index (the SMPL-24 layout)."""
        J = self.joint_weights.numpy()
        return (
            J.shape[0] == J.shape[1]
            and bool(np.all(J == np.eye(J.shape[0])))
            and not bool(self.vertex_weights.abs().sum())
        )


def _tie_row(tie: Tie, model: BodyModel, marks: dict[str, Landmark]):
    """(V,) vertex weights and (24,) joint weights of one tie (float64), or None."""
    V = model.num_vertices
    if tie.kind == "joint":
        jw = np.zeros(SMPL24.num_joints)
        jw[_J[tie.source]] = 1.0
        return np.zeros(V), jw
    if tie.kind == "coco":
        if model.coco_regressor is None:
            raise ValueError(f"body model {model.source} has no coco_regressor")
        return model.coco_regressor[COCO17_NAMES.index(tie.source)].double().numpy(), np.zeros(24)
    if tie.kind == "landmark":
        if tie.source not in marks:
            return None
        ids, w = marks[tie.source]
        vw = np.zeros(V)
        np.add.at(vw, ids, w)
        return vw, np.zeros(SMPL24.num_joints)
    if tie.kind == "mean":
        rows = [_tie_row(p, model, marks) for p in tie.parts]
        if any(r is None for r in rows):
            return None
        return sum(r[0] for r in rows) / len(rows), sum(r[1] for r in rows) / len(rows)
    return None


_REGRESSOR_CACHE: dict[tuple[int, str], KeypointRegressor] = {}


def keypoint_regressor(model: BodyModel, joint_set: str) -> KeypointRegressor:
    """The layout's :class:`KeypointRegressor` for ``model`` (built once per model and set).

    COCO rows are copied from ``coco_regressor`` unchanged (float32), so a COCO-17
    layout reproduces :meth:`BodyModel.coco_keypoints` exactly.
    """
    import torch

    js = get_joint_set(joint_set)
    key = (id(model), js.name)
    if key in _REGRESSOR_CACHE:
        return _REGRESSOR_CACHE[key]
    ties = layout_ties(js.name)
    marks = landmark_regressors(model) if any(_uses_landmarks(t) for t in ties) else {}
    T, V = len(ties), model.num_vertices
    vw = torch.zeros(T, V)
    jw = torch.zeros(T, SMPL24.num_joints)
    fitted = np.zeros(T, bool)
    for i, t in enumerate(ties):
        if t.kind == "coco" and model.coco_regressor is not None:
            vw[i] = model.coco_regressor[COCO17_NAMES.index(t.source)]  # bit-exact copy
            fitted[i] = True
            continue
        row = _tie_row(t, model, marks)
        if row is not None:
            vw[i] = torch.as_tensor(row[0], dtype=torch.float32)
            jw[i] = torch.as_tensor(row[1], dtype=torch.float32)
            fitted[i] = True
    reg = KeypointRegressor(
        joint_set=js.name,
        vertex_weights=vw,
        joint_weights=jw,
        fitted=fitted,
        anchor=tuple(t.anchor for t in ties),
        ties=ties,
    )
    _REGRESSOR_CACHE[key] = reg
    return reg


def _uses_landmarks(t: Tie) -> bool:
    return t.kind == "landmark" or any(_uses_landmarks(p) for p in t.parts)


def layout_keypoints(
    reg: KeypointRegressor, vertices: torch.Tensor, joints: torch.Tensor
) -> torch.Tensor:
    """(B, V, 3) vertices and (B, 24, 3) joints -> (B, T, 3) keypoints; NaN where not fitted."""
    import torch

    kp = torch.einsum("kv,nvc->nkc", reg.vertex_weights.to(vertices.dtype), vertices)
    kp = kp + torch.einsum("kj,njc->nkc", reg.joint_weights.to(joints.dtype), joints)
    kp[:, torch.as_tensor(~reg.fitted)] = float("nan")
    return kp


# --------------------------------------------------------------------------- fit rules

MIN_LEVER_M = 0.03
"""A keypoint constrains a joint's rotation when it moves at least this much per radian."""
TORSO_ANCHORS = (
    "pelvis", "left_hip", "right_hip", "spine3", "neck", "left_shoulder", "right_shoulder",
)  # fmt: skip


def subtree_matrix(parents: np.ndarray) -> np.ndarray:
    """(J, J) S[j, c] = 1 if joint c is j or one of its descendants."""
    J = len(parents)
    S = np.eye(J)
    for c in range(J):  # parents precede children: walk up from each joint
        p = parents[c]
        while p >= 0:
            S[p, c] = 1.0
            p = parents[p]
    return S


def lever_arms(
    A: np.ndarray, D0: np.ndarray, rest_joints: np.ndarray, parents: np.ndarray
) -> np.ndarray:
    """(T, J) metres per radian each keypoint moves when one joint rotates, at rest.

    Args:
        A: (T, J) skinning-blended weights; D0: (T, J, 3) offsets (see
            :class:`pipeline.body.kinematics.KeypointBuffers`); rest_joints: (J, 3).
    Returns:
        ``|m_tj|`` with ``m_tj = sum_{c in subtree(j)} (D0_tc + A_tc J_c) - (sum A_tc) J_j``:
        the part of keypoint t carried by joint j's frame, relative to joint j.
    """
    S = subtree_matrix(parents)  # (j, c)
    carried = np.einsum("jc,tcx->tjx", S, D0 + A[..., None] * rest_joints[None])
    weight = A @ S.T  # (t, j)
    return np.linalg.norm(carried - weight[..., None] * rest_joints[None], axis=-1)


def free_joints(lever: np.ndarray, reg: KeypointRegressor) -> tuple[str, ...]:
    """SMPL-24 joints whose rotation the layout leaves (nearly) free.

    Rule: a non-root joint is constrained when the layout observes both ends of what it
    swings: a fitted keypoint is anchored at the joint, and another fitted keypoint (not
    anchored there) moves by at least :data:`MIN_LEVER_M` per radian of its rotation.
    Every other joint is free (pulled towards rest by ``FitParams.w_free``). COCO-17:
    spine, neck, head, collars, wrists, hands, ankles, feet; SMPL-24: head, hands, feet;
    BODY_25 and the other foot layouts constrain the ankles too, BlazePose the wrists.

    Args:
        lever: (T, 24) from :func:`lever_arms`.
    """
    anchor = np.array([a if a is not None else "" for a in reg.anchor])
    out = []
    for j, name in enumerate(SMPL24.names):
        if j == 0:
            continue
        at = reg.fitted & (anchor == name)
        other = reg.fitted & (anchor != name) & (lever[:, j] >= MIN_LEVER_M)
        if not (at.any() and other.any()):
            out.append(name)
    return tuple(out)


def torso_points(reg: KeypointRegressor) -> np.ndarray:
    """Indices (layout order) of the fitted keypoints anchored at :data:`TORSO_ANCHORS`:
    the points the closed-form root alignment uses (COCO-17: shoulders and hips)."""
    return np.array(
        [i for i, a in enumerate(reg.anchor) if reg.fitted[i] and a in TORSO_ANCHORS], int
    )
