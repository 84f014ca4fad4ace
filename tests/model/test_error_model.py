"""The error model (model floor and extrapolation, measured on the landmarks) and the
coverage of the predicted error on seeded simulations.  The heavier coverage check on the
traced relays of benchmarks/models.py is marked slow."""

import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest

from oapcal import error_model as error_model_module
from oapcal.calibration import calibrate
from oapcal.error_model import GROWTH_EXPONENT, PHYSICAL_GROWTH_EXPONENT, estimate_error_model
from oapcal.io.calibration import calibration_to_dict, load_calibration, save_calibration
from oapcal.model import PARAM_NAMES, RELAY, Model, distort, undistort
from oapcal.optics.relay_model import RelayDesign, relay_mask, relay_params
from oapcal.synthetic import EXAMPLE_TRUTH
from oapcal.uncertainty import (
    ErrorModel,
    hull_distance,
    inside_hull,
    position_covariance,
    predicted_error,
    predicted_error_xy,
    uncertainty_map,
)

REPO = Path(__file__).resolve().parents[2]

#: Eq. (1)'s example truth with two terms the paper model lacks (a radial r^4 term and a
#: thin prism): a model floor of a few tenths of a px over the frame.
TRUTH = EXAMPLE_TRUTH.copy()
TRUTH[PARAM_NAMES.index("k2")] = 5e-13
TRUTH[PARAM_NAMES.index("s1")] = 2e-5

gx, gy = np.meshgrid(np.linspace(0, 639, 33), np.linspace(0, 479, 25))
FIELD = np.stack([gx.ravel(), gy.ravel()], -1)


def _landmarks(seed, layout, truth=TRUTH, noise=0.2, n=150):
    rng = np.random.default_rng(seed)
    lo, hi = ((40, 40), (600, 440)) if layout == "whole" else ((200, 150), (440, 330))
    xy_u = rng.uniform(lo, hi, (n, 2))
    return xy_u, distort(xy_u, truth) + rng.normal(0, noise, xy_u.shape)


def _coverage(cal, truth=TRUTH):
    err = np.hypot(*(undistort(distort(FIELD, truth), cal.params).xy - FIELD).T)
    cov = position_covariance(FIELD, cal.params, cal.covariance, cal.free)
    sigma = np.sqrt(cov[:, 0, 0] + cov[:, 1, 1])
    pred = predicted_error(FIELD, cal)
    inside = inside_hull(FIELD, cal.hull)
    share = {}
    for region, sel in (("in", inside), ("out", ~inside)):
        share[("covariance", region)] = float(np.mean(err[sel] <= 2 * sigma[sel]))
        share[("predicted", region)] = float(np.mean(err[sel] <= 2 * pred[sel]))
    return share


@pytest.mark.parametrize("layout", ["whole", "central"])
def test_predicted_error_covers_the_actual_error_inside_and_outside_the_hull(layout):
    """Four seeds: the paper model on a truth it cannot fit exactly.  The covariance alone
    covers the actual error within 2 sigma at under 70 % of the frame's points (the issue's
    complaint); the predicted error covers 85 % or more inside and outside the hull, and is
    not uselessly large (its median stays within 10x the median actual error)."""
    shares = []
    for seed in range(4):
        xy_u, xy_d = _landmarks(seed, layout)
        cal = calibrate(xy_u, xy_d, "paper", image_size=(640, 480), rotation="none")
        assert cal.error_model is not None and cal.error_model.sides_used == 8
        shares.append(_coverage(cal))
        err = np.hypot(*(undistort(distort(FIELD, TRUTH), cal.params).xy - FIELD).T)
        assert np.median(predicted_error(FIELD, cal)) < 10 * np.median(err)
    mean = {k: np.mean([s[k] for s in shares]) for k in shares[0]}
    assert mean[("covariance", "out")] < 0.7
    assert mean[("predicted", "in")] >= 0.85
    assert mean[("predicted", "out")] >= 0.85


def test_floor_is_small_for_an_exact_model_and_measures_the_misfit_otherwise():
    """With a truth the model describes exactly the floor is far below the noise, and the
    noise estimate is the noise's RMS length (sqrt(2) x 0.2 px); with unfitted terms the
    floor is of the size of the noise-free fit's own misfit (independent of the estimator:
    the RMS of the noise-free landmarks' correction residuals)."""
    xy_u, xy_d = _landmarks(0, "whole", truth=EXAMPLE_TRUTH, n=300)
    cal = calibrate(xy_u, xy_d, "paper", rotation="none")
    em = cal.error_model
    assert em.floor_px < 0.25 * 0.2
    assert em.noise_px == pytest.approx(0.2 * np.sqrt(2), rel=0.15)

    xy_u, _ = _landmarks(1, "whole", n=300)
    clean = distort(xy_u, TRUTH)
    noise_free = calibrate(xy_u, clean, "paper", rotation="none", error_model=False)
    misfit = undistort(clean, noise_free.params).xy - xy_u
    floor_true = float(np.sqrt((misfit**2).sum(axis=1).mean()))
    noisy = calibrate(
        xy_u, clean + np.random.default_rng(5).normal(0, 0.2, clean.shape), "paper", rotation="none"
    )
    assert floor_true > 0.2  # the test's premise: a floor comparable with the noise
    assert noisy.error_model.floor_px == pytest.approx(floor_true, rel=0.4)


