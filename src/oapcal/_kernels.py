"""The compiled numerical core: one implementation of each step, used by everything.

* :func:`bc_point` -- Eq. (1) at one point: the distorted point, its 2x2 point Jacobian
  and the 13 parameter-Jacobian columns (the Brown-Conrady family).
* :func:`point` -- the family dispatch: every kernel below calls a model through it, so a
  new model family (``docs/architecture.md``) adds one entry to ``_POINT`` and nothing else.
* :func:`lm_batch` -- the one Levenberg-Marquardt solver, one item per thread, each item
  with its own free parameters, start and points; optional ``J^T J`` at the solution for
  the covariance.
* :func:`invert_point` -- the one Newton inverse, with the batched wrappers
  :func:`invert_batch` (points out) and :func:`invert_score` (errors out).
* :func:`evaluate`, :func:`grid_map`, :func:`min_det` -- the forward map and Jacobians at
  arbitrary points, on a separable pixel grid (correction maps), and the smallest Jacobian
  determinant (fold-over test).

Everything public goes through :mod:`oapcal.model` and :mod:`oapcal.fitting`; the NumPy
reference implementation the tests check these kernels against lives in
``tests/reference_model.py``.

Why hand-written: selection fits all 4,096 subsets of Eq. (1) and the robustness test
tens of thousands of subsamples; a NumPy solver materialising the ``(B, 2N, 13)``
Jacobian took ~14 s for the 4,096 models on 289 points, these kernels ~0.3 s.
"""

from __future__ import annotations

import functools
import hashlib
import inspect
import os
import types
from pathlib import Path

import numba
import numpy as np

from oapcal._relay_kernel import _D as RELAY_DESIGN
from oapcal._relay_kernel import _M as RELAY_MISALIGNMENT
from oapcal._relay_kernel import relay_point

# Reassociation lets the compiler vectorise the sums over points; NaN and inf keep their
# IEEE meaning (no 'nnan'/'ninf'), which the status tests rely on.
_FASTMATH = {"reassoc", "contract", "nsz", "arcp"}
_JIT = {"cache": True, "nogil": True, "error_model": "numpy"}
# Items are handed to the threads in chunks of this size rather than one equal share per
# thread: fit times differ between models, and on a shared machine one thread may get
# less CPU than the other, so equal shares leave one core idle.
CHUNK = 16
#: Points per task in the point-wise kernels (each task allocates its scratch once).
POINT_BLOCK = 256

#: What a point function computes: the point only, plus its 2x2 point Jacobian, plus the
#: parameter-Jacobian columns.
VALUE, POINT_JAC, PARAM_JAC = 0, 1, 2

#: Family codes of :func:`point` (the Python side: :class:`oapcal.model.ModelFamily`):
#: Eq. (1); Eq. (1) after an in-plane rotation of the reference points (the target's
#: pose); the physical relay (:mod:`oapcal._relay_kernel`).
FAMILY_BC = 0
FAMILY_BC_POSE = 1
FAMILY_RELAY = 2
#: Eq. (1) of the reference points in perspective (the keystone terms, with the rotation).
FAMILY_BC_TILT = 3


# ---------------------------------------------------------------------- model families


@numba.njit(inline="always", fastmath=_FASTMATH, **_JIT)
def bc_point(p, x, y, need, jp, j, want):
    """Eq. (1) at one undistorted point ``(x, y)`` with parameters ``p (13,)``.

    Returns ``(xd, yd, a, b, c, d)``: the distorted point and, when ``need >= POINT_JAC``,
    its point Jacobian ``[[a, b], [c, d]] = d(xd, yd) / d(x, y)`` (zeros otherwise).  When
    ``need == PARAM_JAC`` it also fills ``jp[:, i, j]`` for the parameters ``i``:
    ``jp[0, i, j] = d xd / d p_i`` and ``jp[1, i, j] = d yd / d p_i``, ``i`` in the order of
    :data:`oapcal.model.PARAM_NAMES` (``jp (2, 13, M)`` holds the columns of many points).
    ``want[i]`` says which columns the caller uses; a family may skip the others (this
    one writes all 13: cheaper than a test per column).  Entries that are zero by the
    family's ``moves`` need not be written: callers zero ``jp`` once.
    """
    k1, k2, p1, p2, s1, s2, s3, s4 = p[0], p[1], p[2], p[3], p[4], p[5], p[6], p[7]
    xo, yo, cx, cy, m = p[8], p[9], p[10], p[11], p[12]
    xs = x + xo
    ys = y + yo
    xb = m * xs
    yb = m * ys
    r2 = xb * xb + yb * yb
    radial = 1.0 + r2 * (k1 + k2 * r2)
    xy2 = 2.0 * xb * yb
    xd = xb * radial + p1 * xy2 + p2 * (r2 + 2.0 * xb * xb) + r2 * (s1 + s2 * r2) + cx
    yd = yb * radial + p1 * (r2 + 2.0 * yb * yb) + p2 * xy2 + r2 * (s3 + s4 * r2) + cy
    if need == VALUE:
        return xd, yd, 0.0, 0.0, 0.0, 0.0
    # d(xb_d, yb_d) / d(xb, yb)
    drad = 2.0 * (k1 + 2.0 * k2 * r2)
    sx = 2.0 * (s1 + 2.0 * s2 * r2)
    sy = 2.0 * (s3 + 2.0 * s4 * r2)
    a = radial + drad * xb * xb + 2.0 * p1 * yb + 6.0 * p2 * xb + xb * sx
    b = drad * xb * yb + 2.0 * p1 * xb + 2.0 * p2 * yb + yb * sx
    c = drad * xb * yb + 2.0 * p1 * xb + 2.0 * p2 * yb + xb * sy
    d = radial + drad * yb * yb + 6.0 * p1 * yb + 2.0 * p2 * xb + yb * sy
    if need == PARAM_JAC:
        # Every column (cheaper than testing ``want`` per column for this family), except
        # the entries that are identically zero by ``moves`` (s1, s2, c_x move x only; s3,
        # s4, c_y y only): callers zero them once.
        r4 = r2 * r2
        jp[0, 0, j] = xb * r2
        jp[1, 0, j] = yb * r2
        jp[0, 1, j] = xb * r4
        jp[1, 1, j] = yb * r4
        jp[0, 2, j] = xy2
        jp[1, 2, j] = r2 + 2.0 * yb * yb
        jp[0, 3, j] = r2 + 2.0 * xb * xb
        jp[1, 3, j] = xy2
        jp[0, 4, j] = r2
        jp[0, 5, j] = r4
        jp[1, 6, j] = r2
        jp[1, 7, j] = r4
        jp[0, 8, j] = a * m
        jp[1, 8, j] = c * m
        jp[0, 9, j] = b * m
        jp[1, 9, j] = d * m
        jp[0, 10, j] = 1.0
        jp[1, 11, j] = 1.0
        jp[0, 12, j] = a * xs + b * ys
        jp[1, 12, j] = c * xs + d * ys
    return xd, yd, a * m, b * m, c * m, d * m


