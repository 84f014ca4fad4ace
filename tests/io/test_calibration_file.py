import json

import numpy as np
import pytest

from oapcal.calibration import FitSummary, calibrate
from oapcal.errors import InputFileError
from oapcal.io.calibration import calibration_to_dict, load_calibration, save_calibration
from oapcal.stats import ResidualStats


@pytest.fixture
def cal(pairs):
    return calibrate(pairs.xy_u, pairs.xy_d, "paper", um_per_px=4.8, image_size=(640, 480))


def test_round_trip_is_exact(tmp_path, cal):
    path = tmp_path / "c.json"
    save_calibration(cal, path)
    back = load_calibration(path)
    np.testing.assert_array_equal(back.params, cal.params)
    np.testing.assert_array_equal(back.stderr, cal.stderr)
    np.testing.assert_array_equal(back.covariance, cal.covariance)
    np.testing.assert_array_equal(back.hull, cal.hull)
    assert back.free == cal.free and back.fit == cal.fit and back.residuals == cal.residuals
    assert isinstance(back.fit, FitSummary) and isinstance(back.residuals, ResidualStats)
    assert back.fit.converged and back.fit.k == 8 and back.residuals.mean_um == cal.residuals.mean_um
    assert back.image_size == (640, 480) and back.um_per_px == 4.8
    data = json.loads(path.read_text())
    assert data["format"] == "oapcal-calibration" and data["version"] == 2
    assert data["model_family"] == "brown-conrady" and data["relay_design"] is None
    assert data["created_utc"].endswith("Z") and data["oapcal_version"]


@pytest.mark.parametrize(
    "mutate,pattern",
    [
        (lambda d: d.update(version=3), "field 'version' is 3"),
        (lambda d: d.update(model_family="spline"), "field 'model_family'"),
        (lambda d: d.update(format="other"), "field 'format'"),
        (lambda d: d["params"].update(k1="abc"), r"field 'params.k1': 'abc' is not of type 'number'"),
        (lambda d: d["params"].pop("m"), r"field 'params': 'm' is a required property"),
        (lambda d: d["params"].update(k2=0.5), r"field 'params.k2' is 0.5 but k2 is not in 'free'"),
        (lambda d: d.update(free=["k1", "bogus", "m"]), r"field 'free.1'"),
        (lambda d: d.update(covariance=[[1.0]]), r"field 'covariance' must be 8 x 8"),
        (lambda d: d.update(image_size=[640]), r"field 'image_size'"),
        (lambda d: d.pop("fit"), r"'fit' is a required property"),
    ],
)
def test_malformed_files_name_the_field(tmp_path, cal, mutate, pattern):
    data = calibration_to_dict(cal)
    mutate(data)
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(data))
    with pytest.raises(InputFileError, match=pattern):
        load_calibration(path)


def test_not_json_at_all(tmp_path):
    path = tmp_path / "x.json"
    path.write_text("{ not json")
    with pytest.raises(InputFileError, match="line 1: malformed JSON"):
        load_calibration(path)
    with pytest.raises(InputFileError, match="no such calibration file"):
        load_calibration(tmp_path / "missing.json")


# -- issue 14, items 4 and 11: every number checked, a folding model refused --------------------

