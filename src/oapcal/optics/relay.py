"""The OAP relay: two identical 90-degree off-axis parabolic mirrors, exact chief rays,
the paraxial map and grid distortion (``docs/optics.md`` explains every choice).

Global frame (mm, right-handed): the object point on the axis sits at the origin, the
focus ``F1`` of the first mirror (OAP 1 here, the paper's OAP 2), whose parent
paraboloid opens along ``+z`` with parent focal length ``f_p = f / 2`` (vertex at
``(0, 0, -f_p)``).  The mirror centre is ``(0, f, 0)``: light from ``F1`` leaves along
``+y``, is folded by 90 degrees and travels along ``+z`` through the collimated space to
the second mirror (the paper's OAP 3) centred at ``(0, f, d1)``.

* Orientation ``U``: the second parent paraboloid shares the first's axis (the ``z``
  axis) and opens along ``-z``; its focus ``F2 = (0, 0, d1)``, the outgoing chief ray
  travels along ``-y``.  The relay is mirror-symmetric about the plane ``z = d1 / 2``;
  this orientation cancels the field-dependent astigmatism.
* Orientation ``Z``: the second mirror rotated by 180 degrees about the collimated
  chief ray (``(x, y, z) -> (-x, 2f - y, z)``): focus ``(0, 2f, d1)``, outgoing chief
  ray along ``+y``; the relay is point-symmetric about the middle of the collimated path.

The fold plane is ``x = 0``; the relay is symmetric under ``x -> -x``.  The object plane
is normal to the chief ray leaving ``F1`` (``+y``) with axes ``x_obj = +x`` and
``y_obj = +z`` (the off-axis direction), chosen so that ``x_obj x y_obj`` points back
towards the mirror: ``(x_obj, y_obj)`` are the column and row directions of the object
as seen from the mirror, like a camera's.  The image plane passes through the second
focus, normal to the outgoing chief ray, with the object axes carried along the central
ray by the two reflections (again a camera's column and row directions).

>>> relay = oap_relay(1)
>>> relay.d1_mm, relay.orientation
(860.0, 'U')
>>> import numpy as np
>>> np.round(paraxial_matrix(relay), 9) + 0.0  # an orthogonal, magnification-1 map
array([[-1.,  0.],
       [ 0., -1.]])
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from oapcal.errors import GeometrySpecError
from oapcal.optics.design import DEFAULT_FOCAL_LENGTH_MM
from oapcal.optics.misalign import Misalignment
from oapcal.optics.surfaces import Paraboloid, Plane, Vec, axpy_c, dot_c, reflect_c, sub_c, unit_c
from oapcal.optics.trace import TraceResult, trace_c

#: Collimated path length ``d1`` (mm) of the paper's two test setups.
SETUP_D1_MM: dict[int, float] = {1: 860.0, 2: 660.0}
ORIENTATIONS = ("U", "Z")
#: Diameter of the paper's OAPs (mm; their focal length: ``design.DEFAULT_FOCAL_LENGTH_MM``).
DEFAULT_DIAMETER_MM = 50.8


@dataclass(frozen=True)
class Relay:
    """An OAP relay (build one with :func:`oap_relay`).

    ``m1``, ``m2`` the two mirrors; ``object_plane`` (origin ``F1``), ``stop`` (a plane
    across the collimated path, normal ``+z``, the chief rays pass through its
    ``point``) and ``image_plane`` (origin ``F2``) carry local ``ex, ey`` axes.
    ``focal_length_mm`` is the first mirror's design focal length, ``focal_length_2_mm``
    the second's (``None``: the same), ``d1_mm`` the design's collimated path;
    ``misalignment`` the deviations applied (:class:`~oapcal.optics.misalign.Misalignment`).
    """

    focal_length_mm: float
    diameter_mm: float
    d1_mm: float
    orientation: str
    stop_distance_mm: float
    m1: Paraboloid
    m2: Paraboloid
    object_plane: Plane
    stop: Plane
    image_plane: Plane
    #: Transverse axes of ``m1`` used to parametrize its surface when aiming rays.
    m1_axes: tuple = field(repr=False, default=((1.0, 0.0, 0.0), (0.0, 1.0, 0.0)))
    focal_length_2_mm: float | None = None
    misalignment: Misalignment = field(default_factory=Misalignment)

    @property
    def mirrors(self) -> tuple[Paraboloid, Paraboloid]:
        return (self.m1, self.m2)

    @property
    def focal_lengths_mm(self) -> tuple[float, float]:
        """The design focal lengths ``(f1, f2)`` of the two mirrors."""
        f2 = self.focal_length_mm if self.focal_length_2_mm is None else self.focal_length_2_mm
        return (self.focal_length_mm, f2)

    def with_misalignment(self, misalignment: Misalignment | None = None, **values) -> Relay:
        """The same design with ``misalignment`` (or these named values) applied instead."""
        if misalignment is None:
            misalignment = Misalignment.from_dict(values)
        return self.rebuilt(misalignment=misalignment)

    def rebuilt(self, **changes) -> Relay:
        """This relay built again with some arguments of :func:`oap_relay` changed
        (``orientation="Z"``, ``misalignment=...``)."""
        args = {"d1_mm": self.d1_mm, "orientation": self.orientation,
                "stop_distance_mm": self.stop_distance_mm,
                "focal_length_mm": self.focal_length_mm, "diameter_mm": self.diameter_mm,
                "focal_length_2_mm": self.focal_length_2_mm, "misalignment": self.misalignment}  # fmt: skip
        return oap_relay(None, **{**args, **changes})


def _check_positive(value, name: str) -> float:
    value = float(value)
    if not (np.isfinite(value) and value > 0):
        raise GeometrySpecError(f"{name} must be a positive number of mm, got {value:g}")
    return value


def mirror_frame(mirror: Paraboloid) -> np.ndarray:
    """The rows ``(a, b, n)`` of a mirror's frame at its centre (``docs/optics.md``): ``n``
    the unit normal (towards the reflecting side), ``a = +x``, ``b = n x a``."""
    n = mirror.normal(np.asarray(mirror.aperture_centre))
    a = np.array([1.0, 0.0, 0.0])
    return np.array([a, np.cross(n, a), n])


def _frames(mis: Misalignment, d1: float, f: float, f2: float, orientation: str, stop: float, radius: float):
    """The mirrors and planes of the relay from the one builder of its frames,
    :func:`oapcal._relay_kernel.relay_frames` (the compiled tracer builds its geometry with
    the same function): ``(m1, m2, object plane, stop, image plane, m1_axes)``."""
    from oapcal._relay_kernel import relay_frames  # loads Numba: only when a relay is built

    values = np.array([float(v) for v in mis.to_dict().values()])
    (ex, ey, en, v1, a1, fp1, e1, e2, c1, v2, a2, fp2, c2, sp, sx, sy, sn, ip, jx, jy,
     jn) = relay_frames(values, d1, f, f2, 1.0 if orientation == "U" else -1.0, stop)  # fmt: skip
    m1 = Paraboloid(vertex=v1, axis=a1, focal_length=fp1, aperture_centre=c1, aperture_radius=radius)
    m2 = Paraboloid(vertex=v2, axis=a2, focal_length=fp2, aperture_centre=c2, aperture_radius=radius)
    obj = Plane(point=(0.0, 0.0, 0.0), normal=en, ex=ex, ey=ey)
    stop_plane = Plane(point=sp, normal=sn, ex=sx, ey=sy)
    image = Plane(point=ip, normal=jn, ex=jx, ey=jy)
    return m1, m2, obj, stop_plane, image, (tuple(e1), tuple(e2))


def oap_relay(
    setup: int | None = 1,
    *,
    d1_mm: float | None = None,
    orientation: str = "U",
    stop_distance_mm: float | None = None,
    focal_length_mm: float = DEFAULT_FOCAL_LENGTH_MM,
    diameter_mm: float = DEFAULT_DIAMETER_MM,
    focal_length_2_mm: float | None = None,
    misalignment: Misalignment | dict | None = None,
) -> Relay:
    """Build the relay of the paper's setup ``1`` (d1 = 860 mm) or ``2`` (660 mm), or of
    any collimated path length ``d1_mm`` (which overrides ``setup``).

    ``orientation`` is ``"U"`` (parent axes coincide; default) or ``"Z"`` (second mirror
    rotated by 180 degrees).  ``stop_distance_mm`` puts the aperture stop on a plane
    across the collimated path at that distance from the first mirror's centre (``None``
    or 0: at the first mirror, so chief rays pass through its centre).  ``focal_length_mm``
    is the reflected focal length ``f`` of both mirrors (parent focal length ``f / 2``,
    off-axis distance ``f``), or of the first one when ``focal_length_2_mm`` gives the
    second's (the camera then sits at the second mirror's focus; magnification
    ``f2 / f1``); ``diameter_mm`` their diameter.  ``misalignment`` (a
    :class:`~oapcal.optics.misalign.Misalignment` or a dict of its values) moves the parts
    away from this design (``docs/optics.md``, Misalignment).
    """
    if d1_mm is None:
        if setup not in SETUP_D1_MM:
            raise GeometrySpecError(
                f"unknown setup {setup!r}: use 1 (d1 = 860 mm) or 2 (d1 = 660 mm), or give d1 in mm"
            )
        d1_mm = SETUP_D1_MM[setup]
    d1 = _check_positive(d1_mm, "d1 (the collimated path length)")
    f = _check_positive(focal_length_mm, "the focal length")
    f2 = f if focal_length_2_mm is None else _check_positive(focal_length_2_mm, "the second focal length")
    diameter = _check_positive(diameter_mm, "the mirror diameter")
    key = str(orientation).strip().upper()
    if key not in ORIENTATIONS:
        raise GeometrySpecError(f"unknown orientation {orientation!r}: use U (default) or Z")
    mis = Misalignment.of(misalignment)
    d1_real = d1 + mis.d1
    if not d1_real > 0:
        raise GeometrySpecError(f"a d1 change of {mis.d1:g} mm leaves no collimated path (d1 = {d1:g} mm)")
    stop = 0.0 if stop_distance_mm is None else float(stop_distance_mm)
    if not (np.isfinite(stop) and 0.0 <= stop <= d1_real):
        raise GeometrySpecError(
            f"the stop distance {stop:g} mm is outside the collimated path: give 0 .. {d1_real:g} mm"
        )
    for i, f_i in ((1, f), (2, f2)):
        change = mis.mirror(i)["focal_length"]
        if change and not f_i + change > 0:
            raise GeometrySpecError(f"a focal-length change of {change:g} mm leaves no mirror")
    if not f2 + mis.camera_defocus > 0:  # the sensor sits at the design focus, f2 after the mirror
        raise GeometrySpecError(
            f"a camera defocus of {mis.camera_defocus:g} mm puts the image plane at or behind the second "
            f"mirror (the camera sits {f2:g} mm after it): give a defocus above {-f2:g} mm"
        )
    m1, m2, obj, stop_plane, image, m1_axes = _frames(mis, d1, f, f2, key, stop, 0.5 * diameter)
    return Relay(
        focal_length_mm=f, diameter_mm=diameter, d1_mm=d1, orientation=key, stop_distance_mm=stop,
        m1=m1, m2=m2, object_plane=obj, stop=stop_plane, image_plane=image, m1_axes=m1_axes,
        focal_length_2_mm=None if focal_length_2_mm is None else f2, misalignment=mis,
    )  # fmt: skip


#: The arguments of :func:`oap_relay` that describe the design (the older keyword form of
#: the functions that take a design: :func:`resolve_relay`).
RELAY_KEYWORDS = ("d1_mm", "orientation", "stop_distance_mm", "focal_length_mm", "focal_length_2_mm")


def resolve_relay(design, misalignment=None, keywords: dict | None = None) -> tuple[Relay, float | None]:
    """The relay a library function traces and the design's pixel size (um; None when the
    argument has none), from its ``design`` argument: a
    :class:`~oapcal.optics.relay_model.RelayDesign` (its relay with ``misalignment``), a
    :class:`Relay` (traced as it is), or, the older form, the setup (1, 2 or None) with the
    design's ``keywords`` of :func:`oap_relay` (:data:`RELAY_KEYWORDS`; taken out of the
    dict, so what is left are the function's other keywords)."""
    keywords = {} if keywords is None else keywords
    if "setup" in keywords:
        design = keywords.pop("setup")
    relay_keywords = {k: keywords.pop(k) for k in RELAY_KEYWORDS if k in keywords}
    if isinstance(design, Relay):
        return design, None
    if hasattr(design, "relay") and hasattr(design, "pixel_size_um"):  # a RelayDesign (imports this module)
        return design.relay(misalignment), float(design.pixel_size_um)
    return oap_relay(design, misalignment=misalignment, **relay_keywords), None