@numba.njit(inline="always", **_JIT)
def bc_inverse_start(p, xd, yd):
    """The Newton start of the Brown-Conrady inverse: the inverse of the linear part."""
    m = p[12]
    return (xd - p[10]) / m - p[8], (yd - p[11]) / m - p[9]


@numba.njit(inline="always", fastmath=_FASTMATH, **_JIT)
def bc_pose_point(p, x, y, need, jp, j, want):
    """Eq. (1) after rotating the reference point by ``p[13]`` degrees (counter-clockwise
    about the origin of the fit's coordinates): the target's in-plane pose.  ``p[:13]`` are
    Eq. (1)'s parameters, which already hold its scale (``m``) and shift (``x_o, y_o``).
    The contract of :func:`bc_point`, with the rotation's column ``jp[:, 13, j]`` (per
    degree) from the chain rule."""
    th = p[13] * (np.pi / 180.0)
    cs = np.cos(th)
    sn = np.sin(th)
    xr = cs * x - sn * y
    yr = sn * x + cs * y
    xd, yd, a, b, c, d = bc_point(p, xr, yr, need, jp, j, want)
    if need == VALUE:
        return xd, yd, 0.0, 0.0, 0.0, 0.0
    if need == PARAM_JAC:
        # d(xr, yr) / d(theta) = (-yr, xr), per radian
        jp[0, 13, j] = (b * xr - a * yr) * (np.pi / 180.0)
        jp[1, 13, j] = (d * xr - c * yr) * (np.pi / 180.0)
    # the point Jacobian of Eq. (1) times the rotation's
    return xd, yd, a * cs + b * sn, b * cs - a * sn, c * cs + d * sn, d * cs - c * sn


@numba.njit(inline="always", **_JIT)
def bc_pose_inverse_start(p, xd, yd):
    """The Newton start of Eq. (1) with the rotation: the inverse of the linear part, turned back."""
    xr, yr = bc_inverse_start(p, xd, yd)
    th = p[13] * (np.pi / 180.0)
    return np.cos(th) * xr + np.sin(th) * yr, np.cos(th) * yr - np.sin(th) * xr


@numba.njit(inline="always", fastmath=_FASTMATH, **_JIT)
def bc_tilt_point(p, x, y, need, jp, j, want):
    """Eq. (1) of the reference point in perspective: the point turned by ``p[13]`` degrees
    (as :func:`bc_pose_point`), its offset coordinates ``s = x_r + x_off``, ``t = y_r +
    y_off`` divided by ``w = 1 + tilt_x s + tilt_y t`` (``p[14], p[15]``), then Eq. (1)
    (:func:`bc_point`) of that point.  The contract of :func:`bc_point`; the offsets' and
    the new columns by the chain rule through the projection ``(u, v) = (s, t) / w``."""
    deg = np.pi / 180.0
    cs = np.cos(p[13] * deg)
    sn = np.sin(p[13] * deg)
    xr = cs * x - sn * y
    yr = sn * x + cs * y
    tx = p[14]
    ty = p[15]
    s = xr + p[8]
    t = yr + p[9]
    iw = 1.0 / (1.0 + tx * s + ty * t)
    u = s * iw
    v = t * iw
    xd, yd, a, b, c, d = bc_point(p, u - p[8], v - p[9], need, jp, j, want)
    if need == VALUE:
        return xd, yd, 0.0, 0.0, 0.0, 0.0
    # e = (Eq. 1's point Jacobian) . d(u, v) / d(s, t)
    p11 = iw * (1.0 - u * tx)
    p12 = -u * ty * iw
    p21 = -v * tx * iw
    p22 = iw * (1.0 - v * ty)
    e11 = a * p11 + b * p21
    e12 = a * p12 + b * p22
    e21 = c * p11 + d * p21
    e22 = c * p12 + d * p22
    if need == PARAM_JAC:
        # the offsets move the point before the projection: d(s, t) / d(x_off, y_off) = I
        jp[0, 8, j] = e11
        jp[1, 8, j] = e21
        jp[0, 9, j] = e12
        jp[1, 9, j] = e22
        # d(xr, yr) / d(theta) = (-yr, xr), per radian
        jp[0, 13, j] = (e12 * xr - e11 * yr) * deg
        jp[1, 13, j] = (e22 * xr - e21 * yr) * deg
        # d(u, v) / d(tilt_x) = -(u, v) u, d(u, v) / d(tilt_y) = -(u, v) v
        jp[0, 14, j] = -(a * u + b * v) * u
        jp[1, 14, j] = -(c * u + d * v) * u
        jp[0, 15, j] = -(a * u + b * v) * v
        jp[1, 15, j] = -(c * u + d * v) * v
    # times the rotation's point Jacobian
    return xd, yd, e11 * cs + e12 * sn, e12 * cs - e11 * sn, e21 * cs + e22 * sn, e22 * cs - e21 * sn


