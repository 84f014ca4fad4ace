"""The calibration as a value and the rules the library owns (issue 23): the family carried
by name, one fit record, the two AICc named for what they score, the refusal of a fit that
gives no usable model for every front-end, one entry point for Eq. (1) and the relay."""

import dataclasses

import numpy as np
import pytest

import oapcal
from oapcal.calibration import (
    Calibration,
    FitSummary,
    UnusableFitError,
    calibrate,
    check_fit_usable,
)
from oapcal.errors import DataError, ModelSpecError
from oapcal.fitting import DEFAULT_INIT, fit, fit_batch
from oapcal.model import BROWN_CONRADY, BROWN_CONRADY_POSE, PARAM_NAMES, Model, distort, params_from_dict
from oapcal.select import FRAME_TERMS, select_models, with_frame_terms
from oapcal.synthetic import synthetic_pairs

INDEX = {n: i for i, n in enumerate(PARAM_NAMES)}


@pytest.fixture(scope="module")
def data():
    return synthetic_pairs(seed=0)


@pytest.fixture(scope="module")
def cal(data):
    return calibrate(data.xy_u, data.xy_d, "paper", image_size=(640, 480), error_model=False)


# -- the family by name and the model as a value ------------------------------------------------


def test_calibration_carries_its_family_and_gives_its_model(cal, data):
    assert cal.family is BROWN_CONRADY and cal.model_family == "brown-conrady"
    model = cal.model
    assert isinstance(model, Model) and model.free == cal.free
    np.testing.assert_array_equal(model.params, cal.params)
    np.testing.assert_array_equal(model(data.xy_u), distort(data.xy_u, cal.params))


def test_family_given_by_name_is_kept_and_checked(cal):
    fields = {f.name: getattr(cal, f.name) for f in dataclasses.fields(cal)}
    # an old caller without the family: the family of the vector's length, as before
    old = Calibration(**{**fields, "family": None})
    assert old.family is BROWN_CONRADY
    turned = Calibration(
        **{**fields, "params": np.append(cal.params, 5.0), "family": "brown-conrady+rotation"}
    )
    assert turned.family is BROWN_CONRADY_POSE and turned.model.value("rotation") == 5.0
    with pytest.raises(ModelSpecError, match="brown-conrady\\+rotation calibration has 14 parameters"):
        Calibration(**{**fields, "family": "brown-conrady+rotation"})
    with pytest.raises(ModelSpecError, match="unknown model family 'nope'"):
        Calibration(**{**fields, "family": "nope"})


def test_fit_result_carries_the_family_fit_batch_was_given(data):
    mask = np.zeros((1, 14), bool)
    mask[0, [INDEX["k1"], INDEX["m"], 13]] = True
    p0 = np.append(params_from_dict({"m": 1.0}), 0.0)[None]
    batch = fit_batch(data.xy_u, data.xy_d, mask, p0, family=BROWN_CONRADY_POSE)
    assert batch.family is BROWN_CONRADY_POSE and batch.item(0).family is BROWN_CONRADY_POSE
    assert fit(data.xy_u, data.xy_d, "paper").model.family is BROWN_CONRADY


# -- one fit record --------------------------------------------------------------------------


def test_fit_summary_is_made_from_the_fit_result_and_round_trips(data, cal):
    result = fit(data.xy_u, data.xy_d, "paper")
    summary = FitSummary.from_result(result, n_points=len(data.xy_u), init="auto")
    assert (summary.rss, summary.aicc, summary.k, summary.n_residuals) == (
        result.rss, result.aicc, result.k, result.n,
    )  # fmt: skip
    d = cal.fit.to_dict()
    assert d["aicc"] == d["aicc_forward"] == cal.fit.aicc and d["aicc_corrected"] == cal.fit.aicc_corrected
    assert FitSummary.from_dict(d) == cal.fit
    # a file written before the two names: aicc read as before, aicc_corrected unknown
    old = {k: v for k, v in d.items() if k not in ("aicc_forward", "aicc_corrected")}
    assert FitSummary.from_dict(old).aicc_forward == cal.fit.aicc
    assert FitSummary.from_dict(old).aicc_corrected is None


