"""Sequential real-ray tracing through mirrors onto a plane, vectorized over rays.

>>> import numpy as np
>>> from oapcal.optics.surfaces import Paraboloid, Plane
>>> mirror = Paraboloid(vertex=(0, 0, -1.0), axis=(0, 0, 1), focal_length=1.0)
>>> screen = Plane(point=(0, 0, 0), normal=(0, 0, 1), ex=(1, 0, 0), ey=(0, 1, 0))
>>> origins = np.array([[0.5, 0.0, 5.0], [0.0, -1.5, 5.0]])
>>> result = trace(origins, np.array([0.0, 0.0, -1.0]), [mirror], screen)
>>> bool(np.allclose(result.xy, 0.0))  # rays parallel to the axis meet at the focus
True
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from oapcal.optics.surfaces import Paraboloid, Plane, Vec, axpy_c, dot_c, join, reflect_c, split, unit_c


@dataclass(frozen=True)
class TraceResult:
    """Rays traced to a plane.

    ``hits``: one ``(..., 3)`` array of hit points per mirror, in order; ``points``
    ``(..., 3)`` where the rays meet the final plane, ``xy`` ``(..., 2)`` the same in the
    plane's local coordinates (mm), ``direction`` ``(..., 3)`` unit directions after the
    last mirror; ``clear`` ``(...)`` bool, the ray hit every mirror inside its aperture
    (rays that miss a surface altogether come back as NaN and not clear).
    """

    hits: tuple[np.ndarray, ...]
    points: np.ndarray
    xy: np.ndarray
    direction: np.ndarray
    clear: np.ndarray


def reflect_at_c(mirror: Paraboloid, origin: Vec, direction: Vec) -> tuple[Vec, Vec]:
    """:func:`reflect_at` on component triples; ``direction`` must be unit."""
    t = mirror.intersect_c(origin, direction)
    hit = axpy_c(t, direction, origin)
    return hit, reflect_c(direction, mirror.normal_c(hit))


def reflect_at(mirror: Paraboloid, origin: np.ndarray, direction: np.ndarray):
    """Intersect rays with one mirror and reflect them: ``(hit, new unit direction)``."""
    origin = np.asarray(origin, dtype=float)
    direction = np.asarray(direction, dtype=float)
    hit, out = reflect_at_c(mirror, split(origin), unit_c(split(direction)))
    return join(hit), join(out)


def trace_c(origin: Vec, direction: Vec, mirrors: Sequence[Paraboloid], plane: Plane):
    """:func:`trace` on component triples (``direction`` unit): returns ``(hits, points,
    (x, y), direction, clear)`` with vectors as component triples."""
    clear = True
    hits = []
    for mirror in mirrors:
        origin, direction = reflect_at_c(mirror, origin, direction)
        hits.append(origin)
        clear = clear & mirror.inside_c(origin)
    t = plane.intersect_c(origin, direction)
    points = axpy_c(t, direction, origin)
    xy = plane.local_c(points)
    clear = clear & np.isfinite(t) & np.isfinite(dot_c(points, points))
    return hits, points, xy, direction, clear


def trace(
    origin: np.ndarray,
    direction: np.ndarray,
    mirrors: Sequence[Paraboloid],
    plane: Plane,
) -> TraceResult:
    """Trace rays ``origin + t direction`` (``(..., 3)``, broadcast together) through
    ``mirrors`` in order, then onto ``plane`` (where they meet its extension, before or
    after the last mirror)."""
    origin, direction = np.broadcast_arrays(np.asarray(origin, float), np.asarray(direction, float))
    shape = origin.shape
    hits, points, xy, out, clear = trace_c(split(origin), unit_c(split(direction)), mirrors, plane)
    xy = np.stack(np.broadcast_arrays(*(np.asarray(c, dtype=float) for c in xy)), axis=-1)

    def full(v):
        return np.broadcast_to(join(v), shape).copy()

    xy = np.broadcast_to(xy, shape[:-1] + (2,)).copy()
    clear = np.broadcast_to(clear, shape[:-1]).copy()
    return TraceResult(tuple(full(h) for h in hits), full(points), xy, full(out), clear)
