"""Gaussian priors in the one solver (fit_batch(prior=...)) and the relay's MAP fit."""

import json

import numpy as np
import pytest
from scipy.optimize import least_squares

import reference_model
from oapcal.errors import ModelSpecError
from oapcal.fitting import fit_batch, initial_params
from oapcal.model import RELAY, distort, params_from_dict, parse_model, undistort
from oapcal.optics.relay_model import (
    DEFAULT_PRIORS,
    RelayDesign,
    calibrate_relay,
    parse_priors,
    relay_mask,
    relay_params,
)


def _bc_case(seed=0, n=60, noise=0.3):
    rng = np.random.default_rng(seed)
    truth = params_from_dict({"k1": 2e-7, "p1": 1e-5, "s3": -2e-5, "x_off": -320.0, "y_off": -240.0,
                              "c_x": 321.0, "c_y": 239.0, "m": 1.01})  # fmt: skip
    xy_u = rng.uniform([100, 80], [540, 400], (n, 2))
    return xy_u, reference_model.distort(xy_u, truth) + rng.normal(0, noise, (n, 2))


def test_a_map_fit_is_least_squares_with_the_prior_rows_appended():
    """Against scipy's least_squares on the residuals and rows (p - mean) / sigma, written
    from the definition with the NumPy reference model."""
    xy_u, xy_d = _bc_case()
    mask = parse_model("paper")
    p0 = initial_params("auto", xy_u, xy_d, mask)
    mean = np.zeros(13)
    sigma = np.full(13, np.inf)
    sigma[[0, 2, 6]] = [1e-7, 5e-6, 1e-5]  # k1, p1, s3: tight enough to move the fit
    got = fit_batch(xy_u, xy_d, mask[None], p0[None], prior=(mean, sigma)).item(0)
    free = np.flatnonzero(mask)

    def rows(q):
        p = p0.copy()
        p[free] = q
        data = (reference_model.distort(xy_u, p) - xy_d).T.ravel()
        pri = [(p[i] - mean[i]) / sigma[i] for i in free if np.isfinite(sigma[i])]
        return np.concatenate([data, pri])

    ref = least_squares(rows, p0[free], method="lm", x_scale="jac", xtol=1e-15, ftol=1e-15, gtol=1e-15)
    np.testing.assert_allclose(got.params[free], ref.x, rtol=1e-6, atol=1e-12)
    # the fit moved: it is not the free fit
    plain = fit_batch(xy_u, xy_d, mask[None], p0[None]).item(0)
    assert abs(plain.params[0] - got.params[0]) > 1e-8
    # rss is the data's alone, and 0 < k_eff < k
    data_rss = float((rows(got.params[free])[: 2 * len(xy_u)] ** 2).sum())
    np.testing.assert_allclose(got.rss, data_rss, rtol=1e-9)
    assert 5 < got.k_eff < 8 and got.k == 8


def test_zero_width_is_the_fixed_fit_and_infinite_width_the_free_fit():
    xy_u, xy_d = _bc_case(seed=1)
    mask = parse_model("paper")
    p0 = initial_params("auto", xy_u, xy_d, mask)
    free = fit_batch(xy_u, xy_d, mask[None], p0[None]).item(0)
    wide = fit_batch(xy_u, xy_d, mask[None], p0[None], prior=(np.zeros(13), np.full(13, 1e30))).item(0)
    # the two fits stop at the solver's own tolerance: 2.5e-9 relative apart in one run (the
    # 1e-30 prior rows change the rounding of the normal equations), so 1e-7 here
    np.testing.assert_allclose(wide.params, free.params, rtol=1e-7, atol=1e-15)
    np.testing.assert_allclose(wide.covariance, free.covariance, rtol=1e-6, atol=1e-30)
    assert wide.k_eff == pytest.approx(free.k, abs=1e-6) and wide.aicc == pytest.approx(free.aicc, abs=1e-6)
    # s3 with zero width (mean 0): the fit of paper without s3, computed on its own
    sigma = np.full(13, np.inf)
    sigma[6] = 0.0
    pinned = fit_batch(xy_u, xy_d, mask[None], p0[None], prior=(np.zeros(13), sigma)).item(0)
    no_s3 = mask.copy()
    no_s3[6] = False
    fixed = fit_batch(xy_u, xy_d, no_s3[None], np.where(no_s3, p0, 0)[None]).item(0)
    assert pinned.free == fixed.free and "s3" not in pinned.free
    np.testing.assert_allclose(pinned.params, fixed.params, rtol=1e-12, atol=1e-18)
    # and a tiny width tends to it
    sigma[6] = 1e-16
    tiny = fit_batch(xy_u, xy_d, mask[None], p0[None], prior=(np.zeros(13), sigma)).item(0)
    np.testing.assert_allclose(tiny.params[no_s3], fixed.params[no_s3], rtol=1e-6)
    with pytest.raises(ModelSpecError, match="give it mean 0"):
        fit_batch(
            xy_u,
            xy_d,
            mask[None],
            p0[None],
            prior=(np.full(13, 1.0), np.where(np.arange(13) == 0, 0, np.inf)),
        )
    with pytest.raises(ModelSpecError, match="'m' is always free"):
        fit_batch(xy_u, xy_d, mask[None], p0[None], prior=(np.zeros(13), np.zeros(13)))
    with pytest.raises(ModelSpecError, match="widths"):
        fit_batch(xy_u, xy_d, mask[None], p0[None], prior=(np.zeros(13), np.full(13, -1.0)))


