"""The calibration record, and :func:`calibrate`, which makes it from point pairs:
normalize, fit, score the correction as in the paper's Table 1, record the calibrated
region.  ``imaging`` and ``report`` use the record; its file format lives in
:mod:`oapcal.io.calibration`.

>>> from oapcal.synthetic import synthetic_pairs
>>> data = synthetic_pairs(seed=0)
>>> cal = calibrate(data.xy_u, data.xy_d, model="paper")
>>> cal.fit.converged, cal.residuals.mean_px < 1.0
(True, True)
"""

from __future__ import annotations

import datetime as _dt
from dataclasses import dataclass, field

import numpy as np

from oapcal import __version__, validate
from oapcal.errors import DataError, InputFileError
from oapcal.model import N_PARAMS, ROTATION_SUFFIX, ModelFamily, family_of
from oapcal.normalize import normalize
from oapcal.stats import ResidualStats, correction_residuals

#: Points per side of the grid on which :func:`check_model_region` evaluates the model.
CHECK_GRID = 65

#: ``rotation="auto"``: the target's rotation is fitted as well when Eq. (1) alone does
#: not converge and Eq. (1) with the rotation does, or when the rotation lowers AICc by
#: more than this (Burnham & Anderson: a difference above 10 leaves the model without it
#: "essentially no support").
ROTATION_EVIDENCE_AICC = 10.0

#: The choices of ``calibrate(rotation=...)`` and ``oapcal fit --rotation``.
ROTATION_CHOICES = ("auto", "fit", "none")


@dataclass(frozen=True)
class FitSummary:
    """How the model was fitted: the statistics of :class:`oapcal.fitting.FitResult` that a
    calibration keeps.

    ``n_points`` point pairs give ``n_residuals = 2 n_points`` residuals; ``k`` free
    parameters; ``rss`` the sum of squared forward residuals in the fit's coordinates and
    ``aic``, ``aicc``, ``bic`` from it (:func:`oapcal.stats.information_criteria`);
    ``converged``, ``status`` and ``message`` the solver's verdict after ``n_iter``
    iterations from the start ``init``, on points normalized by ``normalize``; ``k_eff`` the
    effective number of parameters of a fit with priors (AIC, AICc and BIC count it
    instead of ``k``; None without priors).  Fields a calibration file does not hold are None.
    """

    n_points: int
    rss: float | None
    converged: bool
    n_residuals: int | None = None
    k: int | None = None
    aic: float | None = None
    aicc: float | None = None
    bic: float | None = None
    status: int | None = None
    message: str = ""
    n_iter: int | None = None
    init: str | None = None
    normalize: str = "none"
    k_eff: float | None = None


@dataclass(frozen=True)
class Calibration:
    """A fitted distortion model and what is known about it.

    ``params`` is the parameter vector of the model family (``(13,)`` for Eq. 1, ``(14,)``
    with the target's rotation, ``(36,)`` for the physical relay: :func:`oapcal.model.family_of`);
    ``stderr`` its standard errors (NaN for fixed parameters); ``covariance`` the ``k x k``
    covariance over ``free``; ``relay_design`` the nominal design a relay model was fitted
    from (:class:`oapcal.optics.relay_model.RelayDesign` as a dict; None for Eq. 1).  ``fit`` says
    how it was fitted (:class:`FitSummary`); ``residuals`` are the paper's Table-1
    statistics of the corrected calibration points (:class:`oapcal.stats.ResidualStats`).
    ``notes`` are what :func:`calibrate` decided for the user (e.g. that it fitted the
    target's rotation too); they are printed, not stored in the file.  ``priors`` the
    priors of a maximum a posteriori fit
    (:meth:`oapcal.optics.relay_model.RelayPriors.to_dict`, with the noise used); None
    without priors.  ``error_model`` is the model floor and extrapolation measured on the
    landmarks (:class:`oapcal.uncertainty.ErrorModel`, :mod:`oapcal.error_model`), None for
    files written before it existed.
    """

    free: tuple[str, ...]
    params: np.ndarray
    stderr: np.ndarray
    covariance: np.ndarray
    fit: FitSummary
    residuals: ResidualStats
    um_per_px: float | None = None
    image_size: tuple[int, int] | None = None
    bounds: tuple[float, float, float, float] | None = None
    hull: np.ndarray | None = None
    name: str | None = None
    source: str | None = None
    oapcal_version: str = __version__
    created_utc: str = field(default_factory=lambda: _dt.datetime.now(_dt.UTC).strftime("%Y-%m-%dT%H:%M:%SZ"))
    relay_design: dict | None = None
    notes: tuple[str, ...] = ()
    priors: dict | None = None
    error_model: object | None = None

    @property
    def family(self) -> ModelFamily:
        """The model family of ``params``."""
        return family_of(self.params)

    @property
    def mask(self) -> np.ndarray:
        return np.array([n in self.free for n in self.family.param_names])

    @property
    def params_dict(self) -> dict[str, float]:
        return {n: float(v) for n, v in zip(self.family.param_names, self.params)}


