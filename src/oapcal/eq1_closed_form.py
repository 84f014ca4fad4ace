"""Eq. (1), and Eq. (1) after the target's rotation, in closed form with NumPy: the
distorted points, the 2x2 point Jacobian and the parameter Jacobian (13 columns, 14 with
the rotation), over arrays of points at once.

The compiled kernels (:mod:`oapcal._kernels`, ``bc_point`` and ``bc_pose_point``) are the
one implementation of the model for everything that evaluates it many times (fits,
selection, the inverse, large maps).  This module is the same expressions, term for term,
for the few evaluations a command makes before its first frame, where loading the kernels
would cost more than the work: importing Numba and loading the cached machine code takes
a process 0.3-0.8 s, while the closed form gives the fold-over check of a calibration in
about a millisecond and the correction map and trust region of a 640 x 480 output in
milliseconds (``docs/benchmarks.md``, issue 23).  :func:`applies` is the one rule of when it
is used; ``tests/model/test_eq1_closed_form.py`` checks every value and Jacobian column
against the kernels.

The model (``docs/models.md``), with the reference point first turned by ``rotation``
degrees counter-clockwise for the ``+rotation`` family::

    xb = m (x + x_off),  yb = m (y + y_off),  r2 = xb^2 + yb^2
    x_d = xb (1 + k1 r2 + k2 r2^2) + 2 p1 xb yb + p2 (r2 + 2 xb^2) + s1 r2 + s2 r2^2 + c_x
    y_d = yb (1 + k1 r2 + k2 r2^2) + p1 (r2 + 2 yb^2) + 2 p2 xb yb + s3 r2 + s4 r2^2 + c_y

>>> import numpy as np
>>> p = np.array([1e-2, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 1.0])
>>> distort(np.array([[1.0, 0.0]]), p)
array([[1.01, 0.  ]])
"""

from __future__ import annotations

import sys

import numpy as np

#: The family codes (``oapcal.model.ModelFamily.code``) of Eq. (1) and Eq. (1) with the
#: target's rotation, and their parameter counts.
FAMILY_PARAMS = {0: 13, 1: 14}
#: What :func:`point` computes: the point only, plus the point Jacobian, plus the
#: parameter Jacobian (the kernels' ``VALUE``, ``POINT_JAC``, ``PARAM_JAC``).
VALUE, POINT_JAC, PARAM_JAC = 0, 1, 2
#: The most points (map pixels, trust-region nodes) evaluated with the closed form: beyond
#: about 2 Mpx (1920 x 1080 is 2.07 Mpx) the compiled map builder, on both cores, pays for
#: loading it; below, the NumPy map costs less than the load (a 640 x 480 map ~10 ms).
MAX_POINTS = 2**21
#: Points evaluated at a time: the float64 temporaries (about 20 of this size, 128 KiB each)
#: stay in the cache; 2**16 points is 3x slower per point on this machine, 2**12 1.5x.
BLOCK = 1 << 14


def applies(family, n_points: int, params=None) -> bool:
    """Whether a command's evaluation of ``n_points`` points of ``family`` goes through this
    closed form rather than the compiled kernels: an Eq. (1) family (with or without the
    rotation; ``params`` of its length when given), at most :data:`MAX_POINTS` points, and
    Numba not loaded yet in this process (once it is, the kernels cost nothing more and
    stay the one implementation)."""
    code = getattr(family, "code", None)
    if code not in FAMILY_PARAMS or n_points > MAX_POINTS or "numba" in sys.modules:
        return False
    return params is None or np.shape(params) == (FAMILY_PARAMS[code],)


