"""The Panoptic-like dome rig: geometry, naming, the capture circle, the --rig spec."""

from __future__ import annotations

import numpy as np
import pytest

from mvviz.cli.synth import load_rig
from pipeline.synth.rigs import dome_capture_radius, dome_rig, parse_dome_spec
from pipeline.synth.scene_gen import visible_floor_area


@pytest.mark.parametrize("n", [1, 5, 16, 31])
def test_dome_has_n_hd_cameras_aimed_at_the_centre(n):
    rig = dome_rig(n)
    assert len(rig) == n and len(set(rig.names)) == n
    for cam in rig:
        assert (cam.width, cam.height) == (1920, 1080)
        assert 1300 < cam.K[0, 0] < 1700  # Panoptic's HD focal length
        np.testing.assert_allclose(np.linalg.norm(cam.center), 4000.0, rtol=1e-9)
        # the point 1 m above the floor's centre lands on the image centre
        np.testing.assert_allclose(cam.project(np.array([0.0, 0, 1000])), [959.5, 539.5])
        # world z is up in the image: a point above the target is higher (smaller v)
        assert cam.project(np.array([0.0, 0, 1500]))[1] < 539.5


def test_rings_at_several_heights_with_cameras_spread_around():
    rig = dome_rig(31)
    heights = np.unique(np.round(rig.centers[:, 2]))
    assert len(heights) == 4 and heights.min() < 1000 and heights.max() > 3000
    az = np.arctan2(rig.centers[:, 1], rig.centers[:, 0])
    # every 45-degree sector of the dome holds cameras
    assert len(np.unique(np.floor((az + np.pi) / (np.pi / 4)) % 8)) == 8


def test_capture_circle_is_seen_whole_by_many_cameras():
    rig = dome_rig(16)
    area = visible_floor_area(rig, within_mm=dome_capture_radius())
    r = np.linalg.norm(area, axis=1)
    assert r.max() <= 2400 + 1e-6 and len(area) > 400  # ~18 m^2 at 200 mm spacing
    seen = np.zeros(len(area), int)
    for cam in rig:
        ok = np.ones(len(area), bool)
        for h in (0.0, 900.0, 1700.0):
            uv = cam.project(np.column_stack([area, np.full(len(area), h)]))
            ok &= (uv[:, 0] > 0) & (uv[:, 0] < 1920) & (uv[:, 1] > 0) & (uv[:, 1] < 1080)
        seen += ok
    assert seen.min() >= 5 and np.median(seen) >= 8


def test_rig_spec():
    assert parse_dome_spec("shelf") is None
    assert parse_dome_spec("dome:16") == (16, 4000.0)
    assert parse_dome_spec("DOME:31:4500") == (31, 4500.0)
    for bad in ("dome", "dome:0", "dome:x", "dome:4:"):
        with pytest.raises(ValueError, match="dome:N"):
            parse_dome_spec(bad)
    assert len(load_rig("dome:12")) == 12
    assert np.linalg.norm(load_rig("dome:3:5000")[0].center) == pytest.approx(5000.0)
