"""Where the pose prior's checkpoint is, without loading it (no torch): the results'
cache key hashes the file (pipeline/results/store.py); :mod:`pipeline.fit.prior` reads it."""

from __future__ import annotations

import os
from pathlib import Path

from pipeline.core.units import SAMPLE_DATA

DEFAULT_PRIOR_PATH = SAMPLE_DATA / "priors" / "pose_vae.pt"


def resolve_prior_path(path: str | os.PathLike | None = None) -> Path:
    """An explicit checkpoint path, else the shipped one."""
    return Path(path) if path else DEFAULT_PRIOR_PATH
