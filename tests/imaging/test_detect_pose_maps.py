"""The pose search's hand-written application of many 2 x 2 maps (:func:`pose.apply_maps`)
against NumPy's einsum, which it replaces for speed."""

import numpy as np

from oapcal.imaging.detect import pose as P


def test_apply_maps_is_einsum_bit_for_bit():
    rng = np.random.default_rng(3)
    for h, n in ((1, 1), (7, 126), (300, 40)):
        amat = rng.normal(size=(h, 2, 2)) * rng.uniform(0.01, 10, (h, 1, 1))
        xy = rng.normal(size=(n, 2)) * 1e3
        got = P.apply_maps(amat, xy)
        assert got.shape == (h, n, 2)
        assert np.array_equal(got, np.einsum("hij,nj->hni", amat, xy))


def _match_score_loop(match, weight):
    """The per-hypothesis loop the vectorised score replaced."""
    score = np.empty(len(match))
    for hh in range(len(match)):
        m = match[hh]
        sel = m >= 0
        _, first = np.unique(m[sel], return_index=True)
        score[hh] = weight[np.flatnonzero(sel)[first]].sum()
    return score


def test_match_score_counts_each_image_triplet_once_per_hypothesis():
    rng = np.random.default_rng(5)
    weight = np.where(rng.random(60) < 0.3, 0.25, 1.0)
    for density in (0.0, 0.1, 0.6):
        match = np.where(rng.random((40, 60)) < density, rng.integers(0, 12, (40, 60)), -1)
        assert np.array_equal(P._match_score(match, weight), _match_score_loop(match, weight))
    # a hand-made case: row 0 matches image triplet 3 twice (reference 0 and 2) and 5 once
    match = np.array([[3, -1, 3, 5], [-1, -1, -1, -1]])
    w = np.array([1.0, 1.0, 0.25, 0.25])
    assert P._match_score(match, w).tolist() == [1.25, 0.0]