@numba.njit(inline="always", **_JIT)
def bc_tilt_inverse_start(p, xd, yd):
    """The Newton start of Eq. (1) in perspective: the inverse of the linear part, of the
    projection (``(s, t) = (u, v) / (1 - tilt_x u - tilt_y v)``) and of the rotation."""
    xp, yp = bc_inverse_start(p, xd, yd)
    u = xp + p[8]
    v = yp + p[9]
    w = 1.0 / (1.0 - p[14] * u - p[15] * v)
    xr = u * w - p[8]
    yr = v * w - p[9]
    th = p[13] * (np.pi / 180.0)
    return np.cos(th) * xr + np.sin(th) * yr, np.cos(th) * yr - np.sin(th) * xr


@numba.njit(inline="always", **_JIT)
def relay_point_any(p, x, y, need, jp, j, want):
    """:func:`relay_point` with the point contract's arguments.  No analytic parameter
    columns: callers use :func:`fd_param_columns` (the family's ``analytic_jacobian`` is
    False)."""
    return relay_point(p, x, y, min(need, POINT_JAC))


@numba.njit(inline="always", **_JIT)
def identity_start(p, xd, yd):
    return xd, yd


@numba.njit(inline="always", **_JIT)
def bc_rounding_scale(p, jmax):
    """The magnitudes Eq. (1) adds up besides the point's own (distorted units): the centre
    ``c_x, c_y`` and the offsets ``x_o, y_o`` carried through the point Jacobian (largest
    entry ``jmax``); the same for Eq. (1) with the rotation (its ``p[:13]``)."""
    return abs(p[10]) + abs(p[11]) + jmax * (abs(p[8]) + abs(p[9]))


@numba.njit(inline="always", **_JIT)
def relay_rounding_scale(p, jmax):
    """The relay's evaluation goes through its mm-scale ray geometry (mirrors ``f1``, ``f2``
    apart by ``d1``, the stop) and back to px: its rounding is that of those lengths in
    pixels, ``(|d1| + |f1| + |f2| + |stop|) / pixel``.  Measured (101 x 101 points over the
    1 mm field, setup 1): the value scatters by 0.2 (std) and at most 1.8 times
    ``eps * (d1 + f1 + f2) / pixel`` about a smooth curve, at 4.8, 0.96 and 0.1 um pixels."""
    d1 = abs(p[RELAY_DESIGN] + p[RELAY_MISALIGNMENT + 12])
    length = d1 + abs(p[RELAY_DESIGN + 1]) + abs(p[RELAY_DESIGN + 2]) + abs(p[RELAY_DESIGN + 4])
    if p.shape[0] > RELAY_DESIGN + 12:  # relay+microscope: the relay's image magnified |M| times
        length *= max(1.0, abs(p[RELAY_DESIGN + 12]))
    return length / abs(p[RELAY_DESIGN + 5])


@numba.njit(inline="always", **_JIT)
def no_rounding_scale(p, jmax):
    """A family whose evaluation involves no magnitudes beyond its points' (the default)."""
    return 0.0


#: Each family's point function and Newton start, by code: a new family adds one entry.
_POINT = {FAMILY_BC: bc_point, FAMILY_BC_POSE: bc_pose_point, FAMILY_RELAY: relay_point_any,
          FAMILY_BC_TILT: bc_tilt_point}  # fmt: skip
_START = {FAMILY_BC: bc_inverse_start, FAMILY_BC_POSE: bc_pose_inverse_start, FAMILY_RELAY: identity_start,
          FAMILY_BC_TILT: bc_tilt_inverse_start}  # fmt: skip
#: The magnitudes (distorted units) each family's evaluation rounds at, beyond the point's
#: own (:func:`rounding_level`); a family without an entry has none
#: (:func:`no_rounding_scale`).
_ROUNDING = {
    FAMILY_BC: bc_rounding_scale,
    FAMILY_BC_POSE: bc_rounding_scale,
    FAMILY_BC_TILT: bc_rounding_scale,
    FAMILY_RELAY: relay_rounding_scale,
}
#: Compiled functions from other modules that a family's kernels contain (their source
#: files name the kernels' cache entries: :func:`_source_tag`).
_DEPENDS = {FAMILY_RELAY: (relay_point,)}


def point(p, x, y, need, jp, j, want):
    """The model at one point (see :func:`bc_point` for the contract), as the kernels call
    it: in each family's copy of the kernels (:func:`family_kernels`) this name is that
    family's point function (``_POINT``)."""
    raise NotImplementedError("point() exists only inside the kernels; call oapcal.model.distort")


def inverse_start(p, xd, yd):
    """Where the Newton inverse starts for the distorted point ``(xd, yd)``; in each
    family's kernels that family's start (``_START``), like :func:`point`."""
    raise NotImplementedError("inverse_start() exists only inside the kernels; call oapcal.model.undistort")


def rounding_scale(p, jmax):
    """The magnitudes the family's evaluation rounds at beyond the point's own, in
    distorted units (``jmax``: the largest entry of the point Jacobian); in each family's
    kernels that family's (``_ROUNDING``), like :func:`point`."""
    raise NotImplementedError("rounding_scale() exists only inside the kernels; call oapcal.model.undistort")


