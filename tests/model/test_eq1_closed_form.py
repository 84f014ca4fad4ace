"""The closed form of Eq. (1) in NumPy (oapcal.eq1_closed_form) against the compiled kernels,
the one implementation everywhere else: the distorted points, the point Jacobian and every
parameter-Jacobian column, for Eq. (1) and Eq. (1) + rotation; and the correction map and
trust region built through either."""

import dataclasses
import sys

import numpy as np
import pytest

from oapcal import eq1_closed_form as cf
from oapcal.calibration import calibrate
from oapcal.imaging.remap import correction_map, output_geometry, predicted_error_map
from oapcal.model import (
    BROWN_CONRADY,
    BROWN_CONRADY_POSE,
    RELAY,
    distort,
    jacobian_params,
    jacobian_point,
)
from oapcal.synthetic import EXAMPLE_TRUTH, synthetic_pairs
from oapcal.uncertainty import position_covariance
from reference_model import random_eq1_models

FAMILIES = {False: BROWN_CONRADY, True: BROWN_CONRADY_POSE}


def _points(seed, n=400):
    rng = np.random.default_rng(seed)
    return np.column_stack([rng.uniform(-100, 740, n), rng.uniform(-100, 580, n)])


@pytest.mark.parametrize("rotation", [False, True], ids=["eq1", "eq1+rotation"])
def test_values_and_jacobians_match_the_kernels(rotation):
    family = FAMILIES[rotation]
    xy = _points(1 + rotation)
    for p in random_eq1_models(60, 3 + rotation, rotation):
        want = distort(xy, p, family=family)
        got, jac, cols = cf.evaluate(xy, p)
        # rounding only: the kernels may contract and reassociate (fastmath) the same sums
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12 * np.abs(want).max())
        np.testing.assert_array_equal(cf.distort(xy, p), got)
        want_jac = jacobian_point(xy, p, family=family)
        np.testing.assert_allclose(jac, want_jac, rtol=1e-12, atol=1e-12 * np.abs(want_jac).max())
        want_cols = jacobian_params(xy, p, family=family)
        assert cols.shape == want_cols.shape == (len(xy), 2, family.n_params)
        for i, name in enumerate(family.param_names):  # every column, on its own scale
            size = np.abs(want_cols[..., i]).max()
            np.testing.assert_allclose(cols[..., i], want_cols[..., i], rtol=1e-12, atol=1e-12 * size,
                                       err_msg=name)  # fmt: skip
        np.testing.assert_array_equal(cf.jacobian_params(xy, p), cols)
        np.testing.assert_array_equal(cf.jacobian_point(xy, p), jac)


@pytest.mark.parametrize("rotation", [False, True], ids=["eq1", "eq1+rotation"])
def test_the_parameter_columns_are_the_derivatives(rotation):
    """Independently of the kernels: each column is the central difference of the values."""
    xy = _points(7, 50)
    p = np.append(EXAMPLE_TRUTH, 12.0) if rotation else EXAMPLE_TRUTH.copy()
    p[[1, 2, 3, 4, 5, 7]] = [2e-13, 3e-5, -2e-5, 1e-5, 4e-11, -3e-11]  # every term present
    cols = cf.jacobian_params(xy, p)
    for i in range(len(p)):
        h = 1e-6 * max(abs(p[i]), 1e-6 if i < 8 else 1.0)
        up, down = p.copy(), p.copy()
        up[i] += h
        down[i] -= h
        fd = (cf.distort(xy, up) - cf.distort(xy, down)) / (2 * h)
        np.testing.assert_allclose(cols[..., i], fd, rtol=1e-5, atol=1e-7 * np.abs(fd).max() + 1e-12)


def test_the_blocks_and_shapes():
    xy = _points(3, 1000).reshape(4, 250, 2)
    old = cf.BLOCK
    try:
        cf.BLOCK = 97  # several blocks, the last one short
        blocked = cf.evaluate(xy, EXAMPLE_TRUTH)
    finally:
        cf.BLOCK = old
    whole = cf.evaluate(xy, EXAMPLE_TRUTH)
    assert blocked[0].shape == (4, 250, 2) and blocked[1].shape == (4, 250, 2, 2)
    assert blocked[2].shape == (4, 250, 2, 13)
    for a, b in zip(blocked, whole):
        np.testing.assert_array_equal(a, b)
    value_only = cf.evaluate(xy, EXAMPLE_TRUTH, cf.VALUE)
    assert value_only[1] is None and value_only[2] is None


