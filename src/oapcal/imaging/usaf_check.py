"""Check the USAF layout against a real image: a least-squares fit of triplet edges.

Independent of :mod:`oapcal.imaging.detect`: starting from a rough pose (two hand-picked
triplet centres), every triplet of the chosen groups that is large enough (bar width at
least ``min_w_px``) and fully inside the image is sampled in its own layout coordinates and
two profiles are fitted with a model of the triplet (three bars ``w`` wide and ``2 w`` apart
across the bars, one box ``5 w`` long along them, blurred by a Gaussian, on a linear
background, either polarity).  That places the four outer edges of each triplet without
the bias of a threshold; a smooth map from layout um to image px (affine, or quadratic
when there are enough triplets) is then fitted to all edges by linear least squares, the
triplets are re-sampled through the new map, and so on, largest elements first.

The rms of the edge residuals about the fitted map tells how well the layout (the
relative position of every element) matches the target in the image: a misplaced element
or column shows up as residuals of its edges, which a smooth map cannot absorb.

``layer_shifts=True`` lets each layer but the first move freely (two more unknowns per
layer) and reports the shifts in units of the layer's ``w1``: that is how the position of
the nested layer was measured (``docs/usaf.md``).

>>> from oapcal.imaging.usaf import render_usaf, usaf_target
>>> r = render_usaf((4, 5), um_per_px=2.0, image_size=(500, 460))  # bars, squares, digits
>>> t = usaf_target((4, 5))
>>> px = t.to_reference_px(t.triplet_boxes().reshape(-1, 2, 2).mean(axis=1), 2.0, (500, 460))
>>> names = triplet_names(t)
>>> start = {"G4E2H": px[names.index("G4E2H")] + 1.5, "G4E1H": px[names.index("G4E1H")] - 1.0}
>>> fit = fit_layout(r.image, t, similarity_from_points(t, start))
>>> bool(fit.rms_px < 0.05), fit.n_triplets, round(fit.um_per_px, 3)
(True, 24, 2.0)
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from oapcal.errors import DataError
from oapcal.imaging.detect.warp import poly_terms
from oapcal.imaging.usaf import UsafTarget, bar_width_um


@dataclass(frozen=True)
class LayoutFit:
    """The result of :func:`fit_layout`.

    ``coef`` ``(2, k)`` of the map ``px = coef @ phi((um - centre) / scale)`` (``phi`` the
    monomials ``1, u, v[, u^2, u v, v^2[, u^3, u^2 v, u v^2, v^3]]``); ``rms_px`` the rms
    edge residual about it, over
    ``n_edges`` edges of ``n_triplets`` triplets; ``residuals_px`` per edge, with
    ``edge_triplet`` (its triplet's name, e.g. ``G4E1H``), ``edge_um`` (edge midpoints,
    layout um) and ``edge_px`` (measured, image px) and
    ``edge_normal_px`` (unit normal in the image); ``sigma_px`` the fitted blur of each
    triplet; ``polarity`` ``"bright"`` or ``"dark"`` bars; ``layer_shift_w1`` the free shift
    of each layer (even group -> (dx, dy) in its w1) when fitted with ``layer_shifts``;
    ``rejected`` triplets whose profile fit failed (name -> reason); ``edge_bias_px`` how far
    every edge lies outward of the map's edge (bars wider than gaps by twice that: exposure,
    etching, blur; fitted with the map, it is no layout error).
    """

    coef: np.ndarray
    centre_um: np.ndarray
    scale_um: float
    model: str
    rms_px: float
    n_edges: int
    n_triplets: int
    residuals_px: np.ndarray
    edge_triplet: tuple[str, ...]
    edge_um: np.ndarray
    edge_px: np.ndarray
    edge_normal_px: np.ndarray
    sigma_px: dict
    polarity: str
    layer_shift_w1: dict = field(default_factory=dict)
    rejected: dict = field(default_factory=dict)
    edge_bias_px: float = 0.0

    def __call__(self, xy_um) -> np.ndarray:
        """Map layout um ``(..., 2)`` to image px."""
        xy = np.asarray(xy_um, float)
        return _phi((xy - self.centre_um) / self.scale_um, self.model) @ self.coef.T

    def centre_residuals_px(self) -> np.ndarray:
        """Residual of each triplet's centre along each axis, ``(opposite edges) / 2``: what is
        left of the edge residuals when each triplet may be a little wider or narrower
        (print and blur), i.e. the error of the layout's *positions*."""
        out = []
        tri = np.array(self.edge_triplet)
        axis = np.argmax(np.abs(self.edge_normal_px), axis=1)
        sign = np.sign(self.edge_normal_px[np.arange(len(axis)), axis])
        for name in dict.fromkeys(self.edge_triplet):
            for a in (0, 1):
                sel = (tri == name) & (axis == a)
                plus, minus = self.residuals_px[sel & (sign > 0)], self.residuals_px[sel & (sign < 0)]
                if len(plus) and len(minus):
                    out.append(0.5 * (plus.mean() - minus.mean()))
        return np.array(out)

    @property
    def centre_rms_px(self) -> float:
        """rms of :meth:`centre_residuals_px`."""
        return float(np.sqrt(np.mean(self.centre_residuals_px() ** 2)))

    def corners_px(self, target: UsafTarget) -> dict[str, np.ndarray]:
        """The bar corners of the triplets this fit measured, through the fitted map: id ->
        image px (a reference independent of the detector, as good as :attr:`rms_px`)."""
        measured = set(self.edge_triplet)
        names = np.array(
            [f"G{g}E{e}{o}" for g, e, o in zip(target.bar_group, target.bar_element, target.bar_orientation)]
        )
        keep = np.repeat(np.isin(names, list(measured)), 4)
        xy = self(target.corners_um[keep])
        ids = [i for i, k in zip(target.corner_ids, keep) if k]
        return dict(zip(ids, xy))

    @property
    def um_per_px(self) -> float:
        """Mean scale of the map at its centre (um per image px)."""
        a = self.coef[:, 1:3] / self.scale_um
        return float(1.0 / np.sqrt(abs(np.linalg.det(a))))


