"""Surfaces and the tracer: closed-form intersection and reflection against geometry."""

import numpy as np
import pytest
from scipy.optimize import brentq

from oapcal.optics.surfaces import Paraboloid, Plane, reflect
from oapcal.optics.trace import trace


def _rotation(rng):
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    return q * np.sign(np.linalg.det(q))


@pytest.mark.parametrize("tilted", [False, True])
def test_rays_parallel_to_the_axis_meet_at_the_focus(tilted):
    rng = np.random.default_rng(7)
    rot = _rotation(rng) if tilted else np.eye(3)
    fp = 25.4
    axis = rot @ [0.0, 0.0, 1.0]
    vertex = rot @ [0.0, 0.0, -fp] + (rng.normal(size=3) * 10 if tilted else 0.0)
    mirror = Paraboloid(vertex=vertex, axis=axis, focal_length=fp)
    # 1000 rays over a 50.8 mm mirror centred 50.8 mm off the axis, coming in along -axis.
    r = 25.4 * np.sqrt(rng.uniform(size=1000))
    phi = rng.uniform(0, 2 * np.pi, size=1000)
    local = np.stack([r * np.cos(phi), 50.8 + r * np.sin(phi), np.full(1000, 200.0)], -1)
    origins = local @ rot.T + vertex + rot @ [0, 0, fp]
    direction = -axis
    t = mirror.intersect(origins, direction)
    hit = origins + t[:, None] * direction
    out = reflect(np.broadcast_to(direction, hit.shape), mirror.normal(hit))
    # Distance from the focus to each reflected line: |(F - hit) x out| / |out|.
    dist = np.linalg.norm(np.cross(mirror.focus - hit, out), axis=-1) / np.linalg.norm(out, axis=-1)
    assert dist.max() < 1e-12


def test_intersection_agrees_with_a_bracketing_root_finder():
    rng = np.random.default_rng(3)
    mirror = Paraboloid(vertex=(1.0, -2.0, -25.4), axis=(0.1, 0.0, 1.0), focal_length=25.4)
    origins = rng.uniform(-20, 20, size=(20, 3)) + [0, 40, 0]
    directions = rng.normal(size=(20, 3)) * 0.3 + [0, 0, -1]
    t = mirror.intersect(origins, directions)
    a = np.asarray(mirror.axis)

    def g(s, o, d):
        rr = o + s * d - np.asarray(mirror.vertex)
        along = rr @ a
        return (rr - along * a) @ (rr - along * a) - 4 * mirror.focal_length * along

    for o, d, ti in zip(origins, directions, t):
        # Independent: scan for the first sign change, then refine with brentq.
        s = np.linspace(1e-9, 1e3, 200001)
        vals = np.array([g(x, o, d) for x in s[::100]])
        change = np.flatnonzero(np.sign(vals[1:]) != np.sign(vals[:-1]))
        if change.size == 0:
            assert np.isnan(ti)
            continue
        k = change[0]
        ref = brentq(g, s[::100][k], s[::100][k + 1], args=(o, d), xtol=1e-14)
        assert ti == pytest.approx(ref, rel=1e-10, abs=1e-10)


def test_plane_local_and_world_are_inverse_and_trace_hits_plane():
    plane = Plane(point=(1, 2, 3), normal=(0, 1, 1), ex=(1, 0, 0), ey=(0, 1, -1))
    xy = np.array([[0.5, -2.0], [3.0, 1.0]])
    assert np.allclose(plane.local(plane.world(xy)), xy)
    mirror = Paraboloid(vertex=(0, 0, -1.0), axis=(0, 0, 1), focal_length=1.0)
    screen = Plane(point=(0, 0, 0), normal=(0, 0, 1), ex=(1, 0, 0), ey=(0, 1, 0))
    res = trace(np.array([[0.3, 0.4, 5.0]]), np.array([0.0, 0.0, -1.0]), [mirror], screen)
    assert np.abs(res.xy).max() < 1e-14 and res.clear.all()
