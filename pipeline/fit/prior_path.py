"""Where the pose prior's checkpoint is, without loading it (no torch): the results'
cache key hashes the file (pipeline/results/store.py); :mod:`pipeline.fit.prior` reads it."""

from __future__ import annotations

import os
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]
DEFAULT_PRIOR_PATH = REPO_ROOT / "sample_data" / "priors" / "pose_vae.pt"


def resolve_prior_path(path: str | os.PathLike | None = None) -> Path:
    """An explicit checkpoint path, else the shipped one."""
    return Path(path) if path else DEFAULT_PRIOR_PATH