#: Smooth maps and the triplets each needs at least.
MODELS = {"affine": 2, "quadratic": 12, "cubic": 20}


#: Degree of the polynomial maps by name.
_DEGREE = {"affine": 1, "quadratic": 2, "cubic": 3}


def _phi(u: np.ndarray, model: str) -> np.ndarray:
    """The monomials of the map ``model`` at normalised points ``u`` ``(..., 2)``."""
    return poly_terms(u, _DEGREE[model])


def triplet_names(target: UsafTarget) -> list[str]:
    """Names like ``G4E1H`` of :meth:`UsafTarget.triplets` (same order)."""
    return [
        f"G{target.bar_group[b[0]]}E{target.bar_element[b[0]]}{target.bar_orientation[b[0]]}"
        for b in target.triplets()
    ]


def similarity_from_points(target: UsafTarget, points: dict, *, mirrored: bool = False) -> np.ndarray:
    """A ``2 x 3`` affine um -> px (rotation, scale, shift; mirrored left-right if asked) from
    two hand-picked triplet centres ``{"G4E2H": (x, y), "G4E1H": (x, y)}`` in the image."""
    names = triplet_names(target)
    boxes = target.triplet_boxes()
    if len(points) != 2:
        raise DataError("a starting pose needs exactly two triplet centres")
    src, dst = [], []
    for name, xy in points.items():
        if name not in names:
            raise DataError(f"triplet {name!r} is not in groups {target.groups}")
        b = boxes[names.index(name)]
        src.append([(b[0] + b[2]) / 2, (b[1] + b[3]) / 2])
        dst.append(xy)
    src, dst = np.asarray(src, float), np.asarray(dst, float)
    s = src[1] - src[0]
    if mirrored:
        s = s * [-1, 1]
    zs = complex(*s)
    zd = complex(*(dst[1] - dst[0]))
    r = zd / zs
    rot = np.array([[r.real, -r.imag], [r.imag, r.real]])
    lin = rot @ np.diag([-1.0, 1.0]) if mirrored else rot
    return np.column_stack([lin, dst[0] - lin @ src[0]])


