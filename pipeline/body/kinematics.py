"""What the SMPL fit predicts for a target joint set, and the rotation representations.

:class:`KeypointBuffers` holds, per body model and target joint set, everything the fit
needs precomputed once: the layout's keypoints (:mod:`pipeline.body.keypoints`, a mix
of vertex-regressor rows and SMPL-joint rows) folded into the skinning weights, see the
docstring of :mod:`pipeline.fit.smpl`; :func:`predict_targets` and
:func:`~pipeline.body.model.forward_kinematics` are the batched forward pass of the fit
(rotation conversions live in :mod:`pipeline.core.rotations`).
Units: metres (the body model's).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from pipeline.body.keypoints import (
    FITTABLE_JOINT_SETS,
    free_joints,
    keypoint_regressor,
    lever_arms,
    torso_points,
)
from pipeline.body.model import (
    BodyModel,
    KinematicTree,
    forward_kinematics_components,
    scale_bones,
)
from pipeline.core.rotations import (  # noqa: F401  (re-exported: the fit's and the prior's)
    matrix_to_rot6d,
    matrix_to_rotvec,
    rot6d_to_matrix,
    rotvec_to_matrix,
)
from pipeline.data.joint_sets import SMPL24, get_joint_set

NUM_JOINTS = SMPL24.num_joints
# A fit's target is any joint set whose table anchors all limbs (FITTABLE_JOINT_SETS).
# Joints the set leaves free and its torso points follow from the table by the rules of
# pipeline.body.keypoints.free_joints and torso_points.
_J = SMPL24.index
OFFSET_FRAMES = ("pelvis", "spine1", "spine2", "spine3", "neck", "head", "left_collar",
                 "right_collar")  # fmt: skip
"""Joints whose frame may carry a per-track keypoint offset: the trunk and head, i.e. the
keypoints at the ends of a torso bone (hips, shoulders, face points). A limb keypoint
(knee, ankle, elbow, wrist) with its own offset lets the body's limb joints drift from
the observed ones (on the noisy Shelf scene the ankles' SMPL joints moved 45 mm), so
limb proportions are left to the betas."""
FOOT_OFFSET_FRAMES = ("left_ankle", "right_ankle", "left_foot", "right_foot")
"""Frames that may carry the offset of a foot point that is not a joint (no anchor: heels,
big and small toes, landmark vertices of the rest mesh). A detector's toes and heels are
not the model's landmark vertices: on Pose2Sim's balancing trial (OpenPose BODY_25B) the
offsets the fit learns are 30-55 mm, and with them the fitted body's keypoints land a
median 16.2 mm from the RTS joints instead of 21.2 mm. The ankle keypoint itself keeps no
offset, so it still pins the SMPL ankle."""


# --------------------------------------------------------------------------- kinematics


@dataclass(frozen=True, eq=False)
class KeypointBuffers:
    """What the fit needs of a body model for one target joint set, precomputed once.

    Shapes: J = 24 joints, T target joints, B betas. Metres. A target row is a vertex
    regressor row R (folded into the skinning: ``A = R W``, ``D = R W v - A J``), a joint
    row (``A`` one-hot, ``D = 0``, row sum 1), a mix of both, or zero (not fitted).
    """

    joint_set: str
    parents: np.ndarray  # (J,) kinematic parent, -1 for the root
    tree: KinematicTree  # the model's, for body_model.forward_kinematics
    J_template: torch.Tensor  # (J, 3)
    J_shapedirs: torch.Tensor  # (J, 3, B)
    A: torch.Tensor | None  # (T, J) blended skinning weights; None: targets = the 24 joints
    D0: torch.Tensor | None  # (T, J, 3)
    Dbeta: torch.Tensor | None  # (T, J, 3, B)
    E: torch.Tensor | None  # (T, J, 3, 207) pose blend shapes, licensed SMPL only
    rowsum: torch.Tensor | None  # (T,) regressor row sums (1 for a proper regressor)
    free_weight: torch.Tensor  # (J,) 1 for the joints of body_keypoints.free_joints
    torso: np.ndarray  # indices into the target set (body_keypoints.torso_points)
    fitted: np.ndarray  # (T,) bool: targets the model gives (others get weight 0)
    anchors: dict[str, int]  # SMPL-24 joint -> target anchored there (analytic init)
    offset_joint: torch.Tensor  # (T,) the joint whose frame carries a target's offset
    offset_mask: torch.Tensor  # (T,) 1 where a target may have an offset (see below)
    foot_offset: torch.Tensor  # (T,) 1 for the foot points among them (FOOT_OFFSET_FRAMES)
    D_rows: torch.Tensor | None = None
    """(T * (1 + B), 3 * J): D0 and Dbeta as the rows (target, 1 or beta) and columns
    (column, joint) of :func:`predict_targets`' one matrix product."""

    @property
    def num_targets(self) -> int:
        return get_joint_set(self.joint_set).num_joints


_BUFFER_CACHE: dict[tuple[str, str], KeypointBuffers] = {}
"""(model fingerprint, joint set) -> buffers. Keyed by what the model is, not by
``id(model)``: a freed model's id is reused by the next one, which then got the old
model's buffers (a test of two tiny models failed that way, depending on order)."""


def _fold_regressor(model: BodyModel, Rv: torch.Tensor, Rj: torch.Tensor):
    """Vertex rows ``Rv`` (T, V) and joint rows ``Rj`` (T, J) -> A, D0, Dbeta, E, rowsum."""
    # Only the vertices the regressor reads matter (4,465 of the open model's for COCO-17).
    used = torch.nonzero(Rv.abs().sum(0) > 0)[:, 0]
    Rk = Rv[:, used].double()  # (T, V')
    W = model.weights[used].double()  # (V', J)
    RW = Rk[:, :, None] * W[None]  # (T, V', J): each keypoint's skinning blend
    A_v = RW.sum(1)
    B0 = torch.einsum("tvj,vc->tjc", RW, model.v_template[used].double())
    Bb = torch.einsum("tvj,vcb->tjcb", RW, model.shapedirs[used].double())
    D0 = B0 - A_v[..., None] * model.J_template.double()[None]
    Dbeta = Bb - A_v[..., None, None] * model.J_shapedirs.double()[None]
    E = None
    if model.has_posedirs:
        pd = model.posedirs.double().T.reshape(model.num_vertices, 3, -1)[used]
        E = torch.einsum("tvj,vcp->tjcp", RW, pd).float()
    # A joint row adds its one-hot to A (p_j moves the keypoint) and nothing to D.
    A = A_v + Rj.double()
    rowsum = (Rk.sum(1) + Rj.double().sum(1)).float()
    return A.float(), D0.float(), Dbeta.float(), E, rowsum


def keypoint_buffers(model: BodyModel, joint_set: str) -> KeypointBuffers:
    """Precompute (once per model and joint set) the kinematic tree and target regressor."""
    js = get_joint_set(joint_set)
    if js.name not in FITTABLE_JOINT_SETS:
        raise ValueError(f"SMPL fit targets must be one of {FITTABLE_JOINT_SETS}, got {js.name!r}")
    key = (model.fingerprint, js.name)
    if key in _BUFFER_CACHE:
        return _BUFFER_CACHE[key]
    parents = model.parents
    reg = keypoint_regressor(model, js.name)
    with torch.no_grad():
        A = D0 = Dbeta = E = rowsum = None
        if not reg.is_joints:
            A, D0, Dbeta, E, rowsum = _fold_regressor(model, reg.vertex_weights, reg.joint_weights)
        J0 = model.J_template.double().numpy()
        if A is None:  # the targets are the joints: A = I, D = 0
            lever = lever_arms(np.eye(NUM_JOINTS), np.zeros((NUM_JOINTS,) * 2 + (3,)), J0, parents)
        else:
            lever = lever_arms(A.double().numpy(), D0.double().numpy(), J0, parents)
    free = torch.zeros(NUM_JOINTS)
    free[[_J[n] for n in free_joints(lever, reg)]] = 1.0
    # A target's offset frame: the parent of its anchor joint (the bone that ends at the
    # joint), else the joint that moves it most.
    dominant = np.arange(NUM_JOINTS) if A is None else A.double().numpy().argmax(1)
    offset_joint = [
        max(int(parents[_J[a]]), 0) if a is not None and a in _J else int(d)
        for a, d in zip(reg.anchor, dominant, strict=True)
    ]
    # Offsets: keypoints in a trunk or head frame, and foot points that are not joints.
    names = [SMPL24.names[j] for j in offset_joint]
    foot = [
        float(a is None and n in FOOT_OFFSET_FRAMES) for n, a in zip(names, reg.anchor, strict=True)
    ]
    buf = KeypointBuffers(
        joint_set=js.name,
        parents=np.asarray(parents),
        tree=model.tree,
        J_template=model.J_template.detach().clone(),
        J_shapedirs=model.J_shapedirs.detach().clone(),
        A=A,
        D0=D0,
        Dbeta=Dbeta,
        E=E,
        rowsum=rowsum,
        free_weight=free,
        torso=torso_points(reg),
        fitted=reg.fitted.copy(),
        anchors=reg.anchors,
        offset_joint=torch.as_tensor(offset_joint, dtype=torch.long),
        offset_mask=torch.as_tensor(
            [max(float(n in OFFSET_FRAMES), f) for n, f in zip(names, foot, strict=True)]
        ),
        foot_offset=torch.as_tensor(foot),
        D_rows=None if A is None else _keypoint_rows(D0, Dbeta),
    )
    _BUFFER_CACHE[key] = buf
    return buf


def _keypoint_rows(D0: torch.Tensor, Dbeta: torch.Tensor) -> torch.Tensor:
    """(T, J, 3) and (T, J, 3, B) -> (T * (1 + B), 3 * J), see ``KeypointBuffers.D_rows``."""
    T, J = D0.shape[:2]
    both = torch.cat([D0[..., None], Dbeta], -1)  # (T, J, 3, 1 + B)
    return both.permute(0, 3, 2, 1).reshape(T * both.shape[-1], 3 * J).contiguous()


def rest_joints(betas: torch.Tensor, buf: KeypointBuffers) -> torch.Tensor:
    """(N, B) betas -> (N, 24, 3) rest joints, metres."""
    return buf.J_template + torch.einsum("jcb,nb->njc", buf.J_shapedirs, betas)


SCALED_BONES: dict[str, tuple[str, ...]] = {
    "hips": ("left_hip", "right_hip"),
    "thighs": ("left_knee", "right_knee"),
    "shins": ("left_ankle", "right_ankle"),
    "shoulders": ("left_shoulder", "right_shoulder"),
    "upper_arms": ("left_elbow", "right_elbow"),
    "forearms": ("left_wrist", "right_wrist"),
}
"""The bone groups a fit may scale, each named by the joints at the bones' outer ends
(a bone is a joint minus its parent: ``hips`` is pelvis to hip, ``shoulders`` collar to
shoulder): the limbs and the widths of hips and shoulders, which every fittable joint
set pins at both ends. Left and right share a scale (people are near symmetric, and a
shared scale is measured by twice the keypoints). The spine, neck, head, hands and feet
keep the shape space's lengths: few joint sets see both ends of those bones."""


def bone_scale_matrix() -> np.ndarray:
    """(len(SCALED_BONES), 24): a group's scale to each joint's bone (0 where unscaled)."""
    out = np.zeros((len(SCALED_BONES), NUM_JOINTS))
    for g, names in enumerate(SCALED_BONES.values()):
        out[g, [_J[n] for n in names]] = 1.0
    return out


def predict_targets(
    rotmats: torch.Tensor,
    betas: torch.Tensor,
    transl: torch.Tensor,
    buf: KeypointBuffers,
    offsets: torch.Tensor | None = None,
    *,
    rows_per_body: Sequence[int] | None = None,
    bone_scales: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The model's target joints and its SMPL-24 joints.

    Args:
        rotmats: (N, 24, 3, 3) local rotations; transl: (N, 3) metres.
        betas: (N, B) one per row; or with ``rows_per_body`` (K, B), one per body whose
            rows are consecutive, ``rows_per_body[k]`` of them (summing to N): a track's
            rows in the fit. The same numbers, computed per body (one small product
            each instead of every row's own).
        offsets: optional (N, T, 3) metres: where the observed keypoint sits relative to
            the model's, in the frame of its joint ``buf.offset_joint`` (the keypoint's
            anchor, else the joint that moves it most); added to the targets, not to the
            joints.
        bone_scales: optional (N, 24), or (K, 24) with ``rows_per_body``: each bone's
            length as a factor of the shaped body's
            (:func:`~pipeline.body.model.scale_bones`).
    Returns:
        targets (N, T, 3) in ``buf.joint_set`` and joints (N, 24, 3), metres, world.
    """
    N, J = rotmats.shape[:2]
    body_betas = betas
    if rows_per_body is not None:
        if sum(rows_per_body) != N or len(rows_per_body) != len(betas):
            raise ValueError(f"rows_per_body {list(rows_per_body)} does not cover {N} rows of "
                             f"{len(betas)} bodies")  # fmt: skip
    # each body's (scaled) rest skeleton once, then its rows'
    rest = rest_joints(betas, buf)
    if bone_scales is not None:
        rest = scale_bones(rest, bone_scales, buf.parents)
    if rows_per_body is not None:
        rest = torch.repeat_interleave(rest, torch.as_tensor(rows_per_body), 0)
    glob_c, posed_c = forward_kinematics_components(rotmats, rest, buf.tree)
    glob, posed = glob_c.permute(3, 2, 0, 1), posed_c.permute(2, 1, 0)  # (N, J, 3, 3), (N, J, 3)
    joints = posed + transl[:, None]
    if buf.A is None:
        if offsets is None:
            return joints, joints
        return joints + _rotate_offsets(glob, offsets, buf), joints
    # sum_j G_j (D0_tj + Dbeta_tj @ betas), component-major (see _keypoint_products)
    kp = _keypoint_products(glob_c, body_betas, buf, rows_per_body)  # (N, T, 3)
    kp = kp + (buf.A @ posed_c + buf.rowsum[:, None] * transl.t()[:, None]).permute(2, 1, 0)
    if buf.E is not None:
        eye = torch.eye(3, dtype=rotmats.dtype)
        feat = (rotmats[:, 1:] - eye).reshape(N, -1)  # (N, 207)
        Ef = torch.einsum("tjcp,np->ntjc", buf.E, feat)  # pose blend shapes (licensed SMPL)
        kp = kp + torch.einsum("njab,ntjb->nta", glob, Ef)
    if offsets is not None:
        kp = kp + _rotate_offsets(glob, offsets, buf)
    return kp, joints


def _keypoint_products(
    glob_c: torch.Tensor, betas: torch.Tensor, buf: KeypointBuffers,
    rows_per_body: Sequence[int] | None,
) -> torch.Tensor:  # fmt: skip
    """(N, T, 3) sum_j G_j (D0_tj + Dbeta_tj @ betas) of global rotations ``glob_c``
    (3, 3, J, N) (:func:`~pipeline.body.model.forward_kinematics_components`).

    Per body (``rows_per_body``): its (T, 3 J) matrix D0 + Dbeta @ betas first, then one
    (T, 3 J) @ (3 J, 3 n) product over its rows' rotations laid out ((column, joint),
    (row, component)). Per row (betas (N, B)): the rows (target, 1 or beta) times the
    rotations, (T (1 + B), 3 J) @ (3 J, N) for each component, then each row's betas
    contracted. Per body it is ~10x fewer multiplications: on the sample's tracks copied
    to 20 (4,885 rows), forward and backward, 18.7 ms per row, 4.1 ms per body."""
    nb1, n = 1 + betas.shape[1], glob_c.shape[-1]
    T = buf.D_rows.shape[0] // nb1
    if rows_per_body is None:
        coef = torch.cat([torch.ones(1, n, dtype=betas.dtype), betas.t()], 0)  # (1 + B, N)
        Y = buf.D_rows @ glob_c.reshape(3, -1, n)  # (3, T * (1 + B), N)
        return (Y.reshape(3, T, nb1, n) * coef).sum(2).permute(2, 1, 0)
    coef = torch.cat([torch.ones(len(betas), 1, dtype=betas.dtype), betas], 1)  # (K, 1 + B)
    D = (coef[:, None, :, None] * buf.D_rows.reshape(T, nb1, -1)).sum(2)  # (K, T, 3 J)
    cols = glob_c.permute(1, 2, 3, 0).reshape(D.shape[-1], 3 * n)  # ((b, j), (row, a))
    # split, not slices: a slice's backward is a zero array of the whole size per body
    parts = torch.split(cols, [3 * int(r) for r in rows_per_body], 1)
    kp = torch.cat([d @ part for d, part in zip(D.unbind(0), parts, strict=True)], 1)
    return kp.reshape(T, n, 3).transpose(0, 1)


def _rotate_offsets(
    glob: torch.Tensor, offsets: torch.Tensor, buf: KeypointBuffers
) -> torch.Tensor:
    """(N, 24, 3, 3) global rotations, (N, T, 3) local offsets -> (N, T, 3) world offsets."""
    return (glob[:, buf.offset_joint] @ offsets[..., None])[..., 0] * buf.offset_mask[:, None]
