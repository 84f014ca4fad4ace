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

import dataclasses
import datetime as _dt
import functools
from dataclasses import dataclass, field

import numpy as np

from oapcal import __version__, eq1_closed_form, validate
from oapcal.errors import DataError, InputFileError, ModelSpecError
from oapcal.fitting import DEFAULT_INIT
from oapcal.model import (
    BROWN_CONRADY,
    BROWN_CONRADY_TILT,
    N_PARAMS,
    ROTATION_SUFFIX,
    TILT_SUFFIX,
    Model,
    ModelFamily,
    family_named,
    family_of,
)
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


class UnusableFitError(DataError):
    """The fit ran but gave no usable model: non-finite parameters, ``m <= 0`` (a target
    turned by 180 deg that Eq. (1) alone expresses with a negative scale), or a model that
    folds over or is not finite where it applies (:func:`check_fit_usable`).

    ``problem`` is what is wrong (naming the points' ``source``), ``advice`` how to fix it
    in Python terms, and ``code`` one of :data:`UNUSABLE_CODES`, so that a front-end can
    word the fix in its own terms (``oapcal fit`` exits with code 3).  ``"implausible"``:
    a relay fit that is no plausible misalignment (:func:`oapcal.entry.check_relay_plausible`)."""

    def __init__(self, problem: str, advice: str = "", *, code: str, param=None):
        super().__init__(f"{problem}. {advice}" if advice else problem, param=param)
        self.problem = problem
        self.advice = advice
        self.code = code


#: The kinds of :class:`UnusableFitError`.
UNUSABLE_CODES = ("non_finite", "negative_m", "region", "implausible")


