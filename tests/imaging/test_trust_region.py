"""The trust region of a correction map: output pixels whose predicted error exceeds the
threshold sample nothing (the border value), the rest are the whole map's."""

import numpy as np
import pytest

from oapcal.calibration import calibrate
from oapcal.errors import DataError
from oapcal.imaging.remap import (
    MASKED,
    correct_image,
    correction_map,
    output_geometry,
    predicted_error_map,
    trust_summary,
)
from oapcal.model import distort
from oapcal.synthetic import EXAMPLE_TRUTH
from oapcal.uncertainty import hull_distance, predicted_error


@pytest.fixture(scope="module")
def central():
    """The paper model fitted to landmarks in the central 40 % of a 640 x 480 frame."""
    rng = np.random.default_rng(4)
    xy_u = rng.uniform((200, 150), (440, 330), (120, 2))
    xy_d = distort(xy_u, EXAMPLE_TRUTH) + rng.normal(0, 0.3, xy_u.shape)
    return calibrate(xy_u, xy_d, "paper", image_size=(640, 480), rotation="none")


def test_predicted_error_map_matches_the_pointwise_prediction(central):
    geo = output_geometry(central, (480, 640))
    pred = predicted_error_map(central, geo)
    assert pred.shape == (480, 640) and pred.dtype == np.float32
    rng = np.random.default_rng(0)
    cols, rows = rng.integers(0, 640, 300), rng.integers(0, 480, 300)
    direct = predicted_error(np.stack([cols, rows], -1).astype(float), central)
    # linear interpolation between samples every 4 px of a smooth field (kinked at the hull)
    np.testing.assert_allclose(pred[rows, cols], direct, rtol=0.05, atol=0.01)
    # in output px: half the scale, twice the pixels per unit of error
    geo2 = output_geometry(central, (480, 640), out_size=(1280, 960))
    pred2 = predicted_error_map(central, geo2)
    assert pred2[480, 640] == pytest.approx(pred[240, 320] / geo2.scale, rel=0.02)


@pytest.mark.parametrize("interp", ["nearest", "linear", "cubic", "lanczos"])
def test_masked_pixels_get_the_border_and_trusted_ones_are_unchanged(central, interp):
    image = np.random.default_rng(1).integers(10, 250, (480, 640)).astype(np.uint8)
    whole = correction_map(central, (480, 640))
    trusted_map = correction_map(central, (480, 640), max_error_px=1.0)
    trusted = trusted_map.trusted
    assert trusted_map.max_error_px == 1.0
    np.testing.assert_array_equal(trusted, trusted_map.predicted_error <= 1.0)
    assert 0.05 < trusted.mean() < 0.95
    # every pixel over the threshold samples nothing
    assert (trusted_map.map_x[~trusted] == MASKED).all() and (trusted_map.map_y[~trusted] == MASKED).all()
    np.testing.assert_array_equal(trusted_map.map_x[trusted], whole.map_x[trusted])
    out = correct_image(image, trusted_map, interp, border=7)
    ref = correct_image(image, whole, interp, border=7)
    assert (out[~trusted] == 7).all()
    # away from the region's edge (the kernel's reach) the trusted pixels equal the whole map's
    from scipy.ndimage import binary_erosion

    core = binary_erosion(trusted, iterations=5)
    np.testing.assert_array_equal(out[core], ref[core])
    # the hull lies in the trust region (the prediction there is the covariance and the floor)
    gx, gy = np.meshgrid(np.arange(640.0), np.arange(480.0))
    inside = hull_distance(np.stack([gx, gy], -1), central.hull) == 0
    assert trusted[inside].mean() > 0.99


def test_trust_summary_and_refusals(central):
    geo = output_geometry(central, (480, 640))
    s = trust_summary(central, geo, 1.0)
    assert s["output_px"] == [640, 480] and s["has_error_model"]
    assert 0.8 < s["outside_fraction"] < 0.95  # landmarks over 14 % of the frame
    corners = np.array([[0.0, 479.0], [639.0, 0.0], [0.0, 0.0], [639.0, 479.0]])
    assert s["max_distance_px"] == pytest.approx(float(hull_distance(corners, central.hull).max()), rel=0.01)
    assert 0.05 < s["trusted_fraction"] < 0.95
    with pytest.raises(DataError, match="no output pixel"):
        correction_map(central, (480, 640), max_error_px=1e-6)
    with pytest.raises(DataError, match="needs a calibration"):
        correction_map(central.params, (480, 640), max_error_px=1.0)
