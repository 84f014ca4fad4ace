"""Correction maps of the other model families against the model evaluated at every pixel."""

import numpy as np
import pytest

from oapcal.imaging.remap import correction_map
from oapcal.model import BROWN_CONRADY_POSE, RELAY, distort
from oapcal.optics.relay_model import RelayDesign, relay_params


@pytest.mark.parametrize("shape", [(480, 640), (97, 131)])
def test_relay_map_equals_the_model_at_every_pixel(shape):
    design = RelayDesign(setup=1, centre=((shape[1] - 1) / 2, (shape[0] - 1) / 2))
    params = relay_params(design, {"m2_tilt_x": 0.04, "camera_tilt_y": 0.6, "d1": 20.0}, {"rotation": 0.5})
    assert RELAY.map_step  # the relay's map is interpolated between exact nodes
    cmap = correction_map(params, shape)
    rows, cols = shape
    gx, gy = np.meshgrid(np.arange(cols, dtype=float), np.arange(rows, dtype=float))
    exact = distort(np.stack([gx.ravel(), gy.ravel()], -1), params).reshape(rows, cols, 2)
    # float32 maps: rounding is 3e-5 px at 500 px; the spline adds less than that
    assert np.abs(cmap.map_x - exact[..., 0]).max() < 1.2e-4
    assert np.abs(cmap.map_y - exact[..., 1]).max() < 1.2e-4
    assert np.abs(exact[..., 0] - gx).max() > 0.5  # and the field is not trivial


def test_rotation_family_map_is_per_pixel():
    params = np.zeros(14)
    params[[0, 12, 13]] = [1e-7, 1.0, 0.4]
    assert BROWN_CONRADY_POSE.map_step == 0
    cmap = correction_map(params, (60, 80))
    gx, gy = np.meshgrid(np.arange(80.0), np.arange(60.0))
    exact = distort(np.stack([gx.ravel(), gy.ravel()], -1), params).reshape(60, 80, 2)
    np.testing.assert_allclose(cmap.map_x, exact[..., 0], atol=1e-4)
    np.testing.assert_allclose(cmap.map_y, exact[..., 1], atol=1e-4)
