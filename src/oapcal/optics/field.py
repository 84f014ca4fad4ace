"""A dense, smoothly interpolated distortion field of a relay in camera pixels.

Camera px follow ``docs/conventions.md`` (origin at the centre of the top-left pixel,
x = column, y = row); the optical axis (the field centre) is imaged at the image centre
``((w - 1) / 2, (h - 1) / 2)``.  *Paraxial* px are where the paraxial (linear) map puts a
point, *real* px where its real chief ray lands.

>>> field = relay_distortion(1, grid=33)
>>> xy_d = field.forward([[100.0, 50.0]])
>>> bool(abs(field.inverse(xy_d) - [[100.0, 50.0]]).max() < 1e-6)
True
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from oapcal import validate
from oapcal.errors import GeometrySpecError
from oapcal.optics.relay import Relay, apply_matrix, chief_rays, paraxial_map, resolve_relay

#: The cubic Hermite basis: ``[a0, a1, a2, a3] = HERMITE @ [p(0), p(1), p'(0), p'(1)]`` for
#: ``p(s) = a0 + a1 s + a2 s^2 + a3 s^3``.
HERMITE = np.array([[1.0, 0, 0, 0], [0, 0, 1, 0], [-3, 3, -2, -1], [2, -2, 1, 1]])


class BicubicPatches:
    """Fast evaluation of interpolating bicubic splines on a regular grid, both displacement
    components at once, with their first derivatives.

    Why hand-written: ``RectBivariateSpline.ev`` (FITPACK) costs ~0.1 s per component and
    derivative for 300,000 points, and Newton inversion needs six such calls per step.  A
    cubic spline of degree 3 is one bicubic polynomial on every cell between grid nodes
    (its knots are a subset of the nodes), so it equals the bicubic Hermite patch built
    from its value, ``d/dx``, ``d/dy`` and ``d2/dxdy`` at the cell corners.  The patch
    coefficients are computed once; evaluating is a gather and a few polynomial terms.
    Tested against ``RectBivariateSpline.ev`` in ``tests/optics/test_optics_field.py``.

    ``xs`` (nx,), ``ys`` (ny,) uniformly spaced nodes, ``splines`` the fitted splines.
    """

    block = 1 << 16  # points per block: keeps the (block, 2, 4, 4) gather small

    def __init__(self, xs: np.ndarray, ys: np.ndarray, splines) -> None:
        self.x0, self.y0 = float(xs[0]), float(ys[0])
        self.nx, self.ny = len(xs), len(ys)
        self.hx = float(xs[-1] - xs[0]) / (self.nx - 1)
        self.hy = float(ys[-1] - ys[0]) / (self.ny - 1)
        coef = np.empty((self.nx - 1, self.ny - 1, len(splines), 4, 4))
        for c, spline in enumerate(splines):
            f = spline(xs, ys)
            fx = spline(xs, ys, dx=1) * self.hx
            fy = spline(xs, ys, dy=1) * self.hy
            fxy = spline(xs, ys, dx=1, dy=1) * (self.hx * self.hy)
            a, b = slice(None, -1), slice(1, None)
            corners = np.stack([
                np.stack([f[a, a], f[a, b], fy[a, a], fy[a, b]], -1),
                np.stack([f[b, a], f[b, b], fy[b, a], fy[b, b]], -1),
                np.stack([fx[a, a], fx[a, b], fxy[a, a], fxy[a, b]], -1),
                np.stack([fx[b, a], fx[b, b], fxy[b, a], fxy[b, b]], -1),
            ], -2)  # fmt: skip
            coef[:, :, c] = HERMITE @ corners @ HERMITE.T
        self.n_comp = len(splines)
        # Layout (cell, b, comp, a) for a contiguous (n, comp, a) slab per power t^b.
        self.coef = np.ascontiguousarray(coef.transpose(0, 1, 4, 2, 3)).reshape(
            (self.nx - 1) * (self.ny - 1), 4, self.n_comp, 4
        )

    def __call__(self, x: np.ndarray, y: np.ndarray, gradient: bool = True):
        """Values, ``d/dx`` and ``d/dy``, each ``(N, n_comp)``, at points ``x, y`` (N,)
        inside the node range (the caller masks points outside); only the values with
        ``gradient=False``."""
        n = x.shape[0]
        out = [np.empty((n, self.n_comp)) for _ in range(3 if gradient else 1)]
        for lo in range(0, n, self.block):
            sl = slice(lo, min(n, lo + self.block))
            for o, v in zip(out, self._block(x[sl], y[sl], gradient)):
                o[sl] = v
        return tuple(out) if gradient else out[0]

    def _block(self, x, y, gradient):
        sx = (x - self.x0) / self.hx
        sy = (y - self.y0) / self.hy
        i = np.clip(np.floor(sx), 0, self.nx - 2).astype(np.intp)
        j = np.clip(np.floor(sy), 0, self.ny - 2).astype(np.intp)
        s = (sx - i)[:, None]
        t = (sy - j)[:, None, None]
        c = self.coef[i * (self.ny - 1) + j]  # (n, b, comp, a): coefficient of s^a t^b
        c0, c1, c2, c3 = c[:, 0], c[:, 1], c[:, 2], c[:, 3]
        p = c0 + t * (c1 + t * (c2 + t * c3))  # (n, comp, a): Horner in t
        val = p[..., 0] + s * (p[..., 1] + s * (p[..., 2] + s * p[..., 3]))
        if not gradient:
            return (val,)
        q = c1 + t * (2.0 * c2 + 3.0 * t * c3)  # d/dt
        ddx = (p[..., 1] + s * (2.0 * p[..., 2] + 3.0 * s * p[..., 3])) / self.hx
        ddy = (q[..., 0] + s * (q[..., 1] + s * (q[..., 2] + s * q[..., 3]))) / self.hy
        return val, ddx, ddy


@dataclass(frozen=True, eq=False)
class DistortionField:
    """Paraxial <-> real camera px of a relay, from a densely traced grid.

    The displacement ``real - paraxial`` is traced on a regular grid of paraxial px
    covering the image plus a margin (``x_nodes``, ``y_nodes``), and interpolated by
    bicubic splines (``scipy.interpolate.RectBivariateSpline``, exact at the nodes).
    ``matrix`` is the paraxial map (object mm -> image mm, see
    :func:`oapcal.optics.relay.paraxial_matrix`).  Outside the traced grid, results are NaN.
    """

    relay: Relay
    pixel_size_um: float
    image_size: tuple[int, int]
    matrix: np.ndarray
    x_nodes: np.ndarray
    y_nodes: np.ndarray
    _spline_x: object
    _spline_y: object
    _start_tree: object = None
    _start_nodes: object = None
    #: ``(nx, ny)`` bool: the chief ray of a node misses a real mirror (outside its diameter).
    vignetted_nodes: object = None
    #: The splines as :class:`BicubicPatches` (fast evaluation of both components).
    _patches: object = None
    #: Image-plane mm where the field centre is imaged (0 for an aligned relay; see
    #: :func:`oapcal.optics.relay.paraxial_map`); paraxial px include it.
    offset_mm: object = None

    @property
    def centre(self) -> np.ndarray:
        """The image centre ``((w - 1) / 2, (h - 1) / 2)`` in px, where the axis is imaged."""
        w, h = self.image_size
        return np.array([(w - 1) / 2.0, (h - 1) / 2.0])

    def paraxial_from_object_um(self, xy_obj_um) -> np.ndarray:
        """Object-plane um ``(..., 2)`` -> paraxial camera px ``(..., 2)`` (the linear map,
        with the relay's magnification and image orientation)."""
        xy = apply_matrix(self.matrix, np.asarray(xy_obj_um, float)) / self.pixel_size_um
        return xy + self._origin_px

    def object_um_from_paraxial(self, xy_u_px) -> np.ndarray:
        """The inverse of :meth:`paraxial_from_object_um`."""
        inv = np.linalg.inv(self.matrix)
        return apply_matrix(inv, (np.asarray(xy_u_px, float) - self._origin_px) * self.pixel_size_um)

    @property
    def _origin_px(self) -> np.ndarray:
        """Paraxial px of the field centre: the image centre, plus the offset of a
        misaligned relay."""
        if self.offset_mm is None:
            return self.centre
        return self.centre + np.asarray(self.offset_mm) * (1e3 / self.pixel_size_um)

    def _inside(self, x, y):
        return (
            (x >= self.x_nodes[0])
            & (x <= self.x_nodes[-1])
            & (y >= self.y_nodes[0])
            & (y <= self.y_nodes[-1])
        )

    def _evaluate(self, xy, gradient: bool = True):
        """Displacement ``(N, 2)`` and (``gradient``) its x, y derivatives at paraxial px
        ``(N, 2)``; NaN outside the traced grid."""
        x, y = xy[:, 0], xy[:, 1]
        inside = self._inside(x, y)
        if inside.all():
            values = self._patches(x, y, gradient)
            return values if gradient else (values,)
        values = self._patches(x[inside], y[inside], gradient)
        values = values if gradient else (values,)
        out = [np.full(xy.shape, np.nan) for _ in values]
        for o, v in zip(out, values):
            o[inside] = v
        return tuple(out)

    def displacement(self, xy_u_px, dx: int = 0, dy: int = 0) -> np.ndarray:
        """Interpolated ``real - paraxial`` px (or its derivatives) at paraxial px ``(..., 2)``."""
        xy = np.asarray(xy_u_px, dtype=float)
        if (dx, dy) in ((0, 0), (1, 0), (0, 1)) and self._patches is not None:
            flat = xy.reshape(-1, 2)
            if (dx, dy) == (0, 0):
                return self._evaluate(flat, gradient=False)[0].reshape(xy.shape)
            return self._evaluate(flat)[1 if dx else 2].reshape(xy.shape)
        x, y = xy[..., 0], xy[..., 1]
        out = np.stack(
            [
                self._spline_x.ev(x, y, dx=dx, dy=dy),
                self._spline_y.ev(x, y, dx=dx, dy=dy),
            ],
            axis=-1,
        )
        return np.where(self._inside(x, y)[..., None], out, np.nan)

    def forward(self, xy_u_px) -> np.ndarray:
        """Paraxial camera px ``(..., 2)`` -> real (distorted) camera px ``(..., 2)``."""
        xy = np.asarray(xy_u_px, dtype=float)
        return xy + self.displacement(xy)

    def inverse(self, xy_d_px, *, tol: float = 1e-9, max_iter: int = 30) -> np.ndarray:
        """Real camera px ``(..., 2)`` -> paraxial camera px ``(..., 2)``.

        Newton iteration on the interpolated forward map (its Jacobian from the spline
        derivatives), started at the traced node whose real image is nearest (a k-d tree
        over the nodes where the traced map is locally one-to-one); stops when
        ``|forward(x) - xy_d| <= tol`` px.  Points that do not converge within ``max_iter``
        iterations, whose solution lies outside the traced grid, or where the map folds
        (Jacobian determinant <= 0) are NaN.
        """
        target = np.asarray(xy_d_px, dtype=float)
        flat = target.reshape(-1, 2)
        u = np.full(flat.shape, np.nan)
        ok = np.isfinite(flat).all(axis=-1)
        _, idx = self._start_tree.query(flat[ok])
        u[ok] = self._start_nodes[idx]
        done = np.zeros(len(flat), dtype=bool)
        todo = np.flatnonzero(ok)
        with np.errstate(invalid="ignore", divide="ignore"):
            for _ in range(max_iter + 1):
                if todo.size == 0:
                    break
                # Only the points still iterating are evaluated (one patch evaluation
                # gives the residual and the Jacobian).
                uu = u[todo]
                disp, jx, jy = self._evaluate(uu)
                rx = uu[:, 0] + disp[:, 0] - flat[todo, 0]
                ry = uu[:, 1] + disp[:, 1] - flat[todo, 1]
                a, b, c, d = 1.0 + jx[:, 0], jy[:, 0], jx[:, 1], 1.0 + jy[:, 1]
                det = a * d - b * c
                conv = np.hypot(rx, ry) <= tol
                done[todo[conv & (det > 0)]] = True
                keep = ~conv & np.isfinite(det)
                todo, rx, ry = todo[keep], rx[keep], ry[keep]
                a, b, c, d, det = a[keep], b[keep], c[keep], d[keep], det[keep]
                u[todo, 0] -= (d * rx - b * ry) / det
                u[todo, 1] -= (-c * rx + a * ry) / det
        u[~done] = np.nan
        return u.reshape(target.shape)

    def traced(self, xy_u_px) -> np.ndarray:
        """Real camera px by tracing the chief rays exactly (no interpolation)."""
        obj_mm = self.object_um_from_paraxial(xy_u_px) * 1e-3
        image_mm = chief_rays(self.relay, obj_mm).xy_mm
        return image_mm * (1e3 / self.pixel_size_um) + self.centre


def relay_distortion(design=1, *, pixel_size_um: float | None = None, image_size=(640, 480), grid: int = 97,
                     misalignment=None, **keywords) -> DistortionField:  # fmt: skip
    """The traced distortion field of a relay seen by a camera of ``image_size`` (w, h) px
    of ``pixel_size_um`` (None: the design's; 4.8 without one).

    ``design`` a :class:`~oapcal.optics.relay_model.RelayDesign` (traced with
    ``misalignment``, as :func:`~oapcal.optics.relay.oap_relay` takes it), a
    :class:`~oapcal.optics.relay.Relay`, or, the older form, the setup (1, 2 or None) with
    the design's keywords of :func:`~oapcal.optics.relay.oap_relay` (``d1_mm``,
    ``orientation``, ``stop_distance_mm``, ``focal_length_mm``, ``focal_length_2_mm``).

    ``grid`` nodes are traced along the longer image side (proportionally fewer along the
    shorter) over the image plus a margin of 16 px plus 1.1 times the largest displacement
    found on the image border, so that :meth:`DistortionField.inverse` covers every real
    pixel of the image.  The mirrors are treated as unbounded surfaces here: at large
    fields chief rays may fall outside the real mirrors (vignetting), see
    ``DistortionField.vignetted_nodes``.  A misaligned relay's paraxial px are centred on
    the real image of the field centre (``DistortionField.offset_mm``), so the displacement
    is the distortion alone, without the image's shift on the sensor.
    """
    if pixel_size_um is not None and not (float(pixel_size_um) > 0):
        raise GeometrySpecError(f"the pixel size must be a positive number of um, got {pixel_size_um}")
    w, h, n_long, n_short = _field_nodes(image_size, grid)
    relay, pixel = resolve_relay(design, misalignment, keywords)
    if keywords:
        raise TypeError(f"relay_distortion() got an unexpected keyword argument {next(iter(keywords))!r}")
    pixel_size_um = (4.8 if pixel is None else pixel) if pixel_size_um is None else pixel_size_um
    return _traced_field(relay, float(pixel_size_um), w, h, n_long, n_short)


def _field_nodes(image_size, grid) -> tuple[int, int, int, int]:
    """``(w, h, nodes along the longer side, along the shorter)`` of a field's grid,
    refused when the image or the grid is too small or the grid too large for memory."""
    w, h = (int(v) for v in image_size)
    if w < 2 or h < 2:
        raise GeometrySpecError(f"the image size must be at least 2x2 px, got {w}x{h}")
    n_long = validate.whole_number(grid, "grid", -(2**63))
    if n_long < 8:
        raise GeometrySpecError(f"the distortion grid needs at least 8 nodes a side, got {grid}")
    n_short = max(8, int(np.ceil(n_long * min(w, h) / max(w, h))))
    # About 1.1 kB per node measured (grid 201 and 401, 640 x 480): 2 kB allows for the rest.
    validate.memory(
        2048.0 * n_long * n_short,
        f"a traced grid of {n_long:,} x {n_short:,} nodes",
        "give a smaller grid (the default 97 is enough for the inverse of a camera image)",
        param="grid",
    )
    return w, h, n_long, n_short


def _traced_field(relay, pixel_size_um: float, w: int, h: int, n_long: int, n_short: int) -> DistortionField:
    """:func:`relay_distortion` of a built relay: the traced nodes and their splines."""
    from scipy.interpolate import RectBivariateSpline
    from scipy.spatial import cKDTree

    matrix, offset = paraxial_map(relay)
    offset = None if relay.misalignment.is_zero else offset
    probe = DistortionField(relay, pixel_size_um, (w, h), matrix, np.zeros(1), np.zeros(1), None, None,
                            offset_mm=offset)  # fmt: skip
    # The largest displacement on the image border sets the margin.
    t = np.linspace(0.0, 1.0, 65)
    lo, hi = np.array([-0.5, -0.5]), np.array([w - 0.5, h - 0.5])
    border = np.concatenate([
        np.stack([lo[0] + t * (hi[0] - lo[0]), np.full_like(t, lo[1])], -1),
        np.stack([lo[0] + t * (hi[0] - lo[0]), np.full_like(t, hi[1])], -1),
        np.stack([np.full_like(t, lo[0]), lo[1] + t * (hi[1] - lo[1])], -1),
        np.stack([np.full_like(t, hi[0]), lo[1] + t * (hi[1] - lo[1])], -1),
    ])  # fmt: skip
    shift = np.hypot(*(probe.traced(border) - border).T).max()
    margin = 16.0 + 1.1 * shift
    nx, ny = (n_long, n_short) if w >= h else (n_short, n_long)
    xs = np.linspace(lo[0] - margin, hi[0] + margin, nx)
    ys = np.linspace(lo[1] - margin, hi[1] + margin, ny)
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    nodes = np.stack([gx, gy], axis=-1)
    disp = probe.traced(nodes) - nodes
    if not np.isfinite(disp).all():
        raise GeometrySpecError(
            "some chief rays miss a mirror surface over this image; choose a smaller image or pixel size"
        )
    spline_x = RectBivariateSpline(xs, ys, disp[..., 0], kx=3, ky=3)
    spline_y = RectBivariateSpline(xs, ys, disp[..., 1], kx=3, ky=3)
    # Start points of the inverse: nodes where the traced map is locally one-to-one.
    real = nodes + disp
    dxx, dxy = np.gradient(real[..., 0], xs, ys)
    dyx, dyy = np.gradient(real[..., 1], xs, ys)
    good = (dxx * dyy - dxy * dyx) > 0
    vignetted = ~chief_rays(relay, probe.object_um_from_paraxial(nodes) * 1e-3).clear
    return DistortionField(
        relay, pixel_size_um, (w, h), matrix, xs, ys, spline_x, spline_y,
        cKDTree(real[good]), nodes[good], vignetted, BicubicPatches(xs, ys, (spline_x, spline_y)), offset,
    )  # fmt: skip
