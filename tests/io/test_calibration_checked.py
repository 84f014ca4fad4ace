"""A relay calibration file records that its content passed the load checks (``checked``):
loading it unchanged skips the ray tracing (no Numba in a fresh process); any edit, or a
record that does not match, gets the full checks and the same errors as a file without it."""

import json
import subprocess
import sys

import numpy as np
import pytest

from oapcal.errors import InputFileError
from oapcal.io.calibration import CHECKED_KEY, calibration_to_dict, load_calibration, save_calibration
from oapcal.synthetic import synthetic_pairs
from relay_helpers import relay_calibration

LOAD = (
    "import sys; from oapcal.io.calibration import load_calibration; "
    "cal = load_calibration(sys.argv[1]); print(cal.family.name, 'numba' in sys.modules)"
)


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("checked")
    save_calibration(relay_calibration(), d / "stamped.json")
    data = json.loads((d / "stamped.json").read_text())
    plain = {k: v for k, v in data.items() if k != CHECKED_KEY}
    (d / "plain.json").write_text(json.dumps(plain, indent=2))
    return d, data


def _write(path, data):
    path.write_text(json.dumps(data, indent=2))
    return path


def test_a_relay_file_carries_the_record_and_loads_the_same(files):
    d, data = files
    assert set(data[CHECKED_KEY]) == {"sha256"} and len(data[CHECKED_KEY]["sha256"]) == 64
    stamped, plain = load_calibration(d / "stamped.json"), load_calibration(d / "plain.json")
    np.testing.assert_array_equal(stamped.params, plain.params)
    np.testing.assert_array_equal(stamped.covariance, plain.covariance)
    assert stamped.family is plain.family and stamped.relay_design == plain.relay_design
    assert stamped.bounds == plain.bounds and stamped.image_size == plain.image_size
    # written again, the same record (it depends on the content and the code only)
    assert calibration_to_dict(stamped)[CHECKED_KEY] == data[CHECKED_KEY]


def test_loading_the_recorded_file_needs_no_kernels(files):
    d, _ = files
    run = lambda name: subprocess.run(  # noqa: E731
        [sys.executable, "-c", LOAD, str(d / name)], capture_output=True, text=True, check=True
    ).stdout.split()
    assert run("stamped.json") == ["relay", "False"]
    assert run("plain.json") == ["relay", "True"]  # without the record it traces, as before


def _error(path):
    with pytest.raises(InputFileError) as info:
        load_calibration(path)
    return str(info.value)


@pytest.mark.parametrize(
    "edit",
    [
        lambda d: d["params"].update(a11=d["params"]["a11"] * 1.001),  # a design constant
        lambda d: d["params"].update(scale=0.0),  # a model that folds (determinant 0) everywhere
        lambda d: d.update(bounds=[-30000, -30000, 30000, 30000]),  # a region where it folds
    ],
)
def test_an_edited_file_is_refused_as_without_the_record(files, tmp_path, edit):
    _, data = files
    stamped = json.loads(json.dumps(data))
    edit(stamped)
    plain = {k: v for k, v in stamped.items() if k != CHECKED_KEY}
    message = _error(_write(tmp_path / "x.json", plain))
    assert _error(_write(tmp_path / "x.json", stamped)) == message
    assert "x.json" in message


@pytest.mark.parametrize("record", [{"sha256": "0" * 64}, {"sha256": 5}, "yes", None])
def test_a_record_that_does_not_match_is_ignored(files, tmp_path, record):
    _, data = files
    bad = {**data, CHECKED_KEY: record}
    bad["params"] = {**data["params"], "a11": data["params"]["a11"] * 1.001}
    assert "params.a11" in _error(_write(tmp_path / "x.json", bad))


def test_eq1_files_have_no_record():
    from oapcal.calibration import calibrate

    d = synthetic_pairs(seed=0)
    cal = calibrate(d.xy_u, d.xy_d, "paper", image_size=(640, 480))
    assert CHECKED_KEY not in calibration_to_dict(cal)
