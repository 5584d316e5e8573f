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
turned into a rotation by Gram-Schmidt (:func:`pipeline.smpl_fit.rot6d_to_matrix`).

Model: encoder q(z|X) and decoder p(X|z), each an MLP with two hidden layers of
``hidden`` units (LeakyReLU); the encoder outputs the mean and log-variance of a
diagonal Gaussian over ``latent`` dimensions. Loss per pose (Eq. 10)::

    L = sum_joints |R_decoded - R|_F^2 + alpha * KL(q(z|X) || N(0, I))

Training data: by default the synthetic motion library
(:func:`pipeline.synth.motion.sample_pose_library`, every activity, root zeroed) plus
perturbations that cover what the library never moves (collars, wrists, ankles off
axis, toes, limb twists), sampled inside :data:`pipeline.pose_limits.LIMITS`; any
AMASS-style ``.npz`` with a ``poses`` array of (N, 156) (SMPL-H) or (N, 72) (SMPL) can be
added or used instead (the first 72 columns are read; only joints 1-21 are used, which
the two layouts share), and so can a BVH motion capture clip (``.bvh``: our body model
fitted to its joints at 30 fps by :func:`pipeline.mocap.bvh_training_poses`). The
checkpoint's ``info["sources"]`` lists every source (frames, activity, licence).

Checkpoints: ``torch.save`` of ``{"state_dict", "config", "info"}`` (tensors, numbers,
strings only), read back with ``torch.load(weights_only=True)``.
"""

from __future__ import annotations

import dataclasses
import os
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from pipeline import pose_limits
from pipeline.files import SceneFormatError
from pipeline.prior_path import DEFAULT_PRIOR_PATH, resolve_prior_path  # noqa: F401
from pipeline.progress import StageBar
from pipeline.smpl_kinematics import (
    matrix_to_rot6d,
    matrix_to_rotvec,
    rot6d_to_matrix,
    rotvec_to_matrix,
)

REPO_ROOT = Path(__file__).resolve().parents[1]
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


# --------------------------------------------------------------------------- data


def load_pose_data(path: str | os.PathLike) -> np.ndarray:
    """Poses (N, 72) from an AMASS-style ``.npz`` (its ``poses`` array, first 72 columns)
    or a ``.bvh`` clip (the default body model fitted to it at 30 fps)."""
    path = Path(path)
    if path.suffix.lower() == ".bvh":
        from pipeline import mocap  # noqa: PLC0415  (training only; see default_training_poses)

        return mocap.bvh_training_poses(path)[0]
    with np.load(path, allow_pickle=False) as z:
        if "poses" not in z.files:
            raise ValueError(f"{path}: no 'poses' array (keys: {z.files})")
        poses = np.asarray(z["poses"], float)
    if poses.ndim != 2 or poses.shape[1] < 72:
        raise ValueError(f"{path}: expected poses (N, 72) or (N, 156), got {poses.shape}")
    poses = poses[:, :72]
    return poses[np.isfinite(poses).all(1)]


# Joints the motion library never (or only on one axis) moves, and the fraction of their
# limit box the perturbations sample.
_PERTURB_FULL = (
    "left_collar", "right_collar", "left_wrist", "right_wrist", "left_foot", "right_foot",
)  # fmt: skip
_PERTURB_SHRINK = 0.7


def perturb_poses(poses: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Plausible variations of library poses, all inside :data:`pipeline.pose_limits.LIMITS`.

    Collars, wrists and toes get angles drawn uniformly from 70% of their limit box
    (shrunk towards zero); every other limited joint gets its swing-twist angles moved
    by N(0, 6 deg) and, for hips, shoulders and elbows, a twist drawn from 40% of its
    range. Poses that end up outside the limits are dropped.

    Args:
        poses: (N, 72) or (N, 24, 3). Returns: (M <= N, 72).
    """
    p = _as_poses(poses)
    ang = pose_limits.swing_twist(p)
    n = len(p)
    lo = np.where(np.isfinite(pose_limits.LOW), pose_limits.LOW, 0.0)
    hi = np.where(np.isfinite(pose_limits.HIGH), pose_limits.HIGH, 0.0)
    ang = ang + np.where(pose_limits.LIMITED[:, None], rng.normal(0, np.deg2rad(6), ang.shape), 0)
    for name in ("hip", "shoulder", "elbow"):
        for side in ("left", "right"):
            j = pose_limits.J[f"{side}_{name}"]
            ang[:, j, 2] += rng.uniform(0.4 * lo[j, 2], 0.4 * hi[j, 2], n)
    for name in _PERTURB_FULL:
        j = pose_limits.J[name]
        ang[:, j] = rng.uniform(_PERTURB_SHRINK * lo[j], _PERTURB_SHRINK * hi[j], (n, 3))
    out = pose_limits.from_swing_twist(ang)
    out[:, 0] = p[:, 0]
    keep = ~pose_limits.limit_violations(out, tol_deg=0.0).any(1)
    return out[keep].reshape(-1, 72)