def _profile_basis(t, p, offsets, length):
    """Columns ``[1, t, pattern]`` of the profile model, ``pattern`` the bars (centre ``c``,
    scale ``s``) blurred by a Gaussian of ``sig``: the model is linear in the other three."""
    from scipy.special import ndtr

    c, s, sig = p
    pattern = np.zeros_like(t)
    for o in offsets:
        lo, hi = c + s * (o - length / 2), c + s * (o + length / 2)
        pattern += ndtr((t - lo) / sig) - ndtr((t - hi) / sig)
    return np.column_stack([np.ones_like(t), t, pattern])


def _fit_profile(t, prof, w, kind):
    """Fit the triplet model to a profile (variable projection: centre, scale and blur by
    least squares, background, slope and amplitude by linear least squares inside).
    Returns ``(centre, scale, sigma, amplitude, x, bounds)`` or None."""
    from scipy.optimize import least_squares

    offsets, length = ((-2 * w, 0.0, 2 * w), w) if kind == "across" else ((0.0,), 5 * w)
    tn = t / w  # a slope term on a well-scaled axis

    def resid(p):
        basis = _profile_basis(t, p, offsets, length)
        basis[:, 1] = tn
        coef = np.linalg.lstsq(basis, prof, rcond=None)[0]
        return basis @ coef - prof

    lb = [-1.5 * w, 0.7, 0.02 * w]
    ub = [1.5 * w, 1.4, 2.5 * w]
    try:
        r = least_squares(resid, [0.0, 1.0, 0.3 * w], bounds=(lb, ub), x_scale=[w, 0.1, w])
    except ValueError:
        return None
    basis = _profile_basis(t, r.x, offsets, length)
    basis[:, 1] = tn
    amp = np.linalg.lstsq(basis, prof, rcond=None)[0][2]
    return r.x[0], r.x[1], r.x[2], amp, r.x, (lb, ub)


def _sample(image, mapping, pts_um):
    from scipy.ndimage import map_coordinates

    px = mapping(pts_um)
    return map_coordinates(image, [px[..., 1], px[..., 0]], order=1, mode="nearest")


def _measure_triplet(image, mapping, box, w, orient, step, m, split=False):
    """Four edges ``(p_um, n_um, delta_um)`` of one triplet, its blur (um) and polarity sign;
    profiles reach ``m`` um beyond the triplet.  ``split``: measure each edge twice, on two
    halves of its length (eight edges; this also sees the edge's tilt)."""
    cx, cy = (box[0] + box[2]) / 2, (box[1] + box[3]) / 2
    t = np.arange(-2.5 * w - m, 2.5 * w + m + step / 2, step)
    across_axis = np.array([0.0, 1.0]) if orient == "H" else np.array([1.0, 0.0])
    along_axis = across_axis[::-1]
    centre = np.array([cx, cy])
    # across the bars: lines over the central 60 % of their length; along: lines over the width
    if split:
        parts = [
            (np.linspace(-2.0 * w, -0.5 * w, 12), (np.arange(12) + 0.5) / 12 * w - 2.5 * w),
            (np.linspace(0.5 * w, 2.0 * w, 12), (np.arange(12) + 0.5) / 12 * w + 1.5 * w),
        ]
    else:
        parts = [(np.linspace(-1.5 * w, 1.5 * w, 24), (np.arange(30) + 0.5) / 30 * 5 * w - 2.5 * w)]
    edges, sigmas, signs = [], [], []
    for v_lines, u_lines in parts:
        pts = centre + t[None, :, None] * across_axis + v_lines[:, None, None] * along_axis
        across = _sample(image, mapping, pts).mean(axis=0)
        pts = centre + t[None, :, None] * along_axis + u_lines[:, None, None] * across_axis
        along = _sample(image, mapping, pts).mean(axis=0)
        fa = _fit_profile(t, across, w, "across")
        fl = _fit_profile(t, along, w, "along")
        if fa is None or fl is None:
            return None, "profile fit failed"
        for f in (fa, fl):
            x, (lb, ub) = f[4], f[5]
            at_bound = np.isclose(x[:2], lb[:2], rtol=0, atol=1e-6 * w) | np.isclose(
                x[:2], ub[:2], rtol=0, atol=1e-6
            )
            if at_bound.any():
                return None, "profile fit at a bound (not a triplet here)"
        if np.sign(fa[3]) != np.sign(fl[3]):
            return None, "across and along profiles disagree on polarity"
        c_a, s_a = fa[0], fa[1]
        c_l, s_l = fl[0], fl[1]
        v_at, u_at = v_lines.mean(), u_lines.mean()  # where along the edges they were measured
        for sgn in (-1.0, 1.0):
            p = centre + sgn * 2.5 * w * across_axis + v_at * along_axis
            edges.append((p, sgn * across_axis, sgn * c_a + 2.5 * w * (s_a - 1.0)))
            p = centre + sgn * 2.5 * w * along_axis + u_at * across_axis
            edges.append((p, sgn * along_axis, sgn * c_l + 2.5 * w * (s_l - 1.0)))
        sigmas.append(0.5 * (fa[2] + fl[2]))
        signs.append(np.sign(fa[3]))
    if len(set(signs)) > 1:
        return None, "the two halves disagree on polarity"
    return (edges, float(np.mean(sigmas)), float(signs[0])), None