#: The kernels that call a model, by name, with their compiler options: written once
#: below, compiled once per family by :func:`family_kernels`.
_PER_FAMILY: dict[str, tuple] = {}


def per_family(**options):
    """Mark a kernel as written once for all families and compiled once per family."""

    def register(func):
        _PER_FAMILY[func.__name__] = (func, options)
        return func

    return register


def _source_tag(*funcs) -> str:
    """``_<digest>`` of the source files that define ``funcs`` (``_DEPENDS``: the relay's
    tracer in :mod:`oapcal._relay_kernel`), or ``""`` for none.

    Why: Numba's cache checks only the source file of the function it caches, and a cached
    kernel holds the code of the point function compiled into it, so editing
    ``_relay_kernel.py`` would leave the relay's cached kernels running the old tracer.  The
    digest in the kernels' names makes an edited tracer a cache miss (compiled afresh).
    """
    if not funcs:
        return ""
    digest = hashlib.sha256()
    for path in sorted({inspect.getsourcefile(f.py_func) for f in funcs}):
        digest.update(Path(path).read_bytes())
    return f"_{digest.hexdigest()[:10]}"


@functools.cache
def family_kernels(family: int) -> dict:
    """The compiled kernels of ``family``: each :func:`per_family` kernel compiled with
    :func:`point`, :func:`inverse_start` and :func:`rounding_scale` bound to that family's
    functions (and its calls to other kernels to that family's copies).

    Why a copy of each kernel per family, and not a family argument: the point function is
    then a plain global of the kernel, which Numba inlines before typing, so a session that
    fits Eq. (1) never compiles the relay's tracer (~10 s), the Brown-Conrady loops
    vectorise (a run-time family branch made fits 1.4-1.75x slower), and each kernel types
    the point function once (choosing it by a literal family argument in an ``overload``
    re-typed it at every call site: 3-5 s more of a first use's compilation).  Each copy is
    cached under its own name (``<kernel>_family<code>``, see :func:`_source_tag`).
    """
    namespace = dict(globals(), point=_POINT[family], inverse_start=_START[family],
                     rounding_scale=_ROUNDING.get(family, no_rounding_scale))  # fmt: skip
    tag = _source_tag(*_DEPENDS.get(family, ()))
    compiled = {}
    for name, (func, options) in _PER_FAMILY.items():
        copy = types.FunctionType(func.__code__, namespace, name, func.__defaults__, func.__closure__)
        copy.__qualname__ = f"{name}_family{family}{tag}"
        copy.__module__ = func.__module__
        copy.__doc__ = func.__doc__
        compiled[name] = namespace[name] = numba.njit(**options, **_JIT)(copy)
    return compiled


@per_family()
def fd_param_columns(p, x, y, jp, j, want, step):
    """Central-difference parameter Jacobian ``jp[:, i, j]`` (parameters ``i`` flagged in
    ``want``) of the family's model at one point, for families without analytic columns:
    ``h_i = step * max(|p_i|, 1)``."""
    q = p.copy()
    for i in range(p.shape[0]):
        if not want[i]:
            continue
        h = step * max(abs(p[i]), 1.0)
        # one call site for both sides: Numba's SSA check trips over two inlined copies of
        # the point function in one loop (NumbaIRAssumptionWarning)
        for side in range(2):
            q[i] = p[i] + h if side == 0 else p[i] - h
            xs, ys, _, _, _, _ = point(q, x, y, VALUE, jp, j, want)
            sign = 1.0 if side == 0 else -1.0
            if side == 0:
                jp[0, i, j] = 0.0
                jp[1, i, j] = 0.0
            jp[0, i, j] += sign * xs / (2.0 * h)
            jp[1, i, j] += sign * ys / (2.0 * h)
        q[i] = p[i]


# ------------------------------------------------------------------- forward evaluation


@numba.njit(inline="always", **_JIT)
def _batch_item(t, n, params, xy):
    """Item ``b`` and point ``j`` of the index ``t`` of a flattened ``(B, N)`` batch, with
    the item's parameters and the point: ``params (Bp, P)``, ``xy (Bx, N, 2)``, ``Bp`` and
    ``Bx`` 1 (shared by all items) or B."""
    b = t // n
    j = t - b * n
    bx = b if xy.shape[0] > 1 else 0
    return b, j, params[b if params.shape[0] > 1 else 0], xy[bx, j, 0], xy[bx, j, 1]


@per_family()
def evaluate(start, stop, params, xy, need, fd_step, out, jpt, jpar):
    """The model at the points ``start <= t < stop`` of the flattened ``(B, N)`` batch:
    ``params (Bp, P)``, ``xy (Bx, N, 2)`` with ``Bp, Bx`` 1 or B; ``out (B, N, 2)``; with
    ``need >= POINT_JAC`` ``jpt (B, N, 2, 2)``; with ``need == PARAM_JAC``
    ``jpar (B, N, 2, P)`` (central differences with relative step ``fd_step`` unless it is
    None)."""
    n = out.shape[1]
    jp = np.zeros((2, params.shape[1], 1))
    want = np.ones(params.shape[1], dtype=np.bool_)
    for t in range(start, stop):
        b, j, p, x, y = _batch_item(t, n, params, xy)
        # one call site of the point function (two inlined copies trip Numba's SSA check)
        xd, yd, a, bb, c, d = point(p, x, y, need if fd_step is None else min(need, POINT_JAC), jp, 0,
                                    want)  # fmt: skip
        if fd_step is not None and need == PARAM_JAC:
            fd_param_columns(p, x, y, jp, 0, want, fd_step)
        out[b, j, 0] = xd
        out[b, j, 1] = yd
        if need >= POINT_JAC:
            jpt[b, j, 0, 0] = a
            jpt[b, j, 0, 1] = bb
            jpt[b, j, 1, 0] = c
            jpt[b, j, 1, 1] = d
        if need == PARAM_JAC:
            for i in range(jp.shape[1]):
                jpar[b, j, 0, i] = jp[0, i, 0]
                jpar[b, j, 1, i] = jp[1, i, 0]


