"""A fitted model that folds over beyond its landmarks' bounds (where it extrapolates) is
kept, with a note; its trust region ends before the fold; the whole frame is refused."""

import dataclasses

import numpy as np
import pytest

from oapcal.calibration import (
    UnusableFitError,
    calibrate,
    check_model_region,
    folds_beyond_bounds,
)
from oapcal.errors import DataError, InputFileError
from oapcal.imaging.remap import correction_map, output_geometry
from oapcal.model import distort, jacobian_determinant, params_from_dict

# barrel distortion over a 640 x 480 camera: fine over it, turning back ~1300 px from the centre
TRUTH = params_from_dict({"k1": -2e-7, "x_off": -320, "y_off": -240, "c_x": 320, "c_y": 240, "m": 1})


def _pairs(truth=TRUTH):
    gx, gy = np.meshgrid(np.linspace(0, 639, 12), np.linspace(0, 479, 9))
    xy_u = np.stack([gx.ravel(), gy.ravel()], -1)
    rng = np.random.default_rng(0)
    return xy_u, distort(xy_u, truth) + rng.normal(0, 0.05, xy_u.shape)


@pytest.fixture(scope="module")
def wide():
    xy_u, xy_d = _pairs()
    return calibrate(xy_u, xy_d, "paper", image_size=(4000, 4000))


def test_the_fold_is_kept_with_a_note_that_says_where(wide):
    fold = folds_beyond_bounds(wide)
    assert fold is not None and fold["region"] == "4000x4000 px image"
    x, y = fold["point"]
    # the fold is where the map's own Jacobian determinant is <= 0, beyond the points (0..639 x 0..479)
    assert jacobian_determinant(np.array([[x, y]]), wide.params)[0] <= 0
    assert not (0 <= x <= 639 and 0 <= y <= 479)
    assert 0 < fold["fraction"] < 1
    assert any("folds over beyond the reference points' bounds" in n for n in wide.notes)


def test_a_calibration_without_an_error_model_must_not_fold_in_its_frame(wide):
    check_model_region(wide)  # with its error model: kept
    bare = dataclasses.replace(wide, error_model=None)
    with pytest.raises(InputFileError, match="folds over .* inside the 4000x4000 px image"):
        check_model_region(bare)
    with pytest.raises(InputFileError, match="folds over"):
        check_model_region(wide, folds_beyond_bounds=False)
    # a model given as a value (no bounds, no error model) as before
    with pytest.raises(InputFileError, match="folds over"):
        check_model_region(wide.params, (4000, 4000))


def test_a_fold_within_the_bounds_is_refused():
    strong = params_from_dict({"k1": -4e-6, "x_off": -320, "y_off": -240, "c_x": 320, "c_y": 240, "m": 1})
    xy_u, xy_d = _pairs(strong)
    with pytest.raises(UnusableFitError, match="inside the reference points' bounds"):
        calibrate(xy_u, xy_d, "paper", image_size=(640, 480))


def test_the_trust_region_is_written_and_the_whole_frame_is_refused(wide):
    shape = (4000, 4000)
    with pytest.raises(InputFileError, match="beyond the reference points' bounds"):
        output_geometry(wide, shape, extent="input")
    with pytest.raises(InputFileError, match="folds over"):
        correction_map(wide, shape)  # every output pixel
    cmap = correction_map(wide, shape, max_error_px=1.0)
    xy = np.stack(np.meshgrid(np.arange(0, 4000, 50.0), np.arange(0, 4000, 50.0)), -1).reshape(-1, 2)
    det = jacobian_determinant(xy, wide.params)
    trusted = cmap.trusted[xy[:, 1].astype(int), xy[:, 0].astype(int)]
    assert (det <= 0).any() and not trusted[det <= 0].any()  # no folded pixel is trusted
    assert trusted.any()


def test_no_fold_no_note():
    xy_u, xy_d = _pairs()
    cal = calibrate(xy_u, xy_d, "paper", image_size=(640, 480))
    assert folds_beyond_bounds(cal) is None
    assert not any("folds over" in n for n in cal.notes)


def test_an_unconverged_fit_keeps_the_strict_check():
    # without an error model (no converged fit, or error_model=False) a fold in the frame is refused
    xy_u, xy_d = _pairs()
    with pytest.raises(DataError, match="folds over"):
        calibrate(xy_u, xy_d, "paper", image_size=(4000, 4000), error_model=False)