# ------------------------------------------------------------------------ ray aiming


@dataclass(frozen=True)
class AimResult:
    """Rays from object points aimed through targets on the stop plane.

    ``hit`` ``(..., 3)`` the point on the first mirror, ``direction`` ``(..., 3)`` the unit
    direction after it, ``converged`` ``(...)`` bool (the
    ray passes the target within ``tol``), ``miss_mm`` the remaining distance, ``n_iter``.
    """

    hit: np.ndarray
    direction: np.ndarray
    converged: np.ndarray
    miss_mm: np.ndarray
    n_iter: int


#: Rays traced per block: small enough that a block's temporaries stay in the CPU cache
#: (which makes large traces ~2x faster than one pass) and a progress callback gets
#: regular updates.
CHUNK = 1 << 15
#: Newton steps of the ray aiming recompute their Jacobian every this many steps.
JACOBIAN_REFRESH = 3


def _stop_residual_c(relay: Relay, points: Vec, u, v, tx, ty):
    e1, e2 = relay.m1_axes
    q = relay.m1.point_at_c(u, v, e1, e2)
    d_out = reflect_c(unit_c(sub_c(q, points)), relay.m1.normal_c(q))
    t = relay.stop.intersect_c(q, d_out)
    sx, sy = relay.stop.local_c(axpy_c(t, d_out, q))
    return sx - tx, sy - ty, q, d_out


