"""The distortion model of the paper's Eq. (1): parameter layout, presets, forward map,
analytic Jacobians and the Newton inverse.

The map goes from *undistorted* (reference, ideal, paraxial) coordinates ``(x_u, y_u)``
to *distorted* (observed) coordinates ``(x_d, y_d)``; see ``docs/models.md``::

    xb = m (x_u + x_off),  yb = m (y_u + y_off),  r2 = xb^2 + yb^2
    xb_d = xb (1 + k1 r2 + k2 r2^2) + 2 p1 xb yb + p2 (r2 + 2 xb^2) + s1 r2 + s2 r2^2
    yb_d = yb (1 + k1 r2 + k2 r2^2) + p1 (r2 + 2 yb^2) + 2 p2 xb yb + s3 r2 + s4 r2^2
    x_d = xb_d + c_x,  y_d = yb_d + c_y

The tangential terms follow OpenCV's convention (``docs/models.md`` explains why).

Shapes and broadcasting
-----------------------
Points are ``(..., N, 2)`` arrays with x = column, y = row (``docs/conventions.md``).
Parameters are ``(..., 13)`` arrays in the order of :data:`PARAM_NAMES`; their leading
dimensions broadcast against the points' leading dimensions, so ``params`` of shape
``(B, 13)`` with points ``(N, 2)`` evaluates B models on the same points, and with
points ``(B, N, 2)`` evaluates each model on its own points.

A *model* (a subset of free parameters) is a boolean mask of shape ``(13,)``; ``m`` is
always free, every other parameter is free or fixed at 0.  The 12 other flags form the
*bits* of the subset: bit ``i`` is parameter ``PARAM_NAMES[i]`` for ``i < 12``.

Example
-------
>>> import numpy as np
>>> p = params_from_dict({"k1": 1e-2, "m": 1.0})
>>> distort(np.array([[1.0, 0.0]]), p)
array([[1.01, 0.  ]])
>>> inv = undistort(np.array([[1.01, 0.0]]), p)
>>> bool(inv.converged[0]), bool(np.allclose(inv.xy, [[1.0, 0.0]]))
(True, True)
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from oapcal.errors import ModelSpecError

#: The 13 parameters of Eq. (1), in the one order used everywhere in oapcal.
PARAM_NAMES: tuple[str, ...] = (
    "k1", "k2", "p1", "p2", "s1", "s2", "s3", "s4", "x_off", "y_off", "c_x", "c_y", "m",
)  # fmt: skip
N_PARAMS = len(PARAM_NAMES)
INDEX: dict[str, int] = {name: i for i, name in enumerate(PARAM_NAMES)}
#: Number of optional parameters (all but ``m``); there are ``2**N_OPTIONAL`` models.
N_OPTIONAL = N_PARAMS - 1

#: Named models. ``paper`` is the paper's Eq. (2) plus ``x_off``.
PRESETS: dict[str, tuple[str, ...]] = {
    "full": PARAM_NAMES,
    "paper": ("k1", "p1", "s3", "x_off", "y_off", "c_x", "c_y", "m"),
    "radial": ("k1", "x_off", "y_off", "c_x", "c_y", "m"),
}

#: How each parameter scales when all coordinates are divided by a factor ``f``:
#: the parameter is multiplied by ``f ** SCALE_EXPONENTS[i]``.  This reparametrization is
#: exact (the model in the new units gives the old distorted points divided by ``f``).
SCALE_EXPONENTS = np.array([2, 4, 1, 1, 1, 3, 1, 3, -1, -1, -1, -1, 0], dtype=float)


# --------------------------------------------------------------------------- models


def parse_model(spec: str | Mapping | np.ndarray | tuple | list) -> np.ndarray:
    """Return the free-parameter mask ``(13,) bool`` of a model specification.

    ``spec`` is a preset name (``full``, ``paper``, ``radial``), a comma-separated list of
    parameter names (``"k1,p1,s3,y_off,c_x,c_y"``; ``m`` is added if missing), a sequence
    of names, or a boolean mask.

    >>> names_from_mask(parse_model("k1, c_x"))
    ('k1', 'c_x', 'm')
    """
    if isinstance(spec, np.ndarray) and spec.dtype == bool:
        if spec.shape != (N_PARAMS,):
            raise ModelSpecError(f"a model mask must have shape ({N_PARAMS},), got {spec.shape}")
        mask = spec.copy()
    else:
        if isinstance(spec, str):
            key = spec.strip()
            if key in PRESETS:
                names = PRESETS[key]
            else:
                names = tuple(n.strip() for n in key.split(",") if n.strip())
                if not names:
                    raise ModelSpecError(
                        "empty model specification: give a preset "
                        f"({', '.join(PRESETS)}) or a comma list of parameter names"
                    )
        else:
            names = tuple(spec)
        mask = np.zeros(N_PARAMS, dtype=bool)
        for name in names:
            if name not in INDEX:
                raise ModelSpecError(
                    f"unknown parameter or preset {name!r} in model specification: use a preset "
                    f"({', '.join(PRESETS)}) or names from {' '.join(PARAM_NAMES)}"
                )
            mask[INDEX[name]] = True
    mask[INDEX["m"]] = True
    return mask


def names_from_mask(mask: np.ndarray) -> tuple[str, ...]:
    """The names of the free parameters of a mask, in :data:`PARAM_NAMES` order."""
    return tuple(name for name, free in zip(PARAM_NAMES, np.asarray(mask, bool)) if free)


def mask_from_bits(bits: int | np.ndarray) -> np.ndarray:
    """Masks ``(..., 13)`` from 12-bit subset numbers (bit i = ``PARAM_NAMES[i]``; m free)."""
    bits = np.asarray(bits, dtype=np.int64)
    mask = np.ones(bits.shape + (N_PARAMS,), dtype=bool)
    mask[..., :N_OPTIONAL] = (bits[..., None] >> np.arange(N_OPTIONAL)) & 1 == 1
    return mask


def bits_from_mask(mask: np.ndarray) -> np.ndarray:
    """Inverse of :func:`mask_from_bits`: the 12-bit subset numbers of masks ``(..., 13)``."""
    mask = np.asarray(mask, dtype=bool)
    return (mask[..., :N_OPTIONAL].astype(np.int64) << np.arange(N_OPTIONAL)).sum(axis=-1)


def all_masks() -> np.ndarray:
    """All ``2**12 = 4096`` models as masks ``(4096, 13)``, ordered by their bits."""
    return mask_from_bits(np.arange(2**N_OPTIONAL))


# ------------------------------------------------------------------- parameter vectors


def params_from_dict(values: Mapping[str, float], base: np.ndarray | None = None) -> np.ndarray:
    """A full ``(13,)`` parameter vector from a name -> value mapping.

    Unnamed parameters come from ``base`` (default: all 0 with ``m = 1``).
    """
    params = identity_params() if base is None else np.array(base, dtype=float)
    for name, value in values.items():
        if name not in INDEX:
            raise ModelSpecError(f"unknown parameter {name!r}: use names from {' '.join(PARAM_NAMES)}")
        params[INDEX[name]] = float(value)
    return params


def params_to_dict(params: np.ndarray) -> dict[str, float]:
    """Name -> value for a ``(13,)`` parameter vector."""
    return {name: float(v) for name, v in zip(PARAM_NAMES, np.asarray(params, float))}


def identity_params() -> np.ndarray:
    """The identity model: all parameters 0 and ``m = 1``."""
    params = np.zeros(N_PARAMS)
    params[INDEX["m"]] = 1.0
    return params


def pack(params: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """The free values ``(..., k)`` of full parameter vectors ``(..., 13)`` under one mask."""
    return np.asarray(params, float)[..., np.asarray(mask, bool)]


def unpack(free: np.ndarray, mask: np.ndarray, fixed: np.ndarray | None = None) -> np.ndarray:
    """Full vectors ``(..., 13)`` from free values ``(..., k)``; fixed ones from ``fixed`` (0)."""
    free = np.asarray(free, float)
    mask = np.asarray(mask, bool)
    out = np.zeros(free.shape[:-1] + (N_PARAMS,)) if fixed is None else np.array(fixed, float)
    out = np.broadcast_to(out, free.shape[:-1] + (N_PARAMS,)).copy()
    out[..., mask] = free
    return out


def scale_params(params: np.ndarray, factor: float) -> np.ndarray:
    """Parameters for coordinates divided by ``factor`` (an exact reparametrization).

    ``distort(xy / f, scale_params(p, f)) == distort(xy, p) / f``.  Used to fit in
    well-conditioned units whatever the units of the data.
    """
    return np.asarray(params, float) * float(factor) ** SCALE_EXPONENTS


# ------------------------------------------------------------------------- forward map


def _split(xy_u: np.ndarray, params: np.ndarray):
    xy_u = np.asarray(xy_u, dtype=float)
    p = np.asarray(params, dtype=float)[..., None, :]  # (..., 1, 13) broadcasts over N
    k1, k2, p1, p2, s1, s2, s3, s4, xo, yo, cx, cy, m = (p[..., i] for i in range(N_PARAMS))
    xs = xy_u[..., 0] + xo
    ys = xy_u[..., 1] + yo
    xb = m * xs
    yb = m * ys
    r2 = xb * xb + yb * yb
    return (k1, k2, p1, p2, s1, s2, s3, s4, cx, cy, m), xs, ys, xb, yb, r2


def distort(xy_u: np.ndarray, params: np.ndarray) -> np.ndarray:
    """Eq. (1): distorted points ``(..., N, 2)`` from undistorted points ``(..., N, 2)``."""
    (k1, k2, p1, p2, s1, s2, s3, s4, cx, cy, _), _, _, xb, yb, r2 = _split(xy_u, params)
    radial = 1.0 + r2 * (k1 + k2 * r2)
    xd = xb * radial + 2.0 * p1 * xb * yb + p2 * (r2 + 2.0 * xb * xb) + r2 * (s1 + s2 * r2) + cx
    yd = yb * radial + p1 * (r2 + 2.0 * yb * yb) + 2.0 * p2 * xb * yb + r2 * (s3 + s4 * r2) + cy
    return np.stack([xd, yd], axis=-1)


def _inner_jacobian(k1, k2, p1, p2, s1, s2, s3, s4, xb, yb, r2):
    """d(xb_d, yb_d) / d(xb, yb), each entry of shape (..., N)."""
    radial = 1.0 + r2 * (k1 + k2 * r2)
    drad = 2.0 * (k1 + 2.0 * k2 * r2)  # d radial / d xb = drad * xb
    a = radial + drad * xb * xb + 2.0 * p1 * yb + 6.0 * p2 * xb + 2.0 * xb * (s1 + 2.0 * s2 * r2)
    b = drad * xb * yb + 2.0 * p1 * xb + 2.0 * p2 * yb + 2.0 * yb * (s1 + 2.0 * s2 * r2)
    c = drad * xb * yb + 2.0 * p1 * xb + 2.0 * p2 * yb + 2.0 * xb * (s3 + 2.0 * s4 * r2)
    d = radial + drad * yb * yb + 6.0 * p1 * yb + 2.0 * p2 * xb + 2.0 * yb * (s3 + 2.0 * s4 * r2)
    return a, b, c, d


def jacobian_point(xy_u: np.ndarray, params: np.ndarray) -> np.ndarray:
    """d(x_d, y_d) / d(x_u, y_u), shape ``(..., N, 2, 2)`` (row = output, column = input)."""
    (k1, k2, p1, p2, s1, s2, s3, s4, _, _, m), _, _, xb, yb, r2 = _split(xy_u, params)
    a, b, c, d = _inner_jacobian(k1, k2, p1, p2, s1, s2, s3, s4, xb, yb, r2)
    jac = np.stack([np.stack([a, b], -1), np.stack([c, d], -1)], -2)
    return jac * m[..., None, None]


def jacobian_params(xy_u: np.ndarray, params: np.ndarray) -> np.ndarray:
    """d(x_d, y_d) / d(params), shape ``(..., N, 2, 13)``, columns in :data:`PARAM_NAMES` order."""
    (k1, k2, p1, p2, s1, s2, s3, s4, _, _, m), xs, ys, xb, yb, r2 = _split(xy_u, params)
    a, b, c, d = _inner_jacobian(k1, k2, p1, p2, s1, s2, s3, s4, xb, yb, r2)
    zero = np.zeros_like(r2)
    one = np.ones_like(r2)
    r4 = r2 * r2
    xy2 = 2.0 * xb * yb
    cols_x = [
        xb * r2, xb * r4, xy2, r2 + 2.0 * xb * xb, r2, r4, zero, zero,
        a * m, b * m, one, zero, a * xs + b * ys,
    ]  # fmt: skip
    cols_y = [
        yb * r2, yb * r4, r2 + 2.0 * yb * yb, xy2, zero, zero, r2, r4,
        c * m, d * m, zero, one, c * xs + d * ys,
    ]  # fmt: skip
    return np.stack([np.stack(cols_x, -1), np.stack(cols_y, -1)], -2)


# ------------------------------------------------------------------------- the inverse


@dataclass(frozen=True)
class InverseResult:
    """Result of :func:`undistort`.

    Attributes
    ----------
    xy : (..., N, 2) undistorted points; NaN where ``converged`` is False.
    converged : (..., N) bool, the residual ``|distort(xy) - xy_d|`` reached ``tol``
        and the map is locally one-to-one there.
    folded : (..., N) bool, Newton stopped where the Jacobian determinant is <= 0: the
        fitted map folds over near this point, so no trustworthy inverse exists.
    n_iter : number of Newton iterations taken.
    """

    xy: np.ndarray
    converged: np.ndarray
    folded: np.ndarray
    n_iter: int


def undistort(
    xy_d: np.ndarray,
    params: np.ndarray,
    *,
    tol: float = 1e-10,
    max_iter: int = 50,
    xy_start: np.ndarray | None = None,
) -> InverseResult:
    """Correct observed points: solve ``distort(xy_u, params) = xy_d`` for ``xy_u``.

    Newton iteration with the analytic 2x2 point Jacobian and step halving (up to 10
    halvings a step when the residual grows), started from the inverse of the linear part
    of the model, ``xy_u = (xy_d - c) / m - off``, unless ``xy_start`` is given.

    A point converges when ``|distort(xy_u) - xy_d| <= tol`` (Euclidean, in the units of
    the points) within ``max_iter`` iterations *and* the Jacobian determinant there is
    positive.  Where the determinant is <= 0 the map folds over: the point is reported as
    ``folded`` and not converged.  Points that do not converge come back as NaN.

    Shapes follow :func:`distort`: ``xy_d`` ``(..., N, 2)`` with ``params`` ``(..., 13)``.
    """
    xy_d = np.asarray(xy_d, dtype=float)
    params = np.asarray(params, dtype=float)
    shape = np.broadcast_shapes(xy_d.shape[:-2], params.shape[:-1]) + xy_d.shape[-2:]
    xy_d = np.broadcast_to(xy_d, shape)
    p = params[..., None, :]
    if xy_start is None:
        m = p[..., INDEX["m"]]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = np.stack(
                [
                    (xy_d[..., 0] - p[..., INDEX["c_x"]]) / m - p[..., INDEX["x_off"]],
                    (xy_d[..., 1] - p[..., INDEX["c_y"]]) / m - p[..., INDEX["y_off"]],
                ],
                axis=-1,
            )
    else:
        u = np.array(np.broadcast_to(xy_start, shape), dtype=float)
    u = np.array(u, dtype=float)

    with np.errstate(all="ignore"):
        f = distort(u, params) - xy_d
        err = np.hypot(f[..., 0], f[..., 1])
        done = err <= tol
        n_iter = 0
        for n_iter in range(1, max_iter + 1):
            active = ~done & np.isfinite(err)
            if not active.any():
                n_iter -= 1
                break
            jac = jacobian_point(u, params)
            det = jac[..., 0, 0] * jac[..., 1, 1] - jac[..., 0, 1] * jac[..., 1, 0]
            # Newton step -J^{-1} f, with the 2x2 inverse written out.
            step = -np.stack(
                [
                    (jac[..., 1, 1] * f[..., 0] - jac[..., 0, 1] * f[..., 1]) / det,
                    (-jac[..., 1, 0] * f[..., 0] + jac[..., 0, 0] * f[..., 1]) / det,
                ],
                axis=-1,
            )
            step = np.where(active[..., None], step, 0.0)
            t = np.ones(err.shape)
            for _ in range(11):
                u_new = u + t[..., None] * step
                f_new = distort(u_new, params) - xy_d
                err_new = np.hypot(f_new[..., 0], f_new[..., 1])
                worse = active & ~(err_new < err) & ~(err_new <= tol)
                if not worse.any():
                    break
                t = np.where(worse, 0.5 * t, t)
            accept = active & np.isfinite(err_new)
            u = np.where(accept[..., None], u_new, u)
            f = np.where(accept[..., None], f_new, f)
            stalled = active & ~(err_new < err)
            err = np.where(accept, err_new, err)
            done = done | (err <= tol)
            # A point whose residual cannot decrease any more has stalled: stop it.
            err = np.where(stalled & ~done, np.inf, err)
        jac = jacobian_point(u, params)
        det = jac[..., 0, 0] * jac[..., 1, 1] - jac[..., 0, 1] * jac[..., 1, 0]
    folded = ~(det > 0) & np.isfinite(det)
    converged = done & ~folded & np.isfinite(u).all(axis=-1)
    xy = np.where(converged[..., None], u, np.nan)
    return InverseResult(xy=xy, converged=converged, folded=folded, n_iter=n_iter)


def jacobian_determinant(xy_u: np.ndarray, params: np.ndarray) -> np.ndarray:
    """``det d(x_d, y_d)/d(x_u, y_u)`` at each point, ``(..., N)``; <= 0 where the map folds."""
    jac = jacobian_point(xy_u, params)
    return jac[..., 0, 0] * jac[..., 1, 1] - jac[..., 0, 1] * jac[..., 1, 0]
