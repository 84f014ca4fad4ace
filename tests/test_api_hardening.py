"""Hostile values to the public API (issue 24, item 16): every one raises an
:class:`~oapcal.errors.OapcalError` naming the parameter, never NumPy's, SciPy's or
OpenCV's own exception, and writes nothing."""

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import oapcal
from oapcal.errors import DataError, ModelSpecError, OapcalError
from oapcal.model import all_masks, identity_params, mask_from_bits
from oapcal.synthetic import synthetic_pairs

DATA = synthetic_pairs(n_x=6, n_y=5, seed=3)


def _refused(call, param, *words):
    """``call()`` raises an OapcalError whose ``param`` is ``param`` and whose message has ``words``."""
    with pytest.raises(OapcalError) as info:
        call()
    err = info.value
    assert err.param == param or (isinstance(err.param, tuple) and param in err.param), (err.param, str(err))
    for w in words:
        assert w in str(err), str(err)
    assert "\n" not in str(err)
    return err


# -- points: to calibrate, select_models, robustness, write_point_pairs ---------------------------

BAD = st.sampled_from([np.nan, np.inf, -np.inf])


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(which=st.sampled_from(["xy_u", "xy_d"]), row=st.integers(0, len(DATA.xy_u) - 1), col=st.integers(0, 1),
       value=BAD)  # fmt: skip
def test_a_non_finite_coordinate_anywhere_is_refused_by_every_entry(which, row, col, value):
    u, d = DATA.xy_u.copy(), DATA.xy_d.copy()
    (u if which == "xy_u" else d)[row, col] = value
    for call in (
        lambda: oapcal.calibrate(u, d, "paper"),
        lambda: oapcal.select_models(u, d, masks=all_masks()[:2]),
        lambda: oapcal.robustness(u, d, ["paper"], trials=2),
    ):
        _refused(call, which, f"point {row} is not finite")


@pytest.mark.parametrize(
    "u,d,param,words",
    [
        (DATA.xy_u[:, :1], DATA.xy_d, "xy_u", ["(N, 2)", "(30, 1)"]),
        (DATA.xy_u, DATA.xy_d[None], "xy_d", ["(N, 2)", "(1, 30, 2)"]),
        (DATA.xy_u[:-1], DATA.xy_d, "xy_u", ["29 points", "xy_d has 30"]),
        ("abc", DATA.xy_d, "xy_u", ["numbers"]),
        ([[1, 2], [3]], DATA.xy_d, "xy_u", ["numbers"]),
        (None, DATA.xy_d, "xy_u", ["(N, 2)", "shape ()"]),
    ],
)
def test_points_of_the_wrong_shape_or_kind_are_refused(u, d, param, words, tmp_path):
    _refused(lambda: oapcal.calibrate(u, d, "paper"), param, *words)
    _refused(lambda: oapcal.write_point_pairs(tmp_path / "p.csv", u, d), param, *words)
    assert list(tmp_path.iterdir()) == []


def test_write_point_pairs_refuses_ids_of_another_length_and_nan_before_writing(tmp_path):
    out = tmp_path / "p.csv"
    _refused(
        lambda: oapcal.write_point_pairs(out, DATA.xy_u, DATA.xy_d, ids=["a"]),
        "ids",
        "1 entries",
        "30 points",
    )
    _refused(lambda: oapcal.write_point_pairs(out, DATA.xy_u, DATA.xy_d, ids="abc"), "ids", "sequence")
    u = DATA.xy_u.copy()
    u[4, 1] = np.nan
    _refused(lambda: oapcal.write_point_pairs(out, u, DATA.xy_d), "xy_u", "point 4")
    assert list(tmp_path.iterdir()) == []
    oapcal.write_point_pairs(out, DATA.xy_u, DATA.xy_d, ids=[f"P{i}" for i in range(30)])
    back = oapcal.read_points(out)  # and what it writes reads back
    np.testing.assert_array_equal(back.xy_d, DATA.xy_d)


# -- images to correct_image ----------------------------------------------------------------------


@pytest.fixture(scope="module")
def cmap():
    return oapcal.correction_map(identity_params(), (6, 8))


@pytest.mark.parametrize(
    "image,words",
    [
        (np.array(3.0), ["shape ()"]),
        (np.zeros(5, np.float32), ["shape (5,)"]),
        (np.zeros((0, 8), np.uint8), ["no pixels"]),
        ("img.tif", ["not str"]),
        (b"II*\x00", ["not bytes"]),
        (None, ["not NoneType"]),
        (np.zeros((6, 8), bool), ["pixel type bool"]),
        (np.zeros((6, 8), np.int32), ["pixel type int32"]),
        (np.zeros((6, 8), np.float16), ["pixel type float16"]),
        (np.zeros((6, 8), complex), ["pixel type complex128"]),
        (np.zeros((6, 8), object), ["pixel type object"]),
        ([[1, 2], [3]], ["array of pixels"]),
    ],
)
def test_correct_image_refuses_what_is_not_an_image_it_can_correct(image, words, cmap):
    _refused(lambda: oapcal.correct_image(image, cmap), "image", *words)