def check_model_region(
    calibration, size: tuple[int, int] | None = None, *, source: str = "calibration", boxes=()
):
    """Refuse a model that is not finite or folds over (Jacobian determinant <= 0) where it is
    applied: over the reference points' ``bounds``, the calibration's ``image_size`` frame,
    and the frame of ``size = (width, height)`` px if given (the image it is applied to).

    ``boxes`` adds regions ``((x0, y0, x1, y1), description)`` in undistorted coordinates
    (an output region of a correction).  The model is evaluated on a :data:`CHECK_GRID` x
    :data:`CHECK_GRID` grid over each region.
    Raises :class:`InputFileError` naming the first bad point.

    >>> from oapcal.model import params_from_dict
    >>> check_model_region(params_from_dict({"k1": 1e-7}), (640, 480))
    >>> try:
    ...     check_model_region(params_from_dict({"k1": -1e-5}), (640, 480), source="c.json")
    ... except InputFileError as e:
    ...     print(str(e)[:60])
    c.json: the model folds over at (x, y) = (189.703, 0) inside
    """
    params = np.asarray(getattr(calibration, "params", calibration), float)
    family = family_of(params)
    closed_form = family.code in _EQ1_CODES and params.shape == (family.n_params,)
    evaluate = _eq1_region_check if closed_form else _kernel_region_check
    regions = []
    bounds = getattr(calibration, "bounds", None)
    if bounds is not None:
        regions.append((tuple(float(b) for b in bounds), "reference points' bounds"))
    for frame in (getattr(calibration, "image_size", None), size):
        if frame is not None:
            w, h = int(frame[0]), int(frame[1])
            regions.append(((0.0, 0.0, float(max(w - 1, 1)), float(max(h - 1, 1))), f"{w}x{h} px image"))
    regions.extend(boxes)
    with np.errstate(all="ignore"):
        for (x0, y0, x1, y1), what in regions:
            gx, gy = np.meshgrid(np.linspace(x0, x1, CHECK_GRID), np.linspace(y0, y1, CHECK_GRID))
            xy = np.stack([gx.ravel(), gy.ravel()], -1)
            finite, det = evaluate(xy, params)
            bad = ~(finite & np.isfinite(det) & (det > 0))
            if bad.any():
                x, y = xy[np.argmax(bad)]
                how = "folds over" if np.isfinite(det[np.argmax(bad)]) else "is not finite"
                raise InputFileError(
                    f"{source}: the model {how} at (x, y) = ({x:.6g}, {y:.6g}) inside the {what}; "
                    "it cannot correct there (refit with more points or a smaller model)"
                )


#: Family codes of Eq. (1) and Eq. (1) with the target's rotation (``ModelFamily.code``),
#: whose region check evaluates the closed form in NumPy (:func:`_eq1_region_check`).
_EQ1_CODES = (0, 1)


def _kernel_region_check(xy: np.ndarray, params: np.ndarray):
    """Whether the model is finite at each point ``(N, 2)``, and its Jacobian determinant,
    through the compiled kernels (any family)."""
    from oapcal.model import distort, jacobian_determinant

    det = jacobian_determinant(xy, params)
    return np.isfinite(distort(xy, params)).all(-1), det


