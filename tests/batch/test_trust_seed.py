"""The trust region's predicted error is computed once per command: the map of
``correct_stack`` takes the one ``oapcal correct`` computed for its message, and the output
is the same as when the map computes it itself."""

import numpy as np
import pytest

import oapcal.imaging.remap as remap
from oapcal.batch.stack import correct_stack
from oapcal.calibration import calibrate
from oapcal.io.calibration import save_calibration
from oapcal.io.images import read_image, write_image
from oapcal.synthetic import synthetic_pairs

LIMIT = 0.05  # px: small enough that part of the output is masked


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    d = tmp_path_factory.mktemp("trust_seed")
    data = synthetic_pairs(seed=3)
    cal = calibrate(data.xy_u, data.xy_d, "paper", image_size=(640, 480))
    save_calibration(cal, d / "calib.json")
    image = np.random.default_rng(3).integers(0, 255, (480, 640), dtype=np.uint8)
    write_image(d / "img.png", image)
    return d, cal


@pytest.fixture
def calls(monkeypatch):
    count = []
    real = remap.predicted_error_map

    def counting(*args, **kwargs):
        count.append(1)
        return real(*args, **kwargs)

    monkeypatch.setattr(remap, "predicted_error_map", counting)
    return count


def test_a_given_predicted_error_is_used_and_gives_the_same_output(setup, tmp_path, calls):
    d, cal = setup
    correct_stack(cal, [d / "img.png"], tmp_path / "own", max_error_px=LIMIT)
    assert len(calls) == 1
    geometry = remap.output_geometry(cal, (480, 640))
    predicted = remap.predicted_error_map(cal, geometry)
    assert (predicted > LIMIT).any() and (predicted <= LIMIT).any()  # a real trust region
    del calls[:]
    report = correct_stack(cal, [d / "img.png"], tmp_path / "seeded", max_error_px=LIMIT,
                           predicted_errors={(480, 640): (geometry, predicted)})  # fmt: skip
    assert report.ok and calls == []
    np.testing.assert_array_equal(read_image(tmp_path / "seeded" / "img.png"),
                                  read_image(tmp_path / "own" / "img.png"))  # fmt: skip
    # a predicted error for another geometry is not used
    other = remap.output_geometry(cal, (480, 640), out_size=(320, 240))
    correct_stack(cal, [d / "img.png"], tmp_path / "other", max_error_px=LIMIT,
                  predicted_errors={(480, 640): (other, predicted)})  # fmt: skip
    assert len(calls) == 1
    np.testing.assert_array_equal(read_image(tmp_path / "other" / "img.png"),
                                  read_image(tmp_path / "own" / "img.png"))  # fmt: skip


def test_the_command_computes_it_once(setup, tmp_path, calls, run_cli):
    d, cal = setup
    code, _, err = run_cli("correct", d / "calib.json", d / "img.png", "--out-dir", tmp_path / "o",
                           "--max-error-px", LIMIT, "--quiet")  # fmt: skip
    assert code == 0, err
    assert len(calls) == 1
    correct_stack(cal, [d / "img.png"], tmp_path / "lib", max_error_px=LIMIT)
    out, lib = (read_image(tmp_path / name / "img.png") for name in ("o", "lib"))
    np.testing.assert_array_equal(out, lib)
