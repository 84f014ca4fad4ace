"""Model selection over all 4,096 subsets of Eq. (1) and cross-validation.

Selection (:func:`select_models`)
---------------------------------
Every model (``m`` free, each of the other 12 parameters free or fixed at 0) is fitted
from the same starting values; the observed distorted points are then corrected through
the fitted model's inverse (:func:`oapcal.model.undistort`) and the corrected points are
compared with the reference points.  With ``d_i`` the corrected-minus-reference vector of
point ``i`` over ``M`` points:

* ``RSS = sum_i |d_i|^2`` (x and y residuals), ``n = 2 M``, ``K = k + 1`` where ``k`` is
  the number of free parameters (``m`` included) and the one is the error variance;
* ``AIC = n ln(RSS / n) + 2 K``, ``AICc = AIC + 2 K (K + 1) / (n - K - 1)``
  (:func:`oapcal.stats.information_criteria`);
* ``dAICc = AICc - min AICc`` and the Akaike weight ``w = exp(-dAICc / 2) / sum exp(...)``
  over the valid models.

A model is *valid* when its fit converged, its inverse converged at every point (and does
not fold over there) and ``n - K - 1 > 0``.  Invalid models are ranked after all valid
ones, each with its reason; none is dropped.

The subsampling robustness test lives in :mod:`oapcal.subsampling`; its names
(:func:`robustness`, :class:`Robustness`, :class:`ModelRobustness`, :data:`REASONS`,
:func:`hull_grid`) are importable from here too.

>>> from oapcal.synthetic import synthetic_pairs
>>> data = synthetic_pairs(seed=3)
>>> sel = select_models(data.xy_u, data.xy_d, init="pixel")
>>> len(sel.models), sel.models[0].valid, sel.models[0].delta_aicc
(4096, True, 0.0)
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from oapcal import validate
from oapcal.errors import DataError, ModelSpecError
from oapcal.fitting import DEFAULT_INIT, STATUS_MESSAGES, fit_batch, initial_params_many
from oapcal.model import (
    N_OPTIONAL,
    N_PARAMS,
    PARAM_NAMES,
    ModelFamily,
    all_masks,
    bits_from_mask,
    correction_errors,
    parse_model,
    undistort,
)
from oapcal.normalize import normalize
from oapcal.records import finite_or_none, nan_if_none
from oapcal.stats import information_criteria
from oapcal.subsampling import REASONS, ModelRobustness, Robustness, hull_grid, robustness  # noqa: F401 (re-exported)

#: Codes of the reasons a model of a selection is invalid (``ModelScore.reason_code``).
INVALID_REASONS = ("not_converged", "too_few_residuals", "inverse_failed", "aicc_not_finite")
Progress = Callable[[int, int], None]


# ------------------------------------------------------------------------ selection


@dataclass(frozen=True)
class ModelScore:
    """One model of a selection.

    ``k`` is the number of free parameters (``m`` included; AICc uses ``K = k + 1``);
    ``rss`` the sum of squared corrected-minus-reference residuals in the coordinates of
    the fit (after normalization); ``mean_error`` the mean Euclidean corrected error in
    the units of the reference points as given; ``reason`` is empty for a valid model,
    else a message whose kind is ``reason_code`` (one of :data:`INVALID_REASONS`).
    ``cv_mean_error`` is the cross-validated mean error on held-out points (same units),
    ``None`` unless cross-validation ran for this model.

    Two AICc values describe the model: ``aicc`` (also named ``aicc_corrected``), of the
    residuals after correction, by which the selection ranks; and ``aicc_forward``, of the
    forward residuals the fit minimises (what :attr:`oapcal.calibration.FitSummary.aicc`
    holds for a fit of the same model; NaN when not known, e.g. in older files).
    """

    bits: int
    free: tuple[str, ...]
    k: int
    aicc: float
    delta_aicc: float
    weight: float
    rss: float
    mean_error: float
    valid: bool
    reason: str
    fit_status: int
    cv_mean_error: float | None = None
    cv_failed: int = 0
    reason_code: str = ""
    aicc_forward: float = float("nan")

    @property
    def aicc_corrected(self) -> float:
        """AICc of the residuals after correction (``aicc``, named for what it scores)."""
        return self.aicc

    def to_dict(self) -> dict:
        """The JSON entry: ``free k aicc delta_aicc weight rss valid reason`` and extras."""
        out = {
            "free": list(self.free),
            "k": self.k,
            "aicc": finite_or_none(self.aicc),
            "aicc_corrected": finite_or_none(self.aicc),
            "aicc_forward": finite_or_none(self.aicc_forward),
            "delta_aicc": finite_or_none(self.delta_aicc),
            "weight": finite_or_none(self.weight),
            "rss": finite_or_none(self.rss),
            "valid": self.valid,
            "reason": self.reason,
            "reason_code": self.reason_code,
            "fit_status": self.fit_status,
            "mean_error": finite_or_none(self.mean_error),
            "bits": self.bits,
        }
        if self.cv_mean_error is not None or self.cv_failed:
            out["cv_mean_error"] = finite_or_none(self.cv_mean_error)
            out["cv_failed"] = self.cv_failed
        return out

    @classmethod
    def from_dict(cls, m: dict) -> ModelScore:
        """A model of a selection from its JSON entry (:meth:`to_dict`; ``null`` -> NaN;
        entries written before ``fit_status``, ``cv_*`` or ``aicc_forward`` existed load
        with their defaults)."""
        return cls(
            bits=int(m["bits"]),
            free=tuple(m["free"]),
            k=int(m["k"]),
            aicc=nan_if_none(m["aicc"]),
            delta_aicc=nan_if_none(m["delta_aicc"]),
            weight=nan_if_none(m["weight"]),
            rss=nan_if_none(m["rss"]),
            mean_error=nan_if_none(m["mean_error"]),
            valid=bool(m["valid"]),
            reason=m["reason"],
            fit_status=int(m.get("fit_status", 1 if m["valid"] else 0)),
            cv_mean_error=None if "cv_mean_error" not in m else nan_if_none(m["cv_mean_error"]),
            cv_failed=int(m.get("cv_failed", 0)),
            reason_code=m["reason_code"],
            aicc_forward=nan_if_none(m.get("aicc_forward")),
        )


@dataclass(frozen=True)
class Selection:
    """All models of a selection, best first (valid by AICc, then invalid ones)."""

    n_points: int
    normalization: str
    init: str
    models: tuple[ModelScore, ...]
    cv_folds: int | None = None

    @property
    def best(self) -> ModelScore:
        return self.models[0]

    @property
    def n_valid(self) -> int:
        return sum(m.valid for m in self.models)

    def rank_of(self, model) -> int:
        """1-based rank of a model (a spec for :func:`oapcal.model.parse_model`)."""
        bits = int(bits_from_mask(parse_model(model)))
        return next(i for i, m in enumerate(self.models, 1) if m.bits == bits)

    def to_dict(self) -> dict:
        """The JSON object: ``n_points`` and ``models`` (all, best first), plus settings."""
        return {
            "n_points": self.n_points,
            "normalize": self.normalization,
            "init": self.init,
            "cv_folds": self.cv_folds,
            "models": [m.to_dict() for m in self.models],
        }


#: The terms that place the distortion in the camera's frame: in camera px the origin is the
#: image corner, not the distortion centre, so a model used there keeps these free whatever
#: a selection on centred points chose (the paper likewise added x_off to its choice).
FRAME_TERMS = ("x_off", "y_off", "c_x", "c_y")


def with_frame_terms(free) -> tuple[str, ...]:
    """The free parameters ``free`` (names, a :class:`ModelScore` or a :class:`Selection`,
    whose best model is taken) with :data:`FRAME_TERMS` added, in the order of Eq. (1):
    the model ``oapcal demo`` and napari's *Fit & inspect* fit in camera px after a
    selection.

    >>> with_frame_terms(("k1", "m"))
    ('k1', 'x_off', 'y_off', 'c_x', 'c_y', 'm')
    """
    if isinstance(free, Selection):
        free = free.best
    if isinstance(free, ModelScore):
        free = free.free
    return tuple(n for n in PARAM_NAMES if n in free or n in FRAME_TERMS)


@functools.cache
def _all_model_names() -> list[tuple[str, ...]]:
    """The free parameters of every Eq. (1) model, indexed by its bits: the models with bit
    ``i`` set are those below ``2**i`` with ``PARAM_NAMES[i]`` added (built in 1 ms; one
    mask per model took 65 ms of a whole ``oapcal select``)."""
    names: list[tuple[str, ...]] = [()]
    for name in PARAM_NAMES[:N_OPTIONAL]:
        names += [n + (name,) for n in names]
    return [n + PARAM_NAMES[N_OPTIONAL:] for n in names]


def _names_of_bits(bits: int) -> tuple[str, ...]:
    """``names_from_mask(mask_from_bits(bits))`` without building the mask."""
    return _all_model_names()[bits]


def _starts(init, xy_u, xy_d, masks, family=None) -> np.ndarray:
    """Starting values ``(B, P)``: ``init`` itself when it is a ``(B, P)`` array (a family
    that starts from a design, e.g. the relay), else :func:`initial_params_many`."""
    if isinstance(init, np.ndarray) and init.ndim == 2:
        return np.broadcast_to(init, masks.shape).astype(float)
    return initial_params_many(init, xy_u, xy_d, masks, family=family)


def score_models(
    xy_u,
    xy_d,
    masks,
    init=DEFAULT_INIT,
    *,
    max_iter: int = 200,
    progress: Progress | None = None,
    prior=None,
    family: ModelFamily | None = None,
):
    """Fit and score the models ``masks (B, P)`` (any family: ``family``, or without it the
    built-in family of ``P`` entries, and ``init`` is then its ``(B, P)`` starts) on points
    already normalized.

    Returns a dict of arrays over the B models: ``params``, ``status``, ``rss`` (corrected
    residuals), ``mean_error``, ``n_bad`` (points whose inverse failed), ``n_folded``,
    ``aicc`` (of the corrected residuals) and ``aicc_forward`` (of the forward residuals
    the fits minimised).  Works in chunks so that ``progress(done, total)`` can be reported.  ``prior``
    (:func:`oapcal.fitting.fit_batch`'s, ``(B, P)`` arrays) makes each fit a maximum a
    posteriori one, and AICc then counts its effective number of parameters (``k_eff``).
    """
    xy_u = np.asarray(xy_u, float)
    xy_d = np.asarray(xy_d, float)
    masks = np.atleast_2d(np.asarray(masks, bool))
    p0 = _starts(init, xy_u, xy_d, masks, family)
    n_models = len(masks)
    chunk = max(1, min(n_models, 1024 if progress is not None else n_models))  # chunks only to report
    out = {
        "params": np.zeros(masks.shape),
        "status": np.zeros(n_models, dtype=np.int64),
        "rss": np.full(n_models, np.nan),
        "mean_error": np.full(n_models, np.nan),
        "n_bad": np.zeros(n_models, dtype=np.int64),
        "n_folded": np.zeros(n_models, dtype=np.int64),
        "rss_forward": np.full(n_models, np.nan),
    }
    k_free = masks.sum(axis=1).astype(float)
    for start in range(0, n_models, chunk):
        sl = slice(start, min(start + chunk, n_models))
        if prior is None:
            fits = fit_batch(xy_u, xy_d, masks[sl], p0[sl], covariance=False, max_iter=max_iter,
                             family=family)  # fmt: skip
        else:
            part = tuple(np.broadcast_to(a, masks.shape)[sl] for a in prior)
            fits = fit_batch(xy_u, xy_d, masks[sl], p0[sl], covariance=False, max_iter=max_iter, prior=part,
                             family=family)  # fmt: skip
            k_free[sl] = fits.k_eff
        rss, mean_dist, n_bad, n_folded = correction_errors(fits.params, xy_d, xy_u, family=fits.family)
        all_ok = n_bad == 0
        out["rss"][sl] = np.where(all_ok, rss, np.nan)
        out["mean_error"][sl] = np.where(all_ok, mean_dist, np.nan)
        out["params"][sl] = fits.params
        out["status"][sl] = fits.status
        out["n_bad"][sl] = n_bad
        out["n_folded"][sl] = n_folded
        out["rss_forward"][sl] = fits.rss
        if progress is not None:
            progress(sl.stop, n_models)
    n = 2 * len(xy_u)
    out["aicc"] = np.asarray(information_criteria(out["rss"], n, k_free).aicc, dtype=float)
    out["aicc_forward"] = np.asarray(
        information_criteria(out.pop("rss_forward"), n, k_free).aicc, dtype=float
    )
    return out


def invalid_reasons(scores: dict, k: np.ndarray, n_points: int) -> tuple[list[str], list[str]]:
    """The code (one of :data:`INVALID_REASONS`, ``""`` for a valid model) and message of
    each model scored by :func:`score_models` (``k (B,)`` free parameters, ``n_points``
    point pairs): the first of fit not converged, too few residuals for AICc, inverse
    failed, AICc not finite that applies."""
    dofs = (2 * n_points - np.asarray(k) - 2).tolist()  # n - K - 1 with K = k + 1
    codes, reasons = [], []
    for i, (status, dof) in enumerate(zip(scores["status"].tolist(), dofs)):
        if status <= 0:
            why = STATUS_MESSAGES[status].removeprefix("not converged: ")
            code, reason = "not_converged", f"fit did not converge ({why})"
        elif dof <= 0:
            code, reason = "too_few_residuals", f"too few residuals for AICc: n - K - 1 = {dof} <= 0"
        elif scores["n_bad"][i]:
            code = "inverse_failed"
            reason = (
                f"inverse failed at {scores['n_bad'][i]} of {n_points} points "
                f"({scores['n_folded'][i]} where the fitted map folds over)"
            )
        elif not np.isfinite(scores["aicc"][i]):
            code, reason = "aicc_not_finite", f"AICc is not finite (RSS = {scores['rss'][i]:.3g})"
        else:
            code, reason = "", ""
        codes.append(code)
        reasons.append(reason)
    return codes, reasons


def check_masks(masks) -> np.ndarray:
    """Models given as masks: a ``(13,)`` mask or a ``(B, 13)`` array of them (B >= 1) of
    booleans or 0/1, each with ``m`` (the last entry) free; as a ``(B, 13)`` bool array.
    Anything else raises :class:`~oapcal.errors.ModelSpecError` naming ``masks``."""
    how = "give a (B, 13) array of booleans (or 0/1), one row per model, m (the last) always True"
    try:
        arr = np.atleast_2d(np.asarray(masks))
    except (TypeError, ValueError):
        raise ModelSpecError(f"masks must be an array of booleans; {how}", param="masks") from None
    if arr.ndim != 2 or arr.shape[1] != N_PARAMS or arr.shape[0] == 0:
        raise ModelSpecError(
            f"masks has shape {np.shape(masks)}, not (B, {N_PARAMS}) with B >= 1; {how}", param="masks"
        )
    if arr.dtype.kind not in "biu" or not np.isin(arr, (0, 1)).all():
        raise ModelSpecError(f"masks holds values other than True/False (or 1/0); {how}", param="masks")
    arr = arr.astype(bool)
    if not arr[:, -1].all():
        row = int(np.flatnonzero(~arr[:, -1])[0])
        raise ModelSpecError(f"masks row {row} fixes m; m is free in every model: {how}", param="masks")
    return arr


# select_models' keywords are the public API's options (a contract), one per choice.
def select_models(
    xy_u,
    xy_d,
    *,
    normalization: str = "none",
    init=DEFAULT_INIT,
    masks: np.ndarray | None = None,
    cv: int | None = None,
    cv_top: int = 10,
    seed: int = 0,
    max_iter: int = 200,
    progress: Progress | None = None,
) -> Selection:
    """Rank models by AICc of the corrected points (module docstring).

    ``xy_u``, ``xy_d`` are the reference and distorted points ``(N, 2)`` as given;
    ``normalization`` is applied first (``none``, ``experiment`` or ``grid``, see
    :mod:`oapcal.normalize`).  ``masks`` defaults to all 4,096 models.  ``init`` is the
    start of every fit (:func:`oapcal.fitting.initial_params`; default
    :data:`~oapcal.fitting.DEFAULT_INIT`, the data's own centre and scale, which on the
    paper's normalized grids is its zero start).  With ``cv = K``, the best ``cv_top``
    models also get the K-fold cross-validated mean corrected error (:func:`cross_validate`, folds drawn with
    ``seed``).
    """
    norm = normalize(normalization, xy_u, xy_d)
    u, d = norm.xy_u, norm.xy_d
    masks = all_masks() if masks is None else check_masks(masks)
    seed = validate.seed(seed)
    scores = score_models(u, d, masks, init, max_iter=max_iter, progress=progress)
    k = masks.sum(axis=1)
    codes, reasons = invalid_reasons(scores, k, len(u))
    valid = np.array([c == "" for c in codes])
    order, delta, weight = _rank(scores["aicc"], valid, k, bits_from_mask(masks))
    cv_err: dict[int, tuple[float, int]] = {}
    if cv is not None:
        top = order[: max(0, cv_top)]
        errs, failed = cross_validate(u, d, masks[top], folds=cv, init=init, seed=seed, max_iter=max_iter)
        for i, e, f in zip(top, errs, failed):
            cv_err[int(i)] = (float(e) / norm.scale_u, int(f))
    columns = {**scores, "k": k, "valid": valid, "delta": delta, "weight": weight,
               "bits": bits_from_mask(masks), "mean_error": scores["mean_error"] / norm.scale_u}  # fmt: skip
    models = _model_scores(columns, order, codes, reasons, cv_err)
    init_name = init if isinstance(init, str) else "user"
    return Selection(len(u), normalization or "none", init_name, models, cv)


def _rank(aicc, valid, k, bits):
    """``(order, delta_aicc, weight)`` of a selection: valid models by AICc (ties: fewer
    parameters, then bits), invalid ones after them ordered by their (possibly NaN) AICc,
    then bits; dAICc and the Akaike weights over the valid models (NaN for the others)."""
    order_key = np.where(valid, aicc, np.inf)
    inv_key = np.where(np.isfinite(aicc) & ~valid, aicc, np.inf)
    order = np.lexsort((bits, k, inv_key, order_key, ~valid))
    best = aicc[valid].min() if valid.any() else np.nan
    delta = np.where(valid, aicc - best, np.nan)
    weight = np.where(valid, np.exp(-0.5 * np.where(valid, delta, 0.0)), 0.0)
    weight = weight / weight.sum() if valid.any() else np.full(len(aicc), np.nan)
    return order, delta, np.where(valid, weight, np.nan)


def _model_scores(columns: dict, order, codes, reasons, cv_err) -> tuple[ModelScore, ...]:
    """The :class:`ModelScore` of every model, in ``order``, from the arrays ``columns``."""
    names = ("bits", "k", "aicc", "delta", "weight", "rss", "mean_error", "valid", "status", "aicc_forward")
    # Plain Python values once per column (faster than converting 4,096 x 12 NumPy scalars).
    cols = zip(*(np.asarray(columns[n])[order].tolist() for n in names), order.tolist())
    return tuple(
        ModelScore(
            bits=b,
            free=_names_of_bits(b),
            k=kk,
            aicc=a,
            delta_aicc=da,
            weight=w,
            rss=r,
            mean_error=me,
            valid=v,
            reason=reasons[i],
            fit_status=st,
            reason_code=codes[i],
            cv_mean_error=cv_err[i][0] if i in cv_err else None,
            cv_failed=cv_err[i][1] if i in cv_err else 0,
            aicc_forward=af,
        )
        for b, kk, a, da, w, r, me, v, st, af, i in cols
    )


def cross_validate(
    xy_u,
    xy_d,
    masks,
    *,
    folds: int = 5,
    init=DEFAULT_INIT,
    seed: int = 0,
    max_iter: int = 200,
    prior=None,
    family: ModelFamily | None = None,
):
    """K-fold cross-validated mean corrected error of each model ``masks (B, P)`` (``init``
    as in :func:`score_models`).

    The points are shuffled with ``seed`` and split into ``folds`` nearly equal folds;
    each model is fitted (from ``init``) to all folds but one and the held-out fold's
    distorted points are corrected through the fitted inverse and compared with their
    reference points.  Returns ``(mean_error (B,), failed (B,))``: the mean Euclidean error
    over every held-out point that could be scored, and the number of held-out points that
    could not (fit did not converge, or inverse failed).  NaN where none could be scored.
    ``prior``: as in :func:`score_models` (each fold's fit a maximum a posteriori one);
    ``family`` as there.
    """
    xy_u = np.asarray(xy_u, float)
    xy_d = np.asarray(xy_d, float)
    masks = np.atleast_2d(np.asarray(masks, bool))
    n_points = len(xy_u)
    folds = int(folds)
    if not 2 <= folds <= n_points:
        raise DataError(f"cross-validation needs 2 .. {n_points} folds (one point each at most), got {folds}")
    k_max = int(masks.sum(axis=1).max()) if len(masks) else 0
    n_train_min = n_points - -(-n_points // folds)
    if n_train_min < k_max + 2:
        raise DataError(
            f"{folds}-fold cross-validation leaves {n_train_min} training points, too few for a model "
            f"with {k_max} free parameters; use fewer folds"
        )
    rng = np.random.default_rng(validate.seed(seed))
    parts = np.array_split(rng.permutation(n_points), folds)
    p0 = _starts(init, xy_u, xy_d, masks, family)
    total = np.zeros(len(masks))
    count = np.zeros(len(masks), dtype=np.int64)
    failed = np.zeros(len(masks), dtype=np.int64)
    for held in parts:
        train = np.setdiff1d(np.arange(n_points), held)
        fits = fit_batch(xy_u, xy_d, masks, p0, points=train[None], covariance=False, max_iter=max_iter,
                         family=family, **({} if prior is None else {"prior": prior}))  # fmt: skip
        inv = undistort(xy_d[held], fits.params, family=fits.family)
        ok = inv.converged & fits.converged[:, None]
        err = np.hypot(*np.moveaxis(inv.xy - xy_u[held][None], -1, 0))
        total += np.where(ok, err, 0.0).sum(axis=1)
        count += ok.sum(axis=1)
        failed += (~ok).sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(count > 0, total / np.maximum(count, 1), np.nan)
    return mean, failed