def default_training_poses(
    num_poses: int = 60000, seed: int = 0, *, kinds: tuple[str, ...] | None = None
) -> np.ndarray:
    """(M, 72) the default training set: half library poses (of the activities ``kinds``,
    default :data:`pipeline.synth.motion.LIBRARY_ACTIVITIES`), half their perturbations."""
    # The motion library and the BVH importers (~0.15-0.5 s of imports) are the training's:
    # every fit imports this module for the prior, in every process (a batch worker too).
    from pipeline.synth.motion import LIBRARY_ACTIVITIES, sample_pose_library  # noqa: PLC0415

    kinds = LIBRARY_ACTIVITIES if kinds is None else kinds
    rng = np.random.default_rng(seed)
    lib = sample_pose_library(num_poses // 2, seed=seed, kinds=tuple(kinds))
    return np.concatenate([lib, perturb_poses(lib, rng)])


# --------------------------------------------------------------------------- training


def _training_data(poses, seed: int) -> tuple[np.ndarray, str]:
    """(N, 24, 3) training poses and a description, from what :func:`train_prior` takes."""
    if poses is None:
        data, source = default_training_poses(seed=seed), "synthetic library + perturbations"
    elif isinstance(poses, (str, os.PathLike)):
        data, source = load_pose_data(poses), str(poses)
    elif isinstance(poses, Sequence) and poses and isinstance(poses[0], (str, os.PathLike)):
        data = np.concatenate([load_pose_data(p) for p in poses])
        source = ", ".join(str(p) for p in poses)
    else:
        data, source = _as_poses(poses).reshape(-1, 72), "array"
    return _as_poses(data), source


def _train_epochs(
    net: PoseVAE, R_train: torch.Tensor, config: PriorConfig, gen: torch.Generator, progress
) -> tuple[float, float]:
    """Adam with cosine decay over ``config.epochs``; the last epoch's summed
    reconstruction and KL losses (times the batch sizes)."""
    batch_size, lr = config.batch_size, config.lr
    opt = torch.optim.Adam(net.parameters(), lr=lr)
    steps_per_epoch = max(1, int(np.ceil(len(R_train) / batch_size)))
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(
        opt, config.epochs * steps_per_epoch, lr * 0.05
    )
    bar = StageBar("train pose prior", config.epochs, progress, unit="epoch")
    rec_sum = kl_sum = 0.0
    for _epoch in range(config.epochs):
        perm = torch.randperm(len(R_train), generator=gen)
        rec_sum = kl_sum = 0.0
        for s in range(steps_per_epoch):
            batch = R_train[perm[s * batch_size : (s + 1) * batch_size]]
            loss, rec, kl = vae_loss(net, batch, config.alpha, gen)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            sched.step()
            rec_sum += float(rec.detach()) * len(batch)
            kl_sum += float(kl.detach()) * len(batch)
        bar.update()
        bar.set_postfix(rec=f"{rec_sum / len(R_train):.4f}", kl=f"{kl_sum / len(R_train):.2f}")
    bar.close()
    return rec_sum, kl_sum


def train_prior(
    poses: np.ndarray | str | os.PathLike | Sequence[str | os.PathLike] | None = None,
    *,
    epochs: int = 60,
    alpha: float = 0.01,
    seed: int = 0,
    hidden: int = 256,
    latent: int = 32,
    batch_size: int = 256,
    lr: float = 1e-3,
    holdout: float = 0.05,
    progress: bool = True,
    num_threads: int = 1,
    data_name: str | None = None,
    sources: Sequence[dict] | None = None,
) -> PosePrior:
    """Train the VAE (Adam, cosine learning-rate decay) on CPU.

    Args:
        poses: (N, 72) / (N, 24, 3) axis-angle, a path to an AMASS-style npz or a list of
            them; None = :func:`default_training_poses`.
        holdout: fraction of poses kept out of training to report held-out losses.
        data_name: description of the data for the training record (default: derived).
        sources: one record per data source (file, frames, activity, licence, ...),
            stored as ``info["sources"]``.
    Returns:
        The prior; ``info`` holds the data description, final train / held-out losses
        (reconstruction, KL) and the wall time.
    """
    t0 = time.perf_counter()
    data, source = _training_data(poses, seed)
    config = PriorConfig(
        hidden=hidden, latent=latent, alpha=alpha, epochs=epochs, batch_size=batch_size,
        lr=lr, seed=seed,
    )  # fmt: skip
    old_threads = torch.get_num_threads()
    if num_threads > 0:
        torch.set_num_threads(num_threads)
    try:
        torch.manual_seed(seed)
        gen = torch.Generator().manual_seed(seed)
        rng = np.random.default_rng(seed)
        order = rng.permutation(len(data))
        n_hold = int(round(holdout * len(data)))
        R = torch.as_tensor(rotvec_to_matrix(data[:, list(BODY_JOINTS)]), dtype=torch.float32)
        R_hold, R_train = R[order[:n_hold]], R[order[n_hold:]]
        net = PoseVAE(hidden, latent)
        rec_sum, kl_sum = _train_epochs(net, R_train, config, gen, progress)
        net.eval()
        with torch.no_grad():
            hold = (
                [float(x) for x in vae_loss(net, R_hold, alpha, gen)[1:]]
                if n_hold
                else [float("nan")] * 2
            )
    finally:
        torch.set_num_threads(old_threads)
    info = {
        "data": data_name or source,
        "num_poses": int(len(data)),
        "num_train": int(len(R_train)),
        "num_holdout": int(n_hold),
        "train_reconstruction": rec_sum / max(len(R_train), 1),
        "train_kl": kl_sum / max(len(R_train), 1),
        "holdout_reconstruction": hold[0],
        "holdout_kl": hold[1],
        "seconds": time.perf_counter() - t0,
        "torch": str(torch.__version__),
    }
    if sources is not None:
        info["sources"] = [dict(s) for s in sources]
    return PosePrior(net=net, config=config, info=info)


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
