"""The chunked stages (what ``pipeline.run.pipeline.run_stages`` runs) give the same results as
the stages that keep every frame (``pack_run(run_frames(...))``)."""

from dataclasses import fields
from pathlib import Path

import numpy as np
import pytest

from pipeline.config import PipelineConfig
from pipeline.data.scene import load_scene
from pipeline.results.store import EDGE_FIELDS, PipelineResults
from pipeline.run.chunked import run_stages_chunked
from pipeline.run.frames import run_frames, select_2d
from pipeline.run.pipeline import pack_run, run_stages

SCENES = Path(__file__).resolve().parents[2] / "sample_data"


def _arrays(r: PipelineResults) -> dict[str, np.ndarray]:
    return {
        f.name: getattr(r, f.name) for f in fields(r) if isinstance(getattr(r, f.name), np.ndarray)
    }


@pytest.mark.slow
@pytest.mark.parametrize("name", ["shelf_synth", "shelf_synth_noisy"])
def test_chunked_stages_equal_the_stages_that_keep_every_frame(name):
    scene = load_scene(SCENES / name)
    config = PipelineConfig()
    j2d = select_2d(scene, config, None)
    frames = run_frames(scene, config, j2d, progress=False)
    want = pack_run(scene, frames, config, j2d, restored=None)
    got = run_stages_chunked(scene, config, j2d, restored=None, chunk_frames=7, progress=False)
    default = run_stages(scene, config, j2d, restored=None, progress=False)
    for k, v in _arrays(default).items():
        np.testing.assert_array_equal(v, getattr(want, k), err_msg=k)
    a, b = _arrays(want), _arrays(got)
    assert a.keys() == b.keys() and len(want.person_frame) > 500 and len(want.edge_a) > 1000
    for k in a:
        assert a[k].dtype == b[k].dtype, k
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)
    lean = run_stages_chunked(scene, config, j2d, restored=None, keep_edges=False, progress=False)
    for k, v in _arrays(lean).items():
        if k in EDGE_FIELDS:
            assert len(v) == 0, k
        else:
            np.testing.assert_array_equal(v, a[k], err_msg=k)


def test_chunk_size_is_checked():
    scene = load_scene(SCENES / "shelf_synth")
    with pytest.raises(ValueError, match="chunk_frames"):
        run_stages_chunked(scene, PipelineConfig(), scene.detections.keypoints, restored=None,
                           chunk_frames=0, progress=False)  # fmt: skip
