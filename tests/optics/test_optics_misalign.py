"""Misaligned relays: regression against the aligned tracer, reflection, Fermat's principle,
symmetry, first-order behaviour and the sign conventions of ``docs/optics.md``."""

import csv

import numpy as np
import pytest

from oapcal.errors import GeometrySpecError
from oapcal.optics.misalign import PARAMETERS, SYMMETRIC, Misalignment
from oapcal.optics.relay import chief_rays, grid_distortion, oap_relay, paraxial_map, trace_through_stop
from paths import DATA

BASELINE = DATA / "relay_baseline.csv"
BASELINE_CASES = {
    "setup1_U": dict(setup=1),
    "setup2_Z_stop300": dict(setup=2, orientation="Z", stop_distance_mm=300.0),
    "d1_500_U_stop123_f40": dict(d1_mm=500.0, stop_distance_mm=123.0, focal_length_mm=40.0),
}
MIRROR_KEYS = ("tilt_x", "tilt_y", "decentre_x", "decentre_y", "clock")


def _baseline(name):
    with BASELINE.open() as fh:
        rows = [r for r in csv.reader(fh) if not r[0].startswith("#")][1:]
    return np.array([[float(v) for v in r[1:]] for r in rows if r[0] == name])


@pytest.mark.parametrize("name", list(BASELINE_CASES))
@pytest.mark.parametrize("misalignment", [None, Misalignment(), {"m2_tilt_x": 0.0}, {"m1_clock": 1e-12}])
def test_zero_misalignment_reproduces_the_aligned_trace(name, misalignment):
    # Rays traced by the tracer before misalignment existed (tests/data/relay_baseline.csv);
    # a 1e-12 deg clocking runs every general (non-axis-aligned) code path.
    ref = _baseline(name)
    relay = oap_relay(**BASELINE_CASES[name], misalignment=misalignment)
    xy = trace_through_stop(relay, ref[:, :2], ref[:, 2:4], full=False).xy_mm
    assert np.abs(xy - ref[:, 4:]).max() < 1e-12


# ---------------------------------------------------------------- independent geometry


def _rodrigues(axis, deg):
    """Right-handed rotation matrix about a unit ``axis`` (written out, not the library's)."""
    k = np.asarray(axis, float) / np.linalg.norm(axis)
    t = np.radians(deg)
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(t) * kx + (1 - np.cos(t)) * kx @ kx


def _nominal_normal(vertex, axis, fp, p):
    """Unit normal of the paraboloid ``|r_perp|^2 = 4 fp (r . a)`` at ``p`` (gradient)."""
    r = p - vertex
    perp = r - np.outer(r @ axis, axis)
    g = 4 * fp * axis - 2 * perp
    return g / np.linalg.norm(g, axis=-1, keepdims=True)


def _mirror_pose(nominal, values):
    """Rotation and centre of a mirror moved as docs/optics.md states: R = R_b R_a R_n about
    the centre, then the decentre along a, b."""
    c = np.asarray(nominal.aperture_centre)
    n = _nominal_normal(np.asarray(nominal.vertex), np.asarray(nominal.axis), nominal.focal_length, c[None])[
        0
    ]
    a = np.array([1.0, 0, 0])
    b = np.cross(n, a)
    rot = _rodrigues(b, values["tilt_y"]) @ _rodrigues(a, values["tilt_x"]) @ _rodrigues(n, values["clock"])
    return rot, c, c + values["decentre_x"] * a + values["decentre_y"] * b


MISALIGNED = Misalignment(
    m1_tilt_x=0.3, m1_tilt_y=-0.2, m1_decentre_x=0.4, m1_decentre_y=-0.3, m1_clock=2.0,
    m2_tilt_x=-0.25, m2_tilt_y=0.35, m2_decentre_x=-0.5, m2_decentre_y=0.2, m2_clock=-3.0,
)  # fmt: skip


@pytest.mark.parametrize("stop", [None, 200.0])
def test_hits_lie_on_the_moved_mirrors_and_obey_the_law_of_reflection(stop):
    nominal = oap_relay(1, stop_distance_mm=stop)
    relay = nominal.with_misalignment(MISALIGNED)
    rng = np.random.default_rng(3)
    obj = rng.uniform(-0.5, 0.5, (40, 2))
    pupil = rng.uniform(-6, 6, (40, 2))
    rays = trace_through_stop(relay, obj, pupil)
    assert rays.clear.all()
    start = relay.object_plane.world(obj)
    hit1, hit2 = rays.trace.hits
    d0 = (hit1 - start) / np.linalg.norm(hit1 - start, axis=-1, keepdims=True)
    d1 = (hit2 - hit1) / np.linalg.norm(hit2 - hit1, axis=-1, keepdims=True)
    d2 = rays.trace.direction
    for i, (hit, d_in, d_out) in enumerate(((hit1, d0, d1), (hit2, d1, d2)), start=1):
        mirror = nominal.mirrors[i - 1]
        rot, c, c_moved = _mirror_pose(mirror, MISALIGNED.mirror(i))
        back = (hit - c_moved) @ rot + c  # the hit carried back onto the nominal mirror
        v, ax, fp = np.asarray(mirror.vertex), np.asarray(mirror.axis), mirror.focal_length
        r = back - v
        along = r @ ax
        assert np.abs(((r - np.outer(along, ax)) ** 2).sum(-1) - 4 * fp * along).max() < 1e-8
        n = _nominal_normal(v, ax, fp, back) @ rot.T  # the moved mirror's normal
        # Law of reflection: d_out - d_in is along the normal, equal angles, coplanar.
        assert np.abs(np.cross(d_out - d_in, n)).max() < 1e-12
        assert np.allclose(np.abs(d_in @ n.T).diagonal(), np.abs((d_out * n).sum(-1)), atol=1e-12)
        assert np.abs(np.einsum("ij,ij->i", np.cross(d_in, n), d_out)).max() < 1e-12


