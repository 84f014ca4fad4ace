"""The dense distortion field: interpolation against traced rays, round trips."""

import numpy as np
import pytest

from oapcal.optics import relay_distortion
from oapcal.optics.relay import chief_rays


@pytest.fixture(scope="module")
def field():
    return relay_distortion(1)


def test_forward_agrees_with_directly_traced_chief_rays(field):
    rng = np.random.default_rng(5)
    obj_um = rng.uniform(-1200, 1200, size=(300, 2))
    xy_u = field.paraxial_from_object_um(obj_um)
    keep = (xy_u[:, 0] > 0) & (xy_u[:, 0] < 639) & (xy_u[:, 1] > 0) & (xy_u[:, 1] < 479)
    # Independent path: trace the chief rays from the object points, convert mm -> px.
    traced = chief_rays(field.relay, obj_um[keep] * 1e-3).xy_mm * 1e3 / 4.8 + [319.5, 239.5]
    assert np.abs(field.forward(xy_u[keep]) - traced).max() < 1e-3


def test_round_trips_over_the_whole_image(field):
    gx, gy = np.meshgrid(np.linspace(-0.5, 639.5, 41), np.linspace(-0.5, 479.5, 31))
    xy = np.stack([gx.ravel(), gy.ravel()], -1)
    assert np.abs(field.inverse(field.forward(xy)) - xy).max() < 1e-6
    back = field.inverse(xy)  # every real pixel has a paraxial preimage
    assert np.isfinite(back).all()
    assert np.abs(field.forward(back) - xy).max() < 1e-6


def test_paraxial_map_puts_the_axis_at_the_image_centre_with_unit_magnification(field):
    assert field.image_size == (640, 480) and field.pixel_size_um == 4.8
    xy = field.paraxial_from_object_um([[0.0, 0.0], [96.0, 0.0], [0.0, 48.0]])
    assert np.allclose(xy[0], [319.5, 239.5])
    assert np.hypot(*(xy[1] - xy[0])) == pytest.approx(20.0, rel=1e-8)  # 96 um / 4.8 um
    assert np.hypot(*(xy[2] - xy[0])) == pytest.approx(10.0, rel=1e-8)
    assert np.allclose(field.object_um_from_paraxial(xy), [[0, 0], [96, 0], [0, 48]], atol=1e-6)
    assert np.isnan(field.forward([[1e6, 0.0]])).all()  # outside the traced grid
