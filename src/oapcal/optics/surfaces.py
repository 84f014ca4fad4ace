"""Mirror and plane surfaces: closed-form ray intersection, normals and reflection.

All functions are vectorized: points and directions are ``(..., 3)`` float arrays in mm,
in one global right-handed frame; ray parameters ``t`` are ``(...)``.  Directions need
not be unit vectors unless a docstring says so.

A :class:`Paraboloid` is the parent surface of an off-axis parabolic mirror (OAP),
``|r_perp|^2 = 4 f_p (r . a)`` with ``r = X - vertex``, ``a`` the unit axis pointing from
the vertex into the mirror's concave side (towards the focus) and ``f_p`` the parent
focal length.  A 90-degree OAP with reflected focal length ``f`` is the part of a
paraboloid with ``f_p = f / 2`` centred ``f`` off the axis (``oapcal.optics.relay``).

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


def _unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.einsum("...i,...i->...", a, b)


def _dot_const(r: np.ndarray, a) -> np.ndarray:
    """``r . a`` for points ``(..., 3)`` and a constant vector ``a`` (3,), skipping zero
    components of ``a`` (surfaces here are mostly axis-aligned: 2-3 times faster than
    ``einsum`` on a million rays)."""
    out = None
    for k, ak in enumerate(a):
        if ak != 0.0:
            term = r[..., k] * ak
            out = term if out is None else out + term
    return np.zeros(r.shape[:-1]) if out is None else out


def _combine(base, terms, shape) -> np.ndarray:
    """``base + sum(s_i * v_i)`` ``(*shape, 3)`` for a constant point ``base`` (3,), arrays
    ``s_i`` ``shape`` and constant vectors ``v_i`` (3,), one component at a time and
    skipping zero components (same reason as :func:`_dot_const`)."""
    out = np.empty(tuple(shape) + (3,))
    for k in range(3):
        comp = None
        for scalar, vec in terms:
            if vec[k] != 0.0:
                term = scalar * vec[k]
                comp = term if comp is None else comp + term
        out[..., k] = base[k] if comp is None else comp + base[k]
    return out


def reflect(direction: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """Mirror reflection ``d - 2 (d . n) n`` of directions ``(..., 3)``; ``normal`` must be unit."""
    direction = np.asarray(direction, dtype=float)
    return direction - 2.0 * _dot(direction, normal)[..., None] * normal


def _smallest_positive_root(a: np.ndarray, b: np.ndarray, c: np.ndarray, t_min: float) -> np.ndarray:
    """The smallest root > ``t_min`` of ``a t^2 + b t + c = 0`` (NaN if none), elementwise.

    Written with the cancellation-free pair ``q = -(b + sign(b) sqrt(b^2 - 4ac)) / 2``,
    ``t = q / a`` and ``t = c / q``, which also covers ``a = 0`` (a ray parallel to the
    axis of a paraboloid) without a special case.
    """
    with np.errstate(divide="ignore", invalid="ignore"):
        disc = b * b - 4.0 * a * c
        sq = np.sqrt(np.where(disc >= 0, disc, np.nan))
        q = -0.5 * (b + np.where(b >= 0, sq, -sq))
        t1 = q / a
        t2 = c / q
        t1 = np.where(np.isfinite(t1) & (t1 > t_min), t1, np.inf)
        t2 = np.where(np.isfinite(t2) & (t2 > t_min), t2, np.inf)
        t = np.minimum(t1, t2)
    return np.where(np.isfinite(t), t, np.nan)


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

    def _perp(self, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        along = _dot_const(r, self.axis)
        rp = r.copy()
        for k, ak in enumerate(self.axis):
            if ak != 0.0:
                rp[..., k] -= along * ak
        return rp, along

    def intersect(self, origin, direction, t_min: float = 1e-9) -> np.ndarray:
        """Ray parameter ``t`` of the first hit ``origin + t direction`` with ``t > t_min``.

        Substituting the ray into ``|r_perp|^2 = 4 f_p (r . a)`` gives the quadratic
        ``A t^2 + B t + C = 0`` with ``A = |d_perp|^2``, ``B = 2 r0_perp . d_perp -
        4 f_p (d . a)``, ``C = |r0_perp|^2 - 4 f_p (r0 . a)``.  NaN where the ray misses.
        """
        origin = np.asarray(origin, dtype=float)
        direction = np.asarray(direction, dtype=float)
        r0p, r0a = self._perp(origin - np.asarray(self.vertex))
        dp, da = self._perp(direction)
        a = _dot(dp, dp)
        b = 2.0 * _dot(r0p, dp) - 4.0 * self.focal_length * da
        c = _dot(r0p, r0p) - 4.0 * self.focal_length * r0a
        return _smallest_positive_root(a, b, c, t_min)

    def normal(self, point) -> np.ndarray:
        """Unit normals ``(..., 3)`` at surface points, pointing into the concave side.

        The gradient of ``4 f_p (r . a) - |r_perp|^2`` is ``4 f_p a - 2 r_perp``.
        """
        rp, _ = self._perp(np.asarray(point, dtype=float) - np.asarray(self.vertex))
        return _unit(2.0 * self.focal_length * np.asarray(self.axis) - rp)

    def point_at(self, u, v, e1, e2) -> np.ndarray:
        """Surface points ``(..., 3)`` at transverse coordinates ``u, v`` along unit vectors
        ``e1, e2`` (both perpendicular to the axis): ``vertex + u e1 + v e2 + (u^2 + v^2) /
        (4 f_p) a``."""
        u, v = np.broadcast_arrays(np.asarray(u, dtype=float), np.asarray(v, dtype=float))
        sag = (u * u + v * v) / (4.0 * self.focal_length)
        return _combine(self.vertex, [(u, tuple(e1)), (v, tuple(e2)), (sag, self.axis)], u.shape)

    def inside(self, point) -> np.ndarray:
        """Whether hits ``(..., 3)`` fall on the mirror (True everywhere without an aperture)."""
        point = np.asarray(point, dtype=float)
        if self.aperture_centre is None or self.aperture_radius is None:
            return np.isfinite(point).all(axis=-1)
        rp, _ = self._perp(point - np.asarray(self.aperture_centre))
        return _dot(rp, rp) <= self.aperture_radius**2


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

    def intersect(self, origin, direction) -> np.ndarray:
        """Ray parameter ``t`` where ``origin + t direction`` meets the plane (any sign;
        NaN for a ray parallel to it)."""
        origin = np.asarray(origin, dtype=float)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = _dot_const(np.asarray(self.point) - origin, self.normal) / _dot_const(
                np.asarray(direction, float), self.normal
            )
        return np.where(np.isfinite(t), t, np.nan)

    def local(self, point) -> np.ndarray:
        """In-plane coordinates ``(..., 2)`` of points ``(..., 3)`` relative to ``point``."""
        r = np.asarray(point, dtype=float) - np.asarray(self.point)
        return np.stack([_dot_const(r, self.ex), _dot_const(r, self.ey)], axis=-1)

    def world(self, xy) -> np.ndarray:
        """Points ``(..., 3)`` at in-plane coordinates ``xy (..., 2)``."""
        xy = np.asarray(xy, dtype=float)
        return _combine(self.point, [(xy[..., 0], self.ex), (xy[..., 1], self.ey)], xy.shape[:-1])