def test_calibration_file_holds_both_aicc(cal, tmp_path):
    from oapcal.io.calibration import calibration_to_dict, load_calibration, save_calibration

    fit_object = calibration_to_dict(cal)["fit"]
    assert {"aicc", "aicc_forward", "aicc_corrected"} <= set(fit_object)
    save_calibration(cal, tmp_path / "c.json")
    back = load_calibration(tmp_path / "c.json")
    assert back.fit == cal.fit and back.model_family == cal.model_family


# -- the two AICc ------------------------------------------------------------------------------


def test_the_two_aicc_are_named_for_what_they_score(data):
    """For the same model and points, the calibration's aicc_corrected is the selection's
    AICc and its aicc_forward (= aicc) the forward one; the two differ."""
    cal = calibrate(data.xy_u, data.xy_d, "paper", rotation="none", error_model=False)
    mask = np.array([n in cal.free for n in PARAM_NAMES])
    score = select_models(data.xy_u, data.xy_d, masks=[mask]).best
    assert score.free == cal.free
    assert cal.fit.aicc_corrected == pytest.approx(score.aicc_corrected, rel=1e-9)
    assert cal.fit.aicc_forward == pytest.approx(score.aicc_forward, rel=1e-9)
    assert cal.fit.aicc_forward == cal.fit.aicc and score.aicc_corrected == score.aicc
    assert abs(cal.fit.aicc_forward - cal.fit.aicc_corrected) > 1.0


def test_selection_json_has_both_aicc_and_old_files_still_load(data):
    from oapcal.io.results import selection_from_dict, selection_to_dict

    sel = select_models(data.xy_u, data.xy_d, masks=[[True] * 13])
    d = selection_to_dict(sel)
    m = d["models"][0]
    assert m["aicc"] == m["aicc_corrected"] and m["aicc_forward"] == sel.best.aicc_forward
    assert selection_from_dict(d) == sel
    old = {**d, "models": [{k: v for k, v in m.items() if k not in ("aicc_forward", "aicc_corrected")}]}
    back = selection_from_dict(old)
    assert back.best.aicc == sel.best.aicc and np.isnan(back.best.aicc_forward)


# -- the rules, in the library --------------------------------------------------------------------


def test_grid_normalization_is_refused_instead_of_a_map_of_1e7_px(data):
    # before: calibrate(normalization="grid") gave a model in the grid's units, and a
    # 640 x 480 correction map built from it had map_x up to 2.7e7
    with pytest.raises(DataError, match="normalization 'grid' rescales the distorted points") as info:
        calibrate(data.xy_u, data.xy_d, "paper", normalization="grid")
    assert info.value.param == "normalization"


def _barrel():
    gx, gy = np.meshgrid(np.linspace(0, 639, 12), np.linspace(0, 479, 9))
    xy_u = np.stack([gx.ravel(), gy.ravel()], -1)
    truth = params_from_dict({"k1": -2e-7, "x_off": -320, "y_off": -240, "c_x": 320, "c_y": 240, "m": 1})
    return xy_u, distort(xy_u, truth)


def test_a_fit_that_folds_over_on_its_image_is_refused_by_calibrate():
    xy_u, xy_d = _barrel()
    calibrate(xy_u, xy_d, "paper", image_size=(640, 480), error_model=False)  # usable there
    with pytest.raises(UnusableFitError, match=r"p\.csv: the model folds over .* 4000x4000 px image") as info:
        calibrate(xy_u, xy_d, "paper", image_size=(4000, 4000), source="p.csv", error_model=False)
    assert info.value.code == "region" and isinstance(info.value, DataError)
    raw = calibrate(xy_u, xy_d, "paper", image_size=(4000, 4000), error_model=False, check=False)
    with pytest.raises(UnusableFitError):
        check_fit_usable(raw)


