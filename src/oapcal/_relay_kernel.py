"""The physical relay model at one point, compiled: the point function of the ``relay``
model family (:data:`oapcal.optics.relay_model.RELAY`), reached through
:func:`oapcal._kernels.point`.

The parameter vector (its names: ``oapcal.model.RELAY.param_names``) has three parts:

* the target's pose in the reference frame: ``scale``, ``rotation`` (deg, about the
  reference centre, counter-clockwise in the reference's own axes), ``shift_x`` and
  ``shift_y`` (reference px);
* the relay's misalignment, the 20 degrees of freedom of
  :class:`oapcal.optics.misalign.Misalignment` in the order of its ``PARAMETERS`` (deg,
  mm);
* the design, never fitted: ``d1_mm``, ``f1_mm``, ``f2_mm``, ``orientation`` (+1 for U,
  -1 for Z), ``stop_mm``, ``pixel_mm``, the reference centre ``cx``, ``cy`` (px) and
  ``a11 .. a22``, the inverse of the aligned relay's paraxial matrix (image mm -> object
  mm);
* with a microscope behind the relay (the family ``relay+microscope``, whose vector is
  three values longer), the microscope's ``microscope_magnification`` (signed:
  negative inverts the image, i.e. turns it by 180 degrees), ``microscope_k1`` (its own
  radial term, 1/mm^2 at the sensor, about the reference centre) and the design's
  magnification ``microscope_design_magnification`` (never fitted).

A reference point ``r`` (px, the ideal image of the target) is posed,
``r' = c + scale R(rotation) (r - c) + shift``, taken to the object plane through the
aligned relay's paraxial inverse, ``o = A (r' - c) pixel``, and its chief ray (through the
centre of the aperture stop) traced through the misaligned relay onto the (tilted,
defocused) sensor: the distorted point is ``c + image / pixel``.

With a microscope the relay's image plane (tilted and defocused as above) is the
microscope's object plane, and the camera sees it magnified: a reference point is taken
to that plane through the design's magnification ``M0``, ``o = A (r' - c) pixel / M0``,
and the traced point ``h`` (mm on that plane) to the sensor as ``s = M h (1 + k1 |M h|^2)``
(``M`` the fitted magnification, ``k1`` the radial term): the distorted point is
``c + s / pixel``.  The branch is chosen by the vector's length, so the plain relay's
values are computed exactly as without it.

The geometry (the frames of the mirrors, the stop, the sensor and the object plane under
misalignment) is built by one function, :func:`relay_frames`, for this tracer and for the
NumPy tracer :func:`oapcal.optics.relay.oap_relay` (``docs/optics.md``).  The chief ray is
aimed here by Newton with a fresh Jacobian every step, to the rounding level: this is the
reference for chief rays; the NumPy tracer's ``aim`` (any stop point, blocks of rays, to
1e-10 mm) agrees with it to ~3e-10 px, and the tests check the two against each other.

Why hand-written: the solver evaluates the model at every point for every parameter
step (central differences over up to 24 parameters); the NumPy tracer aims rays in
Python over arrays, ~1000x slower per point.
"""

from __future__ import annotations

import math

import numba
import numpy as np

_JIT = {"cache": True, "nogil": True, "error_model": "numpy"}

#: Where the parts of the parameter vector start (names: :data:`oapcal.model.RELAY`).
_M = 4  # the first misalignment value (after the 4 pose values)
_D = 24  # the first design value (after the 20 misalignment values)
_S = 36  # the first microscope value (after the 12 design values), when there is one

#: Newton steps of the ray aiming at most; it stops earlier when a step changes the hit
#: point by less than :data:`AIM_TOL` mm (then the miss is at rounding level).
AIM_MAX_ITER = 12
AIM_TOL = 1e-13
#: Forward-difference step (mm) of the aiming's 2x2 Jacobian.
AIM_STEP = 1e-7
#: Central-difference step (px) of the point Jacobian.
POINT_STEP = 1e-3


# ----------------------------------------------------------------- 3-vector helpers


@numba.njit(inline="always", **_JIT)
def _add(a, b):
    return (a[0] + b[0], a[1] + b[1], a[2] + b[2])


