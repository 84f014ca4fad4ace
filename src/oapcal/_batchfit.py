"""Compiled kernels for fitting and inverting thousands of models at once.

Why hand-written: model selection fits all 4,096 subsets of Eq. (1) and the robustness
test fits tens of thousands of subsamples.  :func:`oapcal.fit.fit_batch` (NumPy)
materialises the ``(B, 2N, 13)`` Jacobian and forms ``J^T J`` by ``einsum`` each
iteration, which takes about 14 s for 4,096 models on 289 points.  The kernels here run
the *same* Levenberg-Marquardt algorithm as :func:`oapcal.fit.fit_batch` (same
coordinate scaling, Marquardt column scaling, damping updates, MINPACK-style stopping
tests and status codes) one model per thread with Numba, accumulating ``J^T J`` over the
free parameters only, in memory that stays in cache.  The tests check them against
:func:`oapcal.fit.fit_batch`, :func:`scipy.optimize.least_squares` and
:func:`oapcal.model.undistort`.

Every item may use its own subset of the points (``idx``, an integer array of point
indices per item), which is how cross-validation and the subsampling test run.

>>> import numpy as np
>>> from oapcal.model import distort, params_from_dict, parse_model
>>> g = np.stack(np.meshgrid(np.linspace(-1, 1, 9), np.linspace(-1, 1, 9)), -1).reshape(-1, 2)
>>> truth = params_from_dict({"k1": 0.05, "c_x": 0.1, "m": 1.2})
>>> res = fit_many(g, distort(g, truth), parse_model("k1,c_x")[None], truth[None])
>>> bool(res.converged[0]), round(float(res.params[0, 0]), 6)
(True, 0.05)
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numba
import numpy as np

from oapcal.errors import ModelSpecError
from oapcal.model import INDEX, N_PARAMS, SCALE_EXPONENTS, scale_params

# Reassociation lets the compiler vectorise the sums over points; NaN and inf keep their
# IEEE meaning (no 'nnan'/'ninf'), which the status tests rely on.
_FASTMATH = {"reassoc", "contract", "nsz", "arcp"}
_JIT = {"cache": True, "nogil": True, "error_model": "numpy"}
# Items are handed to the threads in chunks of this size rather than in one equal share
# per thread: fit times differ between models, and on a shared machine one thread may get
# less CPU than the other, so equal shares leave one core idle.
_CHUNK = 16


@dataclass(frozen=True)
class ManyFits:
    """Results of :func:`fit_many` for B items (the batch axis first).

    ``params (B, 13)`` in the data's units (fixed entries 0), ``rss (B,)`` the sum of
    squared forward residuals over the item's points, ``n`` residuals per item (two per
    point), ``n_iter (B,)`` Jacobian evaluations, ``status (B,)`` with the codes of
    :data:`oapcal.fit.STATUS_MESSAGES` (positive = converged).
    """

    masks: np.ndarray
    params: np.ndarray
    rss: np.ndarray
    n: int
    n_iter: np.ndarray
    status: np.ndarray
    converged: np.ndarray = field(init=False)

    def __post_init__(self):
        object.__setattr__(self, "converged", self.status > 0)


# --------------------------------------------------------------------------- fitting


@numba.njit(fastmath=_FASTMATH, **_JIT)
def _residuals(p, u, d, pts, res, work):
    """Fill ``res (2n,)`` = model - data (x residuals first, then y) and rows 0-4 of
    ``work (9, n)`` with per-point values that :func:`_jacobian` reuses; return the cost.

    Keeping per-point values in rows makes every loop run over contiguous memory and
    vectorise.
    """
    k1, k2, p1, p2, s1, s2, s3, s4 = p[0], p[1], p[2], p[3], p[4], p[5], p[6], p[7]
    xo, yo, cx, cy, m = p[8], p[9], p[10], p[11], p[12]
    n = pts.shape[0]
    xs_, ys_, xb_, yb_, r2_ = work[0], work[1], work[2], work[3], work[4]
    cost = 0.0
    for j in range(n):
        q = pts[j]
        xs = u[q, 0] + xo
        ys = u[q, 1] + yo
        xb = m * xs
        yb = m * ys
        r2 = xb * xb + yb * yb
        radial = 1.0 + r2 * (k1 + k2 * r2)
        xy2 = 2.0 * xb * yb
        rx = xb * radial + p1 * xy2 + p2 * (r2 + 2.0 * xb * xb) + r2 * (s1 + s2 * r2) + cx - d[q, 0]
        ry = yb * radial + p1 * (r2 + 2.0 * yb * yb) + p2 * xy2 + r2 * (s3 + s4 * r2) + cy - d[q, 1]
        res[j] = rx
        res[n + j] = ry
        cost += rx * rx + ry * ry
        xs_[j] = xs
        ys_[j] = ys
        xb_[j] = xb
        yb_[j] = yb
        r2_[j] = r2
    return 0.5 * cost


@numba.njit(fastmath=_FASTMATH, **_JIT)
def _jacobian(p, free, k, jac, work):
    """Fill ``jac (k, 2n)`` at ``p`` from the values :func:`_residuals` left in ``work``
    for the same ``p``."""
    k1, k2, p1, p2, s1, s2, s3, s4 = p[0], p[1], p[2], p[3], p[4], p[5], p[6], p[7]
    m = p[12]
    n = work.shape[1]
    xs_, ys_, xb_, yb_, r2_ = work[0], work[1], work[2], work[3], work[4]
    a_, b_, c_, d_ = work[5], work[6], work[7], work[8]
    for j in range(n):
        xb = xb_[j]
        yb = yb_[j]
        r2 = r2_[j]
        radial = 1.0 + r2 * (k1 + k2 * r2)
        drad = 2.0 * (k1 + 2.0 * k2 * r2)
        sx = 2.0 * (s1 + 2.0 * s2 * r2)
        sy = 2.0 * (s3 + 2.0 * s4 * r2)
        a_[j] = radial + drad * xb * xb + 2.0 * p1 * yb + 6.0 * p2 * xb + xb * sx
        b_[j] = drad * xb * yb + 2.0 * p1 * xb + 2.0 * p2 * yb + yb * sx
        c_[j] = drad * xb * yb + 2.0 * p1 * xb + 2.0 * p2 * yb + xb * sy
        d_[j] = radial + drad * yb * yb + 6.0 * p1 * yb + 2.0 * p2 * xb + yb * sy
    # One column of d(residual)/d(parameter) per free parameter, as in
    # oapcal.model.jacobian_params; one branch per parameter outside the point loop.
    for i in range(k):
        col = jac[i]
        f = free[i]
        if f == 0:  # k1
            for j in range(n):
                col[j] = xb_[j] * r2_[j]
                col[n + j] = yb_[j] * r2_[j]
        elif f == 1:  # k2
            for j in range(n):
                col[j] = xb_[j] * r2_[j] * r2_[j]
                col[n + j] = yb_[j] * r2_[j] * r2_[j]
        elif f == 2:  # p1
            for j in range(n):
                col[j] = 2.0 * xb_[j] * yb_[j]
                col[n + j] = r2_[j] + 2.0 * yb_[j] * yb_[j]
        elif f == 3:  # p2
            for j in range(n):
                col[j] = r2_[j] + 2.0 * xb_[j] * xb_[j]
                col[n + j] = 2.0 * xb_[j] * yb_[j]
        elif f == 4:  # s1
            for j in range(n):
                col[j] = r2_[j]
                col[n + j] = 0.0
        elif f == 5:  # s2
            for j in range(n):
                col[j] = r2_[j] * r2_[j]
                col[n + j] = 0.0
        elif f == 6:  # s3
            for j in range(n):
                col[j] = 0.0
                col[n + j] = r2_[j]
        elif f == 7:  # s4
            for j in range(n):
                col[j] = 0.0
                col[n + j] = r2_[j] * r2_[j]
        elif f == 8:  # x_off
            for j in range(n):
                col[j] = a_[j] * m
                col[n + j] = c_[j] * m
        elif f == 9:  # y_off
            for j in range(n):
                col[j] = b_[j] * m
                col[n + j] = d_[j] * m
        elif f == 10:  # c_x
            for j in range(n):
                col[j] = 1.0
                col[n + j] = 0.0
        elif f == 11:  # c_y
            for j in range(n):
                col[j] = 0.0
                col[n + j] = 1.0
        elif f == 12:  # m
            for j in range(n):
                col[j] = a_[j] * xs_[j] + b_[j] * ys_[j]
                col[n + j] = c_[j] * xs_[j] + d_[j] * ys_[j]


@numba.njit(fastmath=_FASTMATH, **_JIT)
def _normal_equations(jac, res, k, a, g):
    """``a = J^T J`` and ``g = J^T r`` over the free columns (contiguous rows of ``jac``)."""
    n2 = jac.shape[1]
    for i in range(k):
        s = 0.0
        for c in range(n2):
            s += jac[i, c] * res[c]
        g[i] = s
        for q in range(i + 1):
            s = 0.0
            for c in range(n2):
                s += jac[i, c] * jac[q, c]
            a[i, q] = s
            a[q, i] = s


@numba.njit(**_JIT)
def _solve_spd(lhs, rhs, k, out, work):
    """Solve ``lhs x = rhs`` (k x k, symmetric positive definite) by Cholesky.

    Returns False when a pivot is not positive (the caller falls back to least squares).
    """
    for i in range(k):
        for j in range(i + 1):
            s = lhs[i, j]
            for q in range(j):
                s -= work[i, q] * work[j, q]
            if i == j:
                if not s > 0.0:
                    return False
                work[i, i] = np.sqrt(s)
            else:
                work[i, j] = s / work[j, j]
    for i in range(k):
        s = rhs[i]
        for q in range(i):
            s -= work[i, q] * out[q]
        out[i] = s / work[i, i]
    for i in range(k - 1, -1, -1):
        s = out[i]
        for q in range(i + 1, k):
            s -= work[q, i] * out[q]
        out[i] = s / work[i, i]
    return True


@numba.njit(**_JIT)
def _solve_lu(lhs, rhs, k, out, work):
    """Gaussian elimination with partial pivoting (what ``np.linalg.solve`` does), for the
    rare steps where Cholesky meets a non-positive pivot; a zero pivot gives a NaN step."""
    for i in range(k):
        out[i] = rhs[i]
        for j in range(k):
            work[i, j] = lhs[i, j]
    for c in range(k):
        piv = c
        for i in range(c + 1, k):
            if abs(work[i, c]) > abs(work[piv, c]):
                piv = i
        if piv != c:
            for j in range(k):
                work[c, j], work[piv, j] = work[piv, j], work[c, j]
            out[c], out[piv] = out[piv], out[c]
        for i in range(c + 1, k):
            f = work[i, c] / work[c, c]
            for j in range(c, k):
                work[i, j] -= f * work[c, j]
            out[i] -= f * out[c]
    for i in range(k - 1, -1, -1):
        s = out[i]
        for j in range(i + 1, k):
            s -= work[i, j] * out[j]
        out[i] = s / work[i, i]


@numba.njit(**_JIT)
def _lm_one(u, d, pts, mask, p, max_iter, ftol, xtol, gtol):
    """Levenberg-Marquardt for one item, in place on ``p``; the algorithm of
    :func:`oapcal.fit.fit_batch` step for step.  Returns (status, n_iter, cost)."""
    free = np.flatnonzero(mask)
    k = free.shape[0]
    n2 = 2 * pts.shape[0]
    jac = np.empty((k, n2))
    res = np.empty(n2)
    pwork = np.empty((9, pts.shape[0]))
    a = np.empty((k, k))
    g = np.empty(k)
    lhs = np.empty((k, k))
    a_s = np.empty((k, k))
    g_s = np.empty(k)
    step_s = np.empty(k)
    work = np.zeros((k, k))
    dcol = np.empty(k)
    p_new = p.copy()

    cost = _residuals(p, u, d, pts, res, pwork)
    status = 0
    n_iter = 0
    if not np.isfinite(cost):
        return -1, n_iter, cost
    if cost == 0.0:
        return 4, n_iter, cost
    lam = 1e-3
    nu = 2.0
    need_jac = True
    for _ in range(max_iter * 4):
        if need_jac:
            # The work rows and residuals hold the values at p: the last evaluation was at
            # p (the start, or an accepted trial step).
            _jacobian(p, free, k, jac, pwork)
            _normal_equations(jac, res, k, a, g)
            n_iter += 1
            need_jac = False
            rnorm = np.sqrt(2.0 * cost)
            cmax = 0.0
            for i in range(k):
                cn = np.sqrt(a[i, i])
                if cn > 0.0:
                    cos = abs(g[i]) / (cn * rnorm)
                    if cos > cmax:
                        cmax = cos
            if cmax <= gtol:
                status = 1
                break
        for i in range(k):
            di = np.sqrt(a[i, i])
            dcol[i] = di if di > 0.0 else 1.0
        for i in range(k):
            g_s[i] = g[i] / dcol[i]
            for j in range(k):
                a_s[i, j] = a[i, j] / (dcol[i] * dcol[j])
                lhs[i, j] = a_s[i, j]
            lhs[i, i] += lam
        if not _solve_spd(lhs, g_s, k, step_s, work):
            _solve_lu(lhs, g_s, k, step_s, work)
        for i in range(k):
            step_s[i] = -step_s[i]
        # predicted = -(g_s . s + 0.5 s^T A_s s)
        gs = 0.0
        pred_quad = 0.0
        for i in range(k):
            gs += g_s[i] * step_s[i]
            t = 0.0
            for j in range(k):
                t += a_s[i, j] * step_s[j]
            pred_quad += step_s[i] * t
        predicted = -(gs + 0.5 * pred_quad)
        for i in range(N_PARAMS):
            p_new[i] = p[i]
        pnorm = 0.0
        snorm = 0.0
        finite_new = True
        for i in range(k):
            q = free[i]
            p_new[q] = p[q] + step_s[i] / dcol[i]
            pnorm += (p[q] * dcol[i]) ** 2
            snorm += step_s[i] ** 2
            if not np.isfinite(p_new[q]):
                finite_new = False
        cost_new = _residuals(p_new, u, d, pts, res, pwork)
        actual = cost - cost_new
        rho = actual / predicted if predicted > 0.0 else -1.0
        accept = np.isfinite(cost_new) and actual > 0.0 and rho > 1e-4
        rel_actual = abs(actual) / cost if cost > 0.0 else 0.0
        rel_pred = predicted / cost if cost > 0.0 else 0.0
        f_conv = rel_actual <= ftol and rel_pred <= ftol and rho <= 2.0
        x_conv = np.sqrt(snorm) <= xtol * max(np.sqrt(pnorm), 1e-300)
        if accept:
            for i in range(N_PARAMS):
                p[i] = p_new[i]
            cost = cost_new
            need_jac = True
            lam *= max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
            nu = 2.0
        else:
            lam *= nu
            nu *= 2.0
        if f_conv and (accept or abs(actual) <= ftol * cost):
            status = 2
        if x_conv and status == 0:
            status = 3
        if (not finite_new) and (not accept) and lam > 1e16:
            status = -1
        if lam > 1e32 and status == 0:
            status = -2
        if accept and cost_new == 0.0:
            status = 4
        if status != 0:
            break
        if n_iter >= max_iter and need_jac:
            break
    for i in range(N_PARAMS):
        if not np.isfinite(p[i]):
            status = -1
    if not np.isfinite(cost):
        status = -1
    return status, n_iter, cost


@numba.njit(parallel=True, **_JIT)
def _lm_many(u, d, idx, masks, p, max_iter, ftol, xtol, gtol, status, n_iter, cost):
    n_items = masks.shape[0]
    shared = idx.shape[0] == 1
    for b in numba.prange(n_items):
        pts = idx[0] if shared else idx[b]
        s, it, c = _lm_one(u, d, pts, masks[b], p[b], max_iter, ftol, xtol, gtol)
        status[b] = s
        n_iter[b] = it
        cost[b] = c


def _as_idx(idx, n_points: int, n_items: int) -> np.ndarray:
    if idx is None:
        return np.arange(n_points, dtype=np.int64)[None]
    idx = np.ascontiguousarray(np.atleast_2d(idx), dtype=np.int64)
    if idx.shape[0] not in (1, n_items):
        raise ModelSpecError(f"point indices must have 1 or {n_items} rows, got {idx.shape[0]}")
    if idx.size and (idx.min() < 0 or idx.max() >= n_points):
        raise ModelSpecError(f"point indices must lie in 0..{n_points - 1}")
    return idx


def fit_many(
    xy_u: np.ndarray,
    xy_d: np.ndarray,
    masks: np.ndarray,
    p0: np.ndarray,
    *,
    idx: np.ndarray | None = None,
    max_iter: int = 200,
    ftol: float = 1e-12,
    xtol: float = 1e-12,
    gtol: float = 1e-12,
) -> ManyFits:
    """Fit B models by Levenberg-Marquardt, the algorithm of :func:`oapcal.fit.fit_batch`.

    Parameters
    ----------
    xy_u, xy_d : ``(N, 2)`` reference and distorted points, shared by all items.
    masks : ``(B, 13)`` bool free parameters (``m`` free in each).
    p0 : ``(B, 13)`` or ``(13,)`` starting values (fixed entries forced to 0).
    idx : ``(B, n)`` or ``(1, n)`` int, the points each item is fitted to (default: all).
    max_iter, ftol, xtol, gtol : as in :func:`oapcal.fit.fit_batch`.
    """
    xy_u = np.ascontiguousarray(xy_u, dtype=float)
    xy_d = np.ascontiguousarray(xy_d, dtype=float)
    masks = np.ascontiguousarray(np.atleast_2d(masks), dtype=np.bool_)
    if not masks[:, INDEX["m"]].all():
        raise ModelSpecError("the magnification m must be free in every model")
    n_items = masks.shape[0]
    idx = _as_idx(idx, len(xy_u), n_items)
    f = float(max(np.abs(xy_u).max(), np.abs(xy_d).max(), 1e-300))
    p = np.where(masks, scale_params(np.broadcast_to(p0, masks.shape), f), 0.0)
    p = np.ascontiguousarray(p)
    status = np.zeros(n_items, dtype=np.int64)
    n_iter = np.zeros(n_items, dtype=np.int64)
    cost = np.zeros(n_items)
    with numba.parallel_chunksize(_CHUNK):
        _lm_many(xy_u / f, xy_d / f, idx, masks, p, int(max_iter), ftol, xtol, gtol, status, n_iter, cost)
    params = np.where(masks, p * f ** (-SCALE_EXPONENTS), 0.0)
    return ManyFits(masks, params, 2.0 * cost * f * f, 2 * idx.shape[1], n_iter, status)


# --------------------------------------------------------------------------- inverse


@numba.njit(**_JIT)
def _forward(p, x, y):
    """Eq. (1) at one point and its 2x2 point Jacobian: (xd, yd, a, b, c, d)."""
    k1, k2, p1, p2, s1, s2, s3, s4 = p[0], p[1], p[2], p[3], p[4], p[5], p[6], p[7]
    xo, yo, cx, cy, m = p[8], p[9], p[10], p[11], p[12]
    xb = m * (x + xo)
    yb = m * (y + yo)
    r2 = xb * xb + yb * yb
    radial = 1.0 + r2 * (k1 + k2 * r2)
    xd = xb * radial + 2.0 * p1 * xb * yb + p2 * (r2 + 2.0 * xb * xb) + r2 * (s1 + s2 * r2) + cx
    yd = yb * radial + p1 * (r2 + 2.0 * yb * yb) + 2.0 * p2 * xb * yb + r2 * (s3 + s4 * r2) + cy
    drad = 2.0 * (k1 + 2.0 * k2 * r2)
    a = radial + drad * xb * xb + 2.0 * p1 * yb + 6.0 * p2 * xb + 2.0 * xb * (s1 + 2.0 * s2 * r2)
    b = drad * xb * yb + 2.0 * p1 * xb + 2.0 * p2 * yb + 2.0 * yb * (s1 + 2.0 * s2 * r2)
    c = drad * xb * yb + 2.0 * p1 * xb + 2.0 * p2 * yb + 2.0 * xb * (s3 + 2.0 * s4 * r2)
    d = radial + drad * yb * yb + 6.0 * p1 * yb + 2.0 * p2 * xb + 2.0 * yb * (s3 + 2.0 * s4 * r2)
    return xd, yd, a * m, b * m, c * m, d * m


@numba.njit(**_JIT)
def _invert_point(p, xd, yd, tol, max_iter):
    """Newton inverse of one point, step for step as :func:`oapcal.model.undistort`.

    Returns (x, y, converged, folded)."""
    m = p[12]
    x = (xd - p[10]) / m - p[8]
    y = (yd - p[11]) / m - p[9]
    fx, fy, a, b, c, d = _forward(p, x, y)
    fx -= xd
    fy -= yd
    err = np.sqrt(fx * fx + fy * fy)
    done = err <= tol
    # (a, b, c, d) is always the point Jacobian at (x, y): each trial evaluation returns
    # it too, so an accepted step needs no second evaluation.
    for _ in range(max_iter):
        if done or not np.isfinite(err):
            break
        det = a * d - b * c
        sx = -(d * fx - b * fy) / det
        sy = -(-c * fx + a * fy) / det
        t = 1.0
        xn = x
        yn = y
        fxn = fx
        fyn = fy
        an, bn, cn, dn = a, b, c, d
        err_new = err
        for _h in range(11):
            xn = x + t * sx
            yn = y + t * sy
            fxn, fyn, an, bn, cn, dn = _forward(p, xn, yn)
            fxn -= xd
            fyn -= yd
            err_new = np.sqrt(fxn * fxn + fyn * fyn)
            if (err_new < err) or (err_new <= tol):
                break
            t *= 0.5
        stalled = not (err_new < err)
        if np.isfinite(err_new):
            x = xn
            y = yn
            fx = fxn
            fy = fyn
            a, b, c, d = an, bn, cn, dn
            err = err_new
        done = err <= tol
        if stalled and not done:
            err = np.inf
    det = a * d - b * c
    folded = (not det > 0.0) and np.isfinite(det)
    converged = done and (not folded) and np.isfinite(x) and np.isfinite(y)
    return x, y, converged, folded


@numba.njit(parallel=True, **_JIT)
def _invert_many(params, xy_d, idx, tol, max_iter, out, converged, folded):
    n_items = params.shape[0]
    shared = idx.shape[0] == 1
    for b in numba.prange(n_items):
        pts = idx[0] if shared else idx[b]
        for j in range(pts.shape[0]):
            q = pts[j]
            x, y, ok, fold = _invert_point(params[b], xy_d[q, 0], xy_d[q, 1], tol, max_iter)
            out[b, j, 0] = x if ok else np.nan
            out[b, j, 1] = y if ok else np.nan
            converged[b, j] = ok
            folded[b, j] = fold


def invert_many(params, xy_d, *, idx=None, tol: float = 1e-10, max_iter: int = 50):
    """The inverse of :func:`oapcal.model.undistort` for B parameter sets at once.

    ``params (B, 13)``, ``xy_d (N, 2)``; ``idx (B, n)`` or ``(1, n)`` selects the points
    of each item (default all).  Returns ``(xy (B, n, 2), converged (B, n), folded (B, n))``
    with the meaning, tolerance and iteration cap of :func:`oapcal.model.undistort`.
    """
    params = np.ascontiguousarray(np.atleast_2d(params), dtype=float)
    xy_d = np.ascontiguousarray(xy_d, dtype=float)
    idx = _as_idx(idx, len(xy_d), len(params))
    n_items, n = len(params), idx.shape[1]
    out = np.empty((n_items, n, 2))
    converged = np.zeros((n_items, n), dtype=np.bool_)
    folded = np.zeros((n_items, n), dtype=np.bool_)
    with numba.parallel_chunksize(_CHUNK):
        _invert_many(params, xy_d, idx, float(tol), int(max_iter), out, converged, folded)
    return out, converged, folded


@numba.njit(parallel=True, **_JIT)
def _invert_score_many(params, xy_d, xy_u, tol, max_iter, rss, mean_dist, n_bad, n_folded):
    for b in numba.prange(params.shape[0]):
        s2 = 0.0
        s1 = 0.0
        bad = 0
        fold = 0
        for j in range(xy_d.shape[0]):
            x, y, ok, fo = _invert_point(params[b], xy_d[j, 0], xy_d[j, 1], tol, max_iter)
            if ok:
                dx = x - xy_u[j, 0]
                dy = y - xy_u[j, 1]
                s2 += dx * dx + dy * dy
                s1 += np.sqrt(dx * dx + dy * dy)
            else:
                bad += 1
            if fo:
                fold += 1
        rss[b] = s2
        mean_dist[b] = s1 / max(xy_d.shape[0] - bad, 1)
        n_bad[b] = bad
        n_folded[b] = fold


def invert_and_score(params, xy_d, xy_u, *, tol: float = 1e-10, max_iter: int = 50):
    """Correct all points ``xy_d (N, 2)`` through each model ``params (B, 13)`` (as
    :func:`invert_many`) and compare with ``xy_u (N, 2)`` without storing the points.

    Returns ``(rss, mean_dist, n_bad, n_folded)``, each ``(B,)``: the sum of squared and
    the mean Euclidean corrected-minus-reference distances over the points whose inverse
    converged, the number of points whose inverse failed, and how many of those fold.
    """
    params = np.ascontiguousarray(np.atleast_2d(params), dtype=float)
    n_items = len(params)
    rss = np.empty(n_items)
    mean_dist = np.empty(n_items)
    n_bad = np.zeros(n_items, dtype=np.int64)
    n_folded = np.zeros(n_items, dtype=np.int64)
    with numba.parallel_chunksize(_CHUNK):
        _invert_score_many(
            params, np.ascontiguousarray(xy_d, dtype=float), np.ascontiguousarray(xy_u, dtype=float),
            float(tol), int(max_iter), rss, mean_dist, n_bad, n_folded,
        )  # fmt: skip
    return rss, mean_dist, n_bad, n_folded


@numba.njit(parallel=True, **_JIT)
def _min_det_many(params, xy_u, out):
    for b in numba.prange(params.shape[0]):
        lo = np.inf
        for j in range(xy_u.shape[0]):
            _, _, a, bb, c, d = _forward(params[b], xy_u[j, 0], xy_u[j, 1])
            det = a * d - bb * c
            if not det >= lo:  # NaN propagates
                lo = det
        out[b] = lo


def min_jacobian_determinant(params, xy_u) -> np.ndarray:
    """The smallest ``det d(x_d, y_d)/d(x_u, y_u)`` of each model over points ``(M, 2)``.

    ``(B,)``; <= 0 (or NaN) where a model folds over somewhere among the points.
    """
    params = np.ascontiguousarray(np.atleast_2d(params), dtype=float)
    out = np.empty(len(params))
    with numba.parallel_chunksize(_CHUNK):
        _min_det_many(params, np.ascontiguousarray(xy_u, dtype=float), out)
    return out