def test_non_finite_and_negative_m_fits_are_refused(cal, data):
    broken = dataclasses.replace(cal, params=np.where(np.arange(13) == 0, np.inf, cal.params))
    with pytest.raises(UnusableFitError, match="x.csv: the fit gave non-finite parameters") as info:
        check_fit_usable(broken, "x.csv")
    assert info.value.code == "non_finite" and "fit a smaller model" in str(info.value)
    turned = -(data.xy_u - [320, 240]) + [320, 240]
    plain = calibrate(turned, data.xy_d, "paper", rotation="none", error_model=False)  # as given: m < 0
    assert plain.params[INDEX["m"]] < 0
    with pytest.raises(UnusableFitError, match="m = -1.01 <= 0") as info:
        check_fit_usable(plain)
    assert info.value.code == "negative_m" and info.value.param == "rotation"


# -- selection plus the frame terms; one default start ----------------------------------------------


def test_with_frame_terms_adds_the_frame_in_eq1_order(data):
    assert with_frame_terms(("m", "k1")) == ("k1", "x_off", "y_off", "c_x", "c_y", "m")
    sel = select_models(data.xy_u, data.xy_d, masks=[[n in ("k1", "m") for n in PARAM_NAMES]])
    assert with_frame_terms(sel) == with_frame_terms(sel.best) == with_frame_terms(sel.best.free)
    assert set(FRAME_TERMS) <= set(with_frame_terms(sel))


def test_one_default_start_everywhere():
    import inspect

    from oapcal.cli.fit import fit_command
    from oapcal.cli.select import robustness_command, select_command
    from oapcal.select import cross_validate, score_models
    from oapcal.subsampling import robustness

    for func in (calibrate, fit, select_models, score_models, cross_validate, robustness):
        assert inspect.signature(func).parameters["init"].default == DEFAULT_INIT, func.__name__
    for command in (fit_command, select_command, robustness_command):
        (init,) = [p for p in command.params if p.name == "init"]
        assert init.default == DEFAULT_INIT, command.name


# -- one entry point -------------------------------------------------------------------------------


def test_the_entry_point_is_calibrate_for_eq1(data, cal):
    assert oapcal.calibrate.__module__ == "oapcal.entry"
    same = oapcal.calibrate(data.xy_u, data.xy_d, "paper", image_size=(640, 480), error_model=False)
    np.testing.assert_array_equal(same.params, cal.params)
    assert same.fit == cal.fit


def test_the_entry_point_takes_a_relay_design_or_spec():
    from oapcal.model import RELAY
    from oapcal.optics.relay_model import RelayDesign, calibrate_relay, relay_params
    from relay_helpers import IMAGE_SIZE, TRUE_MISALIGNMENT, TRUE_POSE

    rng = np.random.default_rng(7)
    design = RelayDesign(setup=1, pixel_size_um=4.8, centre=(319.5, 239.5))
    truth = relay_params(design, TRUE_MISALIGNMENT, TRUE_POSE)
    xy_u = np.column_stack([rng.uniform(160, 480, 100), rng.uniform(120, 360, 100)])
    xy_d = distort(xy_u, truth, family=RELAY) + rng.normal(0, 0.05, (100, 2))
    via_entry = oapcal.calibrate(xy_u, xy_d, "relay:tilt2,d1", design=design, image_size=IMAGE_SIZE,
                                 error_model=False)  # fmt: skip
    direct = calibrate_relay(xy_u, xy_d, design, "relay:tilt2,d1", image_size=IMAGE_SIZE, error_model=False)
    np.testing.assert_array_equal(via_entry.params, direct.params)
    assert via_entry.family is RELAY and via_entry.relay_design == design.to_dict()
    with pytest.raises(ModelSpecError, match="give its nominal design") as info:
        oapcal.calibrate(xy_u, xy_d, "relay")
    assert info.value.param == "design"
    with pytest.raises(ModelSpecError, match="priors apply to a relay model"):
        oapcal.calibrate(xy_u, xy_d, "paper", priors="default")


def test_the_cli_tables_label_both_aicc(run_cli, data, tmp_path):
    from oapcal.io.points import write_point_pairs

    points = tmp_path / "p.csv"
    write_point_pairs(points, data.xy_u, data.xy_d)
    code, out, err = run_cli("fit", points, "--model", "paper")
    assert code == 0, err
    assert "AICc -1261.44 (forward residuals; -1297.83 after correction" in " ".join(out.split())
    code, out, err = run_cli("select", points, "--top", "3")
    assert code == 0, err
    assert "AICc corrected" in out and "AICc forward" in out