def _aim_c(relay: Relay, points: Vec, tx: np.ndarray, ty: np.ndarray, tol: float, max_iter: int):
    """:func:`aim` for component triples ``points`` and 1-d target arrays ``tx, ty`` (one
    block); returns ``(hit, direction, converged, miss, n_iter)``."""
    e1, e2 = relay.m1_axes
    start = sub_c(relay.stop.world_c(tx, ty), relay.m1.vertex)
    u = np.array(np.broadcast_to(dot_c(start, e1), tx.shape), dtype=float)
    v = np.array(np.broadcast_to(dot_c(start, e2), tx.shape), dtype=float)
    h = 1e-6
    n_iter = 0
    jac = None
    with np.errstate(all="ignore"):
        rx, ry, q, d_out = _stop_residual_c(relay, points, u, v, tx, ty)
        miss = np.hypot(rx, ry)
        for n_iter in range(1, max_iter + 1):
            active = miss > tol  # NaN (a ray that misses) stays inactive
            if not active.any():
                n_iter -= 1
                break
            if jac is None or n_iter % JACOBIAN_REFRESH == 0:
                # Forward-difference Jacobian d(residual)/d(u, v), kept for two more
                # (chord) steps: the map is nearly linear, so each chord step still gains
                # several digits and costs one trace instead of three.
                ux, uy = _stop_residual_c(relay, points, u + h, v, tx, ty)[:2]
                vx, vy = _stop_residual_c(relay, points, u, v + h, tx, ty)[:2]
                ja, jc = (ux - rx) / h, (uy - ry) / h
                jb, jd = (vx - rx) / h, (vy - ry) / h
                det = ja * jd - jb * jc
                jac = (jd / det, -jb / det, -jc / det, ja / det)  # the inverse
            ia, ib, ic, id_ = jac
            u = np.where(active, u - (ia * rx + ib * ry), u)
            v = np.where(active, v - (ic * rx + id_ * ry), v)
            rx, ry, q, d_out = _stop_residual_c(relay, points, u, v, tx, ty)
            miss = np.hypot(rx, ry)
    return q, d_out, miss <= tol, miss, n_iter