def _eq1_region_check(xy: np.ndarray, params: np.ndarray):
    """:func:`_kernel_region_check` for Eq. (1) (13 parameters) and Eq. (1) after the
    target's rotation (14: ``params[13]`` degrees), in NumPy.

    Why not the kernels: loading them costs a command about 0.3-0.8 s before its first frame
    (importing Numba, loading the cached machine code), while this closed form on the check's
    grids takes about a millisecond.  The same expressions as ``_kernels.bc_point`` and
    ``bc_pose_point`` (``docs/models.md``); a test checks it against the kernels.
    """
    k1, k2, p1, p2, s1, s2, s3, s4, xo, yo, cx, cy, m = params[:13]
    x, y = xy[:, 0], xy[:, 1]
    cs, sn = 1.0, 0.0
    if len(params) > 13:  # the rotation of the reference points, counter-clockwise
        th = params[13] * (np.pi / 180.0)
        cs, sn = np.cos(th), np.sin(th)
        x, y = cs * x - sn * y, sn * x + cs * y
    xb, yb = m * (x + xo), m * (y + yo)
    r2 = xb * xb + yb * yb
    radial = 1.0 + r2 * (k1 + k2 * r2)
    xy2 = 2.0 * xb * yb
    xd = xb * radial + p1 * xy2 + p2 * (r2 + 2.0 * xb * xb) + r2 * (s1 + s2 * r2) + cx
    yd = yb * radial + p1 * (r2 + 2.0 * yb * yb) + p2 * xy2 + r2 * (s3 + s4 * r2) + cy
    drad = 2.0 * (k1 + 2.0 * k2 * r2)
    sx = 2.0 * (s1 + 2.0 * s2 * r2)
    sy = 2.0 * (s3 + 2.0 * s4 * r2)
    a = m * (radial + drad * xb * xb + 2.0 * p1 * yb + 6.0 * p2 * xb + xb * sx)
    b = m * (drad * xb * yb + 2.0 * p1 * xb + 2.0 * p2 * yb + yb * sx)
    c = m * (drad * xb * yb + 2.0 * p1 * xb + 2.0 * p2 * yb + xb * sy)
    d = m * (radial + drad * yb * yb + 6.0 * p1 * yb + 2.0 * p2 * xb + yb * sy)
    # the point Jacobian times the rotation's: [[a, b], [c, d]] @ [[cs, -sn], [sn, cs]]
    a, b, c, d = a * cs + b * sn, b * cs - a * sn, c * cs + d * sn, d * cs - c * sn
    return np.isfinite(xd) & np.isfinite(yd), a * d - b * c


