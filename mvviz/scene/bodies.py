"""Bodies the viewer skins in the browser: ground-truth SMPL bodies and fitted ones.

viser's skinned meshes take a bind pose once and per frame only the bone transforms, so a
frame change sends 24 bone poses per body instead of ~13k vertices. A bone's world pose
is the joint's global rotation and posed position (metres) from forward kinematics; the
browser skins ``vertices`` (bind pose: identity rotations at ``rest_joints``) with
``T_world_bone(t) @ T_world_bone(bind)^-1``: linear blend skinning without pose blend
shapes.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import viser.transforms as vtf

from pipeline.body.arrays import BodyModelData, body_data
from pipeline.data.scene import Scene
from pipeline.results.store import PipelineResults

if TYPE_CHECKING:
    from pipeline.body.model import BodyModel

MM = 1e-3  # millimetres -> metres


@dataclass(frozen=True, eq=False)
class Bodies:
    """Skinned bodies: bind pose per body id, bone poses per frame (metres)."""

    ids: np.ndarray  # (P,) person ids (ground truth) or track ids (fits)
    vertices: np.ndarray  # (P, V, 3) shaped rest vertices, m
    rest_joints: np.ndarray  # (P, 24, 3) m
    faces: np.ndarray  # (T, 3)
    weights: np.ndarray  # (V, 24)
    bone_wxyz: np.ndarray  # (P, F, 24, 4)
    bone_position: np.ndarray  # (P, F, 24, 3) m
    present: np.ndarray  # (P, F) bool

    @property
    def person_ids(self) -> np.ndarray:
        return self.ids


GtBodies = Bodies  # the name the first viewer version used


def skinned_bodies(
    ids: np.ndarray,
    frames: np.ndarray,
    pose: np.ndarray,
    betas: np.ndarray,
    transl_mm: np.ndarray,
    model: BodyModel | BodyModelData,
    num_frames: int,
    bone_scales: np.ndarray | None = None,
) -> Bodies | None:
    """Bone poses of body-frames (numpy: the viewer's start never imports torch).

    Args:
        ids: (R,) body id of each row; frames: (R,) frame of each row.
        pose: (R, 24, 3) axis-angle; betas: (R, B); transl_mm: (R, 3).
        bone_scales: optional (R, 24) bone length factors (a fit's): the bones are posed
            at those lengths, the mesh bound at the shaped body's (it follows its joints).
    Each body's bind shape is taken from its first row.
    """
    uniq = np.unique(ids)
    P, F = len(uniq), num_frames
    if P == 0:
        return None
    m = body_data(model)
    # 1. forward kinematics of every row
    glob_rot, posed = m.pose_chain(np.asarray(pose).reshape(-1, 24, 3), betas, bone_scales)
    pos = posed + transl_mm[:, None, :] * MM
    # 2. bind pose per body, from its first row
    first = np.array([np.flatnonzero(ids == p)[0] for p in uniq])
    verts = m.shaped_vertices(betas[first]).astype(np.float32)
    rest0 = m.rest_joints(betas[first]).astype(np.float32)
    wxyz = vtf.SO3.from_matrix(glob_rot.reshape(-1, 3, 3)).wxyz.reshape(len(ids), 24, 4)
    bone_wxyz = np.tile(np.array([1.0, 0, 0, 0]), (P, F, 24, 1))
    bone_pos = np.zeros((P, F, 24, 3))
    present = np.zeros((P, F), bool)
    pi = np.searchsorted(uniq, ids)
    bone_wxyz[pi, frames] = wxyz
    bone_pos[pi, frames] = pos
    present[pi, frames] = True
    return Bodies(
        ids=uniq,
        vertices=verts,
        rest_joints=rest0,
        faces=m.faces,
        weights=m.weights.astype(np.float32),
        bone_wxyz=bone_wxyz,
        bone_position=bone_pos,
        present=present,
    )


def gt_bodies(scene: Scene, model: BodyModel | BodyModelData) -> Bodies | None:
    """Ground-truth bodies (None without GT SMPL parameters)."""
    gt = scene.gt
    if gt is None or gt.smpl_pose is None or gt.smpl_betas is None or gt.transl is None:
        return None
    ok = np.isfinite(gt.smpl_pose).all(1) & np.isfinite(gt.transl).all(1)
    ok &= np.isfinite(gt.smpl_betas).all(1) & (gt.frame < scene.num_frames)
    r = np.flatnonzero(ok)
    return skinned_bodies(
        gt.person_id[r], gt.frame[r], gt.smpl_pose[r], gt.smpl_betas[r], gt.transl[r], model,
        scene.num_frames,
    )  # fmt: skip


def fitted_bodies(results: PipelineResults) -> Bodies | None:
    """The final SMPL fit of every track (SMPL + VAE if present, else step I), or None."""
    fit = results.smpl_vae if results.smpl_vae is not None else results.smpl
    if fit is None:
        return None
    k, f = np.nonzero(fit.present)
    return skinned_bodies(
        k, f, fit.pose_rotvecs[k, f], fit.betas[k], fit.transl[k, f], fit.model,
        results.num_frames, None if fit.bone_scales is None else fit.bone_scales[k],
    )  # fmt: skip
