"""What the SMPL fit predicts for a target joint set, and the rotation representations.

:class:`KeypointBuffers` holds, per body model and target joint set, everything the fit
needs precomputed once: the layout's keypoints (:mod:`pipeline.body_keypoints`, a mix
of vertex-regressor rows and SMPL-joint rows) folded into the skinning weights, see the
docstring of :mod:`pipeline.smpl_fit`; :func:`predict_targets` and
:func:`~pipeline.body_model.forward_kinematics` are the batched forward pass of the fit
(rotation conversions live in :mod:`pipeline.rotations`).
Units: metres (the body model's).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from pipeline.body_keypoints import (
    FITTABLE_JOINT_SETS,
    free_joints,
    keypoint_regressor,
    lever_arms,
    torso_points,
)
from pipeline.body_model import BodyModel, KinematicTree, forward_kinematics
from pipeline.joint_sets import SMPL24, get_joint_set
from pipeline.rotations import (  # noqa: F401  (re-exported: the fit's and the prior's)
    matrix_to_rot6d,
    matrix_to_rotvec,
    rot6d_to_matrix,
    rotvec_to_matrix,
)

NUM_JOINTS = SMPL24.num_joints
SUPPORTED_JOINT_SETS = FITTABLE_JOINT_SETS
"""Every joint set whose table anchors all limbs (``body_keypoints.FITTABLE_JOINT_SETS``).
Joints the set leaves free and its torso points follow from the table by the rules of
``body_keypoints.free_joints`` and ``body_keypoints.torso_points``."""
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
    if js.name not in SUPPORTED_JOINT_SETS:
        raise ValueError(f"SMPL fit targets must be one of {SUPPORTED_JOINT_SETS}, got {js.name!r}")
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
    )
    _BUFFER_CACHE[key] = buf
    return buf


def rest_joints(betas: torch.Tensor, buf: KeypointBuffers) -> torch.Tensor:
    """(N, B) betas -> (N, 24, 3) rest joints, metres."""
    return buf.J_template + torch.einsum("jcb,nb->njc", buf.J_shapedirs, betas)


def predict_targets(
    rotmats: torch.Tensor,
    betas: torch.Tensor,
    transl: torch.Tensor,
    buf: KeypointBuffers,
    offsets: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The model's target joints and its SMPL-24 joints.

    Args:
        rotmats: (N, 24, 3, 3) local rotations; betas: (N, B); transl: (N, 3) metres.
        offsets: optional (N, T, 3) metres: where the observed keypoint sits relative to
            the model's, in the frame of its joint ``buf.offset_joint`` (the keypoint's
            anchor, else the joint that moves it most); added to the targets, not to the
            joints.
    Returns:
        targets (N, T, 3) in ``buf.joint_set`` and joints (N, 24, 3), metres, world.
    """
    rest = rest_joints(betas, buf)
    glob, posed = forward_kinematics(rotmats, rest, buf.tree)
    joints = posed + transl[:, None]
    if buf.A is None:
        if offsets is None:
            return joints, joints
        return joints + _rotate_offsets(glob, offsets, buf), joints
    N = rotmats.shape[0]
    # sum_j G_j D_tj as matrix products over the flattened (joint, column) index:
    # (N, 3, J*3) @ (J*3, T [* B]) then the betas contraction.
    G = glob.permute(0, 2, 1, 3).reshape(N, 3, -1)  # (N, a, j*b)
    kp = G @ buf.D0.permute(1, 2, 0).reshape(-1, buf.D0.shape[0])  # (N, 3, T)
    GDb = (G @ buf.Dbeta.permute(1, 2, 0, 3).reshape(G.shape[-1], -1)).reshape(
        N, 3, -1, betas.shape[1]
    )
    kp = kp + (GDb * betas[:, None, None]).sum(-1)
    if buf.E is not None:
        eye = torch.eye(3, dtype=rotmats.dtype)
        feat = (rotmats[:, 1:] - eye).reshape(N, -1)  # (N, 207)
        Ef = torch.einsum("tjcp,np->ntjc", buf.E, feat)  # pose blend shapes (licensed SMPL)
        kp = kp + torch.einsum("njab,ntjb->nat", glob, Ef)
    kp = kp.transpose(1, 2) + torch.einsum("tj,nja->nta", buf.A, posed)
    kp = kp + buf.rowsum[:, None] * transl[:, None]
    if offsets is not None:
        kp = kp + _rotate_offsets(glob, offsets, buf)
    return kp, joints


def _rotate_offsets(
    glob: torch.Tensor, offsets: torch.Tensor, buf: KeypointBuffers
) -> torch.Tensor:
    """(N, 24, 3, 3) global rotations, (N, T, 3) local offsets -> (N, T, 3) world offsets."""
    return (glob[:, buf.offset_joint] @ offsets[..., None])[..., 0] * buf.offset_mask[:, None]
