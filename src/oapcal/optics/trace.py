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

from oapcal.optics.surfaces import Paraboloid, Plane, reflect


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


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def reflect_at(mirror: Paraboloid, origin: np.ndarray, direction: np.ndarray):
    """Intersect rays with one mirror and reflect them: ``(hit, new unit direction)``."""
    direction = _unit(np.asarray(direction, dtype=float))
    t = mirror.intersect(origin, direction)
    hit = origin + t[..., None] * direction
    return hit, reflect(direction, mirror.normal(hit))


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
    clear = np.ones(origin.shape[:-1], dtype=bool)
    hits = []
    for mirror in mirrors:
        origin, direction = reflect_at(mirror, origin, direction)
        hits.append(origin)
        clear &= mirror.inside(origin)
    t = plane.intersect(origin, direction)
    points = origin + t[..., None] * direction
    clear &= np.isfinite(points).all(axis=-1)
    return TraceResult(tuple(hits), points, plane.local(points), direction, clear)
