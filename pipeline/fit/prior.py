"""A variational auto-encoder pose prior (the method's Eq. 10), trained on CPU in minutes.

Representation: the local rotations of SMPL's 21 body joints (joints 1-21: hips to
wrists; not the root, whose rotation is the global orientation, and not the two hand
joints, which no target of ours observes and which SMPL-H/X replace by fingers), each in
the 6D continuous representation of Zhou et al. 2019 (the first two columns of the
rotation matrix), 126 numbers. Why rotations and not root-relative 3D joints: they are
independent of body shape (joint positions mix pose with betas and bone lengths), they
carry the twists joint positions cannot see (the local-plausibility failures of a fit
are twists and off-axis bends), and the decoder's output feeds forward kinematics
directly. Why 6D: it is continuous, unlike axis-angle (wrap at pi) or quaternions
(double cover), so a network can both read and produce it; the decoder's 6D output is
turned into a rotation by Gram-Schmidt (:func:`pipeline.fit.smpl.rot6d_to_matrix`).

Model: encoder q(z|X) and decoder p(X|z), each an MLP with two hidden layers of
``hidden`` units (LeakyReLU); the encoder outputs the mean and log-variance of a
diagonal Gaussian over ``latent`` dimensions. Loss per pose (Eq. 10)::

    L = sum_joints |R_decoded - R|_F^2 + alpha * KL(q(z|X) || N(0, I))

Training (:mod:`pipeline.prior.training`) uses by default the synthetic motion library
(:func:`pipeline.synth.motion.sample_pose_library`, every activity, root zeroed) plus
perturbations that cover what the library never moves (collars, wrists, ankles off
axis, toes, limb twists), sampled inside :data:`pipeline.body.pose_limits.LIMITS`; any
AMASS-style ``.npz`` with a ``poses`` array of (N, 156) (SMPL-H) or (N, 72) (SMPL) can be
added or used instead (the first 72 columns are read; only joints 1-21 are used, which
the two layouts share), and so can a BVH motion capture clip (``.bvh``: our body model
fitted to its joints at 30 fps by :func:`pipeline.mocap.clips.bvh_training_poses`). The
checkpoint's ``info["sources"]`` lists every source (frames, activity, licence).

Checkpoints: ``torch.save`` of ``{"state_dict", "config", "info"}`` (tensors, numbers,
strings only), read back with ``torch.load(weights_only=True)``.
"""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from pipeline.body.kinematics import (
    matrix_to_rot6d,
    matrix_to_rotvec,
    rot6d_to_matrix,
    rotvec_to_matrix,
)
from pipeline.core.files import SceneFormatError
from pipeline.fit.prior_path import DEFAULT_PRIOR_PATH, resolve_prior_path  # noqa: F401

BODY_JOINTS = tuple(range(1, 22))
"""SMPL joints the prior models (hips .. wrists)."""
CHECKPOINT_VERSION = 1


@dataclass(frozen=True)
class PriorConfig:
    """Architecture and training hyper-parameters of a :class:`PoseVAE`."""

    hidden: int = 256
    latent: int = 32
    alpha: float = 0.01
    """Weight of the KL term (Eq. 10)."""
    epochs: int = 60
    batch_size: int = 256
    lr: float = 1e-3
    seed: int = 0