def _flat_pair(a, da: int, b, db: int):
    """``(shape, a (N, da), b (N, db))``: two arrays of vectors (``(..., da)``,
    ``(..., db)``) broadcast against each other over their leading axes and flattened."""
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    shape = np.broadcast_shapes(a.shape[:-1], b.shape[:-1])
    return (
        shape,
        np.broadcast_to(a, shape + (da,)).reshape(-1, da),
        np.broadcast_to(b, shape + (db,)).reshape(-1, db),
    )


def _blocks(n: int, progress):
    """Slices of ``CHUNK`` rays over ``n``, reporting ``progress(done, n)`` after each."""
    for lo in range(0, n, CHUNK):
        hi = min(n, lo + CHUNK)
        yield slice(lo, hi)
        if progress is not None:
            progress(hi, n)


def aim(
    relay: Relay, points, target_xy, *, tol: float = 1e-10, max_iter: int = 30, progress=None
) -> AimResult:
    """Find, for object points ``(..., 3)``, the rays that pass through ``target_xy``
    ``(..., 2)`` (stop-plane coordinates, mm) after the first mirror.

    The unknown is the hit point on the first mirror, parametrized by its transverse
    coordinates ``(u, v)``, started where a ray parallel to the mirror axis through the
    target would hit (exact for the object point at the focus).  Newton iteration with a
    forward-difference 2x2 Jacobian (step 1e-6 mm) refreshed every third step (chord
    steps in between).  Converged where the ray passes within ``tol`` mm of its target.
    ``progress(done, total)`` is called after each block of rays.
    """
    shape, p, t = _flat_pair(points, 3, target_xy, 2)
    n = p.shape[0]
    hit = np.empty((n, 3))
    direction = np.empty((n, 3))
    converged = np.empty(n, dtype=bool)
    miss = np.empty(n)
    n_iter = 0
    for sl in _blocks(n, progress):
        pc = tuple(np.ascontiguousarray(p[sl, k]) for k in range(3))
        q, d, ok, m, it = _aim_c(relay, pc, t[sl, 0].copy(), t[sl, 1].copy(), tol, max_iter)
        for k in range(3):
            hit[sl, k] = q[k]
            direction[sl, k] = d[k]
        converged[sl], miss[sl] = ok, m
        n_iter = max(n_iter, it)
    return AimResult(
        hit=hit.reshape(shape + (3,)), direction=direction.reshape(shape + (3,)),
        converged=converged.reshape(shape), miss_mm=miss.reshape(shape), n_iter=n_iter,
    )  # fmt: skip


