"""The shipped Shelf samples the diagnose tests run on, loaded once per session, and the
pipeline without the SMPL fit (what sync, calibration and floor look at)."""

from __future__ import annotations

import functools

from pipeline.body.model import load_body_model
from pipeline.config import PipelineConfig
from pipeline.data.scene import load_scene
from pipeline.run.pipeline import run_pipeline
from tests.pipeline.helpers import REPO

CLEAN = REPO / "sample_data" / "shelf_synth"
NOISY = REPO / "sample_data" / "shelf_synth_noisy"
CONFIG = PipelineConfig(fit_smpl=False)


@functools.cache
def shipped_scene(path=CLEAN):
    return load_scene(path)


@functools.cache
def body_model():
    return load_body_model()


def run_without_fit(scene, config: PipelineConfig = CONFIG):
    return run_pipeline(scene, config, body_model(), progress=False)