@per_family(fastmath=_FASTMATH)
def grid_map(start, stop, p, xs, ys, out_x, out_y):
    """The model on the grid ``xs (C,) x ys[start:stop]`` of undistorted points, into the
    rows ``start:stop`` of ``out_x, out_y (R, C)`` (float32): a correction map."""
    jp = np.empty((2, p.shape[0], 1))
    want = np.zeros(p.shape[0], dtype=np.bool_)
    for r in range(start, stop):
        y = ys[r]
        row_x = out_x[r]
        row_y = out_y[r]
        for col in range(xs.shape[0]):
            xd, yd, _, _, _, _ = point(p, xs[col], y, VALUE, jp, 0, want)
            row_x[col] = xd
            row_y[col] = yd


@per_family(fastmath=_FASTMATH)
def min_det(start, stop, params, xy, out):
    """The smallest point-Jacobian determinant of the models ``params[start:stop]`` over the
    points ``xy (2, M)`` (rows x, y), into ``out``; NaN when any determinant is NaN."""
    jp = np.empty((2, params.shape[1], 1))
    want = np.zeros(params.shape[1], dtype=np.bool_)
    xs = xy[0]
    ys = xy[1]
    for b in range(start, stop):
        p = params[b]
        lo = np.inf
        bad = 0
        for j in range(xs.shape[0]):
            _, _, a, bb, c, d = point(p, xs[j], ys[j], POINT_JAC, jp, 0, want)
            det = a * d - bb * c
            lo = det if det < lo else lo
            bad += det != det
        out[b] = np.nan if bad else lo


# ---------------------------------------------------------------------- Newton inverse


#: The inverse's allowance for the model's own rounding (:func:`rounding_level`), in units of
#: ``eps * scale``: 16, about 9 times the largest scatter measured for the relay (1.8).
ROUNDING_ULPS = 16.0
_EPS = float(np.finfo(np.float64).eps)


@per_family(inline="always")
def rounding_level(p, xd, yd, x, y, a, b, c, d):
    """How far from ``(xd, yd)`` the model's value at ``(x, y)`` may be through rounding
    alone (distorted units): :data:`ROUNDING_ULPS` ``* eps *`` the magnitudes the evaluation
    adds up: ``|xd| + |yd|``, the point's ``|x| + |y|`` carried through the point Jacobian
    ``[[a, b], [c, d]]`` (its largest entry) and the family's own (:func:`rounding_scale`)."""
    jmax = max(max(abs(a), abs(b)), max(abs(c), abs(d)))
    scale = rounding_scale(p, jmax) + abs(xd) + abs(yd) + jmax * (abs(x) + abs(y))
    return ROUNDING_ULPS * _EPS * scale


@per_family()
def invert_point(p, xd, yd, x, y, tol, max_iter, jp, want):
    """Solve ``model(x, y) = (xd, yd)`` by Newton from ``(x, y)`` with step halving (up to
    10 halvings while the residual grows); a point whose residual cannot decrease any more
    stops.  Returns ``(x, y, converged, folded, n_iter)``.

    It stops converged when the residual is ``<= tol``, or when it is within the model's
    own rounding (:func:`rounding_level`) and a full Newton step no longer reduces it (a
    residual at rounding level that does fall is followed further); and only where the
    Jacobian determinant is positive: folded when it is <= 0.  At the iteration cap a
    point is not converged.  ``jp``, ``want`` are the scratch of :func:`point`."""
    # One call site of the point function, for the start and every trial of a step (two
    # inlined copies trip Numba's SSA check): ``trial`` -1 evaluates the start, k >= 0
    # the k-th trial (t = 2^-k) of the current Newton step (sx, sy).  (a, b, c, d) is
    # always the point Jacobian at (x, y): each evaluation returns it too, so an accepted
    # step needs no second evaluation.  The rounding level is computed only where a full
    # step fails, so a residual that reaches ``tol`` takes the same path as with an
    # absolute test alone.  (Accepting a residual at rounding level at the iteration cap
    # as well made Eq. (1)'s inverse ~10 % slower, measured, though no Eq. (1) point
    # reached it; at rounding level a residual falls step after step only by chance, so
    # the cap is not reached there.)
    fx = fy = a = b = c = d = 0.0
    err = np.inf
    sx = sy = t = 0.0
    trial = -1
    done = False
    n_iter = 0
    while True:
        xn = x + t * sx
        yn = y + t * sy
        fxn, fyn, an, bn, cn, dn = point(p, xn, yn, POINT_JAC, jp, 0, want)
        fxn -= xd
        fyn -= yd
        err_new = np.sqrt(fxn * fxn + fyn * fyn)
        if trial < 0:  # the start
            fx, fy, a, b, c, d, err = fxn, fyn, an, bn, cn, dn, err_new
        else:
            if not ((err_new < err) or (err_new <= tol)):
                if trial == 0 and err <= rounding_level(p, xd, yd, x, y, a, b, c, d):
                    done = True  # the residual is at the model's precision
                    break
                if trial < 10:
                    t *= 0.5  # the residual grew: halve the step (up to 10 times)
                    trial += 1
                    continue
            stalled = not (err_new < err)
            if np.isfinite(err_new):
                x, y, fx, fy, a, b, c, d, err = xn, yn, fxn, fyn, an, bn, cn, dn, err_new
            if stalled and not err <= tol:
                err = np.inf  # no step decreases the residual any more
        done = err <= tol
        if done or not np.isfinite(err) or n_iter >= max_iter:
            break
        n_iter += 1
        det = a * d - b * c
        sx = -(d * fx - b * fy) / det
        sy = -(-c * fx + a * fy) / det
        t = 1.0
        trial = 0
    det = a * d - b * c
    folded = (not det > 0.0) and np.isfinite(det)
    converged = done and (not folded) and np.isfinite(x) and np.isfinite(y)
    return x, y, converged, folded, n_iter


