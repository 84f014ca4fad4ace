"""How uncertain the correction is at every output pixel.

The corrected image shows at output pixel ``u`` (an undistorted position) the distorted
image sampled at ``d = distort(u; p)`` with the fitted parameters ``p``.  Had the true
parameters been ``p + dp``, the content at ``d`` would truly belong at ``u + du`` with
``distort(u + du; p + dp) = d``; to first order::

    du = -J_u^-1 J_p dp,      J_u = d distort / d u  (2 x 2),   J_p = d distort / d p  (2 x k)

so the covariance of the corrected position is ``S = A C A^T`` with ``A = J_u^-1 J_p`` and
``C`` the fit's covariance of the ``k`` free parameters (``Calibration.covariance``, in
``free`` order).  The map reports ``sigma_x = sqrt(S_xx)``, ``sigma_y = sqrt(S_yy)``, the
positional 1-sigma uncertainty ``sigma = sqrt(S_xx + S_yy)`` (the RMS length of ``du``)
and the semi-major axis of the 1-sigma ellipse, all in output px (the units of the
reference points), and in um with the calibration's scale.

Outside the convex hull of the calibration's reference points the model extrapolates;
those pixels are flagged (``outside_hull``), whatever their sigma says.

**The predicted error** adds what the covariance cannot know, the model floor (what the
model cannot fit) and how fast the error grows where the model extrapolates.  A
calibration made by :func:`oapcal.calibration.calibrate` carries an :class:`ErrorModel`
measured on its own landmarks (:mod:`oapcal.error_model`): the floor ``F`` from the spatial
correlation of the residuals (noise is uncorrelated from landmark to landmark, a floor is
not), and the extrapolation factor ``kappa`` from refits that leave one side of the
landmarks out and predict it.  The predicted 1-sigma error at output point ``u`` is::

    predicted(u)^2 = (k(u) sigma(u))^2 + F^2
    k(u) = (1 + (kappa - 1) min(1, d / d0)) max(1, (1 + d / R) / (1 + t_p))^g

with ``sigma`` the propagated uncertainty above, ``d = d(u)`` the distance of ``u`` outside
the hull (0 inside), ``d0`` the landmarks' spacing, ``R`` the hull's radius (of the disc of
its area), ``t_p`` how far (in ``R``) the refits extrapolated, and ``g`` the growth beyond
that (:func:`predicted_error`, :func:`extrapolation_factor`).  Without an
error model (a file written before it existed) the predicted error is ``sigma`` alone,
which is optimistic outside the hull.

>>> from oapcal.synthetic import synthetic_pairs
>>> from oapcal.calibration import calibrate
>>> data = synthetic_pairs(seed=0)
>>> cal = calibrate(data.xy_u, data.xy_d, "paper", image_size=(640, 480))
>>> umap = uncertainty_map(cal, step=40)
>>> umap.sigma_px.shape, bool(umap.outside_hull[0, 0]), bool(umap.outside_hull[6, 8])
((12, 16), True, False)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from oapcal import eq1_closed_form
from oapcal.errors import DataError
from oapcal.model import as_model


def position_covariance(xy_u, params, covariance, free=None, *, family=None) -> np.ndarray:
    """Covariance ``(..., N, 2, 2)`` of the corrected position at output points ``(..., N, 2)``.

    ``params`` is a :class:`~oapcal.model.Model` (``free`` defaults to its free
    parameters) or a parameter vector of ``family`` (by name; a legacy call without it: the
    built-in family of its length, :func:`oapcal.model.family_of`).  ``covariance`` is
    ``k x k`` over the parameters named in ``free``; see the module docstring for the
    formula.  NaN where the map is singular (folds over).
    """
    xy_u = np.asarray(xy_u, float)
    model = as_model(params, family)
    names = model.family.param_names
    idx = [names.index(name) for name in (model.free if free is None else free)]
    cov = np.asarray(covariance, float)
    if cov.shape != (len(idx), len(idx)):
        raise DataError(
            f"covariance must be {len(idx)} x {len(idx)} (one per free parameter), got {cov.shape}"
        )
    n_points = int(np.prod(xy_u.shape[:-1])) if xy_u.ndim >= 2 and xy_u.shape[-1] == 2 else -1
    if n_points >= 0 and eq1_closed_form.applies(model.family, n_points, model.params):
        # a few Eq. (1) points in a process without the kernels: the same Jacobians in NumPy
        _, ju, jp = eq1_closed_form.evaluate(xy_u, model.params, eq1_closed_form.PARAM_JAC)
        jp = jp[..., idx]
    else:
        jp = model.jacobian_params(xy_u)[..., idx]  # (..., N, 2, k)
        ju = model.jacobian(xy_u)  # (..., N, 2, 2)
    det = ju[..., 0, 0] * ju[..., 1, 1] - ju[..., 0, 1] * ju[..., 1, 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = (
            np.stack(
                [
                    np.stack([ju[..., 1, 1], -ju[..., 0, 1]], -1),
                    np.stack([-ju[..., 1, 0], ju[..., 0, 0]], -1),
                ],
                -2,
            )
            / det[..., None, None]
        )
        inv = np.where((det > 0)[..., None, None], inv, np.nan)
        a = inv @ jp  # (..., N, 2, k)
        return a @ cov @ np.swapaxes(a, -1, -2)


#: Thresholds (px) whose trusted share :meth:`UncertaintyMap.summary` reports.
TRUST_LEVELS_PX = (0.5, 1.0, 2.0)

#: Keys of a calibration file's ``error_model`` object (:meth:`ErrorModel.to_dict`).
ERROR_MODEL_KEYS = ("method", "floor_px", "noise_px", "extrapolation", "ramp_px", "growth_exponent",
                    "probed_distance", "sides", "sides_used", "holdout_fraction")  # fmt: skip


@dataclass(frozen=True)
class ErrorModel:
    """What a calibration's landmarks say about the error its covariance cannot see
    (:mod:`oapcal.error_model` measures it; all lengths in the calibration's reference units).

    ``floor_px`` the model floor ``F`` (RMS length of the misfit the model leaves, from the
    correlation of neighbouring landmarks' residuals); ``noise_px`` the RMS length of the
    uncorrelated part of the residuals (the landmarks' own noise); ``extrapolation`` the
    factor ``kappa >= 1`` by which the propagated uncertainty underestimates the error of
    held-out sides of the landmarks; ``ramp_px`` the distance ``d0`` outside the hull over
    which the factor grows from 1 to ``kappa`` (the landmarks' median spacing); ``sides``
    refits tried, ``sides_used`` those that converged, each leaving out ``holdout_fraction``
    of the landmarks; ``method`` how the sides' factors were combined: ``"leave-side-out"``
    the worst side (a series model: Eq. 1 and its variants), ``"leave-side-out-mean"`` their
    mean (a physical model: the relay families; :mod:`oapcal.error_model`).
    """

    floor_px: float
    noise_px: float
    extrapolation: float
    ramp_px: float
    growth_exponent: float = 0.0
    probed_distance: float = 0.0
    sides: int = 8
    sides_used: int = 8
    holdout_fraction: float = 0.25
    method: str = "leave-side-out"

    def to_dict(self) -> dict:
        return {k: getattr(self, k) for k in ERROR_MODEL_KEYS}

    @classmethod
    def from_dict(cls, data: dict | None) -> ErrorModel | None:
        if not data:
            return None
        return cls(**{k: data[k] for k in ERROR_MODEL_KEYS if k in data})


def hull_distance(xy, hull) -> np.ndarray:
    """Distance of points ``(..., 2)`` outside the convex hull of the polygon ``hull``
    ``(M, 2)``; 0 inside or on it.  A hull without area contains nothing: the distance is
    then to its segments.

    >>> square = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float)
    >>> hull_distance(np.array([[0.5, 0.5], [3.0, 1.0], [2.0, 2.0]]), square).round(4).tolist()
    [0.0, 2.0, 1.4142]
    """
    from scipy.spatial import ConvexHull, QhullError

    xy = np.asarray(xy, float)
    poly = np.asarray(hull, float)
    try:
        poly = poly[ConvexHull(poly).vertices]  # counter-clockwise (x right, y up)
        flat_hull = False
    except QhullError:  # a flat hull (Qhull cannot build a simplex)
        flat_hull = True
    flat = xy.reshape(-1, 2)
    a = poly
    ab = np.roll(poly, -1, axis=0) - a
    ab2 = np.maximum((ab * ab).sum(-1), 1e-300)
    out = np.empty(len(flat))
    block = max(1, 2_000_000 // max(len(poly), 1))
    for lo in range(0, len(flat), block):
        p = flat[lo : lo + block, None, :]
        ap = p - a
        t = np.clip((ap * ab).sum(-1) / ab2, 0.0, 1.0)
        diff = ap - t[..., None] * ab
        dist = np.sqrt((diff * diff).sum(-1)).min(axis=1)
        if not flat_hull:  # inside: on the left of every edge (or on it)
            cross = ab[:, 0] * ap[..., 1] - ab[:, 1] * ap[..., 0]
            dist[(cross >= -1e-9 * np.sqrt(ab2)).all(axis=1)] = 0.0
        out[lo : lo + block] = dist
    return out.reshape(xy.shape[:-1])


def predicted_error(xy_u, calibration) -> np.ndarray:
    """The predicted 1-sigma error ``(...,)`` of the correction at output points ``(..., 2)``
    (module docstring): the propagated uncertainty, inflated by the calibration's
    :class:`ErrorModel` beyond the hull and with its model floor added; the propagated
    uncertainty alone for a calibration without an error model.  NaN where the map folds.
    It is a length: the root sum of squares of :func:`predicted_error_xy`'s two coordinates.
    """
    return np.hypot(*np.moveaxis(predicted_error_xy(xy_u, calibration), -1, 0))


def predicted_error_xy(xy_u, calibration) -> np.ndarray:
    """The predicted 1-sigma error of each coordinate ``(..., 2)`` (x, y) of the correction at
    output points ``(..., 2)``: the propagated variance of that coordinate times the
    extrapolation factor squared, plus half the model floor's squared length (the floor
    ``F`` is an RMS length, shared evenly by the two coordinates).  A coordinate's error
    within 1 / 2 sigma is what a Gaussian puts at 68 / 95 %; the length of
    :func:`predicted_error` at 63 / 98 %."""
    xy_u = np.asarray(xy_u, float)
    cov = position_covariance(xy_u, as_model(calibration), calibration.covariance)
    return _combine(cov[..., 0, 0], cov[..., 1, 1], xy_u, calibration)


def _combine(sxx, syy, xy_u, calibration) -> np.ndarray:
    """Per-coordinate predicted sigmas ``(..., 2)`` from the propagated variances."""
    em = getattr(calibration, "error_model", None)
    var = np.stack([sxx, syy], -1)
    if em is None:
        return np.sqrt(var)
    hull = getattr(calibration, "hull", None)
    if hull is None or len(hull) < 3:
        dist = np.full(np.shape(sxx), np.inf)
    else:
        dist = hull_distance(xy_u, hull)
    k = extrapolation_factor(dist, em, hull_radius(hull))
    return np.sqrt((k * k)[..., None] * var + 0.5 * float(em.floor_px) ** 2)


def hull_radius(hull) -> float:
    """The radius of the disc with the area of the polygon ``hull`` (0 without area)."""
    if hull is None or len(hull) < 3:
        return 0.0
    x, y = np.asarray(hull, float).T
    area = 0.5 * abs(float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))))
    return float(np.sqrt(area / np.pi))


def extrapolation_factor(dist, error_model: ErrorModel, radius: float) -> np.ndarray:
    """The factor ``k`` on the propagated uncertainty at distance ``dist`` outside a hull of
    radius ``radius`` (module docstring): ``1 + (kappa - 1) min(1, d / d0)`` as far as the
    refits probed (``d / R <= t_p``, ``probed_distance``), times
    ``((1 + d / R) / (1 + t_p))^g`` beyond."""
    dist = np.asarray(dist, float)
    ramp = np.minimum(1.0, dist / max(float(error_model.ramp_px), 1e-300))
    k = 1.0 + (float(error_model.extrapolation) - 1.0) * ramp
    g = float(error_model.growth_exponent)
    if g:
        with np.errstate(divide="ignore", invalid="ignore"):
            rel = np.where(radius > 0, dist / max(radius, 1e-300), np.inf)
            k = k * np.maximum(1.0, (1.0 + rel) / (1.0 + float(error_model.probed_distance))) ** g
    return k


def extrapolation_report(calibration, xy_u) -> dict:
    """How far points ``(N, 2)`` (output positions, the calibration's reference units) lie
    beyond the landmarks' hull, and their predicted error: ``{"n", "outside", "max_distance_px",
    "max_predicted_px", "median_predicted_outside_px", "max_predicted_outside_px",
    "predicted"}`` (None where nothing is
    outside, or without a hull; ``predicted`` the ``(N,)`` predicted errors, inf where the
    map folds)."""
    xy_u = np.asarray(xy_u, float).reshape(-1, 2)
    hull = getattr(calibration, "hull", None)
    if hull is None or len(hull) < 3:
        dist = np.full(len(xy_u), np.inf)
    else:
        dist = hull_distance(xy_u, hull)
    pred = predicted_error(xy_u, calibration)
    out = dist > 0
    finite = np.where(np.isfinite(pred), pred, np.inf)
    return {
        "n": int(len(xy_u)),
        "outside": int(out.sum()),
        "max_distance_px": float(dist[out].max()) if out.any() and np.isfinite(dist).all() else None,
        "max_predicted_px": float(finite.max()) if len(finite) else None,
        "median_predicted_outside_px": float(np.median(finite[out])) if out.any() else None,
        "max_predicted_outside_px": float(finite[out].max()) if out.any() else None,
        "predicted": finite,
    }


def inside_hull(xy, hull) -> np.ndarray:
    """Whether points ``(..., 2)`` lie inside (or on) the convex polygon ``hull`` ``(M, 2)``.

    A hull without area (collinear or repeated vertices, as a hand-edited calibration file
    may hold) contains no point: everything is outside.

    >>> square = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float)
    >>> inside_hull(np.array([[0.5, 0.5], [1.5, 0.5], [1.0, 0.2]]), square).tolist()
    [True, False, True]
    >>> inside_hull(np.array([[0.5, 0.5], [1.5, 1.5]]), [[0, 0], [1, 1], [2, 2]]).tolist()
    [False, False]
    """
    from scipy.spatial import Delaunay, QhullError

    xy = np.asarray(xy, float)
    try:
        tri = Delaunay(np.asarray(hull, float))
    except QhullError:  # a flat hull (Qhull cannot build a simplex)
        return np.zeros(xy.shape[:-1], bool)
    flat = xy.reshape(-1, 2)
    return (tri.find_simplex(flat, tol=1e-9) >= 0).reshape(xy.shape[:-1])


@dataclass(frozen=True)
class UncertaintyMap:
    """Per-output-pixel 1-sigma positional uncertainty of the correction.

    ``x`` ``(cols,)`` and ``y`` ``(rows,)`` are the output pixel coordinates sampled (every
    ``step`` px); ``sigma_px``, ``sigma_x_px``, ``sigma_y_px``, ``sigma_major_px`` are
    ``(rows, cols)``; ``outside_hull`` ``(rows, cols)`` bool (all False when the calibration
    has no hull); ``hull`` the hull polygon or None.  ``predicted_px`` ``(rows, cols)`` is
    the predicted error (:func:`predicted_error`: with the calibration's ``error_model``,
    else equal to ``sigma_px``), ``error_model`` the :class:`ErrorModel` used or None.
    """

    x: np.ndarray
    y: np.ndarray
    sigma_px: np.ndarray
    sigma_x_px: np.ndarray
    sigma_y_px: np.ndarray
    sigma_major_px: np.ndarray
    outside_hull: np.ndarray
    hull: np.ndarray | None
    um_per_px: float | None
    predicted_px: np.ndarray | None = None
    error_model: ErrorModel | None = None

    @property
    def sigma_um(self) -> np.ndarray | None:
        return None if self.um_per_px is None else self.sigma_px * self.um_per_px

    def summary(self) -> dict:
        """Median and maximum sigma inside and outside the hull (px, and um with a scale)."""
        out = {}
        for label, sel in (("inside", ~self.outside_hull), ("outside", self.outside_hull)):
            values = self.sigma_px[sel]
            values = values[np.isfinite(values)]
            out[f"{label}_fraction"] = float(sel.mean())
            for stat, fn in (("median", np.median), ("max", np.max)):
                v = float(fn(values)) if values.size else None
                out[f"{label}_{stat}_px"] = v
                if self.um_per_px is not None:
                    out[f"{label}_{stat}_um"] = None if v is None else v * self.um_per_px
            if self.predicted_px is not None:
                pred = self.predicted_px[sel]
                pred = pred[np.isfinite(pred)]
                for stat, fn in (("median", np.median), ("max", np.max)):
                    out[f"{label}_predicted_{stat}_px"] = float(fn(pred)) if pred.size else None
        if self.predicted_px is not None:
            out["error_model"] = None if self.error_model is None else self.error_model.to_dict()
            for limit in TRUST_LEVELS_PX:
                ok = np.isfinite(self.predicted_px) & (self.predicted_px <= limit)
                out[f"trusted_fraction_{limit:g}px"] = float(ok.mean())
        return out

    def trusted(self, max_error_px: float) -> np.ndarray:
        """``(rows, cols)`` bool: where the predicted error is at most ``max_error_px``."""
        pred = self.sigma_px if self.predicted_px is None else self.predicted_px
        return np.isfinite(pred) & (pred <= max_error_px)


def uncertainty_map(calibration, shape: tuple[int, int] | None = None, *, step: int = 1) -> UncertaintyMap:
    """The uncertainty map of a calibration over an output image of ``shape = (rows, cols)``
    (default: the calibration's ``image_size``, else its reference points' bounds), sampled
    every ``step`` px.  Computed in blocks of rows to keep memory small."""
    if shape is None:
        if calibration.image_size:
            w, h = calibration.image_size
            shape = (int(h), int(w))
        elif calibration.bounds is not None:
            x1, y1 = calibration.bounds[2], calibration.bounds[3]
            shape = (int(np.ceil(y1)) + 1, int(np.ceil(x1)) + 1)
        else:
            raise DataError("the calibration has no image_size or bounds; give the output image shape")
    if step < 1:
        raise DataError(f"step must be a positive number of px, got {step}")
    rows, cols = int(shape[0]), int(shape[1])
    x = np.arange(0, cols, step, dtype=float)
    y = np.arange(0, rows, step, dtype=float)
    out = {k: np.empty((len(y), len(x))) for k in ("s", "sx", "sy", "smaj", "pred")}
    block = max(1, 200_000 // max(len(x), 1))
    for r0 in range(0, len(y), block):
        gx, gy = np.meshgrid(x, y[r0 : r0 + block])
        cov = position_covariance(np.stack([gx, gy], -1), as_model(calibration), calibration.covariance)
        sxx, syy, sxy = cov[..., 0, 0], cov[..., 1, 1], cov[..., 0, 1]
        half_tr = 0.5 * (sxx + syy)
        with np.errstate(invalid="ignore"):
            lam = half_tr + np.sqrt(np.maximum(half_tr**2 - (sxx * syy - sxy * sxy), 0.0))
            out["s"][r0 : r0 + block] = np.sqrt(sxx + syy)
            out["sx"][r0 : r0 + block] = np.sqrt(sxx)
            out["sy"][r0 : r0 + block] = np.sqrt(syy)
            out["smaj"][r0 : r0 + block] = np.sqrt(lam)
            pred = _combine(sxx, syy, np.stack([gx, gy], -1), calibration)
            out["pred"][r0 : r0 + block] = np.hypot(pred[..., 0], pred[..., 1])
    hull = getattr(calibration, "hull", None)
    if hull is not None and len(hull) >= 3:
        gx, gy = np.meshgrid(x, y)
        outside = ~inside_hull(np.stack([gx, gy], -1), hull)
    else:
        outside = np.zeros((len(y), len(x)), bool)
    return UncertaintyMap(
        x=x,
        y=y,
        sigma_px=out["s"],
        sigma_x_px=out["sx"],
        sigma_y_px=out["sy"],
        sigma_major_px=out["smaj"],
        outside_hull=outside,
        hull=None if hull is None else np.asarray(hull, float),
        um_per_px=calibration.um_per_px,
        predicted_px=out["pred"],
        error_model=getattr(calibration, "error_model", None),
    )
