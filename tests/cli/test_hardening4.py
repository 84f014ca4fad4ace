"""Hardening, round three (issue 24), the last items: a camera placed behind the second
mirror (A7), a traced grid too large to hold (C16), relay design errors that name their
flag or their file's field (D21).  Every failure is one line on stderr, exit 2."""

import json

import pytest

from oapcal.errors import DataError, GeometrySpecError
from oapcal.optics.relay import oap_relay


def one_error(code, err, expect_code=2):
    assert code == expect_code, err
    assert err.startswith("oapcal: error: ") and err.count("\n") == 1, repr(err)
    assert "internal error" not in err


# -- A7: an image plane at or behind the second mirror ----------------------------------------------


@pytest.mark.parametrize("f2", [None, 25.0, 100.0])
@pytest.mark.parametrize("beyond", [0.0, 1e-9, 0.5, 49.0, 1e6])
def test_a_defocus_that_puts_the_camera_behind_the_second_mirror_is_refused(f2, beyond):
    focus = 50.8 if f2 is None else f2  # the camera sits at the second mirror's focus
    with pytest.raises(GeometrySpecError, match="behind the second mirror"):
        oap_relay(1, focal_length_2_mm=f2, misalignment={"camera_defocus": -focus - beyond})


@pytest.mark.parametrize("f2", [None, 100.0])
def test_a_defocus_that_keeps_the_camera_after_the_mirror_is_traced(f2):
    focus = 50.8 if f2 is None else f2
    relay = oap_relay(1, focal_length_2_mm=f2, misalignment={"camera_defocus": -0.9 * focus})
    assert relay.misalignment.camera_defocus == pytest.approx(-0.9 * focus)


def test_simulate_relay_refuses_a_camera_behind_the_mirror_in_one_line(run_cli, tmp_path):
    out = tmp_path / "grid.csv"
    code, _, err = run_cli("simulate", "relay", "--camera-defocus", "-100", "--out", str(out))
    one_error(code, err)
    assert "-100 mm" in err and "above -50.8 mm" in err, err
    assert not out.exists()


# -- C16: relay_distortion with a grid it cannot hold or that is not a number -----------------------


@pytest.mark.parametrize(
    "grid, error, words",
    [
        (10**6, DataError, "over the 4 GiB limit"),
        (10**5, DataError, "smaller grid"),
        (2**70, DataError, "smaller grid"),
        (97.0, DataError, "whole number"),
        ("97", DataError, "whole number"),
        (True, DataError, "whole number"),
        (7, GeometrySpecError, "at least 8 nodes"),
        (-(2**80), DataError, "whole number from"),
    ],
)
def test_relay_distortion_refuses_a_grid_before_tracing(grid, error, words):
    from oapcal.optics import relay_distortion

    with pytest.raises(error, match=words):
        relay_distortion(1, grid=grid)


# -- D21: relay design errors name the flag or the file's field -------------------------------------


@pytest.fixture(scope="module")
def relay_files(tmp_path_factory):
    from click.testing import CliRunner

    from oapcal.cli import cli

    d = tmp_path_factory.mktemp("d21")
    runner = CliRunner()
    for args in (["simulate", "relay", "--units", "px", "--out", str(d / "grid.csv")],
                 ["fit", str(d / "grid.csv"), "--model", "relay", "--out", str(d / "cal.json")]):  # fmt: skip
        result = runner.invoke(cli, args)
        assert result.exit_code == 0, result.output
    return d


@pytest.mark.parametrize(
    "args, flag",
    [
        (["--focal-length", "1e-10"], "--focal-length"),
        (["--d1", "0.001"], "--d1"),
        (["--relay-centre", "1e308,1e308"], "--relay-centre"),
    ],
)
def test_a_relay_design_from_options_that_images_nothing_names_its_flags(run_cli, relay_files, args, flag):
    out = relay_files / "never.json"
    code, _, err = run_cli("fit", str(relay_files / "grid.csv"), "--model", "relay", *args, "--out", str(out))
    one_error(code, err)
    assert "(set by " in err and flag in err.split("(set by ")[-1], err
    assert not out.exists()


@pytest.mark.parametrize(
    "field, value, named",
    [("focal_length_mm", 1e-10, "relay_design"), ("focal_length_2_mm", 1e-12, "params.f2_mm")],
)
def test_a_calibration_whose_relay_design_images_nothing_names_the_file_and_field(
    run_cli, relay_files, field, value, named
):
    data = json.loads((relay_files / "cal.json").read_text())
    data["relay_design"][field] = value
    bad = relay_files / f"bad_{field}.json"
    bad.write_text(json.dumps(data))
    out = relay_files / "corrected.csv"
    code, _, err = run_cli("correct-points", str(bad), "--distorted", str(relay_files / "grid.csv"),
                           "--out", str(out))  # fmt: skip
    one_error(code, err)
    assert f"{bad.name}: field '{named}'" in err, err
    assert not out.exists()