def test_when_it_applies():
    n = cf.MAX_POINTS
    loaded = "numba" in sys.modules
    assert cf.applies(BROWN_CONRADY, n) is not loaded
    assert cf.applies(BROWN_CONRADY_POSE, 10, np.zeros(14)) is not loaded
    assert not cf.applies(BROWN_CONRADY, n + 1)
    assert not cf.applies(RELAY, 10)
    assert not cf.applies(BROWN_CONRADY, 10, np.zeros(14))  # a vector of another length


def _calibration(rotation):
    data = synthetic_pairs(seed=0)
    if not rotation:
        return calibrate(data.xy_u, data.xy_d, "paper", image_size=(640, 480))
    t = np.radians(8.0)
    turn = np.array([[np.cos(t), np.sin(t)], [-np.sin(t), np.cos(t)]])  # the target turned by -8 deg
    centre = np.array([320.0, 240.0])
    cal = calibrate(
        (data.xy_u - centre) @ turn.T + centre, data.xy_d, "paper+rotation", image_size=(640, 480)
    )
    assert cal.family is BROWN_CONRADY_POSE
    return cal


def _both(monkeypatch, build):
    """``build()`` through the closed form and through the kernels."""
    with monkeypatch.context() as patch:
        patch.setattr(cf, "applies", lambda *a, **k: True)
        closed = build()
    with monkeypatch.context() as patch:
        patch.setattr(cf, "applies", lambda *a, **k: False)
        kernels = build()
    return closed, kernels


@pytest.mark.parametrize("rotation", [False, True], ids=["eq1", "eq1+rotation"])
def test_the_correction_map_is_the_kernels(monkeypatch, rotation):
    cal = _calibration(rotation)
    geometry = output_geometry(cal, (480, 640), extent="full")  # beyond the frame: larger terms
    rows, cols = geometry.shape
    xs = geometry.x0 + geometry.scale * np.arange(cols, dtype=float)
    ys = geometry.y0 + geometry.scale * np.arange(rows, dtype=float)
    # float64, before the cast: the closed-form map's values against the kernels' at every pixel
    gx, gy = np.meshgrid(xs, ys)
    want = distort(np.stack([gx, gy], -1).reshape(-1, 2), cal.params, family=cal.family).reshape(
        rows, cols, 2
    )
    map64 = np.empty((rows, cols)), np.empty((rows, cols))
    cf.grid_map(cal.params, xs, ys, *map64)
    assert max(np.abs(map64[k] - want[..., k]).max() for k in (0, 1)) < 1e-9
    closed, kernels = _both(monkeypatch, lambda: correction_map(cal, (480, 640), geometry=geometry))
    for a, b in zip(closed, kernels):
        assert a.dtype == b.dtype == np.float32 and a.shape == b.shape == (rows, cols)
        np.testing.assert_array_max_ulp(a, b, maxulp=1)
        assert np.mean(a == b) > 0.999  # identical but for the rare value at a rounding tie


@pytest.mark.parametrize("rotation", [False, True], ids=["eq1", "eq1+rotation"])
def test_the_trust_region_is_the_kernels(monkeypatch, rotation):
    cal = _calibration(rotation)
    # k1 < 0 makes the map fold inside a wide output: trusted, untrusted and folded pixels
    params = cal.params.copy()
    params[0] = -4e-7
    wide = dataclasses.replace(cal, params=params)
    geometry = output_geometry(cal, (480, 640), extent="input")
    wide_geometry = dataclasses.replace(geometry, x0=-1700.0, y0=-1400.0, scale=10.0, shape=(300, 410))
    for c, g in ((cal, geometry), (wide, wide_geometry)):
        closed, kernels = _both(monkeypatch, lambda c=c, g=g: predicted_error_map(c, g))
        np.testing.assert_array_equal(np.isinf(closed), np.isinf(kernels))
        ok = np.isfinite(kernels)
        np.testing.assert_allclose(closed[ok], kernels[ok], rtol=1e-6)  # float32 maps
        for limit in (0.05, 0.2, 1.0):
            np.testing.assert_array_equal(closed <= limit, kernels <= limit)
    assert np.isinf(closed).any() and (closed <= 1.0).any()
    xy = np.stack(np.meshgrid(np.linspace(-200, 800, 30), np.linspace(-100, 600, 20)), -1).reshape(-1, 2)
    closed, kernels = _both(monkeypatch, lambda: position_covariance(xy, cal.model, cal.covariance))
    np.testing.assert_allclose(closed, kernels, rtol=1e-9, atol=1e-12 * np.abs(kernels).max())
    closed, kernels = _both(monkeypatch, lambda: correction_map(cal, (480, 640), max_error_px=0.05))
    np.testing.assert_array_equal(closed.trusted, kernels.trusted)
    assert 0.0 < closed.trusted.mean() < 1.0
    np.testing.assert_array_max_ulp(closed.map_x, kernels.map_x, maxulp=1)