def fit_layout(
    image,
    target: UsafTarget,
    pose,
    *,
    min_w_px: float = 3.0,
    model: str = "auto",
    layer_shifts: bool = False,
    iterations: int = 2,
) -> LayoutFit:
    """Fit the layout of ``target`` to ``image`` (module docstring).

    ``pose``: a ``2 x 3`` affine um -> px to start from (:func:`similarity_from_points`).
    ``model``: ``"affine"``, ``"quadratic"``, ``"cubic"`` (e.g. a photograph through a lens
    with radial distortion) or ``"auto"`` (quadratic); a map is used once there are enough
    triplets for it (:data:`MODELS`), a simpler one before.

    The steps: the image normalized to its 0.5-99.5 % range; the map started from the pose
    (:func:`_start_map`); the triplets in view measured coarse to fine, largest first
    (:func:`_stages`), each stage measuring the edges of its triplets through the current
    map (:func:`_measure_edges`) and solving for the map, the layer shifts and the edge
    bias (:func:`_solve_map`).
    """
    img = np.asarray(image, float)
    if img.ndim != 2:
        raise DataError("fit_layout needs a grey image")
    lo, hi = np.percentile(img, [0.5, 99.5])
    img = (img - lo) / max(hi - lo, 1e-12)
    geo = _TripletGeometry.of(target)
    coef, cur_model, lin = _start_map(pose, target, geo)
    um_per_px = 1.0 / np.sqrt(abs(np.linalg.det(lin)))
    stages, split = _stages(geo, geo.mapping(coef, cur_model), img.shape, um_per_px, min_w_px, iterations,
                            continued=isinstance(pose, LayoutFit))  # fmt: skip
    shifts: dict = {}
    rejected: dict = {}
    solved = None
    for sel in stages:
        rows, rejected = _measure_edges(img, geo, geo.mapping(coef, cur_model), sel, shifts, um_per_px, split)
        if len({r[0] for r in rows}) < 2:
            why = "; ".join(f"{k}: {v}" for k, v in rejected.items())
            raise DataError(
                f"fewer than two triplets could be measured ({why}): check the starting pose and groups"
            )
        solved = _solve_map(rows, geo, model, layer_shifts)
        coef, cur_model, shifts = solved.coef, solved.model, solved.shifts
    rows = solved.rows
    lin_px = coef[:, 1:3] / geo.scale
    shift_w1 = {}
    for g, sft in shifts.items():
        shift_w1[int(g)] = (np.linalg.solve(lin_px, sft) / bar_width_um(int(g), 1)).tolist()
    sig = {}
    for r in rows:
        sig.setdefault(geo.names[r[0]], r[4])
    polarity = "bright" if np.mean([r[5] for r in rows]) > 0 else "dark"
    return LayoutFit(
        coef=coef,
        centre_um=geo.centre,
        scale_um=geo.scale,
        model=cur_model,
        rms_px=float(np.sqrt(np.mean(solved.resid**2))),
        n_edges=len(rows),
        n_triplets=solved.n_triplets,
        residuals_px=solved.resid,
        edge_triplet=tuple(geo.names[r[0]] for r in rows),
        edge_um=solved.p_um,
        edge_px=solved.q,
        edge_normal_px=solved.mdir,
        sigma_px=sig,
        polarity=polarity,
        layer_shift_w1=shift_w1,
        rejected=rejected,
        edge_bias_px=solved.bias,
    )


