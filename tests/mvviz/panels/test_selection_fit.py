"""The Selection box's line on the selected track's bodies against the floor."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from mvviz.panels.view_panels import fit_distance_markdown


def fake_results(with_floor: bool = True):
    """Two tracks, 4 frames, 3 joints: step I 3 mm off the RTS joints along x in every
    joint, SMPL + VAE 5 mm (track 1: absent in frame 0), the floor 2 mm."""
    rts = np.zeros((2, 4, 3, 3))
    step1, vae = rts.copy(), rts.copy()
    step1[..., 0] += 3.0
    vae[..., 0] += 5.0
    vae[1, 0] = np.nan
    return SimpleNamespace(
        track_smoothed=rts,
        smpl=SimpleNamespace(keypoints=step1),
        smpl_vae=SimpleNamespace(keypoints=vae),
        fit_floor=np.full((2, 4), 2.0) if with_floor else None,
    )


def test_the_track_s_fits_against_the_floor():
    text = fit_distance_markdown(fake_results(), 1)
    assert "step I 3.0 · SMPL + VAE 5.0 · floor 2.0" in text
    assert "constant bone lengths" in text
    no_floor = fit_distance_markdown(fake_results(with_floor=False), 0)
    assert "floor" not in no_floor and "step I 3.0" in no_floor


def test_no_fit_no_line():
    res = fake_results()
    res.smpl = res.smpl_vae = None
    assert fit_distance_markdown(res, 0) == ""