def test_optical_path_is_stationary_on_tilted_mirrors():
    # Fermat: the traced path object -> q1 -> q2 -> image point is stationary when q1 and
    # q2 slide over their (moved) mirror surfaces; a wrong end point makes it not so.
    relay = oap_relay(1, stop_distance_mm=150.0).with_misalignment(MISALIGNED)
    obj = np.array([[0.4, -0.3], [-0.2, 0.5], [0.0, 0.0]])
    pupil = np.array([[3.0, -2.0], [-5.0, 1.0], [4.0, 4.0]])
    rays = trace_through_stop(relay, obj, pupil)
    p0 = relay.object_plane.world(obj)
    end = rays.trace.points
    mirrors = relay.mirrors

    def surface_frame(m):
        ax = np.asarray(m.axis)
        e1 = np.cross(ax, [0.3, 0.5, 0.8])
        e1 /= np.linalg.norm(e1)
        return e1, np.cross(ax, e1)

    frames = [surface_frame(m) for m in mirrors]
    uv0 = [((q - np.asarray(m.vertex)) @ np.stack(f).T) for q, m, f in zip(rays.trace.hits, mirrors, frames)]

    def path(uv, endpoint):
        q = [m.point_at(c[:, 0], c[:, 1], *f) for c, m, f in zip(uv, mirrors, frames)]
        return (np.linalg.norm(q[0] - p0, axis=-1) + np.linalg.norm(q[1] - q[0], axis=-1)
                + np.linalg.norm(endpoint - q[1], axis=-1))  # fmt: skip

    def gradient(endpoint):
        h = 1e-4
        g = []
        for mirror in range(2):
            for k in range(2):
                step = [np.zeros_like(uv0[0]), np.zeros_like(uv0[1])]
                step[mirror][:, k] = h
                plus = path([u + s for u, s in zip(uv0, step)], endpoint)
                minus = path([u - s for u, s in zip(uv0, step)], endpoint)
                g.append((plus - minus) / (2 * h))
        return np.abs(np.array(g)).max()

    assert np.allclose([m.point_at(c[:, 0], c[:, 1], *f) for c, m, f in zip(uv0, mirrors, frames)],
                       rays.trace.hits, atol=1e-9)  # fmt: skip
    assert gradient(end) < 1e-8
    assert gradient(end + [0.0, 0.0, 0.05]) > 1e-4  # off the ray: not stationary


# ---------------------------------------------------------------- symmetry and first order


def _field(relay, n=9, real=False):
    grid = grid_distortion(relay, n=n, field_mm=1.0)
    return (grid.xy_d if real else grid.displacement).reshape(n, n, 2)


@pytest.mark.parametrize("stop", [None, 250.0])
def test_symmetric_misalignments_keep_the_mirror_symmetry(stop):
    # The fold plane x = 0 stays a symmetry plane: the real image of (-x, y) is the real
    # image of (x, y) mirrored, so x is odd and y even in the object's x ...
    values = dict(zip(SYMMETRIC, np.linspace(0.05, 0.3, len(SYMMETRIC))))
    relay = oap_relay(1, stop_distance_mm=stop, misalignment=values)
    xy = _field(relay, real=True)
    assert np.abs(xy[:, ::-1, 0] + xy[:, :, 0]).max() < 1e-12
    assert np.abs(xy[:, ::-1, 1] - xy[:, :, 1]).max() < 1e-12
    # ... and so is the distortion (to the 1e-9 of the paraxial map's central differences).
    d = _field(relay)
    assert np.abs(d[:, ::-1, 0] + d[:, :, 0]).max() < 1e-8
    assert np.abs(d[:, ::-1, 1] - d[:, :, 1]).max() < 1e-8
    assert np.abs(d - _field(oap_relay(1, stop_distance_mm=stop))).max() > 1e-3  # it did change
    # Every other degree of freedom breaks it (but m1's clocking leaves the chief rays
    # alone with the stop at that mirror: they pass its centre, where neither the position
    # nor the normal changes).
    silent = {"m1_clock"} if stop is None else set()
    for key in sorted(set(PARAMETERS) - set(SYMMETRIC)):
        e = _field(oap_relay(1, stop_distance_mm=stop, misalignment={key: 0.2}), real=True)
        broken = np.abs(e[:, ::-1, 0] + e[:, :, 0]).max()
        assert (broken < 1e-12) if key in silent else (broken > 1e-6), key


