"""The timeline's failure strip: marks land on their frames in their criterion's lane and
colour, the playhead points at the same x, ticks and the next / previous failure."""

from __future__ import annotations

import re

import numpy as np
import pytest

from mvviz.analysis.failures import Failure
from mvviz.analysis.timeline_strip import (
    CRITERION_RGB,
    LANE_GAP,
    LANE_HEIGHT,
    STRIP_WIDTH,
    draw_failure_strip,
    draw_playhead,
    frame_x,
    legend_html,
    next_failure,
    playhead_html,
    strip_height,
    tick_steps,
)


def failure(criterion: str, first: int, last: int, score: float = 1.0, **kw) -> Failure:
    return Failure(
        criterion, score, frame=kw.pop("frame", first), track=kw.pop("track", 0), joint=None,
        view=None, first=first, last=last, **kw,
    )  # fmt: skip


def lane_columns(img: np.ndarray, lane: int, rgb: tuple[int, int, int]) -> np.ndarray:
    """Columns of ``lane``'s middle row in colour ``rgb`` (within 2 grey levels)."""
    row = img[lane * (LANE_HEIGHT + LANE_GAP) + LANE_HEIGHT // 2].astype(int)
    return np.flatnonzero(np.abs(row - rgb).max(-1) <= 2)


def test_marks_cover_their_span_in_their_lane():
    n = 250
    marks = [failure("kalman", 100, 149), failure("reprojection", 10, 10)]
    img = draw_failure_strip(n, marks, criteria=("reprojection", "kalman"))
    assert img.shape == (strip_height(2), STRIP_WIDTH, 3) and img.dtype == np.uint8
    cols = lane_columns(img, 1, CRITERION_RGB["kalman"])
    # (the worst frame, 100, is a darker tick)
    assert abs(cols.min() - frame_x(99.5, n)) <= 3 and abs(cols.max() - frame_x(149.5, n)) <= 1.5
    one = lane_columns(img, 0, CRITERION_RGB["reprojection"])  # one frame: still visible
    assert len(one) >= 3 and abs(one.mean() - frame_x(10, n)) <= 1.5
    assert not len(lane_columns(img, 0, CRITERION_RGB["kalman"]))  # each in its own lane
    # a criterion not asked for is not drawn
    only = draw_failure_strip(n, marks, criteria=("kalman",))
    assert only.shape[0] == strip_height(1)
    assert not len(lane_columns(only, 0, CRITERION_RGB["reprojection"]))


def test_the_worst_are_solid_the_rest_faint():
    marks = [failure("kalman", 10 * i, 10 * i + 2, score=float(i)) for i in range(20)]
    img = draw_failure_strip(200, marks, criteria=("kalman",), top=5)
    solid = lane_columns(img, 0, CRITERION_RGB["kalman"])
    assert frame_x(149, 200) < solid.min() and solid.max() < frame_x(193, 200)  # 15..19
    faint = img[LANE_HEIGHT // 2, int(frame_x(11, 200))]
    assert (faint > np.array(CRITERION_RGB["kalman"])).all()  # lighter than the colour


def test_playhead_points_at_the_frame():
    for n, f in ((250, 62), (20, 0), (20, 19)):
        strip = draw_playhead(n, f)
        dark = np.flatnonzero(strip[-2].max(-1) < 100)
        assert abs(dark.mean() - frame_x(f, n)) <= 1.0


def test_html_playhead_is_where_the_image_one_was():
    """The HTML playhead's triangle: centred at the image playhead's x (as a share of the
    strip's width), as wide and as tall on screen."""
    for n, f in ((250, 62), (20, 0), (20, 19), (5000, 4321)):
        html = playhead_html(n, f)
        pct, half = re.search(r"left:calc\(([\d.]+)% - (\d+)px\)", html).groups()
        dark = np.flatnonzero(draw_playhead(n, f)[1].max(-1) < 100)  # the triangle's top row
        assert abs(float(pct) / 100 * STRIP_WIDTH - dark.mean()) <= 1.0
        assert abs(2 * int(half) * 2 - dark.size) <= 2  # image pixels are half a screen pixel
        assert f"max-width:{STRIP_WIDTH}px" in html


@pytest.mark.parametrize("n", [2, 20, 250, 5000])
def test_ticks_are_readable(n):
    minor, label = tick_steps(n)
    per_frame = frame_x(1, n) - frame_x(0, n)
    assert minor * per_frame >= 10 and label * per_frame >= 90 and label % minor == 0


def test_next_and_previous_failure():
    a, b, c = failure("id", 5, 5), failure("kalman", 20, 30, score=1.0), failure("id", 20, 22, 2.0)
    marks = [b, a, c]
    assert next_failure(marks, 0, +1) is a
    assert next_failure(marks, 5, +1) is c  # same start: the higher score
    assert next_failure(marks, 20, +1) is None
    assert next_failure(marks, 25, -1) is c and next_failure(marks, 20, -1) is a
    assert next_failure([], 3, +1) is None


def test_legend_names_and_counts():
    html = legend_html({"kalman": 3, "id": 0}, {"kalman": "Kalman", "id": "ID"})
    r, g, b = CRITERION_RGB["kalman"]
    assert f"rgb({r},{g},{b})" in html and "Kalman 3" in html and "ID 0" in html
