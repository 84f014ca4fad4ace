"""The OAP relay: physics invariants of the traced distortion and image quality."""

import numpy as np
import pytest

from oapcal.errors import GeometrySpecError
from oapcal.optics.quality import numerical_aperture, pixel_limit_um, sparrow_limit_um, spot_diagram
from oapcal.optics.relay import aim, chief_rays, grid_distortion, oap_relay, paraxial_matrix


@pytest.mark.parametrize("orientation", ["U", "Z"])
@pytest.mark.parametrize("stop", [None, 300.0])
def test_field_centre_is_imaged_onto_the_image_plane_origin(orientation, stop):
    relay = oap_relay(1, orientation=orientation, stop_distance_mm=stop)
    assert np.abs(chief_rays(relay, np.zeros(2)).xy_mm).max() < 1e-12


@pytest.mark.parametrize("orientation", ["U", "Z"])
@pytest.mark.parametrize("kwargs", [{"setup": 1}, {"setup": 2}, {"d1_mm": 500.0, "stop_distance_mm": 123.0}])
def test_paraxial_map_is_orthogonal_with_magnification_one(orientation, kwargs):
    # Two identical mirrors in an afocal relay: unit magnification, no shear.
    j = paraxial_matrix(oap_relay(orientation=orientation, **kwargs))
    assert np.allclose(j.T @ j, np.eye(2), atol=1e-8)


def test_distortion_is_mirror_symmetric_in_x():
    # The fold plane x = 0 is a symmetry plane: dx is odd in x and dy is even in x.
    grid = grid_distortion(oap_relay(1, stop_distance_mm=250.0), n=9, field_mm=1.0)
    d = grid.displacement.reshape(9, 9, 2)
    assert np.allclose(d[:, ::-1, 0], -d[:, :, 0], atol=1e-12)
    assert np.allclose(d[:, ::-1, 1], d[:, :, 1], atol=1e-12)
    assert np.abs(d[..., 1]).max() > 1e-2  # and the distortion itself is not zero


def test_distortion_grows_linearly_with_d1_to_first_order():
    def mean(d1):
        return grid_distortion(oap_relay(d1_mm=d1), n=9).distortion.mean()

    small = mean(10.0)
    assert mean(20.0) / small == pytest.approx(2.0, rel=0.01)
    assert mean(40.0) / small == pytest.approx(4.0, rel=0.02)
    # The paper's path length is still within ~10 % of the first-order slope.
    assert mean(860.0) / (86.0 * small) == pytest.approx(1.0, rel=0.12)


def test_distortion_cancels_in_the_symmetric_z_relay_with_the_stop_midway():
    z = grid_distortion(oap_relay(1, orientation="Z", stop_distance_mm=430.0), n=9)
    u = grid_distortion(oap_relay(1, orientation="U", stop_distance_mm=430.0), n=9)
    assert z.distortion.max() < 1e-9  # mm
    assert u.distortion.max() > 0.1  # mm: U adds the two mirrors' distortion


def test_setup_1_comes_close_to_the_paper():
    # The paper's commercial-software figure: max 193 um over 1 mm x 1 mm, 17 x 17.
    grid = grid_distortion(oap_relay(1), n=17, field_mm=1.0)
    assert grid.distortion.max() * 1e3 == pytest.approx(193.0, rel=0.02)
    # More distortion along y (the off-axis direction) than along x, as the paper says.
    assert np.abs(grid.displacement[:, 1]).max() > 5 * np.abs(grid.displacement[:, 0]).max()


def test_chief_rays_pass_through_the_stop_centre():
    relay = oap_relay(1, stop_distance_mm=300.0)
    obj = np.array([[0.4, -0.3], [-0.5, 0.5]])
    aimed = aim(relay, relay.object_plane.world(obj), np.zeros((2, 2)))
    assert aimed.converged.all()
    centre = np.asarray(relay.stop.point)
    dist = np.linalg.norm(np.cross(centre - aimed.hit, aimed.direction), axis=-1)
    assert dist.max() < 1e-9