@dataclass(frozen=True)
class _TripletGeometry:
    """The triplets of a target: ``names``, ``boxes (T, 4)`` um, bar ``widths (T,)`` um,
    ``orients``, the layer (even group) of each, and the centre and scale (um) of the map's
    own coordinates."""

    names: list
    boxes: np.ndarray
    widths: np.ndarray
    orients: list
    layer_of: np.ndarray
    centre: np.ndarray
    scale: float

    @classmethod
    def of(cls, target: UsafTarget) -> _TripletGeometry:
        boxes = target.triplet_boxes()
        trip_bars = target.triplets()
        return cls(
            names=triplet_names(target),
            boxes=boxes,
            widths=np.array([target.bar_width[b[0]] for b in trip_bars]),
            orients=[target.bar_orientation[b[0]] for b in trip_bars],
            layer_of=np.array([target.bar_group[b[0]] - target.bar_group[b[0]] % 2 for b in trip_bars]),
            centre=target.triplet_boxes().reshape(-1, 2, 2).mean(axis=(0, 1)),
            scale=float(np.ptp(boxes[:, [0, 2]]) + np.ptp(boxes[:, [1, 3]])) / 2 or 1.0,
        )

    def mapping(self, coef, model):
        """The map um -> px of coefficients ``coef (2, k)`` of ``model``."""
        centre, scale = self.centre, self.scale
        return lambda xy: _phi((np.asarray(xy, float) - centre) / scale, model) @ coef.T


def _start_map(pose, target: UsafTarget, geo: _TripletGeometry):
    """The starting map ``(coef, model, lin)``: the affine pose written in the map's own
    coordinates, or an earlier :class:`LayoutFit` (e.g. of another layout) refitted on a
    grid over the target; ``lin`` the linear part (px per um) of the start."""
    if isinstance(pose, LayoutFit):
        model = pose.model
        b = target.full_bbox_um
        g = np.stack(np.meshgrid(np.linspace(b[0], b[2], 9), np.linspace(b[1], b[3], 9)), -1).reshape(-1, 2)
        coef = np.linalg.lstsq(_phi((g - geo.centre) / geo.scale, model), pose(g), rcond=None)[0].T
        return coef, model, coef[:, 1:3] / geo.scale
    pose = np.asarray(pose, float)
    lin = pose[:, :2]
    return np.column_stack([lin @ geo.centre + pose[:, 2], lin * geo.scale]), "affine", lin


def _stages(geo: _TripletGeometry, mapping, shape, um_per_px, min_w_px, iterations, continued: bool):
    """The triplets measured at each stage, coarse to fine (the widest quarter, half, then
    all of those wide enough and in view; all at once when ``continued``), the last stage
    ``iterations`` times; and whether each edge is measured on two halves (few triplets:
    that sees tilts)."""
    h, w_img = shape
    order = np.argsort(-geo.widths, kind="stable")
    usable = geo.widths / um_per_px >= min_w_px
    mapped = mapping(geo.boxes.reshape(-1, 2)).reshape(-1, 2, 2)
    usable &= ((mapped >= 0) & (mapped <= [w_img - 1, h - 1])).all(axis=(1, 2))  # in view
    split = usable.sum() < 8
    stages = []
    for frac in (0.25, 0.5, 1.0) if not continued else (1.0,):
        k = max(2, int(np.ceil(frac * usable.sum())))
        stages.append(order[usable[order]][:k])
    stages += [stages[-1]] * max(0, iterations - 1)
    return stages, split