# -- B-class: a local Dask cluster of more workers than the machine can hold ------------------------


def test_dask_refuses_a_local_cluster_of_thousands_of_workers(run_cli, tmp_path):
    pytest.importorskip("distributed", reason="the dask extra is not installed")
    import numpy as np
    import tifffile

    from oapcal.batch.distributed import max_local_workers
    from oapcal.calibration import calibrate
    from oapcal.io.calibration import save_calibration
    from oapcal.model import distort
    from oapcal.synthetic import EXAMPLE_TRUTH

    rng = np.random.default_rng(1)
    xy_u = rng.uniform((20, 20), (620, 460), (80, 2))
    save_calibration(calibrate(xy_u, distort(xy_u, EXAMPLE_TRUTH), "paper", rotation="none",
                               image_size=(640, 480)), tmp_path / "cal.json")  # fmt: skip
    tifffile.imwrite(tmp_path / "s.tif", np.zeros((2, 480, 640), np.uint8))
    n = max_local_workers() + 1
    code, _, err = run_cli("correct", tmp_path / "cal.json", tmp_path / "s.tif", "--out-dir", tmp_path / "o",
                           "--dask", "--workers", n, "--quiet")  # fmt: skip
    assert code != 0 and f"at most {n - 1} workers" in err and "--workers" in err, err
    assert "Traceback" not in err


# -- C16, fresh values: public calls that took nonsense or raised raw exceptions --------------------


@pytest.mark.parametrize(
    "kwargs, words",
    [
        ({"um_per_px": -1}, "um_per_px must be a positive finite number"),
        ({"um_per_px": float("nan")}, "um_per_px must be a positive finite number"),
        ({"um_per_px": "4.8"}, "um_per_px must be a positive number"),
        ({"image_size": (0, 0)}, "image_size width must be a whole number from 1"),
        ({"image_size": (640,)}, "image_size must be \\(width, height\\)"),
        ({"image_size": (640.5, 480)}, "whole number"),
    ],
)
def test_calibrate_refuses_a_scale_or_image_size_that_is_not_one(kwargs, words):
    import numpy as np

    from oapcal.calibration import calibrate
    from oapcal.model import distort
    from oapcal.synthetic import EXAMPLE_TRUTH

    xy_u = np.random.default_rng(0).uniform(0, 600, (40, 2))
    with pytest.raises(DataError, match=words):
        calibrate(xy_u, distort(xy_u, EXAMPLE_TRUTH), "paper", rotation="none", error_model=False, **kwargs)


@pytest.mark.parametrize("xy", ["abc", [["a", "b"]], object()])
def test_distort_of_points_that_are_not_numbers_is_a_data_error(xy):
    from oapcal.model import distort, identity_params

    with pytest.raises(DataError, match="points must be numbers"):
        distort(xy, identity_params())


def test_saving_a_calibration_onto_a_directory_names_it(tmp_path):
    import numpy as np

    from oapcal.calibration import calibrate
    from oapcal.errors import OutputError
    from oapcal.io.calibration import save_calibration

    xy = np.random.default_rng(0).uniform(0, 600, (30, 2))
    cal = calibrate(xy, xy, "paper", rotation="none", error_model=False)
    with pytest.raises(OutputError, match="is a directory; give the path of a file"):
        save_calibration(cal, tmp_path)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("spec", [{"k1": "no"}, {"k1": 0.0}, {"k1": None}])
def test_a_model_mapping_whose_values_are_not_true_or_false_is_refused(spec):
    from oapcal.errors import ModelSpecError
    from oapcal.model import parse_model

    with pytest.raises(ModelSpecError, match="True or False"):
        parse_model(spec)


def test_a_model_mapping_frees_only_the_names_marked_true():
    from oapcal.model import names_from_mask, parse_model

    assert names_from_mask(parse_model({"k1": True, "p1": False, "c_x": True})) == ("k1", "c_x", "m")


@pytest.mark.parametrize(
    "values",
    [{"pixel_size_um": float("nan")}, {"pixel_size_um": float("inf")}, {"pixel_size_um": -4.8},
     {"d1_mm": 0.0}, {"focal_length_mm": "50.8"}, {"stop_distance_mm": -1.0},
     {"centre": (float("nan"), 0.0)}, {"centre": ("a", 1)}, {"centre": 5}],
)  # fmt: skip
def test_a_relay_design_value_out_of_its_range_is_refused_when_made(values):
    from oapcal.optics.relay_model import RelayDesign

    with pytest.raises(DataError, match="relay design") as info:
        RelayDesign(**values)
    assert info.value.param == "design"