def point(params, x, y, need: int = VALUE):
    """The model at points ``x``, ``y`` (arrays that broadcast against each other):
    ``(xd, yd, jac, jp)``, with ``jac = (a, b, c, d)`` the point Jacobian
    ``[[a, b], [c, d]] = d(x_d, y_d) / d(x, y)`` when ``need >= POINT_JAC`` (else None) and
    ``jp`` ``(..., 2, P)`` the parameter Jacobian (columns in the family's order; row 0
    ``d x_d / d p_i``, row 1 ``d y_d / d p_i``) when ``need == PARAM_JAC`` (else None).
    ``params`` is ``(13,)`` (Eq. 1) or ``(14,)`` (``params[13]`` the rotation in degrees).

    The expressions and their order are the kernels' (``_kernels.bc_point``,
    ``bc_pose_point``), so the two agree to rounding."""
    params = np.asarray(params, float)
    k1, k2, p1, p2, s1, s2, s3, s4, xo, yo, cx, cy, m = params[:13]
    x, y = np.asarray(x, float), np.asarray(y, float)
    turned = len(params) > 13
    if turned:  # the reference point turned counter-clockwise by params[13] degrees
        th = params[13] * (np.pi / 180.0)
        cs, sn = np.cos(th), np.sin(th)
        x, y = cs * x - sn * y, sn * x + cs * y
    xs, ys = x + xo, y + yo
    xb, yb = m * xs, m * ys
    r2 = xb * xb + yb * yb
    radial = 1.0 + r2 * (k1 + k2 * r2)
    xy2 = 2.0 * xb * yb
    xd = xb * radial + p1 * xy2 + p2 * (r2 + 2.0 * xb * xb) + r2 * (s1 + s2 * r2) + cx
    yd = yb * radial + p1 * (r2 + 2.0 * yb * yb) + p2 * xy2 + r2 * (s3 + s4 * r2) + cy
    if need == VALUE:
        return xd, yd, None, None
    # d(xb_d, yb_d) / d(xb, yb); times m: d(x_d, y_d) / d(x, y) before the rotation
    drad = 2.0 * (k1 + 2.0 * k2 * r2)
    sx = 2.0 * (s1 + 2.0 * s2 * r2)
    sy = 2.0 * (s3 + 2.0 * s4 * r2)
    a = radial + drad * xb * xb + 2.0 * p1 * yb + 6.0 * p2 * xb + xb * sx
    b = drad * xb * yb + 2.0 * p1 * xb + 2.0 * p2 * yb + yb * sx
    c = drad * xb * yb + 2.0 * p1 * xb + 2.0 * p2 * yb + xb * sy
    d = radial + drad * yb * yb + 6.0 * p1 * yb + 2.0 * p2 * xb + yb * sy
    jp = _param_columns(len(params), xb, yb, r2, xy2, xs, ys, m, (a, b, c, d)) if need == PARAM_JAC else None
    a, b, c, d = a * m, b * m, c * m, d * m
    if turned:
        if jp is not None:  # d(xr, yr) / d(theta) = (-yr, xr), per radian; per degree here
            jp[..., 0, 13] = (b * x - a * y) * (np.pi / 180.0)
            jp[..., 1, 13] = (d * x - c * y) * (np.pi / 180.0)
        # the point Jacobian of Eq. (1) times the rotation's, [[cs, -sn], [sn, cs]]
        a, b, c, d = a * cs + b * sn, b * cs - a * sn, c * cs + d * sn, d * cs - c * sn
    return xd, yd, (a, b, c, d), jp


def _param_columns(n_params, xb, yb, r2, xy2, xs, ys, m, jac):  # 9 parameters: the terms the columns reuse
    """The parameter Jacobian ``(..., 2, n_params)`` of Eq. (1) from its intermediate terms
    (``jac``: the point Jacobian in the scaled coordinates, ``d(xb_d, yb_d) / d(xb, yb)``).
    Each column is the derivative of ``x_d`` and ``y_d`` above by one parameter: the
    coefficients' terms directly, ``x_off`` and ``y_off`` through ``xb = m (x + x_off)``,
    ``m`` through ``xb`` and ``yb`` both.  Column 13 (the rotation) is the caller's."""
    a, b, c, d = jac
    r4 = r2 * r2
    shape = np.broadcast_shapes(np.shape(xb), np.shape(yb))
    jp = np.zeros(shape + (2, n_params))
    columns = {
        0: (xb * r2, yb * r2),  # k1
        1: (xb * r4, yb * r4),  # k2
        2: (xy2, r2 + 2.0 * yb * yb),  # p1
        3: (r2 + 2.0 * xb * xb, xy2),  # p2
        4: (r2, 0.0),  # s1
        5: (r4, 0.0),  # s2
        6: (0.0, r2),  # s3
        7: (0.0, r4),  # s4
        8: (a * m, c * m),  # x_off
        9: (b * m, d * m),  # y_off
        10: (1.0, 0.0),  # c_x
        11: (0.0, 1.0),  # c_y
        12: (a * xs + b * ys, c * xs + d * ys),  # m
    }
    for i, (dx, dy) in columns.items():
        jp[..., 0, i] = dx
        jp[..., 1, i] = dy
    return jp


def evaluate(xy, params, need: int = PARAM_JAC):
    """The model at points ``xy (..., 2)``: ``(xy_d (..., 2), jac (..., 2, 2) or None,
    jp (..., 2, P) or None)`` (:func:`point`), a block of :data:`BLOCK` points at a time."""
    xy = np.asarray(xy, float)
    lead = xy.shape[:-1]
    flat = xy.reshape(-1, 2)
    n_params = np.shape(params)[-1]
    out = np.empty((len(flat), 2))
    jac = np.empty((len(flat), 2, 2)) if need >= POINT_JAC else None
    jp = np.empty((len(flat), 2, n_params)) if need == PARAM_JAC else None
    for lo in range(0, len(flat), BLOCK):
        sl = slice(lo, lo + BLOCK)
        xd, yd, j, cols = point(params, flat[sl, 0], flat[sl, 1], need)
        out[sl, 0], out[sl, 1] = xd, yd
        if jac is not None:
            jac[sl] = np.stack([np.stack(j[:2], -1), np.stack(j[2:], -1)], -2)
        if jp is not None:
            jp[sl] = cols
    shaped = (out.reshape(lead + (2,)), None if jac is None else jac.reshape(lead + (2, 2)))
    return shaped + (None if jp is None else jp.reshape(lead + (2, n_params)),)