def _measure_edges(img, geo: _TripletGeometry, mapping, sel, shifts, um_per_px, split):
    """The edges of the triplets ``sel`` measured through ``mapping`` (plus their layer's
    shift): rows ``(triplet, edge point um, edge normal px, measured edge px, sigma px,
    sign)``, and the triplets left out with the reason."""
    h, w_img = img.shape
    rows = []
    rejected = {}
    for i in sel:
        shift = shifts.get(geo.layer_of[i], np.zeros(2))
        box = geo.boxes[i]
        width = geo.widths[i]
        corners = np.array([[box[0], box[1]], [box[2], box[1]], [box[2], box[3]], [box[0], box[3]]])
        for m in (1.2 * width, 0.9 * width, 0.6 * width):  # context around the triplet
            grown = corners + np.array([[-m, -m], [m, -m], [m, m], [-m, m]])
            gp = mapping(grown) + shift
            if (gp >= 0).all() and (gp[:, 0] <= w_img - 1).all() and (gp[:, 1] <= h - 1).all():
                break
        else:
            rejected[geo.names[i]] = "not fully inside the image"
            continue

        def local_map(xy, _s=shift):
            return mapping(xy) + _s  # noqa: B023  (used within the iteration)

        step = min(width / 6.0, max(0.35 * um_per_px, width / 40.0))
        res, why = _measure_triplet(img, local_map, box, width, geo.orients[i], step, m, split)
        if res is None:
            rejected[geo.names[i]] = why
            continue
        edges, sigma, sign = res
        for p, n, d in edges:
            q = local_map(p + d * n)
            eps = 1e-3 * width
            mdir = local_map(p + eps * n) - local_map(p - eps * n)
            mdir = mdir / np.hypot(*mdir)
            rows.append((i, p, mdir, q, sigma / um_per_px, sign))
    return rows, rejected


@dataclass(frozen=True)
class _MapSolution:
    rows: list
    coef: np.ndarray
    model: str
    shifts: dict
    bias: float
    resid: np.ndarray
    n_triplets: int
    p_um: np.ndarray
    q: np.ndarray
    mdir: np.ndarray


def _solve_map(rows, geo: _TripletGeometry, model: str, layer_shifts: bool) -> _MapSolution:
    """The map through the measured edges (least squares along each edge's normal), the
    richest of :data:`MODELS` up to ``model`` that the triplets support; with
    ``layer_shifts`` a shift per layer after the first; and one edge bias for all."""
    n_trip = len({r[0] for r in rows})
    wanted = "quadratic" if model == "auto" else model
    cur_model = max((m for m in MODELS if MODELS[m] <= max(n_trip, 2) and MODELS[m] <= MODELS[wanted]),
                    key=MODELS.get)  # fmt: skip
    p_um = np.array([r[1] for r in rows])
    mdir = np.array([r[2] for r in rows])
    q = np.array([r[3] for r in rows])
    phi = _phi((p_um - geo.centre) / geo.scale, cur_model)
    k = phi.shape[1]
    layers = sorted({geo.layer_of[r[0]] for r in rows})
    free_layers = layers[1:] if layer_shifts else []
    a_mat = np.concatenate([phi * mdir[:, :1], phi * mdir[:, 1:]], axis=1)
    extra = np.zeros((len(rows), 2 * len(free_layers)))
    for j, g in enumerate(free_layers):
        on = np.array([geo.layer_of[r[0]] == g for r in rows])
        extra[on, 2 * j] = mdir[on, 0]
        extra[on, 2 * j + 1] = mdir[on, 1]
    # one more unknown: every edge lies outward by the same bias (wider or narrower bars
    # than gaps: exposure, etching, blur of the print), which is no layout error
    a_full = np.concatenate([a_mat, extra, np.ones((len(rows), 1))], axis=1)
    rhs = np.sum(mdir * q, axis=1)
    sol, *_ = np.linalg.lstsq(a_full, rhs, rcond=None)
    return _MapSolution(
        rows=rows,
        coef=np.stack([sol[:k], sol[k : 2 * k]]),
        model=cur_model,
        shifts={g: sol[2 * k + 2 * j : 2 * k + 2 * j + 2] for j, g in enumerate(free_layers)},
        bias=float(sol[-1]),
        resid=a_full @ sol - rhs,
        n_triplets=n_trip,
        p_um=p_um,
        q=q,
        mdir=mdir,
    )


