"""mvviz.analysis.trace_plot: the filter panel's plot and its playhead, drawn off-screen."""

from __future__ import annotations

import dataclasses

import numpy as np

from mvviz.analysis.filter_runs import results_run, run_filter
from mvviz.analysis.trace_plot import (
    PLOT_HEIGHT,
    PLOT_WIDTH,
    TracePlot,
    joint_trace,
    plot_range,
)


def test_plot_image_size_and_frame_marker(viewer_state):
    data = viewer_state.data
    res = data.results
    a = results_run(res)
    b = run_filter(res.track_raw, dataclasses.replace(res.config.kalman, q=1.0))
    plot = TracePlot()
    plot.render(joint_trace(data, a, b, 0, 9), 0, data.num_frames)
    img3, img12 = plot.image(3), plot.image(12)
    assert img3.shape == (PLOT_HEIGHT, PLOT_WIDTH, 3) and img3.dtype == np.uint8
    assert plot.size == (PLOT_WIDTH, PLOT_HEIGHT)
    moved = np.abs(img3.astype(int) - img12).sum(-1) > 0
    cols = np.flatnonzero(moved.any(0))
    assert 0 < len(cols) <= 12  # only two thin vertical lines differ
    assert (img3 != 255).any(-1).mean() > 0.05  # something is drawn
    # no selection: a hint, same size
    plot.render(joint_trace(data, a, b, None, 9), 0, data.num_frames)
    assert plot.image(0).shape == img3.shape


def test_playhead_marks_the_frame_column(viewer_state):
    data = viewer_state.data
    a = results_run(data.results)
    plot = TracePlot()
    plot.render(joint_trace(data, a, a, 0, 9), 0, data.num_frames)
    n = data.num_frames
    for frame in (0, n // 2, n - 1):
        strip = plot.playhead(frame)
        dark = np.flatnonzero((strip[2:27] < 128).all(-1).any(0))
        assert abs(dark.mean() - plot.frame_x(frame)) < 1.5, frame
        assert dark.max() - dark.min() <= 34  # one triangle
    # the playhead column lines up with the plot's own frame line
    line = np.flatnonzero((plot.image(n // 2) != plot.image()).any(-1).any(0))
    assert abs(line.mean() - plot.frame_x(n // 2)) < 1.5
    # a window that does not contain the frame: no marker
    plot.render(joint_trace(data, a, a, 0, 9), 0, n // 4)
    assert not (plot.playhead(n - 1)[2:27] < 128).all(-1).any()


# --------------------------------------------------------------------------- browser


def test_plot_range():
    assert plot_range(20, 5, None) == (0, 20)
    assert plot_range(20, 5, 25) == (0, 20)
    assert plot_range(250, 5, 50) == (0, 101)
    assert plot_range(250, 120, 50) == (70, 171)
    assert plot_range(250, 249, 50) == (149, 250)