class PoseVAE(torch.nn.Module):
    """Encoder q(z|X) and decoder p(X|z) over 6D body-joint rotations.

    Shapes: B poses, P = len(BODY_JOINTS) joints, L latent dimensions.
    """

    def __init__(self, hidden: int, latent: int) -> None:
        super().__init__()
        d = 6 * len(BODY_JOINTS)
        act = torch.nn.LeakyReLU(0.2)
        self.encoder = torch.nn.Sequential(
            torch.nn.Linear(d, hidden), act, torch.nn.Linear(hidden, hidden), act,
            torch.nn.Linear(hidden, 2 * latent),
        )  # fmt: skip
        self.decoder = torch.nn.Sequential(
            torch.nn.Linear(latent, hidden), act, torch.nn.Linear(hidden, hidden), act,
            torch.nn.Linear(hidden, d),
        )  # fmt: skip
        self.latent = latent
        # Start the decoder at the rest pose: bias = 6D identity, last weights small.
        with torch.no_grad():
            last = self.decoder[-1]
            last.weight.mul_(0.01)
            last.bias.copy_(torch.tensor([1.0, 0, 0, 0, 1.0, 0]).repeat(len(BODY_JOINTS)))

    def encode(self, rotmats: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(B, P, 3, 3) -> mean (B, L), log-variance (B, L)."""
        h = self.encoder(matrix_to_rot6d(rotmats).reshape(rotmats.shape[0], -1))
        return h[:, : self.latent], h[:, self.latent :]

    def decode(self, z: torch.Tensor) -> torch.Tensor:
        """(B, L) -> (B, P, 3, 3) rotations."""
        return rot6d_to_matrix(self.decoder(z).reshape(z.shape[0], -1, 6))


def vae_loss(
    net: PoseVAE, rotmats: torch.Tensor, alpha: float, generator: torch.Generator | None = None
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Eq. 10 on a batch (B, P, 3, 3): (loss, reconstruction, KL), each a batch mean."""
    mu, logvar = net.encode(rotmats)
    eps = torch.randn(mu.shape, generator=generator)
    z = mu + torch.exp(0.5 * logvar) * eps  # reparameterisation
    rec = ((net.decode(z) - rotmats) ** 2).sum((1, 2, 3)).mean()
    kl = 0.5 * (mu * mu + logvar.exp() - 1.0 - logvar).sum(1).mean()
    return rec + alpha * kl, rec, kl


@dataclass(frozen=True, eq=False)
class PosePrior:
    """A trained pose VAE and how it was made.

    ``info`` records the training (data, epochs, seconds, final losses) and is saved with
    the weights.
    """

    net: PoseVAE
    config: PriorConfig
    info: dict = field(default_factory=dict)

    @property
    def latent(self) -> int:
        return self.config.latent

    def encode_rotmats(self, body: torch.Tensor) -> torch.Tensor:
        """(B, 23, 3, 3) local rotations of SMPL joints 1-23 -> (B, L) posterior means."""
        idx = [j - 1 for j in BODY_JOINTS]
        mu, _ = self.net.encode(body[:, idx])
        return mu

    def decode_rotmats(self, z: torch.Tensor) -> torch.Tensor:
        """(B, L) -> (B, 23, 3, 3) rotations of SMPL joints 1-23 (hands: identity)."""
        dec = self.net.decode(z)
        out = torch.eye(3, dtype=dec.dtype).repeat(z.shape[0], 23, 1, 1)
        idx = torch.as_tensor([j - 1 for j in BODY_JOINTS])
        return out.index_copy(1, idx, dec)

    def reconstruct(self, pose_rotvecs: np.ndarray) -> np.ndarray:
        """Encode then decode (posterior mean). (N, 24, 3) or (N, 72) axis-angle -> (N, 24, 3);
        the root rotation is kept, the hands are set to rest."""
        r = _as_poses(pose_rotvecs)
        R = torch.as_tensor(rotvec_to_matrix(r), dtype=torch.float32)
        with torch.no_grad():
            dec = self.decode_rotmats(self.encode_rotmats(R[:, 1:]))
        out = r.copy()
        out[:, 1:] = matrix_to_rotvec(dec.double().numpy())
        return out


def _as_poses(poses: np.ndarray) -> np.ndarray:
    p = np.asarray(poses, float)
    if p.ndim == 2 and p.shape[1] >= 72:
        p = p[:, :72].reshape(-1, 24, 3)
    if p.ndim != 3 or p.shape[1:] != (24, 3):
        raise ValueError(f"expected poses (N, 72) or (N, 24, 3) axis-angle, got {p.shape}")
    return p


# --------------------------------------------------------------------------- io


def save_prior(prior: PosePrior, path: str | os.PathLike) -> None:
    """Write the weights, config and training record (loadable with weights_only=True)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    state = {k: v.detach().clone() for k, v in prior.net.state_dict().items()}
    tmp = path.with_suffix(path.suffix + ".tmp")
    torch.save(
        {
            "version": CHECKPOINT_VERSION,
            "state_dict": state,
            "config": dataclasses.asdict(prior.config),
            "info": dict(prior.info),
            "body_joints": list(BODY_JOINTS),
        },
        tmp,
    )
    os.replace(tmp, path)


def load_prior(path: str | os.PathLike | None = None) -> PosePrior:
    """Read a checkpoint written by :func:`save_prior` (default: the shipped one)."""
    path = resolve_prior_path(path)
    if not path.is_file():
        raise SceneFormatError(path, None, "pose prior checkpoint not found")
    try:  # weights_only: tensors and plain containers; a pickled object is refused, never run
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # UnpicklingError, a zip/format error, a truncated file, ...
        why = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise SceneFormatError(path, None, f"not a readable checkpoint ({why[:200]})") from None
    if not isinstance(ckpt, dict) or ckpt.get("version") != CHECKPOINT_VERSION:
        raise SceneFormatError(
            path, "version", f"not a pose prior checkpoint (version {CHECKPOINT_VERSION})"
        )
    if list(ckpt.get("body_joints", [])) != list(BODY_JOINTS):
        raise SceneFormatError(
            path, "body_joints", f"trained on joints {ckpt.get('body_joints')}, not {BODY_JOINTS}"
        )
    try:
        config = PriorConfig(**ckpt["config"])
        net = PoseVAE(config.hidden, config.latent)
        net.load_state_dict(ckpt["state_dict"])
    except (KeyError, TypeError, ValueError, RuntimeError) as exc:
        why = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise SceneFormatError(path, "config/state_dict", f"does not fit: {why[:200]}") from None
    net.eval()
    return PosePrior(net=net, config=config, info=dict(ckpt.get("info", {})))