def test_error_model_is_stored_and_old_files_load_without_it(tmp_path):
    xy_u, xy_d = _landmarks(2, "central")
    cal = calibrate(xy_u, xy_d, "paper", image_size=(640, 480))
    save_calibration(cal, tmp_path / "c.json")
    back = load_calibration(tmp_path / "c.json")
    assert back.error_model == cal.error_model
    np.testing.assert_allclose(predicted_error(FIELD, back), predicted_error(FIELD, cal))
    # a file written before the error model existed: loads, and its predicted error is the
    # covariance alone (flagged in the map's summary)
    data = calibration_to_dict(cal)
    del data["error_model"]
    (tmp_path / "old.json").write_text(json.dumps(data))
    old = load_calibration(tmp_path / "old.json")
    assert old.error_model is None
    cov = position_covariance(FIELD, old.params, old.covariance, old.free)
    np.testing.assert_allclose(predicted_error(FIELD, old), np.sqrt(cov[:, 0, 0] + cov[:, 1, 1]))
    summary = uncertainty_map(old, step=40).summary()
    assert summary["error_model"] is None
    # a bad error model in a file is refused, naming the field
    data["error_model"] = {**cal.error_model.to_dict(), "extrapolation": 0.5}
    (tmp_path / "bad.json").write_text(json.dumps(data))
    with pytest.raises(Exception, match="error_model"):
        load_calibration(tmp_path / "bad.json")


def test_predicted_error_formula_and_hull_distance():
    """The predicted error is (k sigma)^2 + F^2 with k = 1 inside the hull, rising to kappa
    over d0 and growing beyond the probed distance; the hull distance against a brute-force
    distance to densely sampled edges."""
    xy_u, xy_d = _landmarks(3, "central")
    cal = calibrate(xy_u, xy_d, "paper", image_size=(640, 480), rotation="none")
    em = cal.error_model
    cov = position_covariance(FIELD, cal.params, cal.covariance, cal.free)
    sp = np.sqrt(cov[:, 0, 0] + cov[:, 1, 1])
    d = hull_distance(FIELD, cal.hull)
    inside = d == 0
    np.testing.assert_allclose(predicted_error(FIELD, cal)[inside], np.hypot(sp, em.floor_px)[inside])
    x, y = cal.hull.T
    radius = np.sqrt(0.5 * abs(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))) / np.pi)
    near = (d > em.ramp_px) & (d / radius <= em.probed_distance)
    np.testing.assert_allclose(
        predicted_error(FIELD, cal)[near], np.hypot(em.extrapolation * sp, em.floor_px)[near]
    )
    far = d / radius > em.probed_distance
    growth = ((1 + d / radius) / (1 + em.probed_distance)) ** em.growth_exponent
    np.testing.assert_allclose(
        predicted_error(FIELD, cal)[far], np.hypot(em.extrapolation * growth * sp, em.floor_px)[far]
    )
    # hull distance: brute force over 400 points per edge
    hull = cal.hull
    edges = [np.linspace(a, b, 400) for a, b in zip(hull, np.roll(hull, -1, 0))]
    dense = np.concatenate(edges)
    brute = np.sqrt(((FIELD[:, None, :] - dense[None]) ** 2).sum(-1)).min(axis=1)
    np.testing.assert_allclose(d[~inside], brute[~inside], atol=0.5)
    assert (inside == inside_hull(FIELD, hull)).all()


