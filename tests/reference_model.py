"""The NumPy reference implementation of Eq. (1), its Jacobians and the Newton inverse.

oapcal computes all of these in compiled kernels (``oapcal._kernels``, through
``oapcal.model``); the tests check the kernels against this independent, vectorized NumPy
version, written directly from the equations in ``docs/models.md``.  Shapes and
broadcasting as in :mod:`oapcal.model`.
"""

import numpy as np

from oapcal.model import INDEX, N_PARAMS, InverseResult, all_masks  # the result container and the masks


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


#: The inverse's allowance for rounding, in units of ``eps`` times the magnitudes Eq. (1)
#: adds up (``docs/models.md``, "Point correction").
ROUNDING_ULPS = 16.0


def rounding_level(xy_u, xy_d, params, jac):
    """``16 eps (|c_x| + |c_y| + |x_d| + |y_d| + max|J| (|x_off| + |y_off| + |x_u| + |y_u|))``:
    how far Eq. (1)'s value may be from ``xy_d`` through rounding alone."""
    p = np.asarray(params, float)[..., None, :]
    jmax = np.abs(jac).max(axis=(-1, -2))
    centre = np.abs(p[..., INDEX["c_x"]]) + np.abs(p[..., INDEX["c_y"]])
    offset = np.abs(p[..., INDEX["x_off"]]) + np.abs(p[..., INDEX["y_off"]])
    scale = centre + np.abs(xy_d).sum(-1) + jmax * (offset + np.abs(xy_u).sum(-1))
    return ROUNDING_ULPS * np.finfo(float).eps * scale


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
    the points) within ``max_iter`` iterations, or when the residual is within
    :func:`rounding_level` and a full Newton step no longer reduces it, *and* the Jacobian
    determinant there is positive.  Where the
    determinant is <= 0 the map folds over: the point is reported as ``folded`` and not
    converged.  Points that do not converge come back as NaN.

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
            for trial in range(11):
                u_new = u + t[..., None] * step
                f_new = distort(u_new, params) - xy_d
                err_new = np.hypot(f_new[..., 0], f_new[..., 1])
                worse = active & ~(err_new < err) & ~(err_new <= tol)
                if trial == 0:
                    # a full step that does not reduce a residual already at the model's
                    # rounding level: converged where it is
                    floor = worse & (err <= rounding_level(u, xy_d, params, jac))
                    done = done | floor
                    active = active & ~floor
                    worse = worse & ~floor
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


def random_eq1_models(n, seed, rotation):
    """Eq. (1) models of a 640 x 480 px camera with random subsets of the terms, strong
    enough to fold over inside the frame for some, optionally with a rotation."""
    rng = np.random.default_rng(seed)
    masks = all_masks()[rng.integers(0, len(all_masks()), n)]
    scale = np.array([1e-6, 1e-12, 1e-4, 1e-4, 1e-4, 1e-10, 1e-4, 1e-10, 50, 50, 50, 50, 0.3])
    p = rng.standard_normal((n, 13)) * scale * masks
    p[:, 12] += 1.0
    if rotation:
        p = np.hstack([p, rng.uniform(-180, 180, (n, 1))])
    return p