@numba.njit(inline="always", **_JIT)
def _sub(a, b):
    return (a[0] - b[0], a[1] - b[1], a[2] - b[2])


@numba.njit(inline="always", **_JIT)
def _mul(s, a):
    return (s * a[0], s * a[1], s * a[2])


@numba.njit(inline="always", **_JIT)
def _dot(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


@numba.njit(inline="always", **_JIT)
def _cross(a, b):
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


@numba.njit(inline="always", **_JIT)
def _unit(a):
    return _mul(1.0 / math.sqrt(_dot(a, a)), a)


@numba.njit(inline="always", **_JIT)
def _reflect(d, n):
    return _sub(d, _mul(2.0 * _dot(d, n), n))


@numba.njit(inline="always", **_JIT)
def _rotate(v, k, deg):
    """``v`` rotated right-handedly by ``deg`` about the unit axis ``k`` (Rodrigues)."""
    if deg == 0.0:
        return v
    t = math.radians(deg)
    c = math.cos(t)
    s = math.sin(t)
    kxv = _cross(k, v)
    kv = _dot(k, v) * (1.0 - c)
    return (
        v[0] * c + kxv[0] * s + k[0] * kv,
        v[1] * c + kxv[1] * s + k[1] * kv,
        v[2] * c + kxv[2] * s + k[2] * kv,
    )


@numba.njit(inline="always", **_JIT)
def _mount(v, n, a, b, clock, tilt_x, tilt_y):
    """A mirror mount's rotation ``R_b(tilt_y) R_a(tilt_x) R_n(clock)`` applied to ``v``."""
    return _rotate(_rotate(_rotate(v, n, clock), a, tilt_x), b, tilt_y)


# ------------------------------------------------------------------------ the geometry


@numba.njit(**_JIT)
def _mirror(m, i, centre, to_focus, axis, f):
    """Mirror ``i`` (0 or 1) of the relay with its misalignment from ``m`` (the 20
    misalignment values): returns ``(vertex, axis, parent focal length, e1, e2)`` with
    ``e1, e2`` the transverse axes along which its surface is parametrized (the design's
    ``x`` and ``y`` rotated with it), plus the mount rotation's images of the stop's axes
    ``(ex, ey, normal)`` and the decentre shift (used by the stop at the first mirror)."""
    o = 6 * i
    tilt_x, tilt_y, dec_x, dec_y, clock, df = m[o], m[o + 1], m[o + 2], m[o + 3], m[o + 4], m[o + 5]
    fn = f + df
    n = _unit(_add(axis, to_focus))  # the normal at a 90-degree OAP's centre
    a = (1.0, 0.0, 0.0)
    b = _cross(n, a)
    vertex_rel = _sub(_mul(fn, to_focus), _mul(0.5 * fn, axis))  # vertex - centre
    shift = _add(_mul(dec_x, a), _mul(dec_y, b))
    vertex = _add(_add(centre, shift), _mount(vertex_rel, n, a, b, clock, tilt_x, tilt_y))
    ax = _mount(axis, n, a, b, clock, tilt_x, tilt_y)
    e1 = _mount((1.0, 0.0, 0.0), n, a, b, clock, tilt_x, tilt_y)
    e2 = _mount((0.0, 1.0, 0.0), n, a, b, clock, tilt_x, tilt_y)
    sn = _mount((0.0, 0.0, 1.0), n, a, b, clock, tilt_x, tilt_y)
    return vertex, ax, 0.5 * fn, e1, e2, sn, shift


@numba.njit(**_JIT)
def relay_frames(m, d1_design, f1, f2, orient, stop):
    """The frames of the relay's parts under misalignment: the one builder of the relay's
    geometry, used by :func:`relay_point_value` (for every parameter vector the solver
    tries) and by the NumPy tracer :func:`oapcal.optics.relay.oap_relay` (once per relay).

    ``m`` the 20 misalignment values (:data:`oapcal.optics.misalign.PARAMETERS` order),
    ``d1_design`` the design's collimated path (mm; ``m``'s d1 change is added), ``f1``,
    ``f2`` the mirrors' design focal lengths, ``orient`` +1 (U) or -1 (Z), ``stop`` the
    stop's distance after the first mirror (0: the first mirror's own aperture, which moves
    with it).  Returns the tuple (3-vectors as tuples, mm)::

        (obj_ex, obj_ey, obj_n,       the object plane's axes (its origin: 0)
         v1, a1, fp1, e1, e2, c1,     the first mirror: vertex, parent axis, parent focal
                                      length, the axes of its surface's (u, v), centre
         v2, a2, fp2, c2,             the second mirror (without the surface's axes)
         sp, sx, sy, sn,              the stop: its centre, x and y axes, normal
         ip, jx, jy, jn)              the sensor: its centre, x and y axes, normal

    The frames of ``docs/optics.md`` (Misalignment): each mirror rotated about its centre
    by ``R_b(tilt_y) R_a(tilt_x) R_n(clock)`` (``a, b, n`` its design frame), then
    decentred; a focal-length change moves the vertex, not the centre; the sensor at the
    design's second focus, its axes the object's carried along the central ray by both
    reflections, defocused along its normal, then tilted about its own x, then y axis; the
    object plane tilted about its own x, then y axis.
    """
    d1 = d1_design + m[12]
    o_ex = (1.0, 0.0, 0.0)
    o_ey = (0.0, 0.0, 1.0)
    o_n = (0.0, 1.0, 0.0)
    tx, ty = m[18], m[19]
    ex = _rotate(_rotate(o_ex, o_ex, tx), o_ey, ty)
    ey = _rotate(_rotate(o_ey, o_ex, tx), o_ey, ty)
    en = _rotate(_rotate(o_n, o_ex, tx), o_ey, ty)
    c1 = (0.0, f1, 0.0)
    to1 = (0.0, -1.0, 0.0)
    ax1 = (0.0, 0.0, 1.0)
    c2 = (0.0, f1, d1)
    to2 = (0.0, -orient, 0.0)
    ax2 = (0.0, 0.0, -1.0)
    v1, a1, fp1, e1, e2, sn, shift1 = _mirror(m, 0, c1, to1, ax1, f1)
    v2, a2, fp2, _, _, _, shift2 = _mirror(m, 1, c2, to2, ax2, f2)
    # the stop: at the first mirror it is that mirror's aperture and moves with it
    if stop == 0.0:
        sp = _add(c1, shift1)
        sx = e1
        sy = e2
    else:
        sp = (0.0, f1, stop)
        sx = (1.0, 0.0, 0.0)
        sy = (0.0, 1.0, 0.0)
        sn = (0.0, 0.0, 1.0)
    sp = _add(sp, _add(_mul(m[13], sx), _mul(m[14], sy)))
    # the sensor
    n1 = _unit(_add(ax1, to1))
    n2 = _unit(_add(ax2, to2))
    i_ex = _reflect(_reflect(o_ex, n1), n2)
    i_ey = _reflect(_reflect(o_ey, n1), n2)
    i_n = _reflect(_reflect(o_n, n1), n2)
    ip = _add(_add(c2, _mul(f2, to2)), _mul(m[17], i_n))
    ctx, cty = m[15], m[16]
    jx = _rotate(_rotate(i_ex, i_ex, ctx), i_ey, cty)
    jy = _rotate(_rotate(i_ey, i_ex, ctx), i_ey, cty)
    jn = _rotate(_rotate(i_n, i_ex, ctx), i_ey, cty)
    return (ex, ey, en, v1, a1, fp1, e1, e2, _add(c1, shift1), v2, a2, fp2, _add(c2, shift2),
            sp, sx, sy, sn, ip, jx, jy, jn)  # fmt: skip


@numba.njit(inline="always", **_JIT)
def _surface(vertex, axis, fp, e1, e2, u, v):
    return _add(_add(_add(vertex, _mul(u, e1)), _mul(v, e2)), _mul((u * u + v * v) / (4.0 * fp), axis))


@numba.njit(inline="always", **_JIT)
def _normal(vertex, axis, fp, q):
    r = _sub(q, vertex)
    along = _dot(r, axis)
    r_perp = _sub(r, _mul(along, axis))
    return _unit(_sub(_mul(2.0 * fp, axis), r_perp))


@numba.njit(**_JIT)
def _stop_miss(vertex, axis, fp, e1, e2, obj, sp, sx, sy, sn, u, v):
    """Where the ray from ``obj`` reflected at the mirror point ``(u, v)`` crosses the
    stop plane, in the stop's coordinates; also the hit and the reflected direction.
    (Twelve arguments: the frames as tuples, as :func:`_aim_chief_ray`.)"""
    q = _surface(vertex, axis, fp, e1, e2, u, v)
    d = _reflect(_unit(_sub(q, obj)), _normal(vertex, axis, fp, q))
    t = _dot(_sub(sp, q), sn) / _dot(d, sn)
    h = _sub(_add(q, _mul(t, d)), sp)
    return _dot(h, sx), _dot(h, sy), q, d


@numba.njit(inline="always", **_JIT)
def _aim_chief_ray(v1, a1, fp1, e1, e2, obj, sp, sx, sy, sn):
    """The chief ray from ``obj``: the point ``q`` of the first mirror (its surface's
    ``(u, v)``) whose reflection ``d`` passes the stop's centre (Newton, forward-difference
    Jacobian, from the point under the stop's centre).  (Ten arguments: the mirror's and
    the stop's frames, passed as tuples; Numba has no cheap record of them.)"""
    st = _sub(sp, v1)
    u = _dot(st, e1)
    v = _dot(st, e2)
    mx, my, q, d = _stop_miss(v1, a1, fp1, e1, e2, obj, sp, sx, sy, sn, u, v)
    h = AIM_STEP
    for _ in range(AIM_MAX_ITER):
        ux, uy, _, _ = _stop_miss(v1, a1, fp1, e1, e2, obj, sp, sx, sy, sn, u + h, v)
        vx, vy, _, _ = _stop_miss(v1, a1, fp1, e1, e2, obj, sp, sx, sy, sn, u, v + h)
        ja = (ux - mx) / h
        jc = (uy - my) / h
        jb = (vx - mx) / h
        jd = (vy - my) / h
        det = ja * jd - jb * jc
        du = (jd * mx - jb * my) / det
        dv = (-jc * mx + ja * my) / det
        u -= du
        v -= dv
        mx, my, q, d = _stop_miss(v1, a1, fp1, e1, e2, obj, sp, sx, sy, sn, u, v)
        if not (abs(du) + abs(dv) > AIM_TOL):  # converged (or NaN: the ray missed)
            break
    return q, d


@numba.njit(inline="always", **_JIT)
def _paraboloid_hit(q, d, vertex, axis, fp):
    """The distance along the ray ``q + t d`` to its first hit (``t > 1e-9``) of the
    paraboloid ``(vertex, axis, fp)``; inf when it misses (the stable quadratic roots)."""
    r0 = _sub(q, vertex)
    r0a = _dot(r0, axis)
    r0p = _sub(r0, _mul(r0a, axis))
    da = _dot(d, axis)
    dp = _sub(d, _mul(da, axis))
    four_f = 4.0 * fp
    qa = _dot(dp, dp)
    qb = 2.0 * _dot(r0p, dp) - four_f * da
    qc = _dot(r0p, r0p) - four_f * r0a
    sq = math.sqrt(qb * qb - 4.0 * qa * qc) if qb * qb - 4.0 * qa * qc >= 0.0 else np.nan
    qq = -0.5 * (qb + math.copysign(sq, qb))
    t1 = qq / qa if qa != 0.0 else np.inf
    t2 = qc / qq if qq != 0.0 else np.inf
    t1 = t1 if t1 > 1e-9 else np.inf
    t2 = t2 if t2 > 1e-9 else np.inf
    return min(t1, t2)


@numba.njit(inline="always", **_JIT)
def _frames_of(p):
    """:func:`relay_frames` of the parameter vector ``p`` (its misalignment and design)."""
    return relay_frames(p[_M:_D], p[_D], p[_D + 1], p[_D + 2], p[_D + 3], p[_D + 4])


@numba.njit(inline="always", **_JIT)
def _trace_point(p, frames, x, y):
    """The distorted point ``(xd, yd)`` px of the reference point ``(x, y)`` px through the
    relay whose geometry ``frames`` (:func:`_frames_of` of ``p``) is already built; NaN
    where the ray misses a surface."""
    pix = p[_D + 5]
    cx = p[_D + 6]
    cy = p[_D + 7]
    scope = p.shape[0] > _S  # a microscope behind the relay
    # the pose, then the aligned relay's paraxial inverse to the object plane (through the
    # microscope's design magnification first, if there is one)
    th = math.radians(p[1])
    c = math.cos(th)
    s = math.sin(th)
    rx = x - cx
    ry = y - cy
    ix = (p[0] * (c * rx - s * ry) + p[2]) * pix
    iy = (p[0] * (s * rx + c * ry) + p[3]) * pix
    if scope:
        ix /= p[_S + 2]
        iy /= p[_S + 2]
    ox = p[_D + 8] * ix + p[_D + 9] * iy
    oy = p[_D + 10] * ix + p[_D + 11] * iy
    (ex, ey, _, v1, a1, fp1, e1, e2, _, v2, a2, fp2, _, sp, sx, sy, sn, ip, jx, jy,
     jn) = frames  # fmt: skip
    obj = _add(_mul(ox, ex), _mul(oy, ey))
    q, d = _aim_chief_ray(v1, a1, fp1, e1, e2, obj, sp, sx, sy, sn)
    t = _paraboloid_hit(q, d, v2, a2, fp2)
    if not np.isfinite(t):
        return np.nan, np.nan
    q2 = _add(q, _mul(t, d))
    d2 = _reflect(d, _normal(v2, a2, fp2, q2))
    t = _dot(_sub(ip, q2), jn) / _dot(d2, jn)
    hit = _sub(_add(q2, _mul(t, d2)), ip)
    hx = _dot(hit, jx)
    hy = _dot(hit, jy)
    if scope:
        # the microscope: magnification (signed) and its own radial term at the sensor
        hx *= p[_S]
        hy *= p[_S]
        g = 1.0 + p[_S + 1] * (hx * hx + hy * hy)
        hx *= g
        hy *= g
    return cx + hx / pix, cy + hy / pix


@numba.njit(**_JIT)
def relay_point_value(p, x, y):
    """The distorted point ``(xd, yd)`` px of the reference point ``(x, y)`` px (module
    docstring); NaN where the ray misses a surface."""
    return _trace_point(p, _frames_of(p), x, y)


@numba.njit(**_JIT)
def relay_point(p, x, y, need):
    """The point contract of :func:`oapcal._kernels.bc_point` for the relay family: the
    distorted point and, when ``need >= 1``, its point Jacobian by central differences
    (step :data:`POINT_STEP` px).  The parameter columns come from the caller's central
    differences (the family has no analytic ones)."""
    # The frames once for the point and the four steps of its Jacobian; the trace at one
    # call site (inlined once: a loop over the five points, not five inlined copies, which
    # would compile ~5x the code), each result kept by its index.
    frames = _frames_of(p)
    h = POINT_STEP
    xd = yd = xp = yp = xm = ym = up = vp = um = vm = 0.0
    for k in range(1 if need == 0 else 5):
        xs = x + h if k == 1 else (x - h if k == 2 else x)
        ys = y + h if k == 3 else (y - h if k == 4 else y)
        u, v = _trace_point(p, frames, xs, ys)
        if k == 0:
            xd, yd = u, v
        elif k == 1:
            xp, yp = u, v
        elif k == 2:
            xm, ym = u, v
        elif k == 3:
            up, vp = u, v
        else:
            um, vm = u, v
    if need == 0:
        return xd, yd, 0.0, 0.0, 0.0, 0.0
    a = (xp - xm) / (2.0 * h)
    c = (yp - ym) / (2.0 * h)
    b = (up - um) / (2.0 * h)
    d = (vp - vm) / (2.0 * h)
    return xd, yd, a, b, c, d
