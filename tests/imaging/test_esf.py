"""Edge spread fits against synthetic edges of known blur."""

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter
from scipy.special import ndtr

from oapcal.errors import DataError
from oapcal.imaging.bars import bar_target, demo_layout
from oapcal.imaging.esf import analyse_edges, find_edge_rois, fit_edge


def slanted_edge(sigma, angle_deg, shape=(40, 30), noise=0.0, seed=0, falling=False):
    """An erf edge rendered from scipy's normal CDF at each pixel's perpendicular distance."""
    yy, xx = np.mgrid[0 : shape[0], 0 : shape[1]].astype(float)
    t = np.tan(np.radians(angle_deg))
    d = (xx - 14.3 - t * (yy - shape[0] / 2)) / np.hypot(1.0, t)
    image = 20.0 + 100.0 * ndtr((-d if falling else d) / sigma)
    return image + np.random.default_rng(seed).normal(0.0, noise, shape)


@pytest.mark.parametrize("sigma", [0.7, 1.5, 3.0])
@pytest.mark.parametrize("angle", [0.0, 4.0, -7.0])
def test_sigma_recovered_within_5_percent_with_noise(sigma, angle):
    image = slanted_edge(sigma, angle, noise=1.0, seed=int(10 * sigma + angle))  # 1% of the contrast
    fit = fit_edge(image, (0, 0, 29, 39))
    assert fit.ok, fit.message
    assert fit.orientation == "vertical"
    assert fit.sigma_px == pytest.approx(sigma, rel=0.05)
    assert fit.angle_deg == pytest.approx(angle, abs=0.5)
    assert fit.low == pytest.approx(20, abs=1) and fit.high == pytest.approx(120, abs=1)


def test_horizontal_falling_edge_and_um():
    image = slanted_edge(1.2, 3.0, noise=0.5, falling=True).T.copy()  # edge along x, dark below
    fit = fit_edge(image, (0, 0, 39, 29), um_per_px=4.8)
    assert fit.ok and fit.orientation == "horizontal"
    assert fit.sigma_px == pytest.approx(1.2, rel=0.05)
    assert fit.sigma_um == pytest.approx(4.8 * fit.sigma_px)
    # The edge crosses the middle line (x = 19.5) at row 14.3 (set in slanted_edge).
    assert fit.centre[1] == pytest.approx(14.3, abs=0.1)


def test_sigma_against_scipy_gaussian_filter():
    """A sharp step blurred by scipy.ndimage.gaussian_filter on a 10x finer grid, then
    point-sampled: an independent rendering of an edge of known sigma."""
    fine = np.zeros((400, 400))
    fine[:, 203:] = 1.0  # edge half-way between fine pixels 202 and 203
    sigma = 1.6
    blurred = gaussian_filter(fine, sigma * 10, mode="nearest")
    image = 50 + 150 * blurred[5::10, 5::10]
    fit = fit_edge(image, (10, 5, 30, 34))
    assert fit.ok
    assert fit.sigma_px == pytest.approx(sigma, rel=0.02)


def test_no_edge_and_narrow_roi_are_reported_not_raised():
    flat = np.random.default_rng(3).normal(100, 1, (30, 30))
    fit = fit_edge(flat, (2, 2, 27, 27))
    assert not fit.ok and "no clear edge" in fit.message
    wide = slanted_edge(4.0, 0.0)
    fit = fit_edge(wide, (11, 0, 17, 39))  # +-3 px around the edge, sigma 4
    assert not fit.ok


def test_roi_outside_image_raises():
    with pytest.raises(DataError, match="not a rectangle inside the 30 x 40 px image"):
        fit_edge(np.zeros((40, 30)), (0, 0, 30, 10))


def test_auto_rois_on_a_bar_target():
    layout = demo_layout((200, 260), bar=10)
    image, rects = bar_target((200, 260), layout, sigma=1.3, noise=0.01, seed=5)
    rois, labels = find_edge_rois(image)
    # Squares (30 px) give four ROIs; bars (10 x 50 px) only their two long sides, as the
    # short sides (10 px) are too short once their corners are trimmed (3 px each end).
    n_squares = sum(1 for x0, y0, x1, y1 in rects if x1 - x0 == y1 - y0)
    assert len(rois) == 4 * n_squares + 2 * (len(rects) - n_squares)
    summary = analyse_edges(image, rois, labels=labels, um_per_px=2.0)
    assert len(summary.good) == len(rois)
    assert summary.sigma_mean_px == pytest.approx(1.3, rel=0.03)
    assert summary.sigma_max_px < 1.3 * 1.1
    d = summary.to_dict()
    assert d["sigma_mean_um"] == pytest.approx(2.0 * d["sigma_mean_px"])
    assert d["n_edges"] == len(rois) and d["edges"][0]["label"] == labels[0]
