import dataclasses

import numpy as np
import pytest
from scipy.optimize import least_squares

from oapcal.errors import DataError, ModelSpecError
from oapcal.fitting import fit, fit_batch, initial_params
from oapcal.model import (
    BROWN_CONRADY,
    INDEX,
    distort,
    jacobian_params,
    pack,
    params_from_dict,
    parse_model,
    unpack,
)
from oapcal.synthetic import synthetic_pairs


def test_recovers_known_parameters_within_three_standard_errors():
    # The acceptance test of the core issue: ~250 points over 640x480, ~40 px distortion
    # (more in y than x), 0.3 px noise, model 'paper'.
    data = synthetic_pairs(seed=2024)
    dist = data.xy_d_true - data.xy_u
    assert 35 < data.max_distortion_px < 45
    assert np.abs(dist[:, 1]).max() > np.abs(dist[:, 0]).max()
    result = fit(data.xy_u, data.xy_d, "paper")
    assert result.converged
    for name in result.free:
        z = (result.value(name) - data.params[INDEX[name]]) / result.stderr_dict[name]
        assert abs(z) < 3, (name, z)
    # the residual scatter is the noise we put in
    assert result.rss / (result.n - result.k) == pytest.approx(0.09, rel=0.2)


RADIAL_TRUTH = params_from_dict(
    {"k1": 3e-7, "x_off": -300.0, "y_off": -250.0, "c_x": 310.0, "c_y": 245.0, "m": 1.02}
)


@pytest.mark.parametrize(
    "model,init,truth",
    [("paper", "pixel", None), ("radial", "zero", RADIAL_TRUTH), ("full", "pixel", None)],
)
def test_agrees_with_scipy_least_squares_lm(model, init, truth):
    # Each model on data it can describe (a badly misfitting model has a flat minimum that
    # neither solver locates to 1e-8 with cost-based stopping).
    pairs = synthetic_pairs(truth, seed=5)
    mask = parse_model(model)
    p0 = initial_params(init, pairs.xy_u, pairs.xy_d, mask)

    def fun(q):
        return (distort(pairs.xy_u, unpack(q, mask)) - pairs.xy_d).ravel()

    def jac(q):
        return jacobian_params(pairs.xy_u, unpack(q, mask)).reshape(-1, 13)[:, mask]

    tight = dict(ftol=1e-15, xtol=1e-15, gtol=1e-15)
    ref = least_squares(fun, pack(p0, mask), jac=jac, method="lm", max_nfev=20000, **tight)
    assert ref.success
    ours = fit(pairs.xy_u, pairs.xy_d, model, init=init, max_iter=2000, **tight)
    assert ours.converged
    assert ours.rss == pytest.approx(2 * ref.cost, rel=1e-10)
    np.testing.assert_allclose(pack(ours.params, mask), ref.x, rtol=1e-8, atol=1e-12)


def test_batched_fit_equals_single_fits(pairs):
    specs = ["paper", "radial", "k1,s3,c_x,c_y", "k1,k2,p1,y_off,c_y"]
    masks = np.stack([parse_model(s) for s in specs])
    p0 = np.stack([initial_params("pixel", pairs.xy_u, pairs.xy_d, m) for m in masks])
    batch = fit_batch(pairs.xy_u, pairs.xy_d, masks, p0)
    for i, spec in enumerate(specs):
        single = fit(pairs.xy_u, pairs.xy_d, spec, init="pixel")
        np.testing.assert_allclose(batch.item(i).params, single.params, rtol=1e-9, atol=1e-12)
        assert batch.item(i).aicc == pytest.approx(single.aicc, rel=1e-12)


def test_fit_result_is_immutable_and_complete(pairs):
    r = fit(pairs.xy_u, pairs.xy_d, "radial")
    with pytest.raises((AttributeError, TypeError)):
        r.rss = 0.0
    with pytest.raises(ValueError):
        r.params[0] = 1.0
    assert r.params.shape == (13,) and r.covariance.shape == (6, 6)
    assert np.isnan(r.stderr[INDEX["k2"]]) and r.stderr[INDEX["k1"]] > 0
    assert r.n == 2 * len(pairs.xy_u) and r.k == 6
    assert r.aicc > r.aic and r.message.startswith("converged")


def test_the_paper_model_has_two_equivalent_minima(pairs):
    # The zero start reaches a second parameter set giving the same forward map (see
    # docs/models.md); 'auto' breaks the tie toward the pixel start, near the truth.
    a = fit(pairs.xy_u, pairs.xy_d, "paper", init="zero")
    b = fit(pairs.xy_u, pairs.xy_d, "paper", init="pixel")
    assert a.rss == pytest.approx(b.rss, rel=1e-9)
    assert abs(a.value("y_off") - b.value("y_off")) > 100
    g = np.stack(np.meshgrid(np.linspace(0, 640, 30), np.linspace(0, 480, 30)), -1).reshape(-1, 2)
    assert np.abs(distort(g, a.params) - distort(g, b.params)).max() < 1e-6
    auto = fit(pairs.xy_u, pairs.xy_d, "paper")
    assert auto.value("y_off") == pytest.approx(b.value("y_off"))


