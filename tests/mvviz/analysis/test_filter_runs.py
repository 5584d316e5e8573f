"""The Filter A/B panel's re-filter (mvviz/analysis/filter_runs.py)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import mvviz.analysis.filter_runs as filter_runs
from pipeline.config import PipelineConfig
from pipeline.data.scene import load_scene
from pipeline.run.frames import select_2d
from pipeline.run.pipeline import run_stages
from pipeline.stages.kalman import KalmanParams
from tests.conftest import REPO

pytestmark = pytest.mark.slow


@pytest.mark.parametrize("params", [KalmanParams(q=100.0), KalmanParams(q=10.0, smoother=False)])
def test_filter_run_over_blocks_of_tracks_is_the_run_over_all(monkeypatch, params):
    """Blocks of one track give the numbers of one call over every track (a 10,000-frame
    sequence is filtered a few tracks at a time), and filter A's own parameters give the
    results' own arrays."""
    scene = load_scene(REPO / "sample_data" / "shelf_synth_noisy")
    config = dataclasses.replace(PipelineConfig(), kalman=params)
    res = run_stages(scene, config, select_2d(scene, config, None), restored=None,
                     progress=False)  # fmt: skip
    whole = filter_runs.run_filter(res.track_raw, params, skip=res.track_contradicted)
    monkeypatch.setattr(filter_runs, "BLOCK_STEPS", 1)
    blocks = filter_runs.run_filter(res.track_raw, params, skip=res.track_contradicted)
    assert res.num_tracks >= 4 and whole.forward.shape == res.track_raw.shape
    for name in filter_runs.RUN_FIELDS:
        a, b = getattr(whole, name), getattr(blocks, name)
        assert a.dtype == b.dtype and a.shape == b.shape, name
        np.testing.assert_array_equal(a, b, err_msg=name)
    # the pipeline's filter ends a track at its last frame; before that the same numbers
    own = filter_runs.results_run(res)
    alive = np.isfinite(own.smoothed)
    assert alive.mean() > 0.5
    np.testing.assert_allclose(whole.smoothed[alive], own.smoothed[alive], rtol=1e-12)
    empty = filter_runs.run_filter(res.track_raw[:0], params)
    assert empty.forward.shape == (0, *res.track_raw.shape[1:])
