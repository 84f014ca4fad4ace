"""Normalizations of point sets used by the paper.

``experiment`` (the paper's Figure 2 caption; ``--normalize experiment``): the reference
points, which come from another imaging system, are scaled about their top-left corner
(aspect ratio kept) so that their y range equals the distorted points' y range, then
translated so that both sets are aligned along the top and the left (their min x and
min y coincide).  Only the reference points change.

``grid`` (the paper's simulated data; ``--normalize grid``): each of the two point sets is,
independently, centred on the middle of its x and y ranges and scaled (aspect ratio kept)
to span -0.5 .. +0.5 in y.  Both sets change; the distortion centre is then unknown, as in
an experiment.

>>> import numpy as np
>>> ref = np.array([[0.0, 0.0], [10.0, 0.0], [0.0, 20.0]])
>>> dist = np.array([[5.0, 3.0], [10.0, 3.0], [5.0, 13.0]])
>>> normalize_experiment(ref, dist).xy_u
array([[ 5.,  3.],
       [10.,  3.],
       [ 5., 13.]])
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from oapcal.errors import DataError
from oapcal.validate import point_pairs

NORMALIZATIONS = ("none", "experiment", "grid")


@dataclass(frozen=True)
class Normalized:
    """Normalized point sets and the factors applied.

    ``scale_u`` multiplies the reference coordinates (new = (old - origin) * scale + shift),
    so a scale of ``S`` um per px of the original reference points becomes ``S / scale_u``
    um per unit of the normalized ones.
    """

    xy_u: np.ndarray
    xy_d: np.ndarray
    scale_u: float
    scale_d: float


def similarity(points: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The least-squares similarity (rotation, scale, shift) taking ``points`` ``(..., N, 2)``
    onto ``target`` ``(N, 2)`` or ``(..., N, 2)``, in complex form: ``t - c_t = a (p - c_p)``
    with ``c`` each set's centroid and ``a = sum conj(p') t' / sum |p'|^2`` (``|a|`` the
    scale, ``arg a`` the turn).  Returns ``(a, zp - c_p, zt - c_t)``: ``a`` of shape
    ``(...)`` (1 where the points have no spread) and the centred complex points.

    >>> p = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
    >>> a, _, _ = similarity(p, 2 * p[:, ::-1] * [-1, 1])       # turned by 90 deg, scaled by 2
    >>> round(float(abs(a)), 12), round(float(np.degrees(np.angle(a))), 9)
    (2.0, 90.0)
    """
    points = np.asarray(points, float)
    target = np.asarray(target, float)
    zp = points[..., 0] + 1j * points[..., 1]
    zt = target[..., 0] + 1j * target[..., 1]
    pc = zp - zp.mean(-1, keepdims=True)
    tc = zt - zt.mean(-1, keepdims=True)
    norm = (np.abs(pc) ** 2).sum(-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        a = np.where(norm > 0, (np.conj(pc) * tc).sum(-1) / np.where(norm > 0, norm, 1.0), 1.0 + 0.0j)
    return a, pc, tc


def _yrange(xy: np.ndarray, label: str) -> float:
    span = float(np.ptp(xy[:, 1]))
    if not span > 0:
        raise DataError(f"cannot normalize: the {label} points have no extent in y")
    return span


def normalize_experiment(xy_u, xy_d) -> Normalized:
    """The paper's experimental normalization (module docstring)."""
    xy_u = np.asarray(xy_u, float)
    xy_d = np.asarray(xy_d, float)
    s = _yrange(xy_d, "distorted") / _yrange(xy_u, "reference")
    out = (xy_u - xy_u.min(axis=0)) * s + xy_d.min(axis=0)
    return Normalized(out, xy_d.copy(), s, 1.0)


def normalize_grid(xy_u, xy_d) -> Normalized:
    """The paper's simulated-grid normalization (module docstring)."""

    def one(xy, label):
        xy = np.asarray(xy, float)
        centre = 0.5 * (xy.min(axis=0) + xy.max(axis=0))
        s = 1.0 / _yrange(xy, label)
        return (xy - centre) * s, s

    u, su = one(xy_u, "reference")
    d, sd = one(xy_d, "distorted")
    return Normalized(u, d, su, sd)


def normalize(kind: str, xy_u, xy_d) -> Normalized:
    """Apply the normalization named ``kind`` (``none``, ``experiment`` or ``grid``).

    The points enter the fits here (:func:`oapcal.calibrate`, :func:`oapcal.select_models`,
    :func:`oapcal.robustness`): both must be ``(N, 2)`` arrays of finite numbers of one
    length (:func:`oapcal.validate.point_pairs`), else :class:`DataError` naming ``xy_u`` or
    ``xy_d``."""
    xy_u, xy_d = point_pairs(xy_u, xy_d)
    if kind in (None, "none"):
        return Normalized(np.asarray(xy_u, float), np.asarray(xy_d, float), 1.0, 1.0)
    if kind == "experiment":
        return normalize_experiment(xy_u, xy_d)
    if kind == "grid":
        return normalize_grid(xy_u, xy_d)
    raise DataError(f"unknown normalization {kind!r}: use one of {', '.join(NORMALIZATIONS)}")