def distort(xy, params) -> np.ndarray:
    """Distorted points ``(..., 2)`` of undistorted points ``(..., 2)``."""
    return evaluate(xy, params, VALUE)[0]


def jacobian_point(xy, params) -> np.ndarray:
    """``d(x_d, y_d) / d(x, y)``, ``(..., 2, 2)`` (row = output, column = input)."""
    return evaluate(xy, params, POINT_JAC)[1]


def jacobian_params(xy, params) -> np.ndarray:
    """``d(x_d, y_d) / d(params)``, ``(..., 2, P)``, analytic."""
    return evaluate(xy, params, PARAM_JAC)[2]


def grid_map(params, xs, ys, out_x, out_y) -> None:
    """The model on the grid ``xs (C,) x ys (R,)`` of undistorted points into ``out_x,
    out_y (R, C)`` (float32): a correction map, as ``_kernels.grid_map`` builds it (each
    float64 value rounded once to float32)."""
    params = np.asarray(params, float)
    xs, ys = np.asarray(xs, float), np.asarray(ys, float)
    rows = max(1, BLOCK // max(len(xs), 1))
    if len(params) == 13:
        _separable_map(params, xs, ys, rows, out_x, out_y)
        return
    for lo in range(0, len(ys), rows):  # the rotation mixes x and y: every point in full
        xd, yd, _, _ = point(params, xs[None, :], ys[lo : lo + rows, None], VALUE)
        out_x[lo : lo + rows] = xd
        out_y[lo : lo + rows] = yd


def _separable_map(params, xs, ys, rows: int, out_x, out_y) -> None:
    """:func:`grid_map` of Eq. (1) without the rotation, where ``xb`` depends on the column
    only and ``yb`` on the row only.  The same polynomial as :func:`point`, regrouped in
    powers of ``r2`` so that every coefficient that belongs to one column or one row is
    computed once, and each pixel costs 7 operations per coordinate instead of about 16
    (a 640 x 480 map in about a third of the time)::

        x_d = r2 ((k1 xb + p2 + s1) + r2 (k2 xb + s2)) + xb (1 + 2 p1 yb) + (2 p2 xb^2 + c_x)
        y_d = r2 ((k1 yb + p1 + s3) + r2 (k2 yb + s4)) + yb (1 + 2 p2 xb) + (2 p1 yb^2 + c_y)

    The regrouping changes the rounding only (about 1e-13 px on a 640 x 480 map; the tests
    compare the float64 values and the float32 maps with the kernels')."""
    k1, k2, p1, p2, s1, s2, s3, s4, xo, yo, cx, cy, m = params
    xb = m * (xs + xo)
    xx = xb * xb
    # the columns' coefficients (C,)
    x_lin, x_sq, x_cross, x_tail = k1 * xb + (p2 + s1), k2 * xb + s2, 1.0 + 2.0 * p2 * xb, 2.0 * p2 * xx + cx
    r2, acc, term = (np.empty((rows, len(xs))) for _ in range(3))
    for lo in range(0, len(ys), rows):
        yb = (m * (ys[lo : lo + rows] + yo))[:, None]
        n = len(yb)
        r2_, acc_, term_ = r2[:n], acc[:n], term[:n]
        np.add(xx, yb * yb, out=r2_)
        # the rows' coefficients (n, 1)
        y_lin, y_sq, y_cross, y_tail = (
            k1 * yb + (p1 + s3),
            k2 * yb + s4,
            1.0 + 2.0 * p1 * yb,
            2.0 * p1 * yb * yb + cy,
        )
        for out, lin, sq, own, cross, tail in (
            (out_x, x_lin, x_sq, xb, y_cross, x_tail),
            (out_y, y_lin, y_sq, yb, x_cross, y_tail),
        ):
            np.multiply(r2_, sq, out=acc_)
            acc_ += lin
            acc_ *= r2_
            np.multiply(own, cross, out=term_)
            acc_ += term_
            acc_ += tail
            out[lo : lo + n] = acc_


def region_check(xy: np.ndarray, params: np.ndarray):
    """Whether the model is finite at each point ``(N, 2)``, and its point-Jacobian
    determinant there (``<= 0`` where it folds over): the fold-over check of a calibration
    (:func:`oapcal.calibration.check_model_region`)."""
    xd, yd, (a, b, c, d), _ = point(params, xy[:, 0], xy[:, 1], POINT_JAC)
    return np.isfinite(xd) & np.isfinite(yd), a * d - b * c
