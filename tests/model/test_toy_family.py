"""A new model family is one table entry plus its point function (docs/architecture.md,
"Where a new model family goes"): a toy one-term radial family registered here, with no
change to oapcal's modules, is distorted, inverted, fitted and turned into a correction
map through :class:`oapcal.model.Model`, and its expected values come from its formula
written out in NumPy, not from the code under test."""

import numba
import numpy as np
import pytest

from oapcal.errors import ModelSpecError
from oapcal.fitting import fit_batch
from oapcal.imaging.field import ModelDistortionField
from oapcal.imaging.remap import correction_map
from oapcal.model import FAMILIES, Model, ModelFamily, family_named, family_of, register_family

#: One radial term about a free centre: x_d = c + (x_u - c) (1 + k r^2), r = |x_u - c|.
TOY = ModelFamily(
    name="toy-radial",
    code=90,
    param_names=("k", "c_x", "c_y"),
    always_free=(),
    scale_exponents=np.array([2.0, -1.0, -1.0]),  # k f^2, c / f: exact for xy / f
    moves=("xy", "xy", "xy"),
    analytic_jacobian=False,  # the solver differences the point function (the relay's way)
    fd_step=1e-6,
)


@numba.njit(inline="always")
def toy_point(p, x, y, need, jp, j, want):
    """The toy family at one point, with the contract of ``_kernels.bc_point``."""
    k, cx, cy = p[0], p[1], p[2]
    dx, dy = x - cx, y - cy
    r2 = dx * dx + dy * dy
    f = 1.0 + k * r2
    xd, yd = cx + dx * f, cy + dy * f
    if need == 0:
        return xd, yd, 0.0, 0.0, 0.0, 0.0
    return xd, yd, f + 2 * k * dx * dx, 2 * k * dx * dy, 2 * k * dx * dy, f + 2 * k * dy * dy


def toy_numpy(xy, p):
    """The same formula in NumPy: the reference the compiled family is checked against."""
    k, c = p[0], np.asarray(p[1:])
    d = np.asarray(xy) - c
    return c + d * (1.0 + k * (d * d).sum(-1, keepdims=True))


@pytest.fixture(scope="module")
def toy():
    if TOY.name not in FAMILIES:
        register_family(TOY, toy_point)
    return family_named(TOY.name)


P = np.array([3e-7, 330.0, 250.0])
XY = np.random.default_rng(4).uniform([0, 0], [639, 479], (300, 2))


def test_toy_family_distorts_and_inverts_through_model(toy):
    model = Model("toy-radial", P, ("k", "c_x", "c_y"))
    np.testing.assert_allclose(model(XY), toy_numpy(XY, P), rtol=0, atol=1e-9)
    inv = model.inverse(toy_numpy(XY, P))
    assert inv.converged.all()
    np.testing.assert_allclose(inv.xy, XY, atol=1e-8)
    # its 2x2 Jacobian against central differences of the NumPy formula
    h = 1e-4
    num = np.stack([(toy_numpy(XY + [h, 0], P) - toy_numpy(XY - [h, 0], P)) / (2 * h),
                    (toy_numpy(XY + [0, h], P) - toy_numpy(XY - [0, h], P)) / (2 * h)], -1)  # fmt: skip
    np.testing.assert_allclose(model.jacobian(XY), num, atol=1e-8)


def test_toy_family_is_never_found_by_length(toy):
    with pytest.raises(ModelSpecError, match=r"shape \(\.\.\., 13\)"):
        family_of(P)  # a 3-vector is no built-in family, and is not guessed to be the toy


def test_toy_family_fits_with_the_one_solver(toy):
    xy_d = toy_numpy(XY, P) + np.random.default_rng(5).normal(0, 0.01, XY.shape)
    starts = np.array([[0.0, 320.0, 240.0], [1e-7, 300.0, 260.0]])
    fits = fit_batch(XY, xy_d, np.ones((2, 3), bool), starts, family=toy)
    assert fits.converged.all()
    for p in fits.params:
        np.testing.assert_allclose(p, P, rtol=2e-3)
    # noise 0.01 px per coordinate: rms of the residuals within 20 % of it
    assert np.sqrt(fits.rss / fits.n) == pytest.approx(0.01, rel=0.2)


def test_toy_family_correction_map_and_simulation_field(toy):
    model = Model(toy, P, ("k", "c_x", "c_y"))
    mx, my = correction_map(model, (48, 64))
    gx, gy = np.meshgrid(np.arange(64.0), np.arange(48.0))
    want = toy_numpy(np.stack([gx, gy], -1), P)
    np.testing.assert_allclose(mx, want[..., 0], atol=1e-3)  # float32 maps
    np.testing.assert_allclose(my, want[..., 1], atol=1e-3)
    field = ModelDistortionField(model, 4.8, (640, 480))
    np.testing.assert_allclose(field.forward(XY), toy_numpy(XY, P), atol=1e-9)
    np.testing.assert_allclose(field.inverse(field.forward(XY)), XY, atol=1e-8)


def test_register_family_refuses_a_taken_name_or_code(toy):
    with pytest.raises(ModelSpecError, match="exists already"):
        register_family(TOY, toy_point)


def test_toy_family_drives_an_image_simulation(toy):
    from oapcal.imaging.simulate import simulate_image

    field = ModelDistortionField(Model(toy, [4e-6, 99.5, 79.5], ("k", "c_x", "c_y")), 4.8, (200, 160))
    sim = simulate_image((5,), field, snr=None, oversample=1, sigma_px=0)
    # xy_u is the paraxial image of each corner; the truth's distorted corners are the toy
    # formula there
    np.testing.assert_allclose(sim.xy_d, toy_numpy(sim.xy_u, field.params), atol=1e-6)
    assert sim.image.shape == (160, 200) and sim.visible.sum() > 10


def test_toy_family_is_scored_and_cross_validated_by_name(toy):
    from oapcal.select import cross_validate, score_models

    xy_d = toy_numpy(XY, P) + np.random.default_rng(6).normal(0, 0.01, XY.shape)
    masks = np.array([[True, True, True], [False, True, True]])  # k free, and the centre alone
    starts = np.array([[1e-7, 320.0, 240.0], [0.0, 320.0, 240.0]])
    scores = score_models(XY, xy_d, masks, starts, family=toy)
    assert (scores["status"] > 0).all()
    np.testing.assert_allclose(scores["params"][0], P, rtol=2e-3)
    # corrected through the toy's inverse: the noise (mean distance of 2-D Gaussian noise of
    # 0.01 px per coordinate: 0.01 sqrt(pi / 2)), and far more without the radial term
    assert scores["mean_error"][0] == pytest.approx(0.01 * np.sqrt(np.pi / 2), rel=0.2)
    assert scores["mean_error"][1] > 100 * scores["mean_error"][0]
    errs, failed = cross_validate(XY, xy_d, masks, folds=3, init=starts, family=toy)
    assert (failed == 0).all() and errs[0] == pytest.approx(0.01 * np.sqrt(np.pi / 2), rel=0.3)
    with pytest.raises(ModelSpecError, match=r"shape \(\.\.\., 13\)"):
        score_models(XY, xy_d, masks, starts)  # not named: a 3-vector is no built-in family
