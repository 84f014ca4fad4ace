"""Model selection over all 4,096 subsets of Eq. (1), cross-validation, and the
subsampling robustness test.

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

Robustness (:func:`robustness`)
-------------------------------
Each trial keeps a random ``fraction`` of the points, fits every listed model to them and
corrects the held-out points.  A trial *does not converge* for a model, for the first
reason that applies:

``non_finite``
    a parameter or the cost is not finite (solver status -1);
``iteration_cap``
    the solver did not meet any of its tolerances within its iteration cap (status 0);
``stalled``
    no step reduced the cost any more while the damping grew without bound (status -2);
``folded``
    the fitted map folds over (``det d(x_d, y_d)/d(x_u, y_u) <= 0``) somewhere inside the
    convex hull of the reference points (checked on the points and on a 41 x 41 grid
    clipped to the hull);
``wrong_minimum``
    the solver reported success but the RMS residual on the kept points,
    ``sqrt(RSS / kept points)``, exceeds ``wrong_minimum_ratio`` (default 1.5) times the
    RMS the same model reaches on all points from its best start (the lowest of the
    ``pixel``, ``zero`` and the requested start), and by more than ``1e-9`` of the
    points' y span.  Two minima with equal RMS (the ``paper`` model's exact two-fold
    ambiguity, ``docs/models.md``) are not wrong.

>>> from oapcal.synthetic import synthetic_pairs
>>> data = synthetic_pairs(seed=3)
>>> sel = select_models(data.xy_u, data.xy_d, init="pixel")
>>> len(sel.models), sel.models[0].valid, sel.models[0].delta_aicc
(4096, True, 0.0)
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from oapcal.errors import DataError, ModelSpecError
from oapcal.fit import STATUS_MESSAGES, fit_batch, initial_params
from oapcal.model import (
    N_OPTIONAL,
    PARAM_NAMES,
    all_masks,
    bits_from_mask,
    correction_errors,
    mask_from_bits,
    min_jacobian_determinant,
    names_from_mask,
    parse_model,
    undistort,
)
from oapcal.normalize import normalize
from oapcal.records import finite_or_none
from oapcal.stats import information_criteria

#: Codes of the reasons a model of a selection is invalid (``ModelScore.reason_code``).
INVALID_REASONS = ("not_converged", "too_few_residuals", "inverse_failed", "aicc_not_finite")
#: Reasons a robustness trial does not converge, in the order they are tested.
REASONS = ("non_finite", "iteration_cap", "stalled", "folded", "wrong_minimum")
_STATUS_REASON = {-1: "non_finite", 0: "iteration_cap", -2: "stalled"}

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

    def to_dict(self) -> dict:
        """The JSON entry: ``free k aicc delta_aicc weight rss valid reason`` and extras."""
        out = {
            "free": list(self.free),
            "k": self.k,
            "aicc": finite_or_none(self.aicc),
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


@functools.lru_cache(maxsize=2**N_OPTIONAL)
def _names_of_bits(bits: int) -> tuple[str, ...]:
    return names_from_mask(mask_from_bits(bits))


def _starts(init, xy_u, xy_d, masks: np.ndarray) -> np.ndarray:
    full = initial_params(init, xy_u, xy_d, np.ones(len(PARAM_NAMES), bool))
    return np.where(masks, full, 0.0)


def score_models(xy_u, xy_d, masks, init="zero", *, max_iter: int = 200, progress: Progress | None = None):
    """Fit and score the models ``masks (B, 13)`` on points already normalized.

    Returns a dict of arrays over the B models: ``params``, ``status``, ``rss`` (corrected
    residuals), ``mean_error``, ``n_bad`` (points whose inverse failed), ``n_folded``,
    ``aicc``.  Works in chunks so that ``progress(done, total)`` can be reported.
    """
    xy_u = np.asarray(xy_u, float)
    xy_d = np.asarray(xy_d, float)
    masks = np.atleast_2d(np.asarray(masks, bool))
    p0 = _starts(init, xy_u, xy_d, masks)
    n_models = len(masks)
    chunk = max(1, min(n_models, 1024))
    out = {
        "params": np.zeros((n_models, len(PARAM_NAMES))),
        "status": np.zeros(n_models, dtype=np.int64),
        "rss": np.full(n_models, np.nan),
        "mean_error": np.full(n_models, np.nan),
        "n_bad": np.zeros(n_models, dtype=np.int64),
        "n_folded": np.zeros(n_models, dtype=np.int64),
    }
    for start in range(0, n_models, chunk):
        sl = slice(start, min(start + chunk, n_models))
        fits = fit_batch(xy_u, xy_d, masks[sl], p0[sl], covariance=False, max_iter=max_iter)
        rss, mean_dist, n_bad, n_folded = correction_errors(fits.params, xy_d, xy_u)
        all_ok = n_bad == 0
        out["rss"][sl] = np.where(all_ok, rss, np.nan)
        out["mean_error"][sl] = np.where(all_ok, mean_dist, np.nan)
        out["params"][sl] = fits.params
        out["status"][sl] = fits.status
        out["n_bad"][sl] = n_bad
        out["n_folded"][sl] = n_folded
        if progress is not None:
            progress(sl.stop, n_models)
    n = 2 * len(xy_u)
    out["aicc"] = np.asarray(information_criteria(out["rss"], n, masks.sum(axis=1)).aicc, dtype=float)
    return out


def select_models(
    xy_u,
    xy_d,
    *,
    normalization: str = "none",
    init="zero",
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
    start of every fit (:func:`oapcal.fit.initial_params`; default ``zero``, the paper's
    choice).  With ``cv = K``, the best ``cv_top`` models also get the K-fold
    cross-validated mean corrected error (:func:`cross_validate`, folds drawn with
    ``seed``).
    """
    norm = normalize(normalization, xy_u, xy_d)
    u, d = norm.xy_u, norm.xy_d
    masks = all_masks() if masks is None else np.atleast_2d(np.asarray(masks, bool))
    n_points = len(u)
    n = 2 * n_points
    scores = score_models(u, d, masks, init, max_iter=max_iter, progress=progress)
    k = masks.sum(axis=1)
    big_k = k + 1
    reasons, codes = [], []
    for i in range(len(masks)):
        status = int(scores["status"][i])
        if status <= 0:
            why = STATUS_MESSAGES[status].removeprefix("not converged: ")
            code, reason = "not_converged", f"fit did not converge ({why})"
        elif n - big_k[i] - 1 <= 0:
            code = "too_few_residuals"
            reason = f"too few residuals for AICc: n - K - 1 = {n - big_k[i] - 1} <= 0"
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
    valid = np.array([c == "" for c in codes])
    aicc = scores["aicc"]
    bits = bits_from_mask(masks)
    # Valid models by AICc (ties: fewer parameters, then bits); invalid ones after them,
    # ordered by their (possibly NaN) AICc, then bits.
    order_key = np.where(valid, aicc, np.inf)
    inv_key = np.where(np.isfinite(aicc) & ~valid, aicc, np.inf)
    order = np.lexsort((bits, k, inv_key, order_key, ~valid))
    best = aicc[valid].min() if valid.any() else np.nan
    delta = np.where(valid, aicc - best, np.nan)
    weight = np.where(valid, np.exp(-0.5 * np.where(valid, delta, 0.0)), 0.0)
    weight = weight / weight.sum() if valid.any() else np.full(len(masks), np.nan)
    weight = np.where(valid, weight, np.nan)
    mean_error = scores["mean_error"] / norm.scale_u

    cv_err: dict[int, tuple[float, int]] = {}
    if cv is not None:
        top = order[: max(0, cv_top)]
        errs, failed = cross_validate(u, d, masks[top], folds=cv, init=init, seed=seed, max_iter=max_iter)
        for i, e, f in zip(top, errs, failed):
            cv_err[int(i)] = (float(e) / norm.scale_u, int(f))

    # Plain Python values once per column (faster than converting 4,096 x 11 NumPy scalars).
    cols = zip(bits[order].tolist(), k[order].tolist(), aicc[order].tolist(), delta[order].tolist(),
               weight[order].tolist(), scores["rss"][order].tolist(), mean_error[order].tolist(),
               valid[order].tolist(), scores["status"][order].tolist(), order.tolist())  # fmt: skip
    models = tuple(
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
        )
        for b, kk, a, da, w, r, me, v, st, i in cols
    )
    init_name = init if isinstance(init, str) else "user"
    return Selection(n_points, normalization or "none", init_name, models, cv)