@per_family()
def invert_batch(start, stop, params, xy_d, xy_start, tol, max_iter, out, converged, folded, iters):
    """Invert the points ``start <= t < stop`` of the flattened ``(B, N)`` batch:
    ``params (Bp, P)``, ``xy_d (Bx, N, 2)``, ``xy_start`` like ``xy_d`` or None (the family's
    start); outputs ``(B, N, 2)`` and ``(B, N)`` x3."""
    n = out.shape[1]
    jp = np.empty((2, params.shape[1], 1))
    want = np.zeros(params.shape[1], dtype=np.bool_)
    for t in range(start, stop):
        b, j, p, xd, yd = _batch_item(t, n, params, xy_d)
        if xy_start is None:  # pruned at compile time
            x0, y0 = inverse_start(p, xd, yd)
        else:
            bs = b if xy_start.shape[0] > 1 else 0
            x0, y0 = xy_start[bs, j, 0], xy_start[bs, j, 1]
        x, y, ok, fold, it = invert_point(p, xd, yd, x0, y0, tol, max_iter, jp, want)
        out[b, j, 0] = x if ok else np.nan
        out[b, j, 1] = y if ok else np.nan
        converged[b, j] = ok
        folded[b, j] = fold
        iters[b, j] = it


@per_family()
def invert_score(start, stop, params, xy_d, xy_u, tol, max_iter, rss, mean_dist, n_bad, n_folded):
    """Correct all points ``xy_d (N, 2)`` through the models ``params[start:stop]`` and compare
    with ``xy_u (N, 2)`` without storing the points: per model the sum of squared and the
    mean Euclidean distances over the converged points, the number of points whose
    inverse failed, and how many of those fold."""
    jp = np.empty((2, params.shape[1], 1))
    want = np.zeros(params.shape[1], dtype=np.bool_)
    for b in range(start, stop):
        p = params[b]
        s2 = 0.0
        s1 = 0.0
        bad = 0
        fold = 0
        for j in range(xy_d.shape[0]):
            x0, y0 = inverse_start(p, xy_d[j, 0], xy_d[j, 1])
            x, y, ok, fo, _ = invert_point(p, xy_d[j, 0], xy_d[j, 1], x0, y0, tol, max_iter, jp, want)
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


# -------------------------------------------------------------- Levenberg-Marquardt


@per_family(fastmath=_FASTMATH)
def _residuals(p, pts, res, jp, want):
    """``res (2n,)`` = model - data at the item's points ``pts (4, n)`` (rows x_u, y_u,
    x_d, y_d), x residuals first, then y; returns the cost ``0.5 |res|^2``."""
    n = pts.shape[1]
    # 1-d row views: the loop then vectorises
    xu, yu, xo, yo = pts[0], pts[1], pts[2], pts[3]
    res_x = res[:n]
    res_y = res[n : 2 * n]
    cost = 0.0
    for j in range(n):
        xd, yd, _, _, _, _ = point(p, xu[j], yu[j], VALUE, jp, 0, want)
        rx = xd - xo[j]
        ry = yd - yo[j]
        res_x[j] = rx
        res_y[j] = ry
        cost += rx * rx + ry * ry
    return 0.5 * cost


@per_family(fastmath=_FASTMATH)
def _jacobian(p, pts, fd_step, want, cols):
    """Fill the rows ``i`` with ``want[i]`` of ``cols (2, P, >= n)`` with d(model)/d(p_i)
    at the item's points ``pts (4, n)``: ``cols[0]`` the x rows, ``cols[1]`` the y rows.
    Analytic when ``fd_step`` is None, else central differences with that relative step."""
    for j in range(pts.shape[1]):
        if fd_step is None:  # pruned at compile time: one specialization per kind
            point(p, pts[0, j], pts[1, j], PARAM_JAC, cols, j, want)
        else:
            fd_param_columns(p, pts[0, j], pts[1, j], cols, j, want, fd_step)


@numba.njit(fastmath=_FASTMATH, **_JIT)
def _dot(x, y):
    """``x . y`` of two equal-length 1-d views (indices from 0, so the loop vectorises)."""
    s = 0.0
    for c in range(x.shape[0]):
        s += x[c] * y[c]
    return s


@numba.njit(fastmath=_FASTMATH, **_JIT)
def _normal_equations(cols, res, n, free, half, a, g):
    """``a = J^T J`` and ``g = J^T r`` over the free parameters ``free`` (their rows of
    ``cols``, :func:`_jacobian`).  A parameter whose ``half`` is 1 moves x only and 2 y
    only: its other row is zero and skipped."""
    rx = res[:n]
    ry = res[n : 2 * n]
    for i in range(free.shape[0]):
        ri = free[i]
        xi = half[free[i]] != 2
        yi = half[free[i]] != 1
        s = 0.0
        if xi:
            s += _dot(cols[0, ri, :n], rx)
        if yi:
            s += _dot(cols[1, ri, :n], ry)
        g[i] = s
        for q in range(i + 1):
            rq = free[q]
            s = 0.0
            if xi and half[free[q]] != 2:
                s += _dot(cols[0, ri, :n], cols[0, rq, :n])
            if yi and half[free[q]] != 1:
                s += _dot(cols[1, ri, :n], cols[1, rq, :n])
            a[i, q] = s
            a[q, i] = s