def _outline(mapping, box, n: int = 8) -> np.ndarray:
    """The mapped outline of an um box, ``n`` points per side (the map may be curved)."""
    x0, y0, x1, y1 = box
    s = np.linspace(0.0, 1.0, n, endpoint=False)
    side = [
        np.column_stack([x0 + s * (x1 - x0), np.full(n, y0)]),
        np.column_stack([np.full(n, x1), y0 + s * (y1 - y0)]),
        np.column_stack([x1 - s * (x1 - x0), np.full(n, y1)]),
        np.column_stack([np.full(n, x0), y1 - s * (y1 - y0)]),
    ]
    return mapping(np.concatenate(side))


def overlay_image(
    image, target: UsafTarget, mapping, *, zoom: float = 1.0, fit: LayoutFit | None = None
) -> np.ndarray:
    """An 8-bit BGR picture of ``image`` with the reference laid over it through ``mapping``
    (um -> px): bars green, squares cyan, number boxes yellow; with ``fit``, each measured
    edge's residual drawn as a red tick 20x enlarged."""
    import cv2

    img = np.asarray(image, float)
    lo, hi = np.percentile(img, [0.5, 99.5])
    grey = np.clip((img - lo) / max(hi - lo, 1e-12) * 255, 0, 255).astype(np.uint8)
    if zoom != 1.0:
        grey = cv2.resize(grey, None, fx=zoom, fy=zoom, interpolation=cv2.INTER_CUBIC)
    out = cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR)
    shift = 4
    scale = zoom * (1 << shift)

    def poly(box, colour, thick=1):
        pts = _outline(mapping, box)
        pts = np.rint((pts + 0.5) * scale - 0.5 * (1 << shift)).astype(np.int32)
        cv2.polylines(out, [pts], True, colour, thick, cv2.LINE_AA, shift)

    for b in target.bars:
        poly(b, (0, 200, 0))
    for b in target.squares:
        poly(b, (200, 200, 0))
    for b in target.labels:
        poly(b, (0, 200, 220))
    if fit is not None:
        for p, q in zip(fit.edge_um, fit.edge_px):
            a = fit(p[None])[0]
            d = q - a
            tip = a + 20 * d
            pa = tuple(int(v) for v in np.rint((a + 0.5) * zoom - 0.5))
            pb = tuple(int(v) for v in np.rint((tip + 0.5) * zoom - 0.5))
            cv2.line(out, pa, pb, (0, 0, 255), 1, cv2.LINE_AA)
    return out


#: Layout numbers :func:`measure_layout` can fit (``inner_x_w1``, ``inner_y_w1``: the nested
#: layer's offset).
LAYOUT_PARAMS = ("triplet_gap_w", "element_gap_w", "extra_width_w1", "inner_x_w1", "inner_y_w1")


def _layout_with(lay, values: dict):
    from dataclasses import replace

    v = dict(values)
    ox, oy = lay.inner_offset_w1
    ox, oy = v.pop("inner_x_w1", ox), v.pop("inner_y_w1", oy)
    return replace(lay, inner_offset_w1=(float(ox), float(oy)), **{k: float(x) for k, x in v.items()})


def _layout_values(lay) -> dict:
    return {
        "triplet_gap_w": lay.triplet_gap_w,
        "element_gap_w": lay.element_gap_w,
        "extra_width_w1": lay.extra_width_w1,
        "inner_x_w1": lay.inner_offset_w1[0],
        "inner_y_w1": lay.inner_offset_w1[1],
    }