@dataclass(frozen=True)
class FitSummary:
    """How the model was fitted: the statistics of :class:`oapcal.fitting.FitResult` that a
    calibration keeps (:meth:`from_result`).

    ``n_points`` point pairs give ``n_residuals = 2 n_points`` residuals; ``k`` free
    parameters; ``rss`` the sum of squared forward residuals in the fit's coordinates and
    ``aic``, ``aicc``, ``bic`` from it (:func:`oapcal.stats.information_criteria`);
    ``converged``, ``status`` and ``message`` the solver's verdict after ``n_iter``
    iterations from the start ``init``, on points normalized by ``normalize``; ``k_eff`` the
    effective number of parameters of a fit with priors (AIC, AICc and BIC count it
    instead of ``k``; None without priors).  Fields a calibration file does not hold are None.

    Two AICc values describe one fit: ``aicc_forward`` (the same as ``aicc``) scores the
    forward residuals ``distort(xy_u) - xy_d`` that the fit minimises;
    ``aicc_corrected`` scores the residuals after correction, ``undistort(xy_d) - xy_u``,
    as model selection ranks models (:attr:`oapcal.select.ModelScore.aicc_corrected`):
    for the same model and points it equals the selection's value (None in files written
    before it was recorded; NaN when the inverse failed at a point).
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
    aicc_corrected: float | None = None

    @property
    def aicc_forward(self) -> float | None:
        """AICc of the forward residuals (``aicc``, named for what it scores)."""
        return self.aicc

    @classmethod
    def from_result(cls, result, *, n_points: int, init: str | None = None, normalize: str = "none",
                    aicc_corrected: float | None = None) -> FitSummary:  # fmt: skip
        """The summary of a :class:`oapcal.fitting.FitResult` (the one conversion)."""
        return cls(
            n_points=int(n_points),
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
            init=init,
            normalize=normalize or "none",
            k_eff=result.k_eff,
            aicc_corrected=None if aicc_corrected is None else float(aicc_corrected),
        )

    def to_dict(self) -> dict:
        """The ``fit`` object of a calibration file: every field that is not None, and
        ``aicc_forward`` beside ``aicc`` (the same number, named for what it scores)."""
        out = {k: v for k, v in dataclasses.asdict(self).items() if v is not None}
        if self.aicc is not None:
            out["aicc_forward"] = self.aicc
        return out

    @classmethod
    def from_dict(cls, fit: dict) -> FitSummary:
        """The ``fit`` object of a file (absent fields None; ``aicc_forward`` is ``aicc``)."""
        names = {f.name for f in dataclasses.fields(cls)}
        known = {k: v for k, v in fit.items() if k in names}
        if known.get("aicc") is None and fit.get("aicc_forward") is not None:
            known["aicc"] = fit["aicc_forward"]
        known["message"] = known.get("message") or ""
        known["normalize"] = known.get("normalize") or "none"
        return cls(**known)


@dataclass(frozen=True)
class Calibration:
    """A fitted distortion model and what is known about it: the model
    (:attr:`model`, an :class:`oapcal.model.Model`), one fit record (``fit``), the region
    it was fitted on (``bounds``, ``hull``, ``image_size``) and its provenance.

    ``params`` is the parameter vector of the model family (``(13,)`` for Eq. 1, ``(14,)``
    with the target's rotation, ``(36,)`` for the physical relay); ``family`` the family,
    carried by name (a :class:`oapcal.model.ModelFamily` or its name; when not given, the
    family :func:`oapcal.model.family_of` names by the vector's length, as records made
    before the family was carried had it);
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
    files written before it existed.  ``selfcal`` is what a self-calibration found (frames,
    matches, gauge, per-pair residuals: :func:`oapcal.selfcal.solve.selfcal_record`), None
    for a fit to landmarks.
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
    family: ModelFamily | str | None = None
    selfcal: dict | None = None

    def __post_init__(self):
        family = family_of(self.params) if self.family is None else family_named(self.family)
        if np.shape(self.params) != (family.n_params,):
            raise ModelSpecError(
                f"a {family.name} calibration has {family.n_params} parameters, got {np.shape(self.params)}",
                param="params",
            )
        object.__setattr__(self, "family", family)

    @property
    def model_family(self) -> str:
        """The family's name (the file's ``model_family``)."""
        return self.family.name

    @property
    def model(self) -> Model:
        """The fitted model as a value: family, parameters and free ones."""
        return Model(self.family, self.params, self.free)

    @property
    def mask(self) -> np.ndarray:
        return self.model.mask

    @property
    def params_dict(self) -> dict[str, float]:
        return self.model.params_dict


@dataclasses.dataclass(frozen=True)
class ModelRegion:
    """What :func:`check_model_region` reads of a calibration, for a model checked apart
    from its record: the parameters and family, the reference points' ``bounds`` (where a
    fold is never allowed), the ``image_size`` frame and the ``error_model`` (whose trust
    region lets a fold beyond the bounds pass); None where there is none."""

    params: np.ndarray
    family: ModelFamily | str | None = None
    bounds: tuple | None = None
    image_size: tuple | None = None
    error_model: object = None


def check_model_region(
    calibration,
    size: tuple[int, int] | None = None,
    *,
    source: str = "calibration",
    boxes=(),
    error=InputFileError,
    folds_beyond_bounds: bool | None = None,
    check_bounds: bool = True,
):
    """Refuse a model that is not finite or folds over (Jacobian determinant <= 0) where it is
    applied: over the reference points' ``bounds``, the calibration's ``image_size`` frame,
    and the frame of ``size = (width, height)`` px if given (the image it is applied to).

    ``boxes`` adds regions ``((x0, y0, x1, y1), description)`` in undistorted coordinates
    (an output region of a correction).  The model is evaluated on a :data:`CHECK_GRID` x
    :data:`CHECK_GRID` grid over each region.
    Raises ``error`` naming the first bad point: :class:`InputFileError` (the default) for
    a calibration read from a file, :class:`DataError` for a model given as a value.

    ``folds_beyond_bounds``: whether the model may fold over (finite, determinant <= 0) in a
    frame or box beyond the reference points' bounds.  None (the default): when the
    calibration has ``bounds`` and an ``error_model``, whose predicted error is unbounded
    where the map folds (:func:`oapcal.uncertainty.predicted_error`), so that a correction's
    trust region ends before any fold; a model without them must not fold anywhere it is
    applied.  Within the bounds, where the landmarks are, a fold is always refused
    (:func:`folds_beyond_bounds` says where a kept fold is); ``check_bounds=False`` leaves
    the bounds themselves unchecked (checked already when the calibration was fitted or read)
    and uses them only to place a fold.

    >>> from oapcal.model import params_from_dict
    >>> check_model_region(params_from_dict({"k1": 1e-7}), (640, 480))
    >>> try:
    ...     check_model_region(params_from_dict({"k1": -1e-5}), (640, 480), source="c.json")
    ... except InputFileError as e:
    ...     print(str(e)[:60])
    c.json: the model folds over at (x, y) = (189.703, 0) inside
    """
    bounds = getattr(calibration, "bounds", None)
    if folds_beyond_bounds is None:
        folds_beyond_bounds = _has_trust_region(calibration)
    for xy, finite, det, what, is_bounds in _region_grids(calibration, size, boxes, check_bounds):
        bad = ~(finite & np.isfinite(det) & (det > 0))
        if folds_beyond_bounds and not is_bounds:
            bad &= ~(finite & np.isfinite(det) & ~_inside(xy, bounds))  # a fold beyond the bounds
        if bad.any():
            i = int(np.argmax(bad))
            x, y = xy[i]
            how = "folds over" if np.isfinite(det[i]) else "is not finite"
            fix = "refit with more points or a smaller model"
            if np.isfinite(det[i]) and not is_bounds and _has_trust_region(calibration):
                fix = (f"it lies beyond the reference points' bounds: a correction written only within its "
                       f"trust region leaves it out, or {fix}")  # fmt: skip
            raise error(f"{source}: the model {how} at (x, y) = ({x:.6g}, {y:.6g}) inside the {what}; "
                        f"it cannot correct there ({fix})")  # fmt: skip


def folds_beyond_bounds(calibration, size: tuple[int, int] | None = None) -> dict | None:
    """Where a model that :func:`check_model_region` keeps folds over beyond its reference
    points' bounds: ``{"point": (x, y), "fraction": f, "region": description}`` of the first
    frame with a fold (``f`` its share of the check's grid there), or None where it folds
    nowhere in its ``image_size`` frame and the frame of ``size``."""
    for xy, finite, det, what, is_bounds in _region_grids(calibration, size, ()):
        folded = finite & np.isfinite(det) & (det <= 0)
        if not is_bounds and folded.any():
            x, y = xy[np.argmax(folded)]
            return {"point": (float(x), float(y)), "fraction": float(folded.mean()), "region": what}
    return None


def _has_trust_region(calibration) -> bool:
    """Whether a correction by ``calibration`` has a trust region that ends before a fold
    (:func:`check_model_region`): it has reference bounds and an error model."""
    bounds, error_model = getattr(calibration, "bounds", None), getattr(calibration, "error_model", None)
    return bounds is not None and error_model is not None


def _inside(xy: np.ndarray, bounds) -> np.ndarray:
    """Whether each point ``(N, 2)`` lies within ``bounds = (x0, y0, x1, y1)`` (None: none)."""
    if bounds is None:
        return np.zeros(len(xy), bool)
    x0, y0, x1, y1 = (float(b) for b in bounds)
    return (xy[:, 0] >= x0) & (xy[:, 0] <= x1) & (xy[:, 1] >= y0) & (xy[:, 1] <= y1)


def _region_grids(calibration, size, boxes, check_bounds: bool = True):
    """The regions :func:`check_model_region` checks, each as ``(xy, finite, det,
    description, is_bounds)`` on its :data:`CHECK_GRID` x :data:`CHECK_GRID` grid (the
    reference points' bounds first, unless not ``check_bounds``)."""
    params = np.asarray(getattr(calibration, "params", calibration), float)
    carried = getattr(calibration, "family", None)  # a Model's or a record's; None: by length
    family = family_of(params, None if carried is None else family_named(carried))
    closed_form = family.code in _EQ1_CODES and params.shape == (family.n_params,)
    evaluate = _eq1_region_check if closed_form else functools.partial(_kernel_region_check, family=family)
    regions = []
    bounds = getattr(calibration, "bounds", None)
    if bounds is not None and check_bounds:
        regions.append((tuple(float(b) for b in bounds), "reference points' bounds", True))
    for frame in (getattr(calibration, "image_size", None), size):
        if frame is not None:
            w, h = int(frame[0]), int(frame[1])
            box = (0.0, 0.0, float(max(w - 1, 1)), float(max(h - 1, 1)))
            regions.append((box, f"{w}x{h} px image", False))
    regions.extend((box, what, False) for box, what in boxes)
    with np.errstate(all="ignore"):
        for (x0, y0, x1, y1), what, is_bounds in regions:
            gx, gy = np.meshgrid(np.linspace(x0, x1, CHECK_GRID), np.linspace(y0, y1, CHECK_GRID))
            xy = np.stack([gx.ravel(), gy.ravel()], -1)
            finite, det = evaluate(xy, params)
            yield xy, finite, det, what, is_bounds


def check_fit_usable(
    calibration, source: str | None = None, *, sign: bool = True, folds_beyond_bounds: bool | None = None
) -> None:
    """Refuse a fit that gives no usable model, raising :class:`UnusableFitError`: its
    parameters are not all finite; it needs ``m <= 0`` (with ``sign``; Eq. (1) of a target
    turned by 180 deg, which a calibration expresses as a rotation and a calibration file
    cannot hold); or its model is not finite or folds over on its own region (the reference
    points' bounds and its ``image_size`` frame: :func:`check_model_region`).  ``source``
    names the points (default ``calibration.source``).  :func:`calibrate` applies it to
    every fit; ``oapcal fit`` maps the error to exit code 3."""
    source = source or getattr(calibration, "source", None) or "the point data"
    params = np.asarray(calibration.params, float)
    if not np.isfinite(params).all():
        raise UnusableFitError(
            f"{source}: the fit gave non-finite parameters (the points do not determine the model)",
            "Check the points, or fit a smaller model",
            code="non_finite",
            param="model",
        )
    names = calibration.family.param_names
    if sign and "m" in names and params[names.index("m")] <= 0:
        raise UnusableFitError(
            f"{source}: the fit gave m = {params[names.index('m')]:.4g} <= 0: the reference points "
            "are turned by about 180 deg against the distorted ones, which a calibration expresses as "
            "a rotation",
            "Fit the rotation (rotation 'auto', the default, or 'fit')",
            code="negative_m",
            param="rotation",
        )
    try:
        check_model_region(calibration, source=source, folds_beyond_bounds=folds_beyond_bounds)
    except InputFileError as exc:
        raise UnusableFitError(str(exc), code="region") from None


# calibrate's keywords are the public API's options (a contract: docs/architecture.md);
# each is one documented choice of the caller, so they stay separate keywords.


#: Family codes of Eq. (1) and Eq. (1) with the target's rotation (``ModelFamily.code``),
#: whose region check evaluates the closed form in NumPy (:func:`_eq1_region_check`).
_EQ1_CODES = tuple(eq1_closed_form.FAMILY_PARAMS)


def _kernel_region_check(xy: np.ndarray, params: np.ndarray, family=None):
    """Whether the model is finite at each point ``(N, 2)``, and its Jacobian determinant,
    through the compiled kernels (any family)."""
    from oapcal.model import distort, jacobian_determinant

    det = jacobian_determinant(xy, params, family=family)
    return np.isfinite(distort(xy, params, family=family)).all(-1), det


#: :func:`_kernel_region_check` for Eq. (1) (13 parameters) and Eq. (1) after the target's
#: rotation (14), in NumPy: the closed form of :mod:`oapcal.eq1_closed_form`.  Why not the
#: kernels: loading them costs a command about 0.3-0.8 s before its first frame (importing
#: Numba, loading the cached machine code), while the closed form on the check's grids takes
#: about a millisecond; a test checks it against the kernels.
_eq1_region_check = eq1_closed_form.region_check


def calibrate(
    xy_u,
    xy_d,
    model="paper",
    *,
    init=DEFAULT_INIT,
    normalization: str = "none",
    um_per_px: float | None = None,
    image_size: tuple[int, int] | None = None,
    name: str | None = None,
    source: str | None = None,
    relay_design: dict | None = None,
    rotation: str = "auto",
    priors: dict | None = None,
    error_model: bool = True,
    check: bool = True,
    **fit_options,
) -> Calibration:
    """Fit ``model`` to reference points ``xy_u`` and distorted points ``xy_d`` ``(N, 2)``.

    ``model`` is any spec of :func:`oapcal.fitting.fit` (Eq. 1, ``"...+rotation"``, or a
    relay mask with ``init`` its design's vector and ``relay_design`` the design as a dict,
    kept in the record; a relay model is fitted in px, without normalization).

    ``normalization`` is ``"none"`` or ``"experiment"`` (:mod:`oapcal.normalize`: only the
    reference points change, so the model stays in the camera's px); ``"grid"`` is refused
    (:class:`~oapcal.errors.DataError`), because it rescales the distorted points too and
    the model would not correct the camera's pixels (it is for :func:`oapcal.select_models`).
    ``um_per_px`` is the object-space size of one unit of the reference points *as given*;
    with ``normalization="experiment"`` it is converted through the normalization scale.
    The residual statistics are those of :func:`oapcal.stats.correction_residuals`.

    ``rotation`` applies to an Eq. (1) model given without ``+rotation`` (with or without the
    perspective terms: ``"paper+tilt"`` may become ``"paper+rotation+tilt"``): ``"auto"`` (the
    default) fits it both without and with the target's in-plane rotation and keeps the
    rotation when Eq. (1) alone does not converge or needs ``m < 0`` (a target turned by
    180 deg) and the rotation converges, or when the
    rotation lowers AICc by more than :data:`ROTATION_EVIDENCE_AICC` (a turned target is
    otherwise absorbed into a distortion centre that runs away, x_off ~ 1e4 px, and the fit
    hits the iteration cap); when neither converges, it fits the perspective terms as well
    (``...+rotation+tilt``, :func:`_with_tilt`: a target seen at an angle) and keeps them
    when they converge; the record's ``notes`` say so.  ``"fit"`` always adds the
    rotation, ``"none"`` never (Eq. (1) as given: a turned target then keeps ``m < 0``).

    ``check`` (default True) refuses a fit that gives no usable model
    (:func:`check_fit_usable`: :class:`UnusableFitError`; with ``rotation="none"`` the
    sign of ``m`` is left as fitted); False returns the record whatever it holds.

    ``priors`` is recorded only (the priors of a maximum a posteriori relay fit, whose rows
    come in ``fit_options["prior"]``: :func:`oapcal.optics.relay_model.calibrate_relay`).

    ``error_model`` (default True) also measures the model floor and the extrapolation
    error on the landmarks (:func:`oapcal.error_model.estimate_error_model`: a few refits).
    """
    um_per_px, image_size = _check_arguments(normalization, relay_design, um_per_px, image_size, rotation)
    norm = normalize(normalization, xy_u, xy_d)
    result, notes = _fit_model(norm, model, init, rotation if relay_design is None else "none", fit_options)
    scale = None if um_per_px is None else float(um_per_px) / norm.scale_u
    cal = Calibration(
        free=result.free,
        params=np.array(result.params),
        stderr=np.array(result.stderr),
        covariance=np.array(result.covariance),
        fit=FitSummary.from_result(
            result,
            n_points=len(norm.xy_u),
            init=init if isinstance(init, str) else "user",
            normalize=normalization,
            aicc_corrected=_aicc_corrected(result, norm),
        ),  # fmt: skip
        residuals=correction_residuals(result.model, norm.xy_u, norm.xy_d, scale),
        um_per_px=scale,
        image_size=image_size,
        **calibrated_region(norm.xy_u),
        name=name,
        source=source,
        relay_design=relay_design,
        notes=notes,
        priors=priors,
        family=result.family,
    )
    measured = error_model and result.converged  # an error model, whose trust region ends before a fold
    if check:
        check_fit_usable(
            cal, source, sign=rotation != "none" or relay_design is not None, folds_beyond_bounds=measured
        )
    if measured:
        from oapcal.error_model import estimate_error_model

        errors = estimate_error_model(norm.xy_u, norm.xy_d, result.model, **fit_options)
        cal = dataclasses.replace(cal, error_model=errors)
        fold = folds_beyond_bounds(cal)
        if fold is not None:
            cal = dataclasses.replace(cal, notes=(*cal.notes, fold_note(fold)))
    return cal


class Note(str):
    """A note of :func:`calibrate` (:attr:`Calibration.notes`): its text, and ``kind``, what
    it is about (``"rotation"``: the rotation policy fitted the target's turn too;
    ``"fold"``: the model folds over beyond its landmarks; the rotation policy's choice of a
    tilt is a ``"rotation"`` note too), so that a caller acts on the
    kind, not on the words.  A ``str``, so printing and JSON see the text alone."""

    kind: str

    def __new__(cls, text: str, kind: str):
        note = super().__new__(cls, text)
        note.kind = kind
        return note


def fold_note(fold: dict) -> Note:
    """The note of a calibration that folds over beyond its landmarks (:func:`folds_beyond_bounds`)."""
    x, y = fold["point"]
    return Note(
        f"the model folds over beyond the reference points' bounds, at (x, y) = ({x:.6g}, {y:.6g}) "
        f"and over {100 * fold['fraction']:.1f} % of the {fold['region']}: it is extrapolated there "
        "(its predicted error is unbounded), so a correction's trust region ends before it; "
        "a smaller model may correct the whole frame",
        "fold",
    )


def _check_arguments(normalization, relay_design, um_per_px, image_size, rotation):
    """``calibrate``'s arguments checked: ``(um_per_px, image_size)`` as numbers."""
    if relay_design is not None and normalization not in (None, "none"):
        raise DataError(
            f"normalization {normalization!r} cannot be used with the relay model: it fits the "
            "target's pose itself, in px (use normalization 'none')"
        )
    if normalization == "grid":
        raise DataError(
            "normalization 'grid' rescales the distorted points as well, so the model would not "
            "correct the camera's px: use normalization 'none' or 'experiment' (grid is for select_models)",
            param="normalization",
        )
    if um_per_px is not None:
        um_per_px = validate.positive(um_per_px, "um_per_px")
    if image_size is not None:
        image_size = tuple(int(v) for v in validate.image_size(image_size))
    if rotation not in ROTATION_CHOICES:
        choices = ", ".join(ROTATION_CHOICES)
        raise DataError(f"rotation must be one of {choices}, got {rotation!r}", param="rotation")
    return um_per_px, image_size


def _fit_model(norm, model, init, rotation: str, fit_options):
    """The fit of ``model`` to the normalized points, with the rotation policy of
    :func:`calibrate` for an Eq. (1) model: ``(FitResult, notes)``."""
    from oapcal.fitting import fit

    result = fit(norm.xy_u, norm.xy_d, model, init=init, **fit_options)
    unturned_tilt = result.family is BROWN_CONRADY_TILT and not result.mask[N_PARAMS]  # "paper+tilt"
    if rotation != "none" and (result.family is BROWN_CONRADY or unturned_tilt):
        return _with_rotation(result, norm, model, init, rotation, fit_options)
    return result, ()


def _aicc_corrected(result, norm) -> float:
    """AICc of the residuals after correction, ``undistort(xy_d) - xy_u`` (as model
    selection scores a model: :func:`oapcal.select.score_models`); NaN when the inverse
    fails at a point."""
    from oapcal.model import correction_errors
    from oapcal.stats import information_criteria

    if not np.isfinite(result.params).all():
        return float("nan")
    rss, _, n_bad, _ = correction_errors(result.params[None], norm.xy_d, norm.xy_u, family=result.family)
    k = result.k if result.k_eff is None else result.k_eff
    rss = float(rss[0]) if n_bad[0] == 0 else float("nan")
    return float(information_criteria(rss, 2 * len(norm.xy_u), k).aicc)


def calibrated_region(xy_u) -> dict:
    """The calibrated region of the reference points ``xy_u`` ``(N, 2)``, as the keyword
    arguments of :class:`Calibration`: ``bounds`` and the convex ``hull`` (None when the
    points are collinear or too few); of :func:`calibrate` and of a self-calibration."""
    from scipy.spatial import ConvexHull, QhullError

    try:
        hull = xy_u[ConvexHull(xy_u).vertices]
    except (QhullError, ValueError):
        hull = None
    lo = xy_u.min(axis=0)
    hi = xy_u.max(axis=0)
    return {"bounds": (float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])), "hull": hull}