# ------------------------------------------------------------------------ chief rays


@dataclass(frozen=True)
class RayImage:
    """Rays traced from object points to the image plane.

    ``xy_mm`` ``(..., 2)`` image-plane coordinates, ``clear`` ``(...)`` bool (every ray
    hit both mirrors inside their diameter and was aimed to tolerance); ``trace`` the
    full :class:`~oapcal.optics.trace.TraceResult` from the first mirror on (``None``
    when traced with ``full=False``).
    """

    xy_mm: np.ndarray
    clear: np.ndarray
    trace: TraceResult | None


def trace_through_stop(relay: Relay, xy_obj_mm, stop_xy_mm, *, progress=None, full: bool = True) -> RayImage:
    """Trace rays from object points ``(..., 2)`` (object-plane mm) through points
    ``(..., 2)`` of the stop plane (mm from its centre) to the image plane.

    Rays are traced in blocks of :data:`CHUNK`; ``progress(done, total)`` is called after
    each.  ``full=False`` skips collecting the hit points and directions (faster).
    """
    shape, obj, stop = _flat_pair(xy_obj_mm, 2, stop_xy_mm, 2)
    n = obj.shape[0]
    xy = np.empty((n, 2))
    clear = np.empty(n, dtype=bool)
    if full:
        arrays = {name: np.empty((n, 3)) for name in ("hit1", "hit2", "points", "direction")}
    for sl in _blocks(n, progress):
        points = relay.object_plane.world_c(obj[sl, 0].copy(), obj[sl, 1].copy())
        hit1, d1, ok, _, _ = _aim_c(relay, points, stop[sl, 0].copy(), stop[sl, 1].copy(), 1e-10, 30)
        hits, pts, (x, y), d2, ok2 = trace_c(hit1, d1, [relay.m2], relay.image_plane)
        xy[sl, 0], xy[sl, 1] = x, y
        clear[sl] = ok & ok2 & relay.m1.inside_c(hit1)
        if full:
            for name, vec in (("hit1", hit1), ("hit2", hits[0]), ("points", pts), ("direction", d2)):
                for k in range(3):
                    arrays[name][sl, k] = vec[k]
    xy = xy.reshape(shape + (2,))
    clear = clear.reshape(shape)
    result = None
    if full:
        a = {name: value.reshape(shape + (3,)) for name, value in arrays.items()}
        result = TraceResult((a["hit1"], a["hit2"]), a["points"], xy, a["direction"], clear)
    return RayImage(xy, clear, result)