def cross_validate(xy_u, xy_d, masks, *, folds: int = 5, init="zero", seed: int = 0, max_iter: int = 200):
    """K-fold cross-validated mean corrected error of each model ``masks (B, 13)``.

    The points are shuffled with ``seed`` and split into ``folds`` nearly equal folds;
    each model is fitted (from ``init``) to all folds but one and the held-out fold's
    distorted points are corrected through the fitted inverse and compared with their
    reference points.  Returns ``(mean_error (B,), failed (B,))``: the mean Euclidean error
    over every held-out point that could be scored, and the number of held-out points that
    could not (fit did not converge, or inverse failed).  NaN where none could be scored.
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
    rng = np.random.default_rng(seed)
    parts = np.array_split(rng.permutation(n_points), folds)
    p0 = _starts(init, xy_u, xy_d, masks)
    total = np.zeros(len(masks))
    count = np.zeros(len(masks), dtype=np.int64)
    failed = np.zeros(len(masks), dtype=np.int64)
    for held in parts:
        train = np.setdiff1d(np.arange(n_points), held)
        fits = fit_batch(xy_u, xy_d, masks, p0, points=train[None], covariance=False, max_iter=max_iter)
        inv = undistort(xy_d[held], fits.params)
        ok = inv.converged & fits.converged[:, None]
        err = np.hypot(*np.moveaxis(inv.xy - xy_u[held][None], -1, 0))
        total += np.where(ok, err, 0.0).sum(axis=1)
        count += ok.sum(axis=1)
        failed += (~ok).sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(count > 0, total / np.maximum(count, 1), np.nan)
    return mean, failed


# ----------------------------------------------------------------------- robustness


@dataclass(frozen=True)
class ModelRobustness:
    """The subsampling test of one model (module docstring for the reasons).

    ``param_std`` is the standard deviation (ddof = 1) of each free parameter over the
    converged trials, in the fit's coordinates (the input's when ``normalization`` is
    ``none``), ``None`` with fewer than two converged trials.  ``heldout_mean_error`` is
    the mean over converged trials of the mean corrected error on that trial's held-out
    points, in the units of the reference points as given; ``heldout_failed`` counts
    held-out points whose inverse failed in converged trials (left out of that mean).
    ``reference_rms`` is the all-points RMS used by the ``wrong_minimum`` test.
    ``trial_codes (trials,)`` is 0 for a converged trial, else ``1 +`` the index of its
    reason in :data:`REASONS`.
    """

    name: str
    free: tuple[str, ...]
    trials: int
    not_converged: int
    by_reason: dict[str, int]
    param_std: dict[str, float | None]
    heldout_mean_error: float
    heldout_failed: int
    reference_rms: float
    trial_codes: np.ndarray = field(repr=False)

    def to_dict(self) -> dict:
        """``free trials not_converged by_reason param_std heldout_mean_error_px`` and extras."""
        return {
            "free": list(self.free),
            "trials": self.trials,
            "not_converged": self.not_converged,
            "by_reason": dict(self.by_reason),
            "param_std": {n: finite_or_none(v) for n, v in self.param_std.items()},
            "heldout_mean_error_px": finite_or_none(self.heldout_mean_error),
            "heldout_failed_points": self.heldout_failed,
            "reference_rms": finite_or_none(self.reference_rms),
        }


@dataclass(frozen=True)
class Robustness:
    """Result of :func:`robustness`: settings and one :class:`ModelRobustness` per model."""

    n_points: int
    n_keep: int
    fraction: float
    seed: int
    init: str
    normalization: str
    wrong_minimum_ratio: float
    models: tuple[ModelRobustness, ...]

    def to_dict(self) -> dict:
        return {
            "n_points": self.n_points,
            "n_keep": self.n_keep,
            "fraction": self.fraction,
            "seed": self.seed,
            "init": self.init,
            "normalize": self.normalization,
            "wrong_minimum_ratio": self.wrong_minimum_ratio,
            "models": {m.name: m.to_dict() for m in self.models},
        }


def hull_grid(xy: np.ndarray, n: int = 41) -> np.ndarray:
    """The points ``xy (N, 2)`` plus an ``n x n`` grid over their bounding box clipped to
    their convex hull: where the fold-over test looks."""
    from scipy.spatial import ConvexHull, QhullError

    xy = np.asarray(xy, float)
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    gx, gy = np.meshgrid(np.linspace(lo[0], hi[0], n), np.linspace(lo[1], hi[1], n))
    grid = np.stack([gx.ravel(), gy.ravel()], -1)
    try:
        eq = ConvexHull(xy).equations  # rows (a, b, c): inside where a x + b y + c <= 0
    except QhullError:
        raise DataError("the reference points are all on one line; they span no area to test") from None
    tol = 1e-12 * float(np.abs(xy).max())
    inside = (grid @ eq[:, :2].T + eq[:, 2] <= tol).all(axis=1)
    return np.concatenate([xy, grid[inside]])


def _model_name(spec) -> str:
    return spec if isinstance(spec, str) else ",".join(names_from_mask(parse_model(spec)))


def robustness(
    xy_u,
    xy_d,
    models: Sequence = ("paper", "full"),
    *,
    trials: int = 10000,
    fraction: float = 0.9,
    seed: int = 0,
    init="zero",
    normalization: str = "none",
    wrong_minimum_ratio: float = 1.5,
    max_iter: int = 200,
    chunk: int = 1000,
    progress: Progress | None = None,
) -> Robustness:
    """The paper's subsampling test (module docstring).

    In each of ``trials`` trials a random ``round(fraction * N)`` of the points (drawn with
    ``seed``; the same subsets for every model) is kept, each model is fitted to them from
    ``init`` and classified; the held-out points measure overfitting.  ``progress(done,
    total)`` is called after each chunk of trials.
    """
    norm = normalize(normalization, xy_u, xy_d)
    u, d = norm.xy_u, norm.xy_d
    n_points = len(u)
    if not 0.0 < fraction < 1.0:
        raise DataError(f"--fraction must lie strictly between 0 and 1, got {fraction}")
    if trials < 1:
        raise DataError(f"--trials must be at least 1, got {trials}")
    n_keep = int(round(fraction * n_points))
    if not 0 < n_keep < n_points:
        raise DataError(
            f"keeping {fraction:g} of {n_points} points leaves {n_keep} kept and {n_points - n_keep} "
            "held out; both must be at least 1: change --fraction"
        )
    specs = list(models)
    if not specs:
        raise ModelSpecError("no models given: list at least one, e.g. --models paper,full")
    masks = np.stack([parse_model(s) for s in specs])
    for spec, mask in zip(specs, masks):
        if n_keep < mask.sum() + 2:
            raise DataError(
                f"model {_model_name(spec)!r} has {int(mask.sum())} free parameters but each trial keeps "
                f"only {n_keep} points; it needs at least {int(mask.sum()) + 2}: raise --fraction"
            )

    # Reference RMS of each model: all points, best of the pixel, zero and requested starts.
    starts = ["pixel", "zero"] + ([init] if not (isinstance(init, str) and init in ("pixel", "zero")) else [])
    ref_masks = np.repeat(masks, len(starts), axis=0)
    ref_p0 = np.concatenate([_starts(s, u, d, masks) for s in starts])
    ref_p0 = ref_p0.reshape(len(starts), len(masks), -1).transpose(1, 0, 2).reshape(len(ref_masks), -1)
    ref = fit_batch(u, d, ref_masks, ref_p0, covariance=False, max_iter=max_iter)
    ref_rss = np.where(ref.converged, ref.rss, np.inf).reshape(len(masks), len(starts)).min(axis=1)
    ref_rms = np.sqrt(ref_rss / n_points)
    atol = 1e-9 * float(np.ptp(d[:, 1]))

    rng = np.random.default_rng(seed)
    perm = np.argsort(rng.random((trials, n_points)), axis=1)
    keep = np.ascontiguousarray(np.sort(perm[:, :n_keep], axis=1))
    held = np.ascontiguousarray(np.sort(perm[:, n_keep:], axis=1))
    fold_points = hull_grid(u)
    p0 = _starts(init, u, d, masks)

    n_models = len(masks)
    reason_code = np.zeros((n_models, trials), dtype=np.int64)  # 0 = converged, else 1 + REASONS index
    params = np.zeros((n_models, trials, len(PARAM_NAMES)))
    heldout = np.full((n_models, trials), np.nan)
    held_bad = np.zeros((n_models, trials), dtype=np.int64)
    total = trials * n_models
    for start in range(0, trials, chunk):
        sl = slice(start, min(start + chunk, trials))
        for j in range(n_models):
            n_sl = sl.stop - sl.start
            fits = fit_batch(u, d, np.repeat(masks[j][None], n_sl, 0), p0[j], points=keep[sl],
                             covariance=False, max_iter=max_iter)  # fmt: skip
            code = np.zeros(n_sl, dtype=np.int64)
            finite = np.isfinite(fits.params).all(axis=1) & np.isfinite(fits.rss)
            for s, name in _STATUS_REASON.items():
                code[(code == 0) & (fits.status == s)] = 1 + REASONS.index(name)
            code[(code == 0) & ~finite] = 1 + REASONS.index("non_finite")
            todo = code == 0
            min_det = np.full(n_sl, np.nan)
            if todo.any():
                min_det[todo] = min_jacobian_determinant(fits.params[todo], fold_points)
            code[todo & ~(min_det > 0)] = 1 + REASONS.index("folded")
            rms = np.sqrt(fits.rss / n_keep)
            wrong = (rms > wrong_minimum_ratio * ref_rms[j]) & (rms - ref_rms[j] > atol)
            code[(code == 0) & wrong] = 1 + REASONS.index("wrong_minimum")
            ok = code == 0
            if ok.any():
                inv = undistort(d[held[sl][ok]], fits.params[ok])
                conv = inv.converged
                err = np.hypot(*np.moveaxis(inv.xy - u[held[sl][ok]], -1, 0))
                n_ok = conv.sum(axis=1)
                with np.errstate(invalid="ignore", divide="ignore"):
                    h = np.where(n_ok > 0, np.where(conv, err, 0.0).sum(axis=1) / np.maximum(n_ok, 1), np.nan)
                rows = np.arange(sl.start, sl.stop)[ok]
                heldout[j, rows] = h
                held_bad[j, rows] = (~conv).sum(axis=1)
            reason_code[j, sl] = code
            params[j, sl] = fits.params
            if progress is not None:
                progress(sl.start * n_models + (j + 1) * n_sl, total)

    results = []
    for j, spec in enumerate(specs):
        conv = reason_code[j] == 0
        free = names_from_mask(masks[j])
        std = {}
        for name in free:
            i = PARAM_NAMES.index(name)
            std[name] = float(np.std(params[j, conv, i], ddof=1)) if conv.sum() >= 2 else None
        h = heldout[j, conv]
        h = h[np.isfinite(h)]
        results.append(
            ModelRobustness(
                name=_model_name(spec),
                free=free,
                trials=trials,
                not_converged=int((~conv).sum()),
                by_reason={r: int((reason_code[j] == 1 + i).sum()) for i, r in enumerate(REASONS)},
                param_std=std,
                heldout_mean_error=float(h.mean() / norm.scale_u) if h.size else float("nan"),
                heldout_failed=int(held_bad[j, conv].sum()),
                reference_rms=float(ref_rms[j]),
                trial_codes=reason_code[j],
            )
        )
    init_name = init if isinstance(init, str) else "user"
    return Robustness(
        n_points=n_points,
        n_keep=n_keep,
        fraction=float(fraction),
        seed=int(seed),
        init=init_name,
        normalization=normalization or "none",
        wrong_minimum_ratio=float(wrong_minimum_ratio),
        models=tuple(results),
    )
