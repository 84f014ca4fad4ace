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


def test_bicubic_patches_agree_with_fitpack():
    # The hand-written evaluator against scipy's RectBivariateSpline (FITPACK) it replaces.
    from scipy.interpolate import RectBivariateSpline

    from oapcal.optics.field import BicubicPatches

    rng = np.random.default_rng(9)
    xs = np.linspace(-3.0, 5.0, 13)
    ys = np.linspace(1.0, 4.0, 9)
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    splines = [
        RectBivariateSpline(xs, ys, np.sin(gx) * np.cos(1.3 * gy) + 0.1 * gx * gy**2),
        RectBivariateSpline(xs, ys, rng.normal(size=gx.shape)),
    ]
    x = np.concatenate([rng.uniform(-3.0, 5.0, 500), xs])  # include the nodes and both ends
    y = np.concatenate([rng.uniform(1.0, 4.0, 500), ys[np.arange(13) % 9]])
    val, ddx, ddy = BicubicPatches(xs, ys, splines)(x, y)
    for c, spline in enumerate(splines):
        scale = np.abs(spline.ev(x, y)).max()
        assert np.abs(val[:, c] - spline.ev(x, y)).max() < 1e-12 * max(scale, 1)
        assert np.abs(ddx[:, c] - spline.ev(x, y, dx=1)).max() < 1e-10 * max(scale, 1)
        assert np.abs(ddy[:, c] - spline.ev(x, y, dy=1)).max() < 1e-10 * max(scale, 1)


def test_inverse_marks_points_outside_the_traced_grid_and_non_finite_input(field):
    xy = np.array([[1e5, 1e5], [np.nan, 3.0], [320.0, 240.0]])
    out = field.inverse(xy)
    assert np.isnan(out[:2]).all()
    assert np.abs(field.forward(out[2:]) - xy[2:]).max() < 1e-6


def test_grid_plot_of_a_large_grid_draws_a_subgrid(tmp_path):
    from oapcal.optics.relay import grid_distortion, oap_relay
    from oapcal.report.optics_plots import plot_grid

    grid = grid_distortion(oap_relay(1), n=35, field_mm=1.0)
    plot_grid(grid, tmp_path / "g.png", units="px", max_side=9)
    assert (tmp_path / "g.png").read_bytes()[:4] == b"\x89PNG"


def test_misaligned_field_is_centred_on_the_image_of_the_field_centre():
    from oapcal.optics.relay import chief_rays, oap_relay

    mis = {"m2_tilt_x": 0.05, "camera_tilt_y": 0.5}
    field = relay_distortion(1, grid=49, misalignment=mis)
    # The field centre's real image is where the paraxial map puts it (no displacement).
    real = chief_rays(oap_relay(1, misalignment=mis), [0.0, 0.0]).xy_mm * 1e3 / 4.8 + field.centre
    assert np.abs(field.paraxial_from_object_um([0.0, 0.0]) - real).max() < 1e-9
    assert abs(real[1] - field.centre[1]) > 15  # 2 f tan(0.05 deg) = 89 um = 18.5 px off centre
    px = np.random.default_rng(5).uniform([0, 0], [639, 479], (500, 2))
    assert np.abs(field.forward(px) - field.traced(px)).max() < 0.05  # 49 nodes
    assert np.abs(field.inverse(field.forward(px)) - px).max() < 1e-6