def chief_rays(relay: Relay, xy_obj_mm, *, progress=None, full: bool = True) -> RayImage:
    """Real chief rays (through the stop centre) of object points ``(..., 2)`` in mm
    (``progress`` and ``full`` as in :func:`trace_through_stop`)."""
    xy_obj_mm = np.asarray(xy_obj_mm, dtype=float)
    return trace_through_stop(relay, xy_obj_mm, np.zeros(xy_obj_mm.shape), progress=progress, full=full)


def paraxial_matrix(relay: Relay, step_mm: float = 1e-4) -> np.ndarray:
    """The 2x2 Jacobian ``d(image xy) / d(object xy)`` of the chief-ray map at the field
    centre, by central differences (error ~ step^2 x third derivative, ~1e-9 here).

    It maps object-plane mm to image-plane mm; paraxial image points are
    ``xy_obj @ J.T`` (plus :func:`paraxial_map`'s offset for a misaligned relay).
    """
    return paraxial_map(relay, step_mm)[0]


def paraxial_map(relay: Relay, step_mm: float = 1e-4) -> tuple[np.ndarray, np.ndarray]:
    """``(J, offset)``: :func:`paraxial_matrix` and the image ``(2,)`` (image-plane mm) of
    the field centre's chief ray, so that paraxial image points are ``offset + J xy_obj``.
    The offset is 0 (to 1e-12 mm) for an aligned relay; a misaligned one images the field
    centre off the sensor's centre."""
    h = float(step_mm)
    probes = np.array([[h, 0.0], [-h, 0.0], [0.0, h], [0.0, -h], [0.0, 0.0]])
    xy = chief_rays(relay, probes, full=False).xy_mm
    return np.stack([(xy[0] - xy[1]) / (2 * h), (xy[2] - xy[3]) / (2 * h)], axis=-1), xy[4].copy()


# ------------------------------------------------------------------- grid distortion


@dataclass(frozen=True)
class GridDistortion:
    """Paraxial and real chief-ray image points of an object grid (all mm).

    ``xy_obj`` ``(N, 2)`` object points, row by row (y outer, x inner, both ascending);
    ``xy_u`` paraxial image points ``offset + xy_obj @ matrix.T``; ``xy_d`` real chief-ray
    image points; ``clear`` ``(N,)`` chief ray not vignetted; ``matrix`` the paraxial map,
    ``offset`` (2,) the image of the field centre (0 for an aligned relay).
    """

    relay: Relay
    field_mm: float
    n: int
    xy_obj: np.ndarray
    xy_u: np.ndarray
    xy_d: np.ndarray
    clear: np.ndarray
    matrix: np.ndarray
    offset: np.ndarray = field(default_factory=lambda: np.zeros(2))

    @property
    def displacement(self) -> np.ndarray:
        """``xy_d - xy_u`` ``(N, 2)`` in mm."""
        return self.xy_d - self.xy_u

    @property
    def distortion(self) -> np.ndarray:
        """``|xy_d - xy_u|`` ``(N,)`` in mm."""
        return np.hypot(*self.displacement.T)


