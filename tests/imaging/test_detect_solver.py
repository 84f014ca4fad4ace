"""The registration's hand-written Levenberg-Marquardt (``registration.fit_pixels``) against
``scipy.optimize.least_squares`` on the same residuals and Jacobian, and the polynomial warp
(``detect.warp``) against its definition."""

import numpy as np
import pytest

from oapcal.imaging.detect.registration import FitOptions, FitStart, PixelData, Reference, fit_pixels
from oapcal.imaging.detect.warp import PolyWarp, newton_invert, poly_exponents, poly_terms


def _bars_problem():
    """Three bars seen through a known affine warp, with noise: ``(data, true coef)``."""
    rects = np.array([[10.0 + 10 * k, 10.0, 15.0 + 10 * k, 45.0] for k in range(3)])
    ref = Reference(rects, margin=10)
    gy, gx = np.mgrid[0:60, 0:50]
    xs = np.stack([gx.ravel(), gy.ravel()], -1).astype(float)
    basis = np.column_stack([np.ones(len(xs)), (xs - 25) / 25.0])
    true = np.array([[0.6, -0.4], [0.3, 0.1], [-0.2, 0.25]])
    rng = np.random.default_rng(1)
    values = 0.1 + 0.8 * ref.sample(xs + basis @ true, 1.2)[0] + rng.normal(0, 0.01, len(xs))
    return PixelData(values, xs, basis, ref), true


def _least_squares(data: PixelData, t0):
    from scipy.optimize import least_squares

    xs, basis, ref = data.base_u, data.basis, data.ref

    def model(t):
        c = np.stack([t[:3], t[3:6]], -1)
        return ref.sample(xs + basis @ c, t[8], with_sigma=True)

    def fun(t):
        return t[6] + t[7] * model(t)[0] - data.values

    def jac(t):
        r, ru, rv, rs = model(t)
        cols = [t[7] * ru[:, None] * basis, t[7] * rv[:, None] * basis, np.ones((len(xs), 1)), r[:, None]]
        return np.concatenate([*cols, t[7] * rs[:, None]], axis=1)

    out = least_squares(fun, t0, jac=jac, method="lm", x_scale="jac", xtol=1e-12, ftol=1e-12)
    assert out.status > 0
    return np.stack([out.x[:3], out.x[3:6]], -1), out.x[8]


def _cost(data: PixelData, coef, sigma) -> float:
    """The fit's cost at ``coef`` and ``sigma`` with the best background and contrast."""
    r = data.ref.sample(data.base_u + data.basis @ coef, sigma, derivatives=False)[0]
    design = np.column_stack([np.ones_like(r), r])
    ab, *_ = np.linalg.lstsq(design, data.values, rcond=None)
    e = data.values - design @ ab
    return float(e @ e)


def test_fit_pixels_reaches_the_minimum_that_least_squares_finds():
    """Converged tightly, both solvers end at the same warp (measured: 3e-8 px apart); at the
    detection's own stopping rule (a step moving no pixel by 1e-3 reference px) the hand
    solver stops within that of it.  (On real images the two differ more, up to 0.05 px:
    the cost samples a bilinearly interpolated raster with the raster's own gradient as
    Jacobian, so each solver's path decides where it stops; registration.fit_pixels.)
    The blur's column of the Jacobian is the heat equation's (``Reference.sigma_derivative``,
    within 0.5 % of the derivative of the discrete blur), so ``least_squares`` stops where
    that Jacobian is stationary, 3e-6 reference px of blur from the cost's minimum; the hand
    solver, which accepts only steps that lower the cost, ends at the lower cost."""
    data, true = _bars_problem()
    start = FitStart(np.zeros((3, 2)), 0.15, 0.7, 1.0)
    coef_ls, sigma_ls = _least_squares(data, np.r_[np.zeros(6), 0.15, 0.7, 1.0])
    tight = fit_pixels(data, start, FitOptions(fit_sigma=True, tol=1e-9, max_iter=200))
    assert tight.converged
    assert np.abs(data.basis @ (tight.coef - coef_ls)).max() < 1e-6
    assert tight.sigma == pytest.approx(sigma_ls, abs=1e-5)  # measured 2.8e-6 apart
    assert tight.cost <= _cost(data, coef_ls, sigma_ls) * (1 + 1e-12)
    usual = fit_pixels(data, start, FitOptions(fit_sigma=True))
    assert usual.converged and np.abs(data.basis @ (usual.coef - coef_ls)).max() < 1e-3
    # and the minimum is the truth, within the noise
    assert np.abs(data.basis @ (usual.coef - true)).max() < 0.05


def test_poly_warp_fits_and_inverts_a_cubic_map():
    rng = np.random.default_rng(3)
    x = rng.uniform(0, 400, (200, 2))
    z = (x - 200.0) / 150.0
    u = np.column_stack([10 + 0.9 * x[:, 0] + 3 * z[:, 0] ** 3 - 2 * z[:, 0] * z[:, 1],
                         -5 + 1.1 * x[:, 1] + 4 * z[:, 1] ** 2 * z[:, 0]])  # fmt: skip
    warp = PolyWarp.fit(x, u, 3, (200.0, 200.0), 150.0)
    assert np.abs(warp(x) - u).max() < 1e-9  # a cubic is fitted exactly
    back = warp.inverse(u[:20])
    assert np.abs(back - x[:20]).max() < 1e-7
    # the Jacobian against central differences
    h = 1e-4
    num = np.stack([(warp(x[:5] + [h, 0]) - warp(x[:5] - [h, 0])) / (2 * h),
                    (warp(x[:5] + [0, h]) - warp(x[:5] - [0, h])) / (2 * h)], -1)  # fmt: skip
    assert np.allclose(warp.jacobian(x[:5]), num, atol=1e-6)
    # more terms keep the map
    assert np.allclose(warp.with_degree(4)(x), warp(x)) and len(poly_exponents(4)) == 15


def test_poly_terms_are_the_monomials_in_order():
    z = np.array([[2.0, 3.0]])
    assert poly_terms(z, 2).tolist() == [[1.0, 2.0, 3.0, 4.0, 6.0, 9.0]]


def test_newton_invert_solves_each_row():
    def func(x):
        return np.column_stack([x[:, 0] + 0.1 * x[:, 1] ** 2, x[:, 1] - 0.05 * x[:, 0] ** 2])

    def jac(x):
        return np.stack([np.column_stack([np.ones(len(x)), 0.2 * x[:, 1]]),
                         np.column_stack([-0.1 * x[:, 0], np.ones(len(x))])], 1)  # fmt: skip

    x = np.array([[1.0, 2.0], [-3.0, 0.5]])
    assert np.allclose(newton_invert(func, jac, func(x), np.zeros_like(x)), x, atol=1e-10)


def test_fit_pixels_on_a_flat_patch_reports_no_correlation_and_no_warning():
    """Pixels all of one value (the uniform fill around a turned image) gave a NaN ``ncc``
    with numpy's divide warning; it is 0."""
    import warnings

    data, _ = _bars_problem()
    flat = PixelData(np.full_like(data.values, 0.5), data.base_u, data.basis, data.ref)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        res = fit_pixels(flat, FitStart(np.zeros((3, 2)), 0.15, 0.7, 1.0), FitOptions(fit_sigma=True))
    assert res.ncc == 0.0
