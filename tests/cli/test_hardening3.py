"""Hardening, round three (issue 24): group texts, tolerance and ESF limits checked before
any work, and messages that say what is wrong.  Every failure is one line on stderr, exit 2,
nothing written."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from oapcal.errors import DataError
from oapcal.imaging.usaf import HIGHEST_GROUP, LOWEST_GROUP, parse_groups


def one_error(code, err, expect_code=2):
    assert code == expect_code, err
    assert err.startswith("oapcal: error: ") and err.count("\n") == 1, repr(err)
    assert "internal error" not in err


# -- item 14 and 24: group texts --------------------------------------------------------------------

GROUP = st.integers(LOWEST_GROUP, HIGHEST_GROUP)
GROUPS_TILT = ("m1_tilt_x", "m1_tilt_y", "m2_tilt_x", "m2_tilt_y")


@settings(max_examples=200, deadline=None)
@given(st.lists(st.tuples(GROUP, GROUP), min_size=1, max_size=4))
def test_group_ranges_written_low_to_high_give_their_groups(ranges):
    ranges = [(min(a, b), max(a, b)) for a, b in ranges]
    expected = [g for lo, hi in ranges for g in range(lo, hi + 1)]
    text = ",".join(f"{lo}-{hi}" if lo != hi else f"{lo}" for lo, hi in ranges)
    if len(set(expected)) != len(expected):
        with pytest.raises(DataError, match="listed twice"):
            parse_groups(text)
    else:
        assert parse_groups(text) == tuple(sorted(expected))


@settings(max_examples=300, deadline=None)
@given(st.text(alphabet=st.sampled_from("0123456789-, _\u0664\uff14e+.x"), max_size=30) | st.text(max_size=9))
def test_any_group_text_is_groups_or_one_line_naming_groups(text):
    try:
        groups = parse_groups(text)
    except DataError as exc:
        assert exc.param == "groups" and "\n" not in str(exc)
        return
    assert groups == tuple(sorted(set(groups))) and all(LOWEST_GROUP <= g <= HIGHEST_GROUP for g in groups)
    assert all(c in "0123456789-, " or c.isspace() for c in text)  # ASCII digits only


@pytest.mark.parametrize(
    "text,words",
    [
        ("4-99999999999999999999", ["-2 to 9", "not 99999999999999999999"]),
        ("4-" + "9" * 5000, ["-2 to 9"]),
        ("9-3", ["reversed", "3-9"]),
        ("4_5", ["not a group range"]),
        ("\u0664-\u0665", ["not a group range"]),  # Arabic-Indic 4-5
        ("", ["no group given"]),
    ],
)
def test_group_texts_that_are_refused(text, words):
    with pytest.raises(DataError) as info:
        parse_groups(text)
    for w in words:
        assert w in str(info.value)


@pytest.mark.parametrize("groups", ["4-99999999999999999999", "9-3"])
def test_detect_refuses_such_groups_in_one_line_before_reading_the_image(run_cli, tmp_path, groups):
    out = tmp_path / "p.csv"
    args = ("--groups", groups, "--um-per-px", "4.8", "--out", out)
    code, _, err = run_cli("detect", tmp_path / "missing.png", *args)
    one_error(code, err)
    assert "--groups" in err and not out.exists()


# -- item 8 and 21: the Monte Carlo of tolerance, checked before work and streamed -------------------


@pytest.fixture(scope="module")
def small_tolerancing():
    from oapcal.optics.relay import oap_relay
    from oapcal.optics.tolerance import Tolerancing

    return Tolerancing(oap_relay(1), n=41)


def test_the_monte_carlo_is_streamed_in_blocks_with_the_same_numbers(small_tolerancing, monkeypatch):
    import tracemalloc

    from oapcal.optics import tolerance

    tol = {"m1_tilt_x": 0.02, "m2_decentre_y": 0.05}
    whole = small_tolerancing.monte_carlo(tol, 40, seed=3)
    monkeypatch.setattr(tolerance, "monte_carlo_block", lambda n: 7)  # 40 = 5 x 7 + 5
    blocks = small_tolerancing.monte_carlo(tol, 40, seed=3)
    assert blocks == whole

    def peak(trials):
        tracemalloc.start()
        small_tolerancing.monte_carlo(tol, trials, seed=1)
        top = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        return top

    # 100 more trials keep their samples (~5 kB each) but not their traced grids (41 x 41 points,
    # 4 coordinates, 54 kB each: 5.4 MB if they were kept)
    growth = peak(150) - peak(50)
    assert growth < 2.5e6, growth


@pytest.mark.parametrize(
    "kwargs,param,words",
    [
        ({"trials": 0}, "trials", ["from 1 to 500,000"]),
        ({"trials": 1.5}, "trials", ["whole number"]),
        ({"trials": 10**7}, "trials", ["500,000"]),
        (
            {"trials": 500_000, "n": 201, "tolerances": dict.fromkeys(GROUPS_TILT, 0.01)},
            ("trials", "n"),
            ["GiB", "fewer trials or a smaller grid"],
        ),  # fmt: skip
        ({"tolerances": {"d1": 1e12}}, ("tolerances", "d1"), ["reaches -1e+12", "collimated path"]),
        ({"tolerances": {"d1": 500.0}, "distribution": "normal"}, ("tolerances", "d1"), ["reaches -1250"]),
    ],
)
def test_check_monte_carlo_refuses_before_any_tracing(kwargs, param, words):
    from oapcal.errors import GeometrySpecError
    from oapcal.optics.relay import oap_relay
    from oapcal.optics.tolerance import check_monte_carlo

    args = {"tolerances": {"m1_tilt_x": 0.01}, "trials": 100, "distribution": "uniform", "n": 17, **kwargs}
    with pytest.raises(GeometrySpecError) as info:
        check_monte_carlo(oap_relay(1), **args)
    assert info.value.param == param
    for w in words:
        assert w in str(info.value)


def test_check_monte_carlo_accepts_what_the_monte_carlo_runs():
    from oapcal.optics.relay import oap_relay
    from oapcal.optics.tolerance import MAX_TRIALS, check_monte_carlo, monte_carlo_bytes

    check_monte_carlo(oap_relay(1), {"d1": 500.0, "m1_tilt_x": 0.05}, 500)  # uniform: +-500 of 860 mm
    assert monte_carlo_bytes(MAX_TRIALS, 17, 1) < 4 * 2**30  # the limit is reachable


@pytest.mark.parametrize(
    "args,words",
    [
        (["--tol", "d1=1e12"], ["d1", "collimated path", "(set by --d1-error, --tol)"]),
        (["--focal-length-error", "1e5"], ["m1_focal_length", "(set by --focal-length-error, --tol)"]),
        (["--tilt", "0.1", "--trials", "2000000"], ["at most 500,000"]),
        (["--tilt", "0.1", "--trials", "500000", "--grid", "201"], ["GiB", "(set by --trials, --grid)"]),
        (["--pixel-size", "1e300"], ["--pixel-size"]),
        (["--pixel-size", "0"], ["--pixel-size"]),
        (["--field", "1e6"], ["--field"]),
    ],
)
def test_tolerance_refuses_in_one_line_before_tracing(run_cli, monkeypatch, args, words):
    from oapcal.optics import tolerance

    def no_work(*a, **k):
        raise AssertionError("the aligned relay was traced before the options were checked")

    monkeypatch.setattr(tolerance.Tolerancing, "__init__", no_work)
    code, out, err = run_cli("tolerance", *args)
    one_error(code, err)
    assert out == ""
    for w in words:
        assert w in err, err


# -- item 12: esf with many ROIs -----------------------------------------------------------------------


def _edge_image(rows=64, cols=64):
    from scipy.special import ndtr

    x = np.arange(cols)
    return (ndtr((x - cols / 2) / 1.5) * 200 + 20)[None, :].repeat(rows, 0).astype(np.uint8)


def test_analyse_edges_reports_progress_and_refuses_too_many_or_too_large_rois():
    from oapcal.imaging.esf import MAX_EDGES, MAX_ROI_PIXELS, analyse_edges

    img = _edge_image()
    calls = []
    summary = analyse_edges(img, [(22, 5, 42, 25), (22, 30, 42, 50)], progress=lambda *a: calls.append(a))
    assert calls == [(1, 2), (2, 2)] and len(summary.good) == 2
    with pytest.raises(DataError, match="more than 10,000 edges") as info:
        analyse_edges(img, [(22, 5, 42, 25)] * (MAX_EDGES + 1), progress=lambda *a: calls.append(a))
    assert info.value.param == "rois" and len(calls) == 2  # refused before any fit
    side = int(MAX_ROI_PIXELS**0.5) + 1
    with pytest.raises(DataError, match="more than 1,048,576"):
        analyse_edges(np.zeros((side + 1, side + 1), np.uint8), [(0, 0, side, side)])
    with pytest.raises(TypeError):
        analyse_edges(img, [(22, 5, 42, 25)], progress=True)


def test_esf_refuses_an_roi_file_over_the_limit_while_reading_it(run_cli, tmp_path):
    import cv2

    from oapcal.imaging.esf import MAX_EDGES

    cv2.imwrite(str(tmp_path / "edge.png"), _edge_image())
    rois = tmp_path / "rois.csv"
    rois.write_text("x0,y0,x1,y1\n" + "22,5,42,25\n" * 200_000)
    code, out, err = run_cli("esf", tmp_path / "edge.png", "--rois", rois)
    one_error(code, err)
    assert f"line {MAX_EDGES + 2}: more than 10,000 rectangles" in err and out == ""
    rois.write_text("x0,y0,x1,y1\n" + "22,5,42,25\n" * 3)  # and under it, the fits run
    code, out, err = run_cli("esf", tmp_path / "edge.png", "--rois", rois, "--json")
    assert code == 0 and '"n_ok": 3' in out, err


# -- item 24: Ctrl-C and termination are one line ----------------------------------------------------


@pytest.mark.parametrize("signum", [None, 15, 1])
def test_an_interrupt_is_one_line_and_its_exit_code(run_cli, monkeypatch, signum):
    from oapcal.cli import Terminated
    from oapcal.optics import tolerance

    def interrupt(*a, **k):
        raise KeyboardInterrupt if signum is None else Terminated(signum)

    monkeypatch.setattr(tolerance.Tolerancing, "__init__", interrupt)
    code, out, err = run_cli("tolerance", "--tilt", "0.01", "--trials", "10")
    assert code == (130 if signum is None else 128 + signum) and out == ""
    assert err.count("\n") == 1 and err.startswith("oapcal: "), repr(err)
    assert ("interrupted" if signum is None else f"signal {signum}") in err


# -- item 24: misleading texts -------------------------------------------------------------------------


def _pairs():
    from oapcal.synthetic import synthetic_pairs

    return synthetic_pairs(n_x=6, n_y=5, seed=3)


@pytest.mark.parametrize("bad", ["NaN", "Infinity", "-Infinity"])
@pytest.mark.parametrize("which", [2, 4, 7])  # moving x, moving z, fixed z of a 3-D row
def test_a_bigwarp_row_with_one_coordinate_missing_is_named(run_cli, tmp_path, bad, which):
    d = _pairs()
    rows = []
    for i, (u, dd) in enumerate(zip(d.xy_u.tolist(), d.xy_d.tolist())):
        cells = [f"Pt-{i}", "true", repr(dd[0]), repr(dd[1]), "3.0", repr(u[0]), repr(u[1]), "5.0"]
        if i >= 1:  # every row but the first: one coordinate missing, the others numbers
            cells[which] = bad
        rows.append(",".join(f'"{c}"' for c in cells))
    path = tmp_path / "bw.csv"
    path.write_text("\n".join(rows) + "\n")
    code, _, err = run_cli("fit", "--distorted", path)
    one_error(code, err)
    side, ax = ("moving", "xyz"[which - 2]) if which < 5 else ("fixed", "xyz"[which - 5])
    assert f"line 2: landmark 'Pt-1' has {side} {ax} = '{bad}'" in err
    assert "spread over only" not in err


def test_a_single_usable_pair_says_so_not_zero_spread(run_cli, tmp_path):
    rows = ['"Pt-0","true","NaN","NaN","Infinity","Infinity"', '"Pt-1","true","3","4","6","7"']
    path = tmp_path / "bw.csv"
    path.write_text("\n".join(rows) + "\n")
    code, _, err = run_cli("fit", "--distorted", path)
    one_error(code, err)
    assert "only one paired reference landmark point" in err and "0 x 0" not in err


@pytest.mark.parametrize("value", [{"a": {"b": 1}}, None, [1, 2]])
def test_a_via_attribute_that_is_not_text_is_named(run_cli, tmp_path, value):
    from landmark_writers import via2_json

    d = _pairs()
    cam = [(float(x), float(y), {"corner": str(i)}) for i, (x, y) in enumerate(d.xy_d)]
    cam[3] = (cam[3][0], cam[3][1], {"corner": value})
    ref = [(float(x), float(y), {"corner": str(i)}) for i, (x, y) in enumerate(d.xy_u)]
    via2_json(tmp_path / "cam.json", {"cam.png": cam})
    via2_json(tmp_path / "ref.json", {"ref.png": ref})
    args = ("--distorted", tmp_path / "cam.json", "--reference", tmp_path / "ref.json", "--pair-by", "corner")
    code, _, err = run_cli("fit", *args)
    one_error(code, err)
    kind = {dict: "an object", type(None): "null", list: "a list"}[type(value)]
    assert f"region 3: attribute 'corner' is {kind}" in err and "it has: none" not in err


@pytest.mark.parametrize("shape", [(2, 0, 0), (2, 5, 0), (2, 0, 5)])
def test_an_empty_correction_map_is_refused_on_load(tmp_path, shape):
    from oapcal.errors import InputFileError
    from oapcal.io.maps import load_map

    np.save(tmp_path / "m.npy", np.zeros(shape, np.float32))
    np.savez(tmp_path / "m.npz", map_x=np.zeros(shape[1:], np.float32), map_y=np.zeros(shape[1:], np.float32))
    for name in ("m.npy", "m.npz"):
        with pytest.raises(InputFileError, match="it has no pixels") as info:
            load_map(tmp_path / name)
        assert "Assertion" not in str(info.value)


def test_export_opencv_of_a_relay_estimates_its_memory_and_names_the_image_size(run_cli, tmp_path):
    from relay_helpers import write_relay_calibration

    calib = write_relay_calibration(tmp_path / "relay.json")
    out = tmp_path / "cv.json"
    code, _, err = run_cli("export-opencv", calib, "--image-size", "16384x16384", "--out", out)
    one_error(code, err)
    assert "12 GiB" in err and "(set by --image-size" in err and not out.exists()
    # an image far larger than the relay's field, under the memory limit: the image size, not the extent
    code, _, err = run_cli("export-opencv", calib, "--image-size", "100000x40", "--out", out)
    one_error(code, err)
    assert "samples no pixel" in err and "made for 640x480 px" in err and "extent" not in err
    assert not out.exists()
