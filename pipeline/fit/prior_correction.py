"""The joint correction of a step-I SMPL fit by the VAE pose prior (the method's Eq. 11),
made safe: the prior corrects what the cameras did not pin down, it does not move what
they saw.

Phases (after step I of :func:`pipeline.fit.smpl.fit_sequence`; betas and the per-track
keypoint offsets stay fixed; N person-frames, metres):

* 2a, encode: ``z = mean of q(z | body pose of step I)`` per frame.
* 2b, joint refinement (``iters_refine`` Adam iterations, cosine decay): optimised: all
  24 rotations (6D) *starting from step I*, translation per frame, and ``z`` per frame.
  Loss = the step-I data and smoothness terms (:func:`pipeline.fit.smpl._objective`)
  + ``w_latent`` |z|^2 (the N(0, I) prior)
  + sum over joints of ``a_j`` |R_j - decoded(z)_j|_F^2 (the prior as a soft pull, with
  ``a_j = w_anchor`` on joints the targets constrain and ``w_anchor_free`` on those they
  leave free, :func:`pipeline.body.keypoints.free_joints`)
  + ``w_limit_prior`` * squared excess over the joint limits
  (:func:`pipeline.fit.limit_penalty.limit_penalty`) + ``w_pose`` |R - I|^2.
  The pose and its code move together, so the refinement converges to a pose the data
  hold and the prior finds likely; the data term dominates wherever a keypoint was
  measured (``w_anchor`` is small against a millimetre of residual), so an unseen motion
  the prior decodes badly cannot drag the body off the observations.
* 2c, check: a person-frame whose mean residual to its targets grew by more than
  ``max_extra_residual_mm`` over step I's keeps step I's pose (counted in
  :attr:`Correction.reverted`), unless step I's pose breaks a joint limit there and the
  corrected one does not.

Why not the original order (a latent fit with the decoded pose only, then a refinement
anchored to the decoded pose with a weight 100x the data term): on motion the prior has
not seen (CMU walking and hopping) the decoded pose is far from the observations and
the anchor kept the body there: 85 mm against step I's 23 mm on a mocap scene.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import torch

from pipeline.body import pose_limits
from pipeline.body.kinematics import NUM_JOINTS, matrix_to_rot6d, rot6d_to_matrix
from pipeline.core.progress import Progress
from pipeline.fit.limit_penalty import limit_penalty
from pipeline.fit.optim import adam_cosine

if TYPE_CHECKING:
    from pipeline.fit.prior import PosePrior
    from pipeline.fit.types import FitParams


@dataclass(frozen=True, eq=False)
class Correction:
    """The corrected rows. N person-frames.

    Attributes:
        rotmats: (N, 24, 3, 3) local rotations.
        transl: (N, 3) metres.
        reverted: (N,) bool: rows that kept step I's pose (phase 2c).
        seconds: wall time of phases 2a-2c.
    """

    rotmats: torch.Tensor
    transl: torch.Tensor
    reverted: np.ndarray
    seconds: float


def in_distribution(
    prior: PosePrior, R: torch.Tensor, z: torch.Tensor, rec0: float
) -> torch.Tensor:
    """(N,) how much to trust the prior on each pose: ``rec0 / max(rec, rec0)``, ``rec`` the
    prior's reconstruction error of the pose (sum over its body joints of
    |R_j - decoded(z)_j|_F^2; ``z`` (N, L) the pose's code, ``R`` (N, 24, 3, 3)). 1 for a
    pose the prior reconstructs within ``rec0`` (its training poses: 0.55 on average),
    ``rec0 / rec`` beyond; ``rec0 <= 0``: 1 everywhere.

    Measured with the library prior on step-I poses: median ``rec`` 0.36 / 0.63 on the
    shipped clean / noisy samples (motion like its training data), 13.3 / 11.2 on CMU
    walking / hopping (motion it never saw)."""
    if rec0 <= 0:
        return torch.ones(R.shape[0])
    idx = list(range(1, 22))  # pose_prior.BODY_JOINTS (imported there: a cycle here)
    dec = prior.decode_rotmats(z)[:, [j - 1 for j in idx]]
    rec = ((R[:, idx] - dec) ** 2).sum((-1, -2)).sum(-1)
    return rec0 / rec.clamp_min(rec0)


def correct_with_prior(
    prior: PosePrior,
    R1: torch.Tensor,
    transl1: torch.Tensor,
    *,
    objective: Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
    row_residual: Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
    free_weight: torch.Tensor,
    params: FitParams,
    progress: Progress = False,
) -> Correction:
    """Phases 2a-2c (module docstring).

    Args:
        prior: the trained VAE.
        R1: (N, 24, 3, 3) step-I local rotations; transl1: (N, 3) metres.
        objective: ``(R, transl) -> loss``, step I's data + smoothness terms with its
            betas and offsets fixed.
        row_residual: ``(R, transl) -> (N,)`` mean distance (m) of each row's model
            keypoints to its targets.
        free_weight: (24,) 1 for the joints the targets leave free.
    """
    t0 = time.perf_counter()
    frozen = [p.requires_grad for p in prior.net.parameters()]
    for p in prior.net.parameters():
        p.requires_grad_(False)
    try:
        # Phase 2a: encode the step-I body pose.
        with torch.no_grad():
            z = prior.encode_rotmats(R1[:, 1:]).clone()
            trust = in_distribution(prior, R1, z, params.in_distribution_rec)  # (N,)
        z.requires_grad_(True)
        rot6d = matrix_to_rot6d(R1).clone().requires_grad_(True)
        transl = transl1.clone().requires_grad_(True)
        a = params.w_anchor + (params.w_anchor_free - params.w_anchor) * free_weight[1:]
        a = trust[:, None] * a  # (N, 23)
        w_rest = torch.full((NUM_JOINTS,), params.w_pose)
        w_rest[0] = 0.0

        # Phase 2b: the pose and its code, refined together.
        def loss_refine() -> torch.Tensor:
            R = rot6d_to_matrix(rot6d)
            dec = prior.decode_rotmats(z)  # (N, 23, 3, 3)
            pull = ((R[:, 1:] - dec) ** 2).sum((-1, -2))  # (N, 23)
            loss = objective(R, transl) + (pull * a).sum(1).mean()
            loss = loss + params.w_latent * (z * z).sum(-1).mean()
            if params.w_limit_prior > 0:
                loss = loss + params.w_limit_prior * limit_penalty(R).mean()
            return loss + (((R - torch.eye(3)) ** 2).sum((-1, -2)) * w_rest).sum(1).mean()

        adam_cosine(
            [
                ([rot6d], params.lr_refine * params.lr_rot),
                ([transl], params.lr_refine * params.lr_transl_m),
                ([z], params.lr_latent),
            ],
            loss_refine,
            params.iters_refine,
            progress=progress,
            desc="SMPL fit (VAE refine)",
        )
    finally:
        for p, s in zip(prior.net.parameters(), frozen, strict=True):
            p.requires_grad_(s)
    # Phase 2c: no row ends farther from its observations than step I.
    with torch.no_grad():
        R2, t2 = rot6d_to_matrix(rot6d), transl.detach()
        extra_mm = 1000.0 * (row_residual(R2, t2) - row_residual(R1, transl1))
        # ...unless step I's pose there is implausible (a joint outside its limits by
        # more than the counting tolerance) and the corrected one is not: then the prior
        # fixed what the cameras left loose, which is its job (on the shipped sample all
        # 5 remaining violations per 1000 bodies were in rows kept at step I).
        tol = np.deg2rad(pose_limits.DEFAULT_TOL_DEG) ** 2
        fixes = (limit_penalty(R1) > tol) & (limit_penalty(R2) <= tol)
        bad = (extra_mm > params.max_extra_residual_mm) & ~fixes
        R2 = torch.where(bad[:, None, None, None], R1, R2)
        t2 = torch.where(bad[:, None], transl1, t2)
    return Correction(R2, t2, bad.numpy(), time.perf_counter() - t0)