def _relay_case(seed=3, n=40, noise=0.3, share=0.4):
    design = RelayDesign(setup=1, centre=(319.5, 239.5))
    rng = np.random.default_rng(seed)
    mis = {"m2_tilt_x": 0.03, "m1_tilt_y": -0.04, "m2_decentre_y": 0.15, "d1": 20.0, "camera_tilt_x": 0.6,
           "camera_defocus": 0.12, "m1_decentre_x": -0.1}  # fmt: skip
    truth = relay_params(design, mis, {"rotation": 0.4})
    lo, hi = np.array([215.0, 135.0]), np.array([424.0, 344.0])  # the 1 mm field
    mid, half = (lo + hi) / 2, share / 2 * (hi - lo)
    xy_u = rng.uniform(mid - half, mid + half, (n, 2))
    xy_d = distort(xy_u, truth) + rng.normal(0, noise, (n, 2))
    g = np.stack(np.meshgrid(np.linspace(lo[0], hi[0], 21), np.linspace(lo[1], hi[1], 21)), -1).reshape(-1, 2)
    return design, xy_u, xy_d, g, distort(g, truth)


def test_relay_zero_width_equals_the_fixed_subset_and_infinite_width_the_free_one():
    design, xy_u, xy_d, _, _ = _relay_case(n=60, noise=0.05, share=0.8)
    spec = "relay:decentre2,d1,camera"
    free = calibrate_relay(xy_u, xy_d, design, spec)
    wide = calibrate_relay(
        xy_u, xy_d, design, spec, priors="base=none,decentre=1e9,d1_mm=1e12,camera_tilt=1e9"
    )
    np.testing.assert_allclose(wide.params, free.params, rtol=1e-7, atol=1e-9)
    pinned = calibrate_relay(xy_u, xy_d, design, spec, priors="base=none,camera_tilt=0")
    fixed = calibrate_relay(xy_u, xy_d, design, "relay:decentre2,d1")
    assert set(pinned.free) == set(fixed.free)
    np.testing.assert_allclose(pinned.params, fixed.params, rtol=1e-9, atol=1e-10)


def test_priors_reduce_the_extrapolation_error_of_few_central_landmarks():
    """Seeded: 40 landmarks over the central 40 % of the field, 0.3 px noise; the error over
    the whole 1 mm field with the default priors is smaller than without."""
    design, xy_u, xy_d, grid_u, grid_d = _relay_case()
    errors = {}
    for priors in (None, "default"):
        cal = calibrate_relay(xy_u, xy_d, design, "default", priors=priors)
        errors[priors] = np.nanmean(np.hypot(*(undistort(grid_d, cal.params).xy - grid_u).T))
    assert errors["default"] < 0.75 * errors[None], errors


def test_priors_are_recorded_and_counted(tmp_path):
    from oapcal.io.calibration import load_calibration, save_calibration

    design, xy_u, xy_d, _, _ = _relay_case()
    cal = calibrate_relay(xy_u, xy_d, design, "default", priors="tilt=0.1,noise_px=0.3")
    assert cal.priors["widths"]["tilt"] == 0.1 and cal.priors["noise_used_px"] == 0.3
    assert cal.priors["sigma"]["d1"] == pytest.approx(0.05 * 860.0)
    assert cal.fit.k_eff < cal.fit.k
    # AICc counts k_eff
    from oapcal.stats import information_criteria

    assert cal.fit.aicc == pytest.approx(
        information_criteria(cal.fit.rss, cal.fit.n_residuals, cal.fit.k_eff).aicc
    )
    path = tmp_path / "c.json"
    save_calibration(cal, path)
    back = load_calibration(path)
    assert back.priors == json.loads(path.read_text())["priors"] and back.fit.k_eff == pytest.approx(
        cal.fit.k_eff
    )
    # a fit without priors writes no priors key (old files: none, and they load)
    plain = calibrate_relay(xy_u, xy_d, design, "default")
    save_calibration(plain, tmp_path / "p.json")
    assert "priors" not in json.loads((tmp_path / "p.json").read_text())


def test_parse_priors_words():
    assert parse_priors("off") is None and parse_priors(None) is None
    assert dict(parse_priors("default").widths) == DEFAULT_PRIORS
    p = parse_priors("tilt=inf,d1=2")
    sig = p.sigma(RelayDesign(setup=2))
    assert np.isinf(sig["m1_tilt_x"]) and sig["d1"] == pytest.approx(0.02 * 660.0)
    assert sig["camera_tilt_y"] == 1.0
    for bad, match in (("tilt", "key=value"), ("wobble=1", "unknown prior 'wobble'"), ("tilt=-1", ">= 0"),
                       ("noise_px=0", "positive")):  # fmt: skip
        with pytest.raises(ModelSpecError, match=match):
            parse_priors(bad)
    assert relay_mask("all")[RELAY.param_names.index("m1_clock")]