def _with_rotation(plain, norm, model, init, rotation: str, fit_options):
    """``calibrate``'s choice between Eq. (1) ``plain`` and Eq. (1) with the rotation."""
    from oapcal.fitting import fit
    from oapcal.model import names_from_mask, parse_any_model

    mask = parse_any_model(model)
    tilt = plain.family is BROWN_CONRADY_TILT  # the rotation is its entry N_PARAMS
    mask = np.concatenate([mask[:N_PARAMS], [True], mask[N_PARAMS + 1 :]])
    turned = fit(norm.xy_u, norm.xy_d, mask, init=init, **fit_options)
    base = model.strip() if isinstance(model, str) else ",".join(names_from_mask(mask[:N_PARAMS]))
    base = base.removesuffix(TILT_SUFFIX) if tilt else base
    spec = base + ROTATION_SUFFIX + (TILT_SUFFIX if tilt else "")
    angle = f"{turned.params[N_PARAMS]:+.3g} deg"
    if rotation == "fit":
        return turned, (Note(f"fitted {spec} (the target's rotation, {angle})", "rotation"),)
    if not turned.converged:
        if plain.converged or tilt or rotation != "auto":
            return plain, ()
        return _with_tilt(plain, norm, mask, base, init, fit_options)
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
    return turned, (Note(f"the target is turned by {angle}: fitted {spec}, because {why}", "rotation"),)


def _with_tilt(plain, norm, mask, base: str, init, fit_options):
    """``calibrate``'s last resort when neither Eq. (1) nor Eq. (1) with the rotation
    converges: the perspective terms too (``...+rotation+tilt``), kept when they converge.
    Why: a view of the target from an angle (a tilted camera or target) holds a keystone that
    Eq. (1) can only mimic with a distortion centre running away to ~1e4 px, so its fit hits
    the iteration cap (measured: the 552 corners of the real ``whole_target.png``, a photo of
    the whole target; ``paper+rotation+tilt`` converges in 68 iterations to 0.33 px mean,
    against 0.37 px unconverged)."""
    from oapcal.fitting import fit

    tilted_mask = np.concatenate([mask[:N_PARAMS], [True, True, True]])
    tilted = fit(norm.xy_u, norm.xy_d, tilted_mask, init=init, **fit_options)
    if not tilted.converged:
        return plain, ()
    spec = base + ROTATION_SUFFIX + TILT_SUFFIX
    cause = plain.message.removeprefix("not converged: ")
    why = f"Eq. (1) alone and with the rotation did not converge ({cause})"
    return tilted, (Note(f"the target is seen at an angle: fitted {spec}, because {why}", "rotation"),)
