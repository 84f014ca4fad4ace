import numpy as np
import pytest

from oapcal.calibration import calibrate
from oapcal.errors import DataError
from oapcal.normalize import normalize, normalize_experiment, normalize_grid


def test_experiment_normalization_matches_the_figure_caption(rng):
    ref = rng.uniform(0, 100, (30, 2)) * [1.0, 2.0] + [7.0, -3.0]
    dist = rng.uniform(0, 1, (30, 2)) * [300, 250] + [40.0, 25.0]
    out = normalize_experiment(ref, dist)
    # y range equals the distorted y range; aligned at the top and the left
    assert np.ptp(out.xy_u[:, 1]) == pytest.approx(np.ptp(dist[:, 1]))
    np.testing.assert_allclose(out.xy_u.min(axis=0), dist.min(axis=0))
    # aspect ratio kept: one scale for x and y, about the top-left corner
    s = np.ptp(dist[:, 1]) / np.ptp(ref[:, 1])
    np.testing.assert_allclose(out.xy_u, (ref - ref.min(axis=0)) * s + dist.min(axis=0))
    assert out.scale_u == pytest.approx(s)
    np.testing.assert_array_equal(out.xy_d, dist)


def test_grid_normalization_spans_half_unit_in_y_independently(rng):
    ref = rng.uniform(-2, 2, (50, 2)) * [3, 1]
    dist = rng.uniform(10, 20, (50, 2))
    out = normalize_grid(ref, dist)
    for xy in (out.xy_u, out.xy_d):
        assert xy[:, 1].min() == pytest.approx(-0.5) and xy[:, 1].max() == pytest.approx(0.5)
        np.testing.assert_allclose(xy.min(axis=0) + xy.max(axis=0), 0, atol=1e-12)
    assert np.ptp(out.xy_u[:, 0]) / np.ptp(out.xy_u[:, 1]) == pytest.approx(
        np.ptp(ref[:, 0]) / np.ptp(ref[:, 1])
    )


def test_errors():
    with pytest.raises(DataError, match="no extent in y"):
        normalize_experiment(np.array([[0.0, 1], [2, 1]]), np.array([[0.0, 0], [1, 1]]))
    with pytest.raises(DataError, match="unknown normalization"):
        normalize("bogus", np.zeros((2, 2)), np.zeros((2, 2)))


def test_scale_is_carried_through_the_normalization(pairs):
    # Reference points given in units of 2 px (9.6 um each) are scaled by the ratio of the
    # y ranges; one unit of the normalized points is then 9.6 um / that ratio.
    ref_half = pairs.xy_u / 2.0
    cal = calibrate(ref_half, pairs.xy_d, "paper", normalization="experiment", um_per_px=9.6)
    ratio = np.ptp(pairs.xy_d[:, 1]) / np.ptp(ref_half[:, 1])
    assert cal.um_per_px == pytest.approx(9.6 / ratio, rel=1e-12)
    assert cal.residuals.mean_um == pytest.approx(cal.residuals.mean_px * cal.um_per_px)
    assert cal.fit.converged and cal.residuals.mean_px < 0.6