def test_per_coordinate_predicted_error_shares_the_floor_and_makes_up_the_length():
    """Each coordinate's predicted sigma is its own propagated variance (times k^2) plus half
    the floor's squared length; the length of the two is predicted_error."""
    xy_u, xy_d = _landmarks(3, "central")
    cal = calibrate(xy_u, xy_d, "paper", image_size=(640, 480), rotation="none")
    em = cal.error_model
    assert em.floor_px > 0.05  # the truth has terms the paper model lacks
    cov = position_covariance(FIELD, cal.params, cal.covariance, cal.free)
    xy = predicted_error_xy(FIELD, cal)
    assert xy.shape == FIELD.shape
    inside = hull_distance(FIELD, cal.hull) == 0
    half_floor2 = 0.5 * em.floor_px**2
    np.testing.assert_allclose(xy[inside, 0], np.sqrt(cov[inside, 0, 0] + half_floor2))
    np.testing.assert_allclose(xy[inside, 1], np.sqrt(cov[inside, 1, 1] + half_floor2))
    np.testing.assert_allclose(np.hypot(xy[:, 0], xy[:, 1]), predicted_error(FIELD, cal))
    # anisotropic: the paper model constrains x and y differently over the frame
    assert not np.allclose(xy[:, 0], xy[:, 1], rtol=0.05)


@pytest.fixture
def fixed_side_ratios(monkeypatch):
    """The sides' factors kappa^2 of every refit set to 1, 4 and 16 (what the refits measured
    is not under test here, only how they are combined)."""

    def sides(*args, **kwargs):
        return [1.0, 4.0, 16.0], [np.array([0.2, 0.4])]

    monkeypatch.setattr(error_model_module, "_side_ratios", sides)


def test_a_series_model_keeps_its_worst_side(fixed_side_ratios):
    xy_u, xy_d = _landmarks(3, "central")
    cal = calibrate(xy_u, xy_d, "paper", image_size=(640, 480), rotation="none")
    em = estimate_error_model(xy_u, xy_d, cal.model)
    assert em.extrapolation == pytest.approx(4.0)  # sqrt(16)
    assert em.growth_exponent == GROWTH_EXPONENT == 2.0
    assert em.method == "leave-side-out"


def test_a_physical_model_keeps_the_mean_of_its_sides(fixed_side_ratios):
    """The relay lacks no terms of a series: its sides estimate one factor (their mean), which
    grows beyond the probed distance as the field (g = 1), not two orders faster."""
    design = RelayDesign(setup=1, pixel_size_um=4.8, centre=(319.5, 239.5))
    truth = relay_params(design, {"m2_tilt_x": 0.03}, {"rotation": 0.2})
    model = Model.from_mask(RELAY, truth, relay_mask("default"))
    rng = np.random.default_rng(5)
    xy_u = rng.uniform((200, 150), (440, 330), (60, 2))
    xy_d = distort(xy_u, truth, family=RELAY) + rng.normal(0, 0.1, xy_u.shape)
    em = estimate_error_model(xy_u, xy_d, model)
    assert em.extrapolation == pytest.approx(np.sqrt(7.0))  # sqrt((1 + 4 + 16) / 3)
    assert em.growth_exponent == PHYSICAL_GROWTH_EXPONENT == 1.0
    assert em.method == "leave-side-out-mean"


def test_few_landmarks_give_no_error_model():
    xy_u, xy_d = _landmarks(0, "central", n=11)
    cal = calibrate(xy_u, xy_d, "paper", rotation="none")
    assert cal.error_model is None
    assert estimate_error_model(xy_u, xy_d, cal.params, cal.mask) is None


def test_error_model_round_trips_as_a_dict():
    em = ErrorModel(floor_px=0.1, noise_px=0.4, extrapolation=2.0, ramp_px=3.0, growth_exponent=2.0,
                    probed_distance=0.5)  # fmt: skip
    assert ErrorModel.from_dict(em.to_dict()) == em
    assert ErrorModel.from_dict(None) is None


@pytest.mark.slow
def test_coverage_on_traced_relays_for_every_family():
    """benchmarks/uncertainty.py on its 10 seeds at 0.3 px noise: the predicted error of each
    coordinate covers its actual error within 2 sigma at >= 85 % of the field points on
    average, inside and outside the hull, for every model and landmark layout; and at no
    more than 99 % (not conservative) for the issue's cases: paper, bc+rotation and relay
    (with and without the priors), landmarks over the field and central
    (docs/benchmarks.md has the 10-seed table)."""
    spec = importlib.util.spec_from_file_location("uncertainty_bench", REPO / "benchmarks" / "uncertainty.py")
    import sys

    sys.path.insert(0, str(REPO / "benchmarks"))
    try:
        bench = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(bench)
        grid, field = bench.reference_grid(), bench.field_points()
        for scenario in bench.SCENARIOS:
            for model in bench.MODELS:
                rows = [bench.run_case(s, scenario, model, 0.3, 250, grid, field) for s in range(10)]
                for region in ("in", "out"):
                    share = np.nanmean([r[f"xy_{region}_2"] for r in rows])
                    assert share >= 0.85, (scenario, model, region, share)
                    if scenario != "few central":
                        assert share <= 0.99, (scenario, model, region, share)
    finally:
        sys.path.remove(str(REPO / "benchmarks"))
