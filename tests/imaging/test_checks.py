"""Straightness and aspect-ratio checks against hand-computed geometry."""

import numpy as np
import pytest
from scipy.special import ndtr

from oapcal.imaging.bars import bar_target
from oapcal.imaging.checks import check_target, residual_vectors
from oapcal.model import distort
from oapcal.synthetic import EXAMPLE_TRUTH


def test_straight_bars_and_known_aspect_ratios():
    bars = [(20.5, 20.5, 30.5, 70.5), (60.5, 30.5, 110.5, 40.5), (70.5, 60.5, 94.5, 84.5)]
    image, _ = bar_target((100, 140), bars, sigma=1.2, noise=0.005, seed=2)
    result = check_target(image, expected_ratios=(5.0, 1.0))
    assert len(result.edges) == 12 and len(result.shapes) == 3
    assert result.straightness_max_px < 0.1
    by_box = sorted(result.shapes, key=lambda s: s.box)
    # widths and heights exactly as drawn: 10 x 50, 50 x 10, 24 x 24 (sorted by left edge)
    assert [round(s.width_px, 1) for s in by_box] == [10.0, 50.0, 24.0]
    assert [round(s.height_px, 1) for s in by_box] == [50.0, 10.0, 24.0]
    assert [s.expected for s in by_box] == [5.0, 5.0, 1.0]
    assert max(abs(s.error_pct) for s in by_box) < 1.0


def test_bent_edge_rms_matches_hand_computation():
    # A dark field whose right part is bright beyond the parabola x = 30 + c (y - 40)^2.
    rows, cols, c = 81, 60, 0.004
    yy, xx = np.mgrid[0:rows, 0:cols].astype(float)
    edge = 30.0 + c * (yy - 40.0) ** 2
    image = ndtr((xx - edge) / 0.8)
    image[:, :5] = 0.0
    # Exclude top/bottom rows: the component touches the image border there (left side only).
    result = check_target(image, expected_ratios=())
    (left,) = [e for e in result.edges if e.side == "left"]
    # The rows used are those left after trimming a fifth of the side at each end.
    rows_used = left.points[:, 1]
    sag = c * (rows_used - 40.0) ** 2
    coef = np.polyfit(rows_used, sag, 1)
    expected = np.sqrt(np.mean((sag - np.polyval(coef, rows_used)) ** 2))  # small tilt ignored
    assert left.rms_px == pytest.approx(expected, rel=0.05)
    assert expected > 0.3  # the bend is well above the noise-free floor


def test_distortion_bends_edges_and_correction_straightens_them():
    bars = [(40.5, 40.5, 50.5, 90.5), (200.5, 150.5, 250.5, 160.5)]
    distorted, _ = bar_target((240, 320), bars, sigma=1.0, params=EXAMPLE_TRUTH_SMALL)
    straight, _ = bar_target((240, 320), bars, sigma=1.0)
    assert check_target(distorted).straightness_max_px > 5 * check_target(straight).straightness_max_px


EXAMPLE_TRUTH_SMALL = EXAMPLE_TRUTH.copy()
EXAMPLE_TRUTH_SMALL[[8, 9, 10, 11]] = [-160.0, -120.0, 160.0, 120.0]  # centred on a 320 x 240 frame
EXAMPLE_TRUTH_SMALL[0] *= 4  # k1: about as strong over the half-size frame


def test_residual_vectors_are_corrected_minus_reference():
    xy_u = np.array([[100.0, 100.0], [300.0, 250.0], [500.0, 400.0]])
    xy_d = distort(xy_u, EXAMPLE_TRUTH) + np.array([[0.0, 0.0], [0.0, 0.0], [0.5, 0.0]])
    vec = residual_vectors(EXAMPLE_TRUTH, xy_u, xy_d)
    np.testing.assert_allclose(vec.dxy[:2], 0.0, atol=1e-8)
    assert vec.length[2] > 0.3
