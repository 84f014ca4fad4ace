"""The trust region's interpolation of the coarse predicted-error grid is NumPy's
(imaging.remap._bilinear_on_grid, no scipy.ndimage import per command): the same values as
scipy.ndimage.map_coordinates(order=1, mode="nearest") on the grid, to rounding, and
non-finite at the same pixels."""

import dataclasses

import numpy as np
import pytest
from scipy.ndimage import map_coordinates

from oapcal.calibration import calibrate
from oapcal.imaging import remap
from oapcal.imaging.remap import OutputGeometry, _bilinear_on_grid, predicted_error_map
from oapcal.synthetic import synthetic_pairs


def _scipy(values, rows_f, cols_f):
    ri, ci = np.meshgrid(rows_f, cols_f, indexing="ij")
    with np.errstate(invalid="ignore"):
        return map_coordinates(values, [ri, ci], order=1, mode="nearest")


def _indices(rng, n, count):
    """Fractional indices over [0, n - 1]: random ones, every node exactly, both ends."""
    return np.sort(np.concatenate([rng.uniform(0, n - 1, count), np.arange(n, dtype=float), [0.0, n - 1.0]]))


@pytest.mark.parametrize("shape", [(7, 9), (1, 5), (6, 1), (2, 2), (40, 61)])
@pytest.mark.parametrize("n_inf", [0, 1, 5])
def test_same_as_map_coordinates_with_inf_cells(shape, n_inf):
    rng = np.random.default_rng(shape[0] * 100 + shape[1] + n_inf)
    values = rng.uniform(0.01, 3.0, shape)
    flat = values.ravel()
    flat[rng.choice(flat.size, min(n_inf, flat.size - 1), replace=False)] = np.inf
    rows_f, cols_f = _indices(rng, shape[0], 50), _indices(rng, shape[1], 70)
    ours, theirs = _bilinear_on_grid(values, rows_f, cols_f), _scipy(values, rows_f, cols_f)
    assert ours.shape == theirs.shape == (len(rows_f), len(cols_f))
    np.testing.assert_array_equal(np.isfinite(ours), np.isfinite(theirs))
    ok = np.isfinite(theirs)
    np.testing.assert_allclose(ours[ok], theirs[ok], rtol=1e-14, atol=0)
    # float32, as the map holds it: equal or one unit in the last place apart
    np.testing.assert_array_max_ulp(ours[ok].astype(np.float32), theirs[ok].astype(np.float32), maxulp=1)
    if n_inf and min(shape) > 1:
        assert not ok.all()  # the inf nodes reached the output


def test_a_zero_weight_inf_node_makes_the_pixel_non_finite_as_before():
    values = np.array([[1.0, 2.0, 3.0], [4.0, np.inf, 6.0], [7.0, 8.0, 9.0]])
    rows_f = np.array([0.0, 0.5, 1.0, 2.0, 2.0])
    cols_f = np.array([0.0, 0.5, 2.0])
    ours = _bilinear_on_grid(values, rows_f, cols_f)
    theirs = _scipy(values, rows_f, cols_f)
    np.testing.assert_array_equal(np.isfinite(ours), np.isfinite(theirs))
    assert not np.isfinite(ours[0, 0])  # the node (1, 1) is inf, at weight 0
    assert ours[3, 2] == 9.0 and ours[2, 2] == 6.0  # the last row and column: nearest


def test_predicted_error_map_as_with_map_coordinates(monkeypatch):
    """The whole map (a geometry reaching where the model folds: inf cells) is the one the
    scipy interpolation gives, to float32 rounding, inf at the same pixels."""
    data = synthetic_pairs(seed=0)
    cal = calibrate(data.xy_u, data.xy_d, "paper", image_size=(640, 480))
    params = cal.params.copy()
    params[0] = -4e-7  # k1 < 0: the model folds beyond about 900 px from the centre
    cal = dataclasses.replace(cal, params=params)
    geometry = OutputGeometry((300, 410), x0=-1700.0, y0=-1400.0, scale=10.0)
    ours = predicted_error_map(cal, geometry)
    monkeypatch.setattr(remap, "_bilinear_on_grid", _scipy)
    theirs = predicted_error_map(cal, geometry)
    assert ours.dtype == theirs.dtype == np.float32
    inf = np.isinf(theirs)
    assert 0.01 < inf.mean() < 0.99  # the sample holds trusted and folded pixels alike
    np.testing.assert_array_equal(np.isinf(ours), inf)
    assert np.isfinite(ours[~inf]).all()
    np.testing.assert_array_max_ulp(ours[~inf], theirs[~inf], maxulp=1)