_NUMBERS = [
    (lambda d: d["params"].update(k1=float("nan")), r"field 'params.k1' is nan"),
    (lambda d: d["params"].update(m=float("inf")), r"field 'params.m' is inf"),
    (lambda d: d["params"].update(c_x=float("-inf")), r"field 'params.c_x' is -inf"),
    (lambda d: d["params"].update(k1=1e300), r"field 'params.k1' is 1e\+300"),
    (lambda d: d["params"].update(m=-1.0), r"field 'params.m' is -1; the magnification"),
    (lambda d: d["params"].update(x_off=10**400), r"field 'params.x_off' is too large"),
    (lambda d: d["stderr"].update(k1=float("nan")), r"field 'stderr.k1' is nan"),
    (lambda d: d["covariance"][0].__setitem__(0, float("inf")), r"field 'covariance.0.0' is inf"),
    (lambda d: d["fit"].update(rss=float("nan")), r"field 'fit.rss' is nan"),
    (lambda d: d["residuals"].update(max_px=float("inf")), r"field 'residuals.max_px' is inf"),
    (lambda d: d.update(um_per_px=float("nan")), r"field 'um_per_px' is nan"),
    (lambda d: d.update(um_per_px=float("inf")), r"field 'um_per_px' is inf"),
    (lambda d: d.update(um_per_px=1e-300), r"field 'um_per_px' is 1e-300; it must be between"),
    (lambda d: d.update(image_size=[100_000_000, 480]), r"field 'image_size' is 100000000x480"),
    (lambda d: d.update(bounds=[float("nan"), 0, 1, 1]), r"field 'bounds.0' is nan"),
    (lambda d: d.update(bounds=[600, 0, 10, 400]), r"field 'bounds' is \[600, 0, 10, 400\]"),
    (lambda d: d.update(hull=[[0, 0], [float("nan"), 1], [1, 1]]), r"field 'hull.1.0' is nan"),
    (lambda d: d.update(hull=[[0, 0], [1, 1]]), r"field 'hull' has 2 vertices"),
]


@pytest.mark.parametrize("mutate,pattern", _NUMBERS)
def test_non_finite_and_absurd_numbers_are_refused(tmp_path, cal, mutate, pattern):
    data = calibration_to_dict(cal)
    mutate(data)
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(data))  # json.dumps writes NaN / Infinity as a hand edit would
    with pytest.raises(InputFileError, match=pattern):
        load_calibration(path)


def test_a_model_that_folds_inside_its_image_is_refused(tmp_path, cal):
    data = calibration_to_dict(cal)
    data["params"]["k1"] = -1e-5  # barrel so strong the map turns back inside 640x480
    path = tmp_path / "fold.json"
    path.write_text(json.dumps(data))
    with pytest.raises(InputFileError, match=r"fold\.json: the model folds over at \(x, y\) = "):
        load_calibration(path)


def test_a_model_is_checked_on_the_image_it_is_applied_to(tmp_path, cal):
    data = calibration_to_dict(cal)
    data["image_size"] = None
    data["params"]["k1"] = -2e-8  # fine over the points (bounds), folds far outside them
    path = tmp_path / "c.json"
    path.write_text(json.dumps(data))
    load_calibration(path)  # no image size: only the bounds are checked
    with pytest.raises(InputFileError, match=r"inside the 20000x20000 px image"):
        load_calibration(path, image_size=(20000, 20000))


@pytest.mark.parametrize(
    "mutate,argv",
    [
        (lambda d: d["params"].update(k1=float("nan")), "correct {c} {img} --out-dir {o}/out"),
        (lambda d: d["params"].update(m=float("inf")), "export-opencv {c} --out {o}/cv.yml"),
        (lambda d: d["params"].update(k1=1e300), "correct {c} {img} --out-dir {o}/out --save-map {o}/m.npz"),
        (lambda d: d.update(um_per_px=float("nan")), "correct {c} {img} --out-dir {o}/out --um-per-px 2"),
        (lambda d: d.update(bounds=[600, 0, 9, 9]), "correct {c} {img} --out-dir {o}/o --extent calibrated"),
        (lambda d: d.update(hull=[[0, 0], [float("nan"), 1], [1, 1]]), "report {c} --out {o}/r.html"),
        (lambda d: d.update(um_per_px=float("inf")), "report {c} --out {o}/r.html"),
    ],
)  # fmt: skip
def test_commands_refuse_bad_calibrations(run_cli, tmp_path, cal, mutate, argv):
    import cv2

    data = calibration_to_dict(cal)
    mutate(data)
    (tmp_path / "c.json").write_text(json.dumps(data))
    cv2.imwrite(str(tmp_path / "img.png"), np.full((480, 640), 128, np.uint8))
    out = tmp_path / "o"
    out.mkdir()
    names = {"c": tmp_path / "c.json", "img": tmp_path / "img.png", "o": out}
    code, _, err = run_cli(*argv.format(**names).split())
    assert code == 2 and err.startswith("oapcal: error: ") and "c.json: field" in err, err
    assert err.count("\n") == 1 and list(out.iterdir()) == []
