"""Training the VAE pose prior (:mod:`pipeline.fit.prior`): its data and its loop.

Data: by default the synthetic motion library
(:func:`pipeline.synth.motion.sample_pose_library`) plus perturbations of it inside the
joint limits (:func:`perturb_poses`); AMASS-style ``.npz`` files and BVH clips
(:func:`load_pose_data`) can be added or used instead. The model, its loss and its
checkpoints are :mod:`pipeline.fit.prior`'s: a fit needs only those, so this module
(and the motion library and BVH importers it reads) is imported by training alone.
"""

from __future__ import annotations

import os
import time
import zipfile
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from pipeline.body import pose_limits
from pipeline.body.kinematics import rotvec_to_matrix
from pipeline.core.files import SceneFormatError
from pipeline.core.progress import StageBar
from pipeline.fit.prior import (
    BODY_JOINTS,
    PosePrior,
    PoseVAE,
    PriorConfig,
    _as_poses,
    vae_loss,
)
from pipeline.mocap.clips import bvh_training_poses
from pipeline.synth.motion import LIBRARY_ACTIVITIES, sample_pose_library


def load_pose_data(path: str | os.PathLike) -> np.ndarray:
    """Poses (N, 72) from an AMASS-style ``.npz`` (its ``poses`` array, first 72 columns)
    or a ``.bvh`` clip (the default body model fitted to it at 30 fps)."""
    path = Path(path)
    if path.suffix.lower() == ".bvh":
        return bvh_training_poses(path)[0]
    try:
        with np.load(path, allow_pickle=False) as z:
            if "poses" not in z.files:
                raise SceneFormatError(path, "poses", f"missing (keys: {z.files[:5]})")
            poses = np.asarray(z["poses"], float)
    except SceneFormatError:
        raise
    except (ValueError, TypeError, EOFError, OSError, zipfile.BadZipFile) as exc:
        msg = f"not an AMASS-style .npz with a numeric 'poses' array ({exc})"
        raise SceneFormatError(path, "poses", msg) from None
    if poses.ndim != 2 or poses.shape[1] < 72:
        raise SceneFormatError(path, "poses", f"expected (N, 72) or (N, 156), got {poses.shape}")
    poses = poses[:, :72]
    return poses[np.isfinite(poses).all(1)]


# Joints the motion library never (or only on one axis) moves, and the fraction of their
# limit box the perturbations sample.
_PERTURB_FULL = (
    "left_collar", "right_collar", "left_wrist", "right_wrist", "left_foot", "right_foot",
)  # fmt: skip


_PERTURB_SHRINK = 0.7


def perturb_poses(poses: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Plausible variations of library poses, all inside :data:`pipeline.body.pose_limits.LIMITS`.

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

    kinds = LIBRARY_ACTIVITIES if kinds is None else kinds
    rng = np.random.default_rng(seed)
    lib = sample_pose_library(num_poses // 2, seed=seed, kinds=tuple(kinds))
    return np.concatenate([lib, perturb_poses(lib, rng)])


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