def test_u_cancels_the_field_dependent_astigmatism_and_z_does_not():
    corner = (0.5, 0.5)
    u = spot_diagram(oap_relay(1, orientation="U"), corner, beam_diameter_mm=20.0)
    z = spot_diagram(oap_relay(1, orientation="Z"), corner, beam_diameter_mm=20.0)
    assert u.rms_um < 0.2 * z.rms_um
    # On axis the paraboloids image perfectly.
    assert spot_diagram(oap_relay(1), (0.0, 0.0)).rms_um < 1e-6


def test_resolution_limits_match_the_paper():
    na = numerical_aperture(20.0, 50.8)
    assert na == pytest.approx(0.193, abs=5e-4)
    assert sparrow_limit_um(0.193, 850.0) == pytest.approx(2.07, abs=0.005)
    assert pixel_limit_um(4.8, 1.0) == pytest.approx(9.6)


@pytest.mark.parametrize(
    "kwargs,pattern",
    [
        ({"setup": 3}, "unknown setup 3"),
        ({"d1_mm": -1.0}, "must be a positive"),
        ({"orientation": "V"}, "unknown orientation"),
        ({"stop_distance_mm": 900.0}, "outside the collimated path"),
    ],
)
def test_bad_geometry_raises_named_errors(kwargs, pattern):
    with pytest.raises(GeometrySpecError, match=pattern):
        oap_relay(**kwargs)


@pytest.mark.parametrize("stop", [None, 300.0])
def test_tracing_in_blocks_reports_progress_and_does_not_change_results(monkeypatch, stop):
    import oapcal.optics.relay as relay_module

    relay = oap_relay(1, stop_distance_mm=stop)
    obj = np.random.default_rng(2).uniform(-0.5, 0.5, size=(1000, 2))
    one_block = chief_rays(relay, obj)
    monkeypatch.setattr(relay_module, "CHUNK", 64)
    calls = []
    blocks = chief_rays(relay, obj, progress=lambda done, total: calls.append((done, total)))
    assert np.array_equal(blocks.xy_mm, one_block.xy_mm)
    assert np.array_equal(blocks.clear, one_block.clear)
    assert np.array_equal(blocks.trace.hits[1], one_block.trace.hits[1])
    assert calls[-1] == (1000, 1000) and len(calls) == 16  # ceil(1000 / 64)
    assert all(a[0] < b[0] for a, b in zip(calls, calls[1:]))


def test_component_and_array_forms_of_the_surfaces_agree():
    # The tracer's component triples against the (..., 3) array methods on a tilted mirror.
    from oapcal.optics.surfaces import Paraboloid, join, split

    rng = np.random.default_rng(4)
    mirror = Paraboloid(vertex=(1.0, -2.0, -25.4), axis=(0.1, 0.2, 1.0), focal_length=25.4)
    origin = rng.uniform(-10, 10, size=(50, 3)) + [0, 0, 100]
    direction = rng.normal(size=(50, 3)) * 0.05 + [0, 0, -1]
    t = mirror.intersect(origin, direction)
    hit = origin + t[:, None] * direction
    # The hit is on the surface |r_perp|^2 = 4 f_p (r . a), written out independently.
    a = np.asarray(mirror.axis)
    r = hit - np.asarray(mirror.vertex)
    along = r @ a
    perp = r - along[:, None] * a
    assert np.abs((perp**2).sum(-1) - 4 * 25.4 * along).max() < 1e-9
    # The normal is the normalized gradient 4 f_p a - 2 r_perp of the implicit surface.
    grad = 4 * 25.4 * a - 2 * perp
    assert np.allclose(mirror.normal(hit), grad / np.linalg.norm(grad, axis=-1, keepdims=True), atol=1e-14)
    assert np.allclose(join(mirror.normal_c(split(hit))), mirror.normal(hit), atol=0)


def test_radial_fit_of_a_large_grid_uses_a_subgrid_close_to_the_full_fit():
    from oapcal.optics.relay import radial_fit

    grid = grid_distortion(oap_relay(1), n=49, field_mm=1.0)
    full = radial_fit(grid, max_side=49)
    sub = radial_fit(grid, max_side=33)
    # Residuals are means over all 49 x 49 points either way; the subgrid fit is close.
    assert sub[1] == pytest.approx(full[1], rel=0.01)
    assert sub[2] == pytest.approx(full[2], rel=0.01)
    assert sub[1] != full[1]  # and it really was a different fit
