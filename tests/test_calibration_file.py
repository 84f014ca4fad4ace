import json

import numpy as np
import pytest

from oapcal.calibrate import calibrate
from oapcal.errors import InputFileError
from oapcal.io.calibration import load_calibration, save_calibration


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
    assert back.image_size == (640, 480) and back.um_per_px == 4.8
    data = json.loads(path.read_text())
    assert data["format"] == "oapcal-calibration" and data["version"] == 1
    assert data["created_utc"].endswith("Z") and data["oapcal_version"]


@pytest.mark.parametrize(
    "mutate,pattern",
    [
        (lambda d: d.update(version=2), "field 'version' is 2"),
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
    data = cal.to_dict()
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
