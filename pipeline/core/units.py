"""Units and the product's own places, in one home.

The pipeline's world is in millimetres (z up, floor at z = 0); the body model and the
file formats that other tools read (SMPL, AMASS, glTF, Pose2Sim calibrations) are in
metres. Paths: the repository and its shipped sample data, for defaults that name a
shipped file (the body model, the pose prior, the mocap clips).
"""

from __future__ import annotations

from pathlib import Path

MM_PER_M = 1000.0
"""Millimetres per metre: ``x_mm = x_m * MM_PER_M``."""

PIPELINE_DIR = Path(__file__).resolve().parents[1]
"""The ``pipeline`` package's folder (what the results cache's code digest hashes)."""
REPO_ROOT = PIPELINE_DIR.parent
SAMPLE_DATA = REPO_ROOT / "sample_data"