@numba.njit(**_JIT)
def solve_spd(lhs, rhs, k, out, work):
    """Solve ``lhs x = rhs`` (k x k, symmetric positive definite) by Cholesky.

    Returns False when a pivot is not positive (the caller falls back to :func:`solve_lu`).
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
def solve_lu(lhs, rhs, k, out, work):
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
def _prior_rows(p, mu, w, free, a, g, normal):
    """The prior rows ``w_q (p_q - mu_q)`` of the free parameters (``w`` 0: no row): their
    cost ``0.5 sum r^2``, and with ``normal`` their terms added to ``a = J^T J`` (``w_q^2``
    on the diagonal) and ``g = J^T r`` (``w_q r_q``).  A MAP fit with Gaussian priors is
    least squares on the residuals with these rows appended (``oapcal.fitting.fit_batch``)."""
    c = 0.0
    for i in range(free.shape[0]):
        q = free[i]
        wq = w[q]
        if wq > 0.0:
            r = wq * (p[q] - mu[q])
            c += r * r
            if normal:
                a[i, i] += wq * wq
                g[i] += wq * r
    return 0.5 * c


@per_family()
def lm_item(u, d, idx, n, mask, half, p, max_iter, ftol, xtol, gtol, fd_step, want_jtj, jtj_out,
            scratch, prior_mu, prior_w, has_prior):  # fmt: skip
    """Levenberg-Marquardt for one item, in place on ``p``; returns (status, n_iter, cost).

    MINPACK-style: Marquardt column scaling, damping ``lam`` raised by ``nu`` on a rejected
    step and lowered by ``max(1/3, 1 - (2 rho - 1)^3)`` on an accepted one; stops on
    ``gtol`` (status 1), ``ftol`` (2), ``xtol`` (3), zero residuals (4), the iteration cap
    (0), non-finite values (-1) or unbounded damping (-2).  With ``want_jtj``,
    ``jtj_out (P, P)`` receives ``J^T J`` at the final ``p`` (free rows and columns).
    ``scratch`` is :func:`lm_scratch` (reused from item to item).  With ``has_prior`` the
    rows of :func:`_prior_rows` (``prior_mu``, ``prior_w``, each ``(P,)``) are part of the
    residuals and of the returned cost; ``jtj_out`` stays the data's ``J^T J`` alone.
    """
    cols, res_all, jp, pts_all = scratch
    # The item's points, gathered once into contiguous rows (the loops over them vectorise).
    pts = pts_all[:, :n]
    for j in range(n):
        q = idx[j]
        pts[0, j] = u[q, 0]
        pts[1, j] = u[q, 1]
        pts[2, j] = d[q, 0]
        pts[3, j] = d[q, 1]
    free = np.flatnonzero(mask)
    k = free.shape[0]
    n_params = p.shape[0]
    n2 = 2 * n
    res = res_all[:n2]
    a = np.empty((k, k))
    g = np.empty(k)
    lhs = np.empty((k, k))
    a_s = np.empty((k, k))
    g_s = np.empty(k)
    step_s = np.empty(k)
    work = np.zeros((k, k))
    dcol = np.empty(k)
    p_new = p.copy()

    cost = _residuals(p, pts, res, jp, mask)
    if has_prior:
        cost += _prior_rows(p, prior_mu, prior_w, free, a, g, False)
    status = 0
    n_iter = 0
    if not np.isfinite(cost):
        status = -1
    elif cost == 0.0:
        status = 4
    lam = 1e-3
    nu = 2.0
    need_jac = True
    for _ in range(max_iter * 4 if status == 0 else 0):
        if need_jac:
            # The residuals hold the values at p: the last evaluation was at p (the start,
            # or an accepted trial step).
            _jacobian(p, pts, fd_step, mask, cols)
            _normal_equations(cols, res, n, free, half, a, g)
            if has_prior:
                _prior_rows(p, prior_mu, prior_w, free, a, g, True)
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
        if not solve_spd(lhs, g_s, k, step_s, work):
            solve_lu(lhs, g_s, k, step_s, work)
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
        for i in range(n_params):
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
        cost_new = _residuals(p_new, pts, res, jp, mask)
        if has_prior:
            cost_new += _prior_rows(p_new, prior_mu, prior_w, free, a, g, False)
        actual = cost - cost_new
        rho = actual / predicted if predicted > 0.0 else -1.0
        accept = np.isfinite(cost_new) and actual > 0.0 and rho > 1e-4
        rel_actual = abs(actual) / cost if cost > 0.0 else 0.0
        rel_pred = predicted / cost if cost > 0.0 else 0.0
        f_conv = rel_actual <= ftol and rel_pred <= ftol and rho <= 2.0
        x_conv = np.sqrt(snorm) <= xtol * max(np.sqrt(pnorm), 1e-300)
        if accept:
            for i in range(n_params):
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
    for i in range(n_params):
        if not np.isfinite(p[i]):
            status = -1
    if not np.isfinite(cost):
        status = -1
    if want_jtj:
        # J^T J at the final p for the covariance (the residual buffer may hold a
        # rejected trial step, so evaluate again at p).
        _residuals(p, pts, res, jp, mask)
        _jacobian(p, pts, fd_step, mask, cols)
        _normal_equations(cols, res, n, free, half, a, g)
        for i in range(k):
            for j in range(k):
                jtj_out[free[i], free[j]] = a[i, j]
    return status, n_iter, cost


@numba.njit(**_JIT)
def lm_scratch(n_params, n_max):
    """Work arrays of :func:`lm_item` for up to ``n_params`` parameters and ``n_max`` points."""
    return (
        np.zeros((2, n_params, n_max)),  # zeros: entries a family leaves unwritten are 0
        np.empty(2 * n_max),
        np.zeros((2, n_params, 1)),
        np.empty((4, n_max)),
    )


@per_family()
def lm_batch(start, stop, u, d, idx, counts, masks, half, p, max_iter, ftol, xtol, gtol, fd_step,
             want_jtj, status, n_iter, cost, jtj, prior_mu=None, prior_w=None, has_prior=False):  # fmt: skip
    """:func:`lm_item` for the items ``start <= b < stop``: points ``u (Bu, N, 2)``,
    ``d (Bd, N, 2)`` (each 1 or B), point indices ``idx (Bi, nmax)`` with ``counts (Bi,)``
    used (``Bi`` 1 or B), free parameters ``masks (B, P)``, starts ``p (B, P)``
    (overwritten with the solutions); with ``want_jtj`` ``jtj (B, P, P)`` receives
    ``J^T J`` at each solution, else it may be ``(1, P, P)``; ``prior_mu``, ``prior_w``
    ``(Bp, P)`` (``Bp`` 1 or B) the prior rows of each item when ``has_prior``."""
    scratch = lm_scratch(masks.shape[1], idx.shape[1])
    if prior_w is None:  # no priors (pruned at compile time)
        mu_all = np.zeros((1, masks.shape[1]))
        w_all = mu_all
        use_prior = False
    else:
        mu_all = prior_mu
        w_all = prior_w
        use_prior = has_prior
    for i in range(start, stop):
        bi = i if idx.shape[0] > 1 else 0
        bu = i if u.shape[0] > 1 else 0
        bd = i if d.shape[0] > 1 else 0
        bj = i if want_jtj else 0
        bp = i if w_all.shape[0] > 1 else 0
        s, it, c = lm_item(u[bu], d[bd], idx[bi], counts[bi], masks[i], half, p[i], max_iter,
                           ftol, xtol, gtol, fd_step, want_jtj, jtj[bj], scratch, mu_all[bp],
                           w_all[bp], use_prior)  # fmt: skip
        status[i] = s
        n_iter[i] = it
        cost[i] = c


# ----------------------------------------------------------------------- threads

_POOL: list = []


def n_threads() -> int:
    """Threads the kernels run on: the CPUs this process may use (``NUMBA_NUM_THREADS``
    caps it, as it would Numba's own threading)."""
    try:
        cpus = len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        cpus = os.cpu_count() or 1
    return max(1, min(cpus, int(os.environ.get("NUMBA_NUM_THREADS", cpus))))


def run_blocks(kernel, n: int, block: int, family: int, *args) -> None:
    """Call ``family``'s copy of ``kernel`` (:func:`family_kernels`) as
    ``kernel(start, stop, *args)`` over ``0 <= start < n`` in blocks of ``block``, the
    blocks shared out to :func:`n_threads` threads (the kernels release the GIL).

    Why threads and not ``numba.prange``: the same speed, and each kernel compiles in a
    fraction of the time (no parallel-loop lowering), which is what a first call costs.
    """
    kernel = family_kernels(family)[kernel.__name__]
    blocks = [(s, min(n, s + block)) for s in range(0, n, max(1, block))]
    threads = min(n_threads(), len(blocks))
    if threads <= 1:
        for start, stop in blocks:
            kernel(start, stop, *args)
        return
    if not _POOL or _POOL[0][0] < threads:
        from concurrent.futures import ThreadPoolExecutor

        _POOL[:] = [(threads, ThreadPoolExecutor(threads, thread_name_prefix="oapcal-kernel"))]
    pool = _POOL[0][1]
    for future in [pool.submit(kernel, start, stop, *args) for start, stop in blocks]:
        future.result()


def _init_numba_target() -> None:
    """Set up Numba's CPU target now, without importing ``scipy.linalg``.

    Numba sets up its target when it first compiles or loads a function from the cache;
    one of the modules it imports then, ``numba.np.arraymath``, imports
    ``scipy.linalg.cython_blas`` only to record whether ``np.dot`` and the like may call
    BLAS.  Importing ``scipy.linalg`` takes 0.15-0.2 s (half of it SciPy's array-API layer
    importing ``numpy.f2py``), a fifth of a whole ``oapcal select`` command, and no kernel
    here calls BLAS.  So the import is refused while the target is set up (a ``None`` in
    ``sys.modules`` makes it fail at once, without importing the package), and the flag is
    then set as Numba would have set it: BLAS is available when SciPy is installed (Numba
    checks SciPy again when a function that uses BLAS is compiled).  When SciPy's linear
    algebra is already imported, or the target is already set up, nothing is done; on a
    Numba without these internals the target is set up as usual.
    """
    import importlib.util
    import sys

    if "numba.np.arraymath" in sys.modules or "scipy.linalg" in sys.modules:
        return
    from numba.core.registry import cpu_target

    name = "scipy.linalg.cython_blas"
    sys.modules[name] = None
    try:
        cpu_target.target_context.refresh()
    finally:
        if name in sys.modules and sys.modules[name] is None:
            del sys.modules[name]
    arraymath = sys.modules.get("numba.np.arraymath")
    if arraymath is not None and hasattr(arraymath, "_HAVE_BLAS"):
        arraymath._HAVE_BLAS = importlib.util.find_spec("scipy") is not None


_init_numba_target()


def block_size(n: int, minimum: int) -> int:
    """Blocks of at least ``minimum`` (work below that runs on the calling thread: waking a
    thread costs more), else about eight per thread (load balance on a shared machine
    without much scheduling overhead)."""
    return max(minimum, -(-n // (8 * n_threads())))