def calibrate(
    xy_u,
    xy_d,
    model="paper",
    *,
    init="auto",
    normalization: str = "none",
    um_per_px: float | None = None,
    image_size: tuple[int, int] | None = None,
    name: str | None = None,
    source: str | None = None,
    relay_design: dict | None = None,
    rotation: str = "auto",
    priors: dict | None = None,
    error_model: bool = True,
    **fit_options,
) -> Calibration:
    """Fit ``model`` to reference points ``xy_u`` and distorted points ``xy_d`` ``(N, 2)``.

    ``model`` is any spec of :func:`oapcal.fitting.fit` (Eq. 1, ``"...+rotation"``, or a
    relay mask with ``init`` its design's vector and ``relay_design`` the design as a dict,
    kept in the record; a relay model is fitted in px, without normalization).

    ``um_per_px`` is the object-space size of one unit of the reference points *as given*;
    with ``normalization="experiment"`` it is converted through the normalization scale.
    The residual statistics are those of :func:`oapcal.stats.correction_residuals`.

    ``rotation`` applies to an Eq. (1) model given without ``+rotation``: ``"auto"`` (the
    default) fits it both without and with the target's in-plane rotation and keeps the
    rotation when Eq. (1) alone does not converge or needs ``m < 0`` (a target turned by
    180 deg) and the rotation converges, or when the
    rotation lowers AICc by more than :data:`ROTATION_EVIDENCE_AICC` (a turned target is
    otherwise absorbed into a distortion centre that runs away, x_off ~ 1e4 px, and the fit
    hits the iteration cap); the record's ``notes`` say so.  ``"fit"`` always adds the
    rotation, ``"none"`` never.

    ``priors`` is recorded only (the priors of a maximum a posteriori relay fit, whose rows
    come in ``fit_options["prior"]``: :func:`oapcal.optics.relay_model.calibrate_relay`).

    ``error_model`` (default True) also measures the model floor and the extrapolation
    error on the landmarks (:func:`oapcal.error_model.estimate_error_model`: a few refits).
    """
    from scipy.spatial import ConvexHull, QhullError

    from oapcal.fitting import fit

    if relay_design is not None and normalization not in (None, "none"):
        raise DataError(
            f"normalization {normalization!r} cannot be used with the relay model: it fits the "
            "target's pose itself, in px (use normalization 'none')"
        )
    if um_per_px is not None:
        um_per_px = validate.positive(um_per_px, "um_per_px")
    if image_size is not None:
        image_size = validate.image_size(image_size)
    if rotation not in ROTATION_CHOICES:
        choices = ", ".join(ROTATION_CHOICES)
        raise DataError(f"rotation must be one of {choices}, got {rotation!r}", param="rotation")
    norm = normalize(normalization, xy_u, xy_d)
    result = fit(norm.xy_u, norm.xy_d, model, init=init, **fit_options)
    notes: tuple[str, ...] = ()
    if rotation != "none" and relay_design is None and len(result.params) == N_PARAMS:
        result, notes = _with_rotation(result, norm, model, init, rotation, fit_options)
    scale = None if um_per_px is None else float(um_per_px) / norm.scale_u
    residuals = correction_residuals(result.params, norm.xy_u, norm.xy_d, scale)
    try:
        hull = norm.xy_u[ConvexHull(norm.xy_u).vertices]
    except QhullError:
        hull = None
    lo = norm.xy_u.min(axis=0)
    hi = norm.xy_u.max(axis=0)
    init_name = init if isinstance(init, str) else "user"
    errors = None
    if error_model and result.converged:
        from oapcal.error_model import estimate_error_model

        mask = np.array([n in result.free for n in family_of(result.params).param_names])
        errors = estimate_error_model(norm.xy_u, norm.xy_d, result.params, mask, **fit_options)
    return Calibration(
        free=result.free,
        params=np.array(result.params),
        stderr=np.array(result.stderr),
        covariance=np.array(result.covariance),
        fit=FitSummary(
            n_points=len(norm.xy_u),
            n_residuals=int(result.n),
            k=int(result.k),
            rss=float(result.rss),
            aic=float(result.aic),
            aicc=float(result.aicc),
            bic=float(result.bic),
            converged=bool(result.converged),
            status=int(result.status),
            message=str(result.message),
            n_iter=int(result.n_iter),
            init=init_name,
            normalize=normalization or "none",
            k_eff=result.k_eff,
        ),
        residuals=residuals,
        um_per_px=scale,
        image_size=tuple(int(v) for v in image_size) if image_size else None,
        bounds=(float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])),
        hull=hull,
        name=name,
        source=source,
        relay_design=relay_design,
        notes=notes,
        priors=priors,
        error_model=errors,
    )


def _with_rotation(plain, norm, model, init, rotation: str, fit_options):
    """``calibrate``'s choice between Eq. (1) ``plain`` and Eq. (1) with the rotation."""
    from oapcal.fitting import fit
    from oapcal.model import names_from_mask, parse_any_model

    mask = np.append(parse_any_model(model), True)
    turned = fit(norm.xy_u, norm.xy_d, mask, init=init, **fit_options)
    base = model.strip() if isinstance(model, str) else ",".join(names_from_mask(mask)[:-1])
    spec = base + ROTATION_SUFFIX
    angle = f"{turned.params[N_PARAMS]:+.3g} deg"
    if rotation == "fit":
        return turned, (f"fitted {spec} (the target's rotation, {angle})",)
    if not turned.converged:
        return plain, ()
    if plain.converged and plain.params[N_PARAMS - 1] <= 0:
        # m < 0 is Eq. (1) with the target turned by 180 deg (m -> -m, x_off -> -x_off and
        # the reference points -> -reference points give the same map): the sign belongs
        # to the rotation, and a calibration keeps m > 0
        why = f"Eq. (1) alone needs m = {plain.params[N_PARAMS - 1]:.4g} < 0"
    elif not plain.converged:
        why = f"Eq. (1) alone did not converge ({plain.message.removeprefix('not converged: ')})"
    elif turned.aicc < plain.aicc - ROTATION_EVIDENCE_AICC:
        why = f"it lowers AICc by {plain.aicc - turned.aicc:.1f}"
    else:
        return plain, ()
    return turned, (f"the target is turned by {angle}: fitted {spec}, because {why}",)
