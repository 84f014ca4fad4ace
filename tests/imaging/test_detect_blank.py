"""Blank areas (``detect.blank``): an image turned onto a padded canvas, or clipped, shows
nothing there, and the pose search and the registration expect no triplet or corner there."""

import numpy as np
import pytest

from oapcal.imaging.detect import pose as P
from oapcal.imaging.detect.blank import BLANK_WINDOW_PX, blank_mask, blank_near
from test_detect_pose_turned import SHAPE, _image_triplets


def _noisy(shape=(60, 80), seed=0):
    return np.random.default_rng(seed).normal(0.5, 0.01, shape)


def test_a_noisy_image_has_no_blank_area():
    assert blank_mask(_noisy()) is None
    # 8-bit, dark, noise of 1 DN: neighbours still differ somewhere in every 5 x 5 square
    dark = np.clip(np.rint(np.random.default_rng(1).normal(6.0, 1.0, (60, 80))), 0, 255).astype(np.uint8)
    assert blank_mask(dark) is None


def test_a_clipped_or_noise_free_background_is_not_blank():
    """A constant area at the darkest or brightest level may be the target's background
    (clipped, or rendered without noise): a missing triplet there is still evidence."""
    img = np.zeros((60, 80))
    img[20:40, 30:35] = 1.0  # a bar on a noise-free background
    assert blank_mask(img) is None
    assert blank_mask(1.0 - img) is None
    img[:, 60:] = 0.5  # padding at a level between
    assert blank_mask(img)[:, 62:].all()


def test_padding_is_blank_and_the_image_beside_it_is_not():
    img = _noisy()
    img[:, 50:] = 0.5  # padding at one grey level (the image's median)
    blank = blank_mask(img)
    half = BLANK_WINDOW_PX // 2
    assert blank[:, 50 + half :].all()
    assert not blank[:, : 50 + half].any()  # a square reaching into the image is not blank


def test_blank_near_looks_at_the_footprint():
    blank = np.zeros((40, 40), bool)
    blank[:, 30:] = True
    xy = np.array([[20.0, 20.0], [20.0, 20.0], [35.0, 20.0], [np.nan, 5.0]])
    got = blank_near(blank, xy, np.array([5.0, 12.0, 0.0, 0.0]))
    assert got.tolist() == [False, True, True, False]
    assert not blank_near(None, xy).any()


def test_no_triplet_is_expected_in_the_padding():
    """Groups 4-5 through an exact similarity with the image right of x = 300 padded: the
    true pose counts the triplets predicted there as missing without the blank mask, none
    with it, and scores that much higher."""
    trips, ref, j, (s, phi) = _image_triplets(20.0, 0.0)
    lin = np.array([[np.cos(phi), -np.sin(phi)], [np.sin(phi), np.cos(phi)]])
    h, w = SHAPE
    centre_um = 0.5 * (ref.centre[j].min(axis=0) + ref.centre[j].max(axis=0))
    t = (np.array([w, h], float) - 1) / 2 - s * lin @ centre_um
    cut = 300
    seen = trips.centre[:, 0] < cut
    trips = trips.take(np.flatnonzero(seen))
    blank = np.zeros(SHAPE, bool)
    blank[:, cut:] = True
    from scipy.spatial import cKDTree

    listed = np.isin(ref.group, [4, 5])
    args = (np.array([s]), lin[None], t[None])
    without = P._score(*args, P._Scene(ref, trips, cKDTree(trips.centre), SHAPE, listed))
    with_blank = P._score(*args, P._Scene(ref, trips, cKDTree(trips.centre), SHAPE, listed, blank))
    assert without[1][0] >= 3  # the padded third's triplets, counted missing
    assert with_blank[1][0] == 0
    assert with_blank[0][0] == pytest.approx(without[0][0] + P.MISSING_PENALTY * without[1][0])