@pytest.mark.parametrize("dtype", ["uint8", "uint16", "int16", "float32", "float64"])
def test_correct_image_keeps_every_pixel_type_it_names(dtype, cmap):
    image = (np.arange(48).reshape(6, 8) % 7).astype(dtype)
    out = oapcal.correct_image(image, cmap, "nearest")
    assert out.dtype == image.dtype
    np.testing.assert_array_equal(out, image)  # the identity map


# -- masks, seeds and trials ----------------------------------------------------------------------


@pytest.mark.parametrize(
    "masks,words",
    [
        ([5], ["shape (1,)"]),
        (np.zeros((2, 2), int), ["shape (2, 2)"]),
        ([], ["shape (0,)"]),
        (np.zeros((0, 13), bool), ["shape (0, 13)"]),
        ("abc", ["shape ()"]),
        (np.full((1, 13), 2), ["other than True/False"]),
        (np.full((1, 13), 0.5), ["other than True/False"]),
        (np.array([["k1"] * 13]), ["other than True/False"]),
        (np.zeros((3, 13), bool), ["row 0 fixes m"]),
    ],
)
def test_select_models_refuses_masks_that_are_not_models(masks, words):
    err = _refused(lambda: oapcal.select_models(DATA.xy_u, DATA.xy_d, masks=masks), "masks", *words)
    assert isinstance(err, ModelSpecError)


def test_select_models_takes_a_single_mask_and_0_1_masks():
    one = mask_from_bits(np.array([1]))[0]  # k1 and m
    a = oapcal.select_models(DATA.xy_u, DATA.xy_d, masks=one)
    b = oapcal.select_models(DATA.xy_u, DATA.xy_d, masks=one.astype(int)[None])
    assert len(a.models) == len(b.models) == 1 and a.models[0].free == b.models[0].free == ("k1", "m")


@pytest.mark.parametrize("seed", [-1, 2**63, 1.5, "0", True, None])
def test_seeds_outside_0_to_2_63_or_not_whole_are_refused(seed):
    _refused(
        lambda: oapcal.robustness(DATA.xy_u, DATA.xy_d, ["paper"], trials=2, seed=seed),
        "seed",
        "0 to 2**63 - 1",
    )
    _refused(lambda: oapcal.select_models(DATA.xy_u, DATA.xy_d, masks=[True] * 13, cv=2, seed=seed), "seed")


@pytest.mark.parametrize("trials,words", [(0, ["from 1"]), (10**12, ["10,000,000"]), (1.5, ["whole number"])])
def test_robustness_refuses_trial_counts_out_of_range(trials, words):
    _refused(lambda: oapcal.robustness(DATA.xy_u, DATA.xy_d, ["paper"], trials=trials), "trials", *words)


def test_robustness_estimates_its_memory_before_any_work():
    from oapcal.subsampling import robustness_bytes

    many = np.random.default_rng(0).uniform(0, 100, (5000, 2))  # 5,000 points x 10 million trials
    assert robustness_bytes(10**7, 5000, 1) > 4 * 2**30
    err = _refused(
        lambda: oapcal.robustness(many, many * 1.01, ["paper"], trials=10**7), "trials", "GiB", "limit"
    )
    assert isinstance(err, DataError) and "fewer trials" in str(err)


def test_the_command_line_keeps_the_librarys_trial_limits():
    from oapcal import subsampling
    from oapcal.cli import select as cli_select

    assert cli_select.MAX_TRIALS == subsampling.MAX_TRIALS
    assert cli_select.BYTES_PER_TRIAL_POINT == subsampling.BYTES_PER_TRIAL_POINT
    assert cli_select.BYTES_PER_TRIAL_MODEL == subsampling.BYTES_PER_TRIAL_MODEL


@pytest.mark.parametrize("spec", [5, 1.5, None, object()])
def test_parse_model_of_a_non_spec_is_a_named_error(spec):
    from oapcal.errors import ModelSpecError
    from oapcal.model import parse_model

    with pytest.raises(ModelSpecError, match="a model specification is a preset"):
        parse_model(spec)


def test_fit_refuses_non_finite_points_by_name():
    from oapcal.errors import DataError
    from oapcal.fitting import fit

    xy = np.random.default_rng(0).uniform(0, 100, (30, 2))
    bad = xy.copy()
    bad[3, 1] = np.inf
    with pytest.raises(DataError, match="not finite"):
        fit(xy, bad, "paper")