def measure_layout(image, groups, lay, pose, *, params=LAYOUT_PARAMS, rounds: int = 4, **kwargs):
    """Fit the layout numbers ``params`` (:data:`LAYOUT_PARAMS`) of a target to an image,
    together with the smooth map: Gauss-Newton on the edge residuals of :func:`fit_layout`
    (the layout moves each triplet linearly in these numbers).  Returns the fitted
    :class:`~oapcal.imaging.usaf.UsafLayout` and the final :class:`LayoutFit`."""
    from dataclasses import replace

    from oapcal.imaging.usaf import usaf_target

    fit = None
    for _ in range(rounds):
        target = usaf_target(groups, lay)
        fit = fit_layout(image, target, pose if fit is None else fit, **kwargs)
        names = triplet_names(target)
        centres = target.triplet_boxes().reshape(-1, 2, 2).mean(axis=1)
        vals = _layout_values(lay)
        d_centre = []
        for name in params:
            t2 = usaf_target(groups, _layout_with(lay, {name: vals[name] + 1e-3}))
            assert triplet_names(t2) == names
            d_centre.append((t2.triplet_boxes().reshape(-1, 2, 2).mean(axis=1) - centres) / 1e-3)
        d_centre = np.stack(d_centre, axis=-1)  # (triplets, 2, params)
        idx = np.array([names.index(n) for n in fit.edge_triplet])
        p, m, q = fit.edge_um, fit.edge_normal_px, fit.edge_px
        eps = 1e-2
        jx = (fit(p + [eps, 0]) - fit(p - [eps, 0])) / (2 * eps)
        jy = (fit(p + [0, eps]) - fit(p - [0, eps])) / (2 * eps)
        jac = np.stack([jx, jy], axis=-1)  # (edges, 2 px, 2 um)
        phi = _phi((p - fit.centre_um) / fit.scale_um, fit.model)
        a_map = np.concatenate([phi * m[:, :1], phi * m[:, 1:], np.ones((len(p), 1))], axis=1)
        a_lay = np.einsum("ei,eij,ejk->ek", m, jac, d_centre[idx])
        moved = d_centre[np.unique(idx)]  # numbers that move measured triplets relative to each other
        seen = (np.ptp(moved[:, 0], axis=0) > 1e-6) | (np.ptp(moved[:, 1], axis=0) > 1e-6)
        a_all = np.concatenate([a_map, a_lay[:, seen]], axis=1)
        sol = np.linalg.lstsq(a_all, np.sum(m * q, axis=1), rcond=None)[0]
        step = dict(zip(np.array(params)[seen], sol[a_map.shape[1] :]))
        lay = _layout_with(lay, {k: vals[k] + dv for k, dv in step.items()})
        k = phi.shape[1]  # the map solved with the layout, in the new layout's coordinates
        fit = replace(fit, coef=np.stack([sol[:k], sol[k : 2 * k]]))  # (sol[2 k]: the edge bias)

    target = usaf_target(groups, lay)
    fit = fit_layout(image, target, fit, **kwargs)
    return lay, fit


#: The shared real images (``../shared/real/usaf``) with their layout, the groups in view
#: and two hand-picked triplet centres (image px, read off the image by eye) to start from.
REAL_IMAGES: dict[str, dict] = {
    "fpm_brightfield.png": {
        "layout": "compact",
        "groups": (4, 5, 6, 7),
        "start": {"G4E2H": (363.0, 272.0), "G4E1H": (945.5, 862.5)},
    },
    "labumk_negative.tif": {
        "layout": "spaced",
        "groups": (4, 5, 6, 7),
        "start": {"G4E3H": (84.5, 64.3), "G4E6H": (81.0, 215.5)},
    },
    "whole_target.png": {
        "layout": "whole-target",
        "groups": (-2, -1, 0, 1),
        "start": {"G-2E2H": (100.0, 156.0), "G-2E1H": (424.5, 460.5)},
    },
    "highmag_g7e1.jpg": {
        "layout": "compact",
        "groups": (7,),
        "start": {"G7E1V": (235.0, 334.0), "G7E1H": (255.0, 567.0)},
    },
}


def check_real_image(image, name: str, **kwargs) -> tuple[UsafTarget, LayoutFit]:
    """:func:`fit_layout` of ``image``, the real image ``name`` of :data:`REAL_IMAGES` (its file
    name), in its layout, from its starting points."""
    from oapcal.imaging.usaf import usaf_target

    cfg = REAL_IMAGES[name]
    target = usaf_target(cfg["groups"], cfg["layout"])
    return target, fit_layout(image, target, similarity_from_points(target, cfg["start"]), **kwargs)