def object_grid(n: int, field_mm: float) -> np.ndarray:
    """A square ``n x n`` grid ``(n*n, 2)`` spanning ``field_mm`` (full width), centred."""
    if int(n) < 2:
        raise GeometrySpecError(f"the grid needs at least 2 points a side, got {n}")
    field_mm = _check_positive(field_mm, "the field width")
    s = np.linspace(-0.5 * field_mm, 0.5 * field_mm, int(n))
    gx, gy = np.meshgrid(s, s)
    return np.stack([gx.ravel(), gy.ravel()], axis=-1)


def grid_distortion(relay: Relay, n: int = 17, field_mm: float = 1.0, *, progress=None) -> GridDistortion:
    """Trace the chief rays of an ``n x n`` object grid over ``field_mm`` x ``field_mm``;
    ``progress(done, total)`` (rays) is called as blocks of rays finish."""
    xy_obj = object_grid(n, field_mm)
    matrix, offset = paraxial_map(relay)
    real = chief_rays(relay, xy_obj, progress=progress, full=False)
    return GridDistortion(relay, float(field_mm), int(n), xy_obj, apply_matrix(matrix, xy_obj) + offset,
                          real.xy_mm, real.clear, matrix, offset)  # fmt: skip


def apply_matrix(matrix: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """``xy @ matrix.T`` for points ``(..., 2)``, written out (NumPy's matmul with a 2x2
    right operand is several times slower on a million points)."""
    xy = np.asarray(xy, dtype=float)
    x, y = xy[..., 0], xy[..., 1]
    return np.stack([matrix[0, 0] * x + matrix[0, 1] * y, matrix[1, 0] * x + matrix[1, 1] * y], axis=-1)


#: :func:`radial_fit` fits at most this many grid points per side (a regular subgrid).
RADIAL_FIT_MAX_SIDE = 129


def radial_fit(grid: GridDistortion, max_side: int = RADIAL_FIT_MAX_SIDE):
    """Fit the second-order radial model (``k1`` with free centre and magnification,
    preset ``radial``) to a grid after the paper's grid normalization.

    Returns ``(fit result, mean forward residual in mm, mean correction residual in mm)``:
    the forward residual is ``|distort(u) - d|`` converted from normalized distorted units
    back to image mm; the correction residual (the paper's Table-1 convention) corrects
    the real points through the fitted inverse and compares them with the paraxial points
    in image mm.  Grids larger than ``max_side`` points a side are fitted on a regular
    subgrid of ``max_side`` rows and columns (border included): fitting all points of a
    1001 x 1001 grid takes ~40 s, the 129 x 129 subgrid ~2 s, and its mean residuals are
    0.4 % above the full fit's (25.47 against 25.37 um for setup 1 over 1 mm).  Both
    residuals are always means over every grid point, normalized with the whole grid.
    """
    from oapcal.fitting import fit
    from oapcal.normalize import normalize_grid
    from oapcal.stats import correction_residuals

    norm = normalize_grid(grid.xy_u, grid.xy_d)
    use = slice(None)
    if grid.n > max_side:
        k = np.unique(np.round(np.linspace(0, grid.n - 1, int(max_side))).astype(int))
        use = (k[:, None] * grid.n + k[None, :]).ravel()  # rows are y, columns x
    result = fit(norm.xy_u[use], norm.xy_d[use], "radial", init="zero")
    forward = np.hypot(*(result.model(norm.xy_u) - norm.xy_d).T).mean() / norm.scale_d
    corrected = correction_residuals(result.model, norm.xy_u, norm.xy_d).mean_px / norm.scale_u
    return result, float(forward), float(corrected)
