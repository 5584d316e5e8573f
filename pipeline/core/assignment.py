"""One-to-one matching by the Hungarian algorithm over the allowed pairs only: what
tracking (people to tracks), re-identification, the evaluation (predictions to ground
truth) and the viewer's frame previews (re-run people to tracks) all do."""

from __future__ import annotations

import numpy as np


def gated_assignment(
    cost: np.ndarray, valid: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """The pairs of a one-to-one assignment that uses allowed pairs only.

    Among assignments the number of matches is maximised first, then their total cost
    minimised: a disallowed pair costs more than any full set of allowed ones, so the
    assignment never trades an allowed match for a cheaper total.

    Args:
        cost: (A, B) cost of each pair.
        valid: (A, B) bool, the allowed pairs; default: where ``cost`` is finite.
    Returns:
        ``(rows, cols)``: (M,) int indices of the matched pairs, ``rows`` increasing.
    """
    cost = np.asarray(cost, float)
    valid = np.isfinite(cost) if valid is None else np.asarray(valid, bool) & np.isfinite(cost)
    if not valid.any():
        return np.zeros(0, int), np.zeros(0, int)
    # scipy.optimize (~0.1 s of imports) where a matching runs, not wherever this is imported
    from scipy.optimize import linear_sum_assignment

    big = (np.abs(cost[valid]).max() + 1.0) * (min(cost.shape) + 1)
    rows, cols = linear_sum_assignment(np.where(valid, cost, big))
    good = valid[rows, cols]
    return rows[good], cols[good]
