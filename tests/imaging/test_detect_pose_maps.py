"""The pose search's hand-written application of many 2 x 2 maps (:func:`pose.apply_maps`)
against NumPy's einsum, which it replaces for speed; its vectorised score and its bounded
look-up of predicted triplets against what they replace."""

import numpy as np
import pytest

from oapcal.imaging.detect import pose as P
from oapcal.imaging.detect.bars import Triplets

SHAPE = (480, 640)


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


def _matched_every_pair(pred, wpred, apred, scene, anchor, loose, width_tol):
    """``pose._matched`` as it was: every prediction looked up in the tree over the whole
    image, every pair's width and direction tested (the reference for the bounded look-up)."""
    img = scene.img
    h, w = scene.shape
    dist, k = scene.tree.query(pred.reshape(-1, 2), k=1, distance_upper_bound=float(max(h, w)))
    dist = dist.reshape(pred.shape[:2])
    k = k.reshape(pred.shape[:2])
    valid = k < len(img)
    kk = np.where(valid, k, 0)
    tol = 0.6 * wpred
    if anchor is not None:
        tol = tol + loose * 0.05 * np.hypot(*(pred - anchor[:, None, :]).transpose(2, 0, 1))
    ok = (
        valid
        & (dist < tol)
        & (np.abs(np.log(img.width[kk] / wpred)) < np.log(width_tol))
        & (P._angle_diff(img.angle[kk], apred) < np.deg2rad(P.ANGLE_TOL_DEG))
        & (wpred >= 0.7 * P.MIN_EXPECTED_BAR_PX)
    )
    return ok, np.where(ok, kk, -1)


@pytest.mark.parametrize("with_anchor", [False, True])
def test_the_bounded_look_up_matches_what_looking_up_every_prediction_matched(with_anchor):
    """``pose._matched`` looks up only the predictions that can match (wide enough, within the
    largest tolerance of the image) and stops the tree there: the same matches as looking up
    every one, on hypotheses scattered over and far beyond a 640 x 480 image; a prediction
    without a value (NaN) matches nothing (the tree refuses to look it up)."""
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(5)
    n_img, n_hyp, n_ref = 40, 300, 60
    centre = rng.uniform([0, 0], [640, 480], (n_img, 2))
    img = Triplets(centre, rng.uniform(0, np.pi, n_img), rng.uniform(1.5, 12, n_img), np.full(n_img, 20.0),
                   np.ones(n_img), np.zeros((n_img, 3, 2)))  # fmt: skip
    scene = P._Scene(None, img, cKDTree(centre), SHAPE)
    # predictions: near image triplets (jittered), anywhere, far outside, a few NaN
    near = centre[rng.integers(0, n_img, (n_hyp, n_ref))] + rng.normal(0, 4, (n_hyp, n_ref, 2))
    pred = np.where(rng.random((n_hyp, n_ref, 1)) < 0.5, near, rng.uniform(-800, 1400, (n_hyp, n_ref, 2)))
    wpred = rng.uniform(0.5, 14, (n_hyp, n_ref))
    apred = rng.uniform(0, np.pi, (n_hyp, n_ref))
    anchor = rng.uniform([0, 0], [640, 480], (n_hyp, 2)) if with_anchor else None
    got = P._matched(pred, wpred, apred, scene, anchor, 0.8, P.WIDTH_TOL)
    want = _matched_every_pair(pred, wpred, apred, scene, anchor, 0.8, P.WIDTH_TOL)
    assert want[0].sum() > 100  # the test matches something
    np.testing.assert_array_equal(got[0], want[0])
    np.testing.assert_array_equal(got[1], want[1])
    pred[0, :5] = np.nan
    ok, match = P._matched(pred, wpred, apred, scene, anchor, 0.8, P.WIDTH_TOL)
    assert not ok[0, :5].any() and (match[0, :5] == -1).all()
    np.testing.assert_array_equal(ok[1:], want[0][1:])
