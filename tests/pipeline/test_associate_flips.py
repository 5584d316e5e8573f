"""The left/right resolution's pair selection (pipeline/association/flips.py) against the
dense (n, n) form it replaced (flips themselves: tests/pipeline/test_associate.py and
test_pose2sim_demo.py)."""

import numpy as np
import pytest

from pipeline.association.flips import _cluster_pairs


@pytest.mark.parametrize(
    "cluster",
    [np.array([3, 1, 3, 0, 1, 3]), np.zeros(0, int), np.array([5]), np.arange(7)[::-1]],
)
def test_cluster_pairs_are_the_same_label_pairs(cluster):
    ia, ib = _cluster_pairs(cluster)
    n = len(cluster)
    want = {(i, j) for i in range(n) for j in range(n) if cluster[i] == cluster[j]}
    assert len(ia) == len(want) and set(zip(ia.tolist(), ib.tolist(), strict=True)) == want


def test_cluster_pairs_on_a_dome_sized_frame():
    """459 detections in ~25 clusters: the pairs the dense mask ``cluster == cluster.T``
    holds, each once, in ~1/20 of its n^2 entries."""
    cluster = np.random.default_rng(0).integers(0, 25, 459) * 17  # labels need not be dense
    ia, ib = _cluster_pairs(cluster)
    dense = cluster[:, None] == cluster[None, :]
    got = np.zeros_like(dense)
    got[ia, ib] = True
    np.testing.assert_array_equal(got, dense)
    assert len(ia) == dense.sum() < dense.size / 15
