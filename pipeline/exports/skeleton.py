"""A fitted SMPL track as an animated skeleton in a Y-up file's axes (BVH, glTF).

The fit's body is ``1000 * model(pose, betas) + transl`` in world mm, z up, where the
model's canonical frame is y up and the root rotation ``R_0`` carries it into the world
(:mod:`pipeline.fit.smpl`). In forward kinematics the root joint sits at its rest
position ``J_0`` (not rotated) plus the translation, and each child ``j`` at
``G_parent @ (J_j - J_parent)``. So in a Y-up file (``M`` = :data:`WORLD_TO_Y_UP`,
metres):

* joint offsets: the shaped rest joints' differences ``J_j - J_parent`` (canonical
  frame = the file's, both y up) times the fit's bone scales, the root's offset zero;
* root position per frame: ``M @ (J_0 + transl / 1000)``;
* root rotation per frame: ``M @ R_0``; every other joint's local rotation as fitted.

The skeleton's world joints are then ``M @ fit.joints / 1000`` exactly (tests check it
through the BVH reader and through a glTF evaluator).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from pipeline.body.model import torch_body_model
from pipeline.core.units import MM_PER_M
from pipeline.data.joint_sets import SMPL24
from pipeline.exports.common import WORLD_TO_Y_UP, hold_indices
from pipeline.fit.types import SmplFit


@dataclass(frozen=True, eq=False)
class TrackSkeleton:
    """One fitted track, F frames (poses held over missing frames), J = 24 joints.

    Attributes:
        names: (J,) joint names (the body model's, else SMPL's).
        parents: (J,) parent index, -1 for the root.
        rest_joints: (J, 3) shaped rest joints, metres, canonical (= file) axes, y up.
        offsets: (J, 3) ``rest_joints[j] - rest_joints[parent]`` times the fit's bone
            scale (``SmplFit.bone_scales``), the root's zero; a glTF binds the mesh at
            ``rest_joints``, so its surface follows the scaled joints.
        local_rotations: (F, J, 3, 3) local rotations, the root's in the file's axes.
        root_position: (F, 3) metres, file axes.
        present: (F,) bool, frames the fit has; the others repeat ``held_from``.
        held_from: (F,) int, the frame whose pose each frame shows.
        betas: (B,) the track's shape.
    """

    names: tuple[str, ...]
    parents: np.ndarray
    rest_joints: np.ndarray
    offsets: np.ndarray
    local_rotations: np.ndarray
    root_position: np.ndarray
    present: np.ndarray
    held_from: np.ndarray
    betas: np.ndarray

    @property
    def num_frames(self) -> int:
        return int(self.root_position.shape[0])


def track_skeleton(fit: SmplFit, k: int) -> TrackSkeleton:
    """The skeleton of track ``k`` of ``fit`` (see the module docstring)."""
    model = torch_body_model(fit.model)  # a loaded run's fit holds the numpy arrays
    present = fit.present[k]
    if not present.any():
        raise ValueError(f"track {k} has no fitted frame")
    held = hold_indices(present)
    betas = np.asarray(fit.betas[k], float)
    with torch.no_grad():
        rest = model.rest_joints(torch.as_tensor(betas[None], dtype=torch.float32))
    rest = rest[0].double().numpy()  # (J, 3)
    parents = np.asarray(model.parents, int)
    offsets = rest.copy()
    offsets[0] = 0.0
    offsets[1:] = rest[1:] - rest[parents[1:]]
    if fit.bone_scales is not None:  # the fit's bone lengths (the mesh stays bound to rest)
        offsets[1:] *= np.nan_to_num(np.asarray(fit.bone_scales[k], float), nan=1.0)[1:, None]
    pose = np.asarray(fit.pose_rotvecs[k][held], float)  # (F, J, 3)
    F, J = pose.shape[:2]
    local = Rotation.from_rotvec(pose.reshape(-1, 3)).as_matrix().reshape(F, J, 3, 3)
    local[:, 0] = WORLD_TO_Y_UP @ local[:, 0]
    root = (rest[0] + np.asarray(fit.transl[k][held], float) / MM_PER_M) @ WORLD_TO_Y_UP.T
    names = tuple(model.joint_names or SMPL24.names)
    return TrackSkeleton(
        names=names, parents=parents, rest_joints=rest, offsets=offsets,
        local_rotations=local, root_position=root, present=present.copy(), held_from=held,
        betas=betas,
    )  # fmt: skip


def end_site_offsets(fit: SmplFit, skel: TrackSkeleton) -> dict[int, np.ndarray]:
    """Leaf joint -> (3,) offset of a bone tip (metres, canonical axes): twice the mean
    offset of the rest-mesh vertices the leaf moves most (the top of the head, the toes,
    the fingertips, roughly), so importers draw leaf bones of a sensible length."""
    model = torch_body_model(fit.model)  # a loaded run's fit holds the numpy arrays
    parents = skel.parents
    leaves = [j for j in range(len(parents)) if j not in set(parents.tolist())]
    with torch.no_grad():
        v = model(torch.zeros(1, 72), torch.as_tensor(skel.betas[None], dtype=torch.float32))
    verts = v.vertices[0].double().numpy()
    owner = model.weights.numpy().argmax(1)
    out = {}
    for j in leaves:
        mine = verts[owner == j]
        if len(mine) == 0:  # no vertex: continue the parent's bone by half its length
            out[j] = 0.5 * skel.offsets[j]
        else:
            out[j] = 2.0 * (mine.mean(0) - skel.rest_joints[j])
    return out
