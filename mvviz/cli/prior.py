"""``mvviz train-prior``: train the VAE pose prior used to correct SMPL fits."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from pipeline.fit.prior import DEFAULT_PRIOR_PATH, PriorConfig, save_prior
from pipeline.mocap.clips import bvh_training_poses, format_residuals
from pipeline.prior.training import default_training_poses, load_pose_data, train_prior

_DEFAULTS = PriorConfig()


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "train-prior",
        help="train the VAE pose prior (CPU, a few minutes)",
        description=(
            "Train the variational pose prior over SMPL body-joint rotations (6D). Without "
            "--data it trains on the synthetic motion library plus plausible perturbations; "
            "with --data it trains on AMASS-style .npz files (a 'poses' array, (N, 156) or "
            "(N, 72)) and BVH motion capture clips (.bvh: the body model is fitted to the "
            "clip's joints at 30 fps and the fit residual per joint group is printed; scale, "
            "axes, activity and licence from a clips.json beside the file, see "
            "sample_data/mocap/cmu131); add --with-library to mix in the synthetic poses. "
            "Every source (frames, activity, licence) is recorded in the checkpoint's info."
        ),
    )
    p.add_argument("--data", type=Path, nargs="+", default=None, metavar="NPZ|BVH")
    p.add_argument(
        "--with-library", action="store_true", help="add the synthetic library to --data"
    )
    p.add_argument(
        "--out",
        type=Path,
        default=DEFAULT_PRIOR_PATH,
        help=f"checkpoint (default {DEFAULT_PRIOR_PATH})",
    )
    p.add_argument("--epochs", type=int, default=_DEFAULTS.epochs)
    p.add_argument("--alpha", type=float, default=_DEFAULTS.alpha, help="KL weight (Eq. 10)")
    p.add_argument("--seed", type=int, default=_DEFAULTS.seed)
    p.add_argument("--latent", type=int, default=_DEFAULTS.latent)
    p.add_argument("--hidden", type=int, default=_DEFAULTS.hidden)
    p.add_argument(
        "--num-poses", type=int, default=60000, help="synthetic library size before filtering"
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    parts, names, sources, fits = [], [], [], []
    if args.data is None or args.with_library:
        parts.append(default_training_poses(args.num_poses, seed=args.seed))
        names.append(
            f"synthetic library ({args.num_poses} poses, seed {args.seed}) + perturbations"
        )
        sources.append(
            {"file": names[-1], "frames": len(parts[-1]), "activity": "walk, reach, crouch, "
             "stand, wave (pipeline/synth/motion.py)", "licence": "generated"}
        )  # fmt: skip
    for path in args.data or []:
        if path.suffix.lower() == ".bvh":
            poses, info, fit = bvh_training_poses(path)
            fits.append(fit)
            sources.append(dict(info, file=str(path)))
        else:
            poses = load_pose_data(path)
            sources.append(
                {"file": str(path), "frames": len(poses), "activity": "unknown",
                 "licence": "unknown"}
            )  # fmt: skip
        parts.append(poses)
        names.append(str(path))
    if fits:
        print(format_residuals(fits))
    poses = np.concatenate(parts)
    prior = train_prior(
        poses,
        epochs=args.epochs,
        alpha=args.alpha,
        seed=args.seed,
        latent=args.latent,
        hidden=args.hidden,
        data_name="; ".join(names),
        sources=sources,
    )
    save_prior(prior, args.out)
    print(json.dumps(prior.info, indent=1))
    print(f"wrote {args.out} ({args.out.stat().st_size / 1e6:.2f} MB)")
    return 0
