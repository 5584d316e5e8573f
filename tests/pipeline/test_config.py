"""Pipeline configuration: defaults, JSON round trip, overrides and their errors."""

from __future__ import annotations

import json

import pytest

from pipeline.config import PipelineConfig, load_config, save_config
from pipeline.core.files import SceneFormatError


def test_round_trip(tmp_path):
    c = PipelineConfig().with_overrides(["kalman.q=50", "source=smpl", "association.min_views=3"])
    assert c.kalman.q == 50 and c.source == "smpl" and c.association.min_views == 3
    save_config(c, tmp_path / "c.json")
    assert load_config(tmp_path / "c.json") == c
    assert PipelineConfig.from_dict(json.loads(c.to_json())) == c


def test_bad_values_name_the_field(tmp_path):
    with pytest.raises(ValueError, match="field 'kalman.qq': no such field"):
        PipelineConfig().with_overrides(["kalman.qq=1"])
    with pytest.raises(SceneFormatError, match="source"):
        PipelineConfig().with_overrides(["source=magic"])
    (tmp_path / "bad.json").write_text(json.dumps({"kalman": {"r": "lots"}}))
    with pytest.raises(SceneFormatError, match=r"bad\.json: field 'kalman\.r'"):
        load_config(tmp_path / "bad.json")
    (tmp_path / "neg.json").write_text(json.dumps({"kalman": {"r": -1}}))
    with pytest.raises(
        SceneFormatError, match=r"neg\.json: field .kalman\.r.: expected a finite number"
    ):
        load_config(tmp_path / "neg.json")
