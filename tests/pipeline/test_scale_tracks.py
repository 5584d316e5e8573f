"""Tracks that equal people on big rigs (issue 14): the association's refinement moves on
hand-made affinities, then whole scenes of the suite's own making (a wide ring whose
people are seen by few cameras far away, a dome) scored end to end."""

from __future__ import annotations

import numpy as np

from pipeline.associate import _average_linkage, refine_clusters


def _ring_pair_case() -> tuple[np.ndarray, np.ndarray]:
    """Person X in views 0-6, person Y in views 7-11 and 0; X's view 6 and Y's view 0
    agree with each other (0.97) a little better than with their own people (0.93)."""
    views = np.array([0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 0])
    x, y = np.arange(7), np.arange(7, 13)
    aff = np.full((13, 13), -1.0)
    aff[np.ix_(x, x)] = 0.95
    aff[np.ix_(y, y)] = 0.95
    aff[6, x] = aff[x, 6] = 0.93
    aff[12, y] = aff[y, 12] = 0.93
    aff[6, 12] = aff[12, 6] = 0.97
    aff[views[:, None] == views[None, :]] = np.nan
    return aff, views


def test_refinement_returns_a_wrong_pair_to_the_people_that_back_its_members():
    aff, views = _ring_pair_case()
    greedy = _average_linkage(aff, views, 0.3)
    assert greedy[6] == greedy[12] and greedy[6] != greedy[0]  # the greedy merge's mistake
    out = refine_clusters(aff, views, greedy, 0.3)
    assert len(set(out[:7].tolist())) == 1 and len(set(out[7:].tolist())) == 1
    assert out[0] != out[7]


def test_refinement_keeps_a_two_view_person_whose_partner_has_nowhere_else_to_go():
    # Pose2Sim demo, frame 84: the man in views 0, 1, 3 (rows 0, 2, 4), the woman in
    # views 1 and 2 (rows 1, 3); row 3 agrees with the man about as well as with her.
    views = np.array([0, 1, 1, 2, 3])
    aff = np.array(
        [
            [np.nan, -0.97, 0.92, 0.34, 0.95],
            [-0.97, np.nan, np.nan, 0.62, -0.78],
            [0.92, np.nan, np.nan, 0.86, 0.97],
            [0.34, 0.62, 0.86, np.nan, 0.62],
            [0.95, -0.78, 0.97, 0.62, np.nan],
        ]
    )
    greedy = _average_linkage(aff, views, 0.3)
    out = refine_clusters(aff, views, greedy, 0.3, min_views=2)
    assert out[1] == out[3] and out[0] == out[2] == out[4] and out[0] != out[1]