def test_non_convergence_is_a_value(pairs):
    r = fit(pairs.xy_u, pairs.xy_d, "full", init="zero", max_iter=2)
    assert not r.converged and r.status == 0 and "iteration cap" in r.message


def test_too_few_points_is_an_input_error(pairs):
    with pytest.raises(DataError, match="too few"):
        fit(pairs.xy_u[:9], pairs.xy_d[:9], "paper")


def test_user_initial_values():
    p = initial_params("k1=1e-6, m=2", np.zeros((3, 2)), np.zeros((3, 2)), parse_model("radial"))
    np.testing.assert_array_equal(p, params_from_dict({"k1": 1e-6, "m": 2.0}))
    p = initial_params({"s3": 5.0}, np.zeros((3, 2)), np.zeros((3, 2)), parse_model("radial"))
    assert p[INDEX["s3"]] == 0.0  # fixed parameters start (and stay) at 0


def test_point_subsets_by_index_and_by_mask_equal_fits_to_the_subsets(pairs):
    mask = parse_model("paper")
    n = len(pairs.xy_u)
    rng = np.random.default_rng(0)
    keep = np.sort(np.argsort(rng.random((3, n)), axis=1)[:, : n - 40], axis=1)
    p0 = initial_params("pixel", pairs.xy_u, pairs.xy_d, mask)
    masks = np.repeat(mask[None], 3, 0)
    scale = float(np.abs(np.concatenate([pairs.xy_u, pairs.xy_d])).max())
    by_index = fit_batch(pairs.xy_u, pairs.xy_d, masks, p0, points=keep)
    selected = np.zeros((3, n), bool)
    selected[np.arange(3)[:, None], keep] = True
    by_mask = fit_batch(pairs.xy_u, pairs.xy_d, masks, p0, points=selected)
    for i in range(3):
        alone = fit_batch(pairs.xy_u[keep[i]], pairs.xy_d[keep[i]], mask[None], p0, scale=scale)
        for batch in (by_index, by_mask):
            np.testing.assert_allclose(batch.params[i], alone.params[0], rtol=1e-12, atol=1e-12)
            assert batch.rss[i] == pytest.approx(alone.rss[0], rel=1e-12)
            assert batch.n[i] == 2 * (n - 40) and batch.status[i] == alone.status[0]
            np.testing.assert_allclose(batch.covariance[i], alone.covariance[0], rtol=1e-9, atol=1e-300)


def test_each_item_may_have_its_own_points_and_covariance_is_optional(pairs):
    mask = parse_model("radial")
    shifted = pairs.xy_d + [3.0, -2.0]
    xy_d = np.stack([pairs.xy_d, shifted])
    p0 = initial_params("pixel", pairs.xy_u, pairs.xy_d, mask)
    batch = fit_batch(pairs.xy_u, xy_d, np.repeat(mask[None], 2, 0), p0, covariance=False)
    assert batch.covariance is None and batch.converged.all()
    # the second item's data are the first's shifted by (3, -2): only c_x and c_y change
    diff = batch.params[1] - batch.params[0]
    np.testing.assert_allclose(diff[INDEX["c_x"]] - diff[INDEX["x_off"]] * batch.params[0][INDEX["m"]], 3.0,
                               rtol=1e-6)  # fmt: skip
    with pytest.raises(ModelSpecError, match="without covariance"):
        batch.item(0)
    with pytest.raises(ValueError):
        batch.params[0, 0] = 1.0


def test_finite_difference_family_fits_like_the_analytic_one(pairs):
    # A family without analytic columns: the solver differentiates the point function.
    numeric = dataclasses.replace(BROWN_CONRADY, analytic_jacobian=False)
    mask = parse_model("paper")
    p0 = initial_params("pixel", pairs.xy_u, pairs.xy_d, mask)
    exact = fit_batch(pairs.xy_u, pairs.xy_d, mask[None], p0)
    approx = fit_batch(pairs.xy_u, pairs.xy_d, mask[None], p0, family=numeric)
    assert approx.converged[0]
    assert approx.rss[0] == pytest.approx(exact.rss[0], rel=1e-9)
    np.testing.assert_allclose(np.sqrt(np.diag(approx.covariance[0])), np.sqrt(np.diag(exact.covariance[0])),
                               rtol=1e-4)  # fmt: skip


def test_bad_solver_arguments_are_named_errors(pairs):
    mask = parse_model("paper")
    with pytest.raises(ModelSpecError, match="'m' must be free"):
        fit_batch(pairs.xy_u, pairs.xy_d, mask & (np.arange(13) != INDEX["m"]), np.zeros(13))
    with pytest.raises(ModelSpecError, match="point indices must lie"):
        fit_batch(pairs.xy_u, pairs.xy_d, mask, np.zeros(13), points=np.array([[0, 1, 10_000]]))
    with pytest.raises(ModelSpecError, match="point mask must have shape"):
        fit_batch(pairs.xy_u, pairs.xy_d, mask, np.zeros(13), points=np.ones(5, bool))
