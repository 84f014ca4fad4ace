"""A relay model through the calibration record, its file and the correction map."""

import json

import numpy as np
import pytest

from oapcal.calibration import calibrate
from oapcal.errors import DataError
from oapcal.imaging.remap import correction_map
from oapcal.io.calibration import load_calibration, save_calibration
from oapcal.model import RELAY, distort
from oapcal.optics.relay_model import RelayDesign, relay_mask, relay_params


@pytest.fixture(scope="module")
def relay_points():
    rng = np.random.default_rng(5)
    design = RelayDesign(setup=1, centre=(320.0, 240.0))
    truth = relay_params(design, {"m2_tilt_x": 0.03, "camera_tilt_y": 0.4}, {"rotation": 0.3})
    xy_u = np.column_stack([rng.uniform(20, 620, 200), rng.uniform(20, 460, 200)])
    xy_d = distort(xy_u, truth, family=RELAY) + rng.normal(0, 0.05, (200, 2))
    return design, truth, xy_u, xy_d


def test_relay_calibration_file_round_trip_and_map(relay_points, tmp_path):
    design, truth, xy_u, xy_d = relay_points
    cal = calibrate(xy_u, xy_d, relay_mask("default"), init=relay_params(design),
                    relay_design=design.to_dict(), image_size=(640, 480))  # fmt: skip
    assert cal.family is RELAY and cal.fit.converged
    assert cal.residuals.mean_px < 0.1  # the noise, corrected (0.05 px per axis)
    path = tmp_path / "relay.json"
    save_calibration(cal, path)
    data = json.loads(path.read_text())
    assert data["version"] == 2 and data["model_family"] == "relay"
    assert data["relay_design"]["centre"] == [320.0, 240.0]
    back = load_calibration(path)
    np.testing.assert_array_equal(back.params, cal.params)
    assert back.free == cal.free and back.family is RELAY
    # the correction map samples the distorted image where the model puts each output pixel
    cmap = correction_map(back, (480, 640))
    ys, xs = np.array([10, 240, 470]), np.array([5, 320, 630])
    got = np.stack([cmap.map_x[ys, xs], cmap.map_y[ys, xs]], -1)
    want = distort(np.stack([cmap.geometry.x0 + cmap.geometry.scale * xs,
                             cmap.geometry.y0 + cmap.geometry.scale * ys], -1), cal.params)  # fmt: skip
    np.testing.assert_allclose(got, want, atol=1e-3)  # float32 maps


def test_version_1_files_still_load(tmp_path):
    from oapcal.synthetic import synthetic_pairs

    data = synthetic_pairs(seed=0)
    cal = calibrate(data.xy_u, data.xy_d, "paper")
    path = tmp_path / "v1.json"
    save_calibration(cal, path)
    raw = json.loads(path.read_text())
    raw["version"] = 1
    del raw["model_family"], raw["relay_design"]
    path.write_text(json.dumps(raw))
    back = load_calibration(path)
    np.testing.assert_array_equal(back.params, cal.params)


def test_relay_fit_refuses_normalization(relay_points):
    design, _, xy_u, xy_d = relay_points
    with pytest.raises(DataError, match="normalization 'experiment' cannot be used with the relay model"):
        calibrate(xy_u, xy_d, relay_mask(), init=relay_params(design), relay_design=design.to_dict(),
                  normalization="experiment")  # fmt: skip


def _edited(tmp_path, edit):
    """A saved relay calibration, edited by ``edit(data)`` and written back."""
    import json

    from relay_helpers import write_relay_calibration

    path = write_relay_calibration(tmp_path / "relay.json")
    data = json.loads(path.read_text())
    edit(data)
    path.write_text(json.dumps(data))
    return path


def _set(part, **values):
    return lambda data: data.update(relay_design=None) if part is None else data[part].update(values)


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        # a design constant changed by hand: the design it came from says otherwise
        (_set("params", f1_mm=-50.0), r"field 'params.f1_mm' is -50 but the relay_design gives 50.8"),
        (_set("params", pixel_mm=-0.0048), r"field 'params.pixel_mm' is -0.0048 but .* gives 0.0048"),
        (_set("params", a22=0.0), r"field 'params.a22' is 0 but the relay_design gives"),
        # the design itself out of range or unknown
        (_set("relay_design", focal_length_mm=0), r"'relay_design.focal_length_mm' is 0; .* in \(0, 10000\]"),
        (_set("relay_design", pixel_size_um="4.8"), r"'relay_design.pixel_size_um' is '4.8'"),
        (
            _set("relay_design", orientation="X"),
            r"'relay_design.orientation' is 'X'; .* \"U\" or \"Z\"",
        ),
        (_set("relay_design", setup=3), r"'relay_design.setup' is 3; it must be 1, 2 or null"),
        (_set("relay_design", centre=[1, None]), r"'relay_design.centre' is \[1, None\]"),
        (_set("relay_design", wavelength=850), r"'relay_design.wavelength' is not a design field"),
        (_set(None), r"field 'relay_design' must be an object"),
    ],
)
def test_a_relay_calibration_with_an_impossible_design_is_refused_naming_the_field(tmp_path, edit, message):
    from oapcal.errors import InputFileError
    from oapcal.io.calibration import load_calibration

    path = _edited(tmp_path, edit)
    with pytest.raises(InputFileError, match=message):
        load_calibration(path)


def test_an_unedited_relay_calibration_still_loads_with_its_design(tmp_path):
    from oapcal.io.calibration import load_calibration
    from relay_helpers import relay_calibration

    cal = load_calibration(_edited(tmp_path, lambda d: None))
    np.testing.assert_array_equal(cal.params, relay_calibration().params)
    assert cal.relay_design == relay_calibration().relay_design