def test_a_small_tilt_agrees_with_the_first_order_prediction():
    def field(tilt):
        return _field(oap_relay(1, misalignment={"m2_tilt_y": tilt}))

    base = field(0.0)
    h = 1e-3
    slope = (field(h) - field(-h)) / (2 * h)  # per deg, central differences
    errors = []
    for tilt in (0.04, 0.02):
        change = field(tilt) - base
        errors.append(np.abs(change - tilt * slope).max() / np.abs(change).max())
    assert errors[0] < 0.01  # the linear prediction holds within 1 % at 0.04 deg ...
    assert errors[0] / errors[1] == pytest.approx(2.0, rel=0.1)  # ... and the rest is second order


@pytest.mark.parametrize("mirror", [1, 2])
def test_a_mirror_tip_deflects_the_image_by_twice_the_angle_times_f(mirror):
    # Rotating a mirror by t about a (through its centre) turns the reflected central ray
    # by 2 t, which the focusing mirror turns into an image shift of 2 t f along y.
    t = 1e-4
    for f in (50.8, 30.0):
        _, offset = paraxial_map(oap_relay(1, focal_length_mm=f, misalignment={f"m{mirror}_tilt_x": t}))
        assert abs(offset[0]) < 1e-12
        assert abs(offset[1]) == pytest.approx(2 * np.radians(t) * f, rel=2e-4)


def test_moving_the_focusing_mirror_sideways_moves_the_image_with_it():
    # A paraboloid moved across a collimated beam carries its focus along.
    relay = oap_relay(1, misalignment={"m2_decentre_x": 0.2})
    grid = grid_distortion(relay, n=5)
    assert grid.offset == pytest.approx([0.2, 0.0], abs=1e-12)
    assert np.abs(grid.displacement - grid_distortion(oap_relay(1), n=5).displacement).max() < 1e-3


def test_d1_change_is_a_longer_design_and_stop_moves_with_the_first_mirror():
    a = chief_rays(oap_relay(1, misalignment={"d1": 12.5}), [[0.3, -0.4]]).xy_mm
    b = chief_rays(oap_relay(d1_mm=872.5), [[0.3, -0.4]]).xy_mm
    assert np.abs(a - b).max() < 1e-12
    # Stop at the first mirror: every chief ray hits its moved centre.
    relay = oap_relay(1, misalignment={"m1_tilt_x": 0.3, "m1_decentre_y": 0.5, "m1_tilt_y": -0.2})
    hits = chief_rays(relay, np.random.default_rng(1).uniform(-0.5, 0.5, (20, 2))).trace.hits[0]
    assert np.abs(hits - np.asarray(relay.m1.aperture_centre)).max() < 1e-9
    assert np.abs(np.asarray(relay.m1.aperture_centre) - [0.0, 50.8, 0.0]).max() > 0.3
    # A stop elsewhere stays put and a stop decentre moves the chief rays' crossing.
    relay = oap_relay(1, stop_distance_mm=300.0, misalignment={"m1_tilt_x": 0.3, "stop_decentre_x": 1.5})
    assert relay.stop.point == pytest.approx((1.5, 50.8, 300.0))


@pytest.mark.parametrize(
    "values,pattern",
    [
        ({"m3_tilt_x": 1.0}, "unknown misalignment 'm3_tilt_x'"),
        ({"m1_tilt_x": float("nan")}, "must be a finite number"),
        ({"m1_tilt_x": "abc"}, "must be a number"),
        ({"m2_focal_length": -60.0}, "leaves no mirror"),
        ({"d1": -900.0}, "leaves no collimated path"),
    ],
)
def test_bad_misalignments_raise_named_errors(values, pattern):
    with pytest.raises(GeometrySpecError, match=pattern):
        oap_relay(1, misalignment=values)


def test_the_command_line_offers_every_degree_of_freedom():
    from oapcal.cli.simulate_relay import MISALIGNMENT_UNITS

    # --d1 already sets the collimated path; every other parameter has its own option.
    assert MISALIGNMENT_UNITS == {k: unit for k, (unit, _) in PARAMETERS.items() if k != "d1"}


@pytest.mark.parametrize("orientation", ["U", "Z"])
def test_a_second_focal_length_magnifies_by_the_ratio(orientation):
    from oapcal.optics.relay import paraxial_matrix

    relay = oap_relay(1, orientation=orientation, focal_length_2_mm=60.0)
    assert np.allclose(paraxial_matrix(relay), -(60.0 / 50.8) * np.eye(2), atol=1e-8)
    # The camera sits at the second focus: the field centre is imaged at its origin.
    assert np.abs(chief_rays(relay, np.zeros(2)).xy_mm).max() < 1e-12
