"""Mirror and plane surfaces: closed-form ray intersection, normals and reflection.

All public functions are vectorized: points and directions are ``(..., 3)`` float arrays
in mm, in one global right-handed frame; ray parameters ``t`` are ``(...)``.  Directions
need not be unit vectors unless a docstring says so.

A :class:`Paraboloid` is the parent surface of an off-axis parabolic mirror (OAP),
``|r_perp|^2 = 4 f_p (r . a)`` with ``r = X - vertex``, ``a`` the unit axis pointing from
the vertex into the mirror's concave side (towards the focus) and ``f_p`` the parent
focal length.  A 90-degree OAP with reflected focal length ``f`` is the part of a
paraboloid with ``f_p = f / 2`` centred ``f`` off the axis (``oapcal.optics.relay``).

Every method also has a *component* form (``intersect_c``, ``normal_c``, ...) that takes
and returns vectors as triples ``(x, y, z)`` of arrays (or plain floats, which
broadcast).  The tracer uses those: each component is a contiguous array, and products
with the exact zeros of axis-aligned surfaces are skipped, which makes a million-ray
trace several times faster than on interleaved ``(..., 3)`` arrays (see
``benchmarks/bench_optics.py``).

>>> import numpy as np
>>> mirror = Paraboloid(vertex=(0, 0, -1.0), axis=(0, 0, 1), focal_length=1.0)
>>> origin = np.array([0.5, 0.0, 10.0]); direction = np.array([0.0, 0.0, -1.0])
>>> t = mirror.intersect(origin, direction)
>>> hit = origin + t * direction
>>> out = reflect(direction, mirror.normal(hit))
>>> s = -hit[0] / out[0]  # the reflected ray crosses the axis ...
>>> bool(np.allclose(hit + s * out, [0, 0, 0]))  # ... at the focus
True
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: A vector as three components, each an array or a plain float (broadcast together).
Vec = tuple


def _unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.einsum("...i,...i->...", a, b)


def _zero(x) -> bool:
    return isinstance(x, float) and x == 0.0


def split(v) -> Vec:
    """``(..., 3)`` array -> component triple (views)."""
    v = np.asarray(v, dtype=float)
    return (v[..., 0], v[..., 1], v[..., 2])


def join(v: Vec) -> np.ndarray:
    """Component triple -> ``(..., 3)`` array (plain floats broadcast to the shape)."""
    return np.stack(np.broadcast_arrays(*(np.asarray(c, dtype=float) for c in v)), axis=-1)


def dot_c(a: Vec, b: Vec):
    """``a . b`` of component triples, skipping exact (float) zeros."""
    out = None
    for x, y in zip(a, b):
        if _zero(x) or _zero(y):
            continue
        term = x * y
        out = term if out is None else out + term
    return 0.0 if out is None else out


def sub_c(a: Vec, b: Vec) -> Vec:
    """``a - b`` componentwise (skipping subtraction of exact zeros)."""
    return tuple(x if _zero(y) else (-y if _zero(x) else x - y) for x, y in zip(a, b))


def axpy_c(s, d: Vec, o: Vec) -> Vec:
    """``o + s d`` componentwise for a scalar field ``s``."""
    return tuple(x if _zero(y) else x + s * y for x, y in zip(o, d))


def unit_c(v: Vec) -> Vec:
    """``v / |v|`` componentwise."""
    n = np.sqrt(dot_c(v, v))
    return tuple(x if _zero(x) else x / n for x in v)


def reflect_c(d: Vec, n: Vec) -> Vec:
    """Mirror reflection ``d - 2 (d . n) n`` of component triples; ``n`` must be unit."""
    s = 2.0 * dot_c(d, n)
    return tuple(x if _zero(y) else x - s * y for x, y in zip(d, n))


def reflect(direction: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """Mirror reflection ``d - 2 (d . n) n`` of directions ``(..., 3)``; ``normal`` must be unit."""
    direction = np.asarray(direction, dtype=float)
    return direction - 2.0 * _dot(direction, normal)[..., None] * normal


def _smallest_positive_root(a, b, c, t_min: float) -> np.ndarray:
    """The smallest root > ``t_min`` of ``a t^2 + b t + c = 0`` (NaN if none), elementwise.

    Written with the cancellation-free pair ``q = -(b + sign(b) sqrt(b^2 - 4ac)) / 2``,
    ``t = q / a`` and ``t = c / q``, which also covers ``a = 0`` (a ray parallel to the
    axis of a paraboloid) without a special case.
    """
    with np.errstate(divide="ignore", invalid="ignore"):
        sq = np.sqrt(b * b - 4.0 * a * c)  # NaN where the ray misses
        q = -0.5 * (b + np.copysign(sq, b))
        t1 = q / a
        t2 = c / q
        # NaN and -inf fail the test and become +inf; +inf stays (no root there).
        t1 = np.where(t1 > t_min, t1, np.inf)
        t2 = np.where(t2 > t_min, t2, np.inf)
        t = np.asarray(np.minimum(t1, t2))
    t[np.isinf(t)] = np.nan
    return t


@dataclass(frozen=True)
class Paraboloid:
    """A paraboloid of revolution (a mirror's parent surface).

    ``vertex`` (3,) mm, ``axis`` (3,) direction from the vertex towards the focus (made
    unit), ``focal_length`` the parent focal length ``f_p`` (vertex to focus), mm.
    ``aperture_centre`` and ``aperture_radius`` optionally bound the mirror: a hit is
    inside the mirror when its distance from ``aperture_centre`` measured perpendicular
    to the axis is at most ``aperture_radius`` (a round mirror cut parallel to the axis).
    """

    vertex: tuple
    axis: tuple
    focal_length: float
    aperture_centre: tuple | None = None
    aperture_radius: float | None = None

    def __post_init__(self):
        object.__setattr__(self, "vertex", tuple(float(v) for v in self.vertex))
        object.__setattr__(self, "axis", tuple(float(v) for v in _unit(self.axis)))
        if self.aperture_centre is not None:
            object.__setattr__(self, "aperture_centre", tuple(float(v) for v in self.aperture_centre))

    @property
    def focus(self) -> np.ndarray:
        """The focus ``vertex + f_p axis`` (3,)."""
        return np.asarray(self.vertex) + self.focal_length * np.asarray(self.axis)

    # ------------------------------------------------------------ component forms

    def _perp_c(self, r: Vec) -> tuple[Vec, object]:
        """``(r_perp, r . a)``; for an axis along a coordinate axis the component along it
        is exactly 0 (returned as the float 0.0, so later products skip it)."""
        a = self.axis
        along = dot_c(r, a)
        rp = tuple(
            0.0 if abs(ak) == 1.0 else (rk if ak == 0.0 else (-along * ak if _zero(rk) else rk - along * ak))
            for rk, ak in zip(r, a)
        )
        return rp, along

    def intersect_c(self, origin: Vec, direction: Vec, t_min: float = 1e-9) -> np.ndarray:
        """:meth:`intersect` on component triples."""
        r0p, r0a = self._perp_c(sub_c(origin, self.vertex))
        dp, da = self._perp_c(direction)
        four_f = 4.0 * self.focal_length
        a = dot_c(dp, dp)
        b = 2.0 * dot_c(r0p, dp) - four_f * da
        c = dot_c(r0p, r0p) - four_f * r0a
        a, b, c = np.broadcast_arrays(*(np.asarray(v, dtype=float) for v in (a, b, c)))
        return _smallest_positive_root(a, b, c, t_min)

    def normal_c(self, point: Vec) -> Vec:
        """:meth:`normal` on component triples."""
        rp, _ = self._perp_c(sub_c(point, self.vertex))
        two_f = 2.0 * self.focal_length
        g = tuple((two_f * ak if ak != 0.0 else 0.0) if _zero(rk) else two_f * ak - rk for rk, ak in
                  zip(rp, self.axis))  # fmt: skip
        return unit_c(g)

    def point_at_c(self, u, v, e1, e2) -> Vec:
        """:meth:`point_at` on component triples."""
        sag = (u * u + v * v) / (4.0 * self.focal_length)
        out = []
        for k in range(3):
            comp = self.vertex[k]
            for s, e in ((u, e1[k]), (v, e2[k]), (sag, self.axis[k])):
                if e != 0.0:
                    comp = comp + (s if e == 1.0 else s * e)
            out.append(comp)
        return tuple(out)

    def inside_c(self, point: Vec) -> np.ndarray:
        """:meth:`inside` on component triples."""
        if self.aperture_centre is None or self.aperture_radius is None:
            return np.isfinite(dot_c(point, point))
        rp, _ = self._perp_c(sub_c(point, self.aperture_centre))
        return dot_c(rp, rp) <= self.aperture_radius**2

    # ------------------------------------------------------------ array forms

    def intersect(self, origin, direction, t_min: float = 1e-9) -> np.ndarray:
        """Ray parameter ``t`` of the first hit ``origin + t direction`` with ``t > t_min``.

        Substituting the ray into ``|r_perp|^2 = 4 f_p (r . a)`` gives the quadratic
        ``A t^2 + B t + C = 0`` with ``A = |d_perp|^2``, ``B = 2 r0_perp . d_perp -
        4 f_p (d . a)``, ``C = |r0_perp|^2 - 4 f_p (r0 . a)``.  NaN where the ray misses.
        """
        return self.intersect_c(split(origin), split(direction), t_min)

    def normal(self, point) -> np.ndarray:
        """Unit normals ``(..., 3)`` at surface points, pointing into the concave side.

        The gradient of ``4 f_p (r . a) - |r_perp|^2`` is ``4 f_p a - 2 r_perp``.
        """
        point = np.asarray(point, dtype=float)
        n = join(self.normal_c(split(point)))
        return np.broadcast_to(n, point.shape).copy() if n.shape != point.shape else n

    def point_at(self, u, v, e1, e2) -> np.ndarray:
        """Surface points ``(..., 3)`` at transverse coordinates ``u, v`` along unit vectors
        ``e1, e2`` (both perpendicular to the axis): ``vertex + u e1 + v e2 + (u^2 + v^2) /
        (4 f_p) a``."""
        u, v = np.broadcast_arrays(np.asarray(u, dtype=float), np.asarray(v, dtype=float))
        e1 = tuple(float(x) for x in e1)
        e2 = tuple(float(x) for x in e2)
        return join(self.point_at_c(u, v, e1, e2))

    def inside(self, point) -> np.ndarray:
        """Whether hits ``(..., 3)`` fall on the mirror (True everywhere without an aperture)."""
        return np.asarray(self.inside_c(split(point)))


@dataclass(frozen=True)
class Plane:
    """A plane through ``point`` with unit ``normal`` (3,), and in-plane unit axes
    ``ex, ey`` (``ex x ey`` is parallel to the normal) for local coordinates."""

    point: tuple
    normal: tuple
    ex: tuple
    ey: tuple

    def __post_init__(self):
        for name in ("point", "normal", "ex", "ey"):
            value = np.asarray(getattr(self, name), dtype=float)
            if name != "point":
                value = _unit(value)
            object.__setattr__(self, name, tuple(float(v) for v in value))

    def intersect_c(self, origin: Vec, direction: Vec) -> np.ndarray:
        """:meth:`intersect` on component triples."""
        p_n = float(np.dot(self.point, self.normal))
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.divide(np.subtract(p_n, dot_c(origin, self.normal)), dot_c(direction, self.normal))
        return np.where(np.isfinite(t), t, np.nan)

    def local_c(self, point: Vec) -> tuple:
        """:meth:`local` on component triples: ``(x, y)``."""
        px = float(np.dot(self.point, self.ex))
        py = float(np.dot(self.point, self.ey))
        return dot_c(point, self.ex) - px, dot_c(point, self.ey) - py

    def world_c(self, x, y) -> Vec:
        """:meth:`world` on components: ``x``, ``y`` arrays -> component triple."""
        out = []
        for k in range(3):
            comp = self.point[k]
            for s, e in ((x, self.ex[k]), (y, self.ey[k])):
                if e != 0.0:
                    comp = comp + (s if e == 1.0 else s * e)
            out.append(comp)
        return tuple(out)

    def intersect(self, origin, direction) -> np.ndarray:
        """Ray parameter ``t`` where ``origin + t direction`` meets the plane (any sign;
        NaN for a ray parallel to it)."""
        return self.intersect_c(split(origin), split(direction))

    def local(self, point) -> np.ndarray:
        """In-plane coordinates ``(..., 2)`` of points ``(..., 3)`` relative to ``point``."""
        point = np.asarray(point, dtype=float)
        x, y = self.local_c(split(point))
        return np.stack(np.broadcast_arrays(x, y), axis=-1)

    def world(self, xy) -> np.ndarray:
        """Points ``(..., 3)`` at in-plane coordinates ``xy (..., 2)``."""
        xy = np.asarray(xy, dtype=float)
        x, y = xy[..., 0], xy[..., 1]
        comps = self.world_c(x, y)
        return np.stack([np.broadcast_to(np.asarray(c, dtype=float), x.shape) for c in comps], axis=-1)
