"""The paper's subsampling robustness test: refit models on random subsets of the points.

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

The names are also importable from :mod:`oapcal.select` (their earlier home).

>>> from oapcal.synthetic import synthetic_pairs
>>> data = synthetic_pairs(seed=3)
>>> rob = robustness(data.xy_u, data.xy_d, ["paper"], trials=20, init="pixel")
>>> rob.models[0].trials, rob.models[0].not_converged
(20, 0)
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from oapcal import validate
from oapcal.errors import DataError, ModelSpecError
from oapcal.fitting import DEFAULT_INIT, fit_batch, initial_params_many
from oapcal.model import (
    ModelFamily,
    family_named,
    family_of,
    family_of_spec,
    min_jacobian_determinant,
    parse_any_model,
    undistort,
)
from oapcal.normalize import normalize
from oapcal.records import finite_or_none

#: Reasons a robustness trial does not converge, in the order they are tested.
REASONS = ("non_finite", "iteration_cap", "stalled", "folded", "wrong_minimum")
_STATUS_REASON = {-1: "non_finite", 0: "iteration_cap", -2: "stalled"}

Progress = Callable[[int, int], None]


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


@dataclass(frozen=True)
class StartedModel:
    """A model of a family that starts from a design (the relay): its ``name``, free-parameter
    ``mask (P,)`` and starting vector ``p0 (P,)`` (:func:`oapcal.optics.relay_model.relay_params`);
    ``family`` the model family (by name; None: the built-in family of the mask's length);
    ``prior`` Gaussian priors ``(mean, sigma)`` as :func:`oapcal.fitting.fit_batch` takes
    them (every trial and the reference fit are then maximum a posteriori fits), or None."""

    name: str
    mask: np.ndarray
    p0: np.ndarray
    family: ModelFamily | str | None = None
    prior: tuple | None = None


def _prior_of(spec):
    return spec.prior if isinstance(spec, StartedModel) else None


def _model_name(spec) -> str:
    if isinstance(spec, StartedModel):
        return spec.name
    if isinstance(spec, str):
        return spec
    return ",".join(n for n, m in zip(_family_of(spec).param_names, parse_any_model(spec)) if m)


def _mask_of(spec) -> np.ndarray:
    return np.asarray(spec.mask, bool) if isinstance(spec, StartedModel) else parse_any_model(spec)


def _family_of(spec) -> ModelFamily:
    """The family of a model of :func:`robustness`: a :class:`StartedModel`'s own (or, not
    given, its mask's), else the family the spec names (:func:`oapcal.model.family_of_spec`)."""
    if isinstance(spec, StartedModel):
        return family_of(spec.mask) if spec.family is None else family_named(spec.family)
    return family_of_spec(spec)


def _starts_of(spec, init, u, d, mask) -> np.ndarray:
    """The start ``(P,)`` of one model: its own for a :class:`StartedModel`, else ``init``
    for Eq. (1) (the rotation, if any, starting at 0)."""
    if isinstance(spec, StartedModel):
        return np.asarray(spec.p0, float)
    return initial_params_many(init, u, d, mask[None])[0]


#: Most trials of :func:`robustness`.
MAX_TRIALS = 10_000_000
#: Memory of one trial, per point and per model (the subsets drawn: a float and an index per
#: point, the kept and held-out indices; the parameters, codes and errors per model), with
#: room: measured about 10 B per point for 252 points.
BYTES_PER_TRIAL_POINT = 16
BYTES_PER_TRIAL_MODEL = 512


def robustness_bytes(trials: int, n_points: int, n_models: int) -> int:
    """The memory estimate of :func:`robustness` (bytes), checked before any work."""
    return trials * (BYTES_PER_TRIAL_POINT * n_points + BYTES_PER_TRIAL_MODEL * n_models)


# keyword options of the public robustness test (each an `oapcal robustness` option)
def robustness(
    xy_u,
    xy_d,
    models: Sequence = ("paper", "full"),
    *,
    trials: int = 10000,
    fraction: float = 0.9,
    seed: int = 0,
    init=DEFAULT_INIT,
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
    total)`` is called after each chunk of trials.  ``models`` are specs of
    :func:`oapcal.model.parse_any_model` (Eq. 1, ``"...+rotation"``) or
    :class:`StartedModel` (a relay subset with its design's start).
    """
    norm = normalize(normalization, xy_u, xy_d)
    u, d = norm.xy_u, norm.xy_d
    specs = list(models)
    trials = validate.whole_number(trials, "trials", 1, MAX_TRIALS)
    seed = validate.seed(seed)
    chunk = validate.whole_number(chunk, "chunk", 1)
    validate.memory(
        robustness_bytes(trials, len(u), len(specs)),
        f"{trials:,} trials of {len(u)} points x {len(specs)} models", "give fewer trials", param="trials",
    )  # fmt: skip
    n_keep, masks = _check_robustness(len(u), trials, fraction, specs)
    ref_rms = _reference_rms(u, d, specs, masks, init, max_iter)
    keep, held = _draw_subsets(seed, trials, len(u), n_keep)
    families = [_family_of(s) for s in specs]
    trial = _Trials(u, d, masks, families, ref_rms, wrong_minimum_ratio, n_keep, trials)
    p0 = [_starts_of(s, init, u, d, m) for s, m in zip(specs, masks)]
    n_models = len(masks)
    for start in range(0, trials, chunk):
        sl = slice(start, min(start + chunk, trials))
        for j in range(n_models):
            fits = fit_batch(u, d, np.repeat(masks[j][None], sl.stop - sl.start, 0), p0[j], points=keep[sl],
                             covariance=False, max_iter=max_iter, family=trial.families[j],
                             prior=_prior_of(specs[j]))  # fmt: skip
            trial.record(j, sl, fits, held[sl])
            if progress is not None:
                progress(sl.start * n_models + (j + 1) * (sl.stop - sl.start), trials * n_models)
    return Robustness(
        n_points=len(u),
        n_keep=n_keep,
        fraction=float(fraction),
        seed=int(seed),
        init=init if isinstance(init, str) else "user",
        normalization=normalization or "none",
        wrong_minimum_ratio=float(wrong_minimum_ratio),
        models=tuple(trial.summary(j, spec, norm.scale_u) for j, spec in enumerate(specs)),
    )


def _check_robustness(n_points: int, trials: int, fraction: float, specs: list) -> tuple[int, np.ndarray]:
    """Refuse settings no trial could fit; the points each trial keeps and the models' masks."""
    if not 0.0 < fraction < 1.0:
        raise DataError(f"fraction must lie strictly between 0 and 1, got {fraction}", param="fraction")
    if trials < 1:
        raise DataError(f"trials must be at least 1, got {trials}", param="trials")
    n_keep = int(round(fraction * n_points))
    if not 0 < n_keep < n_points:
        raise DataError(
            f"keeping {fraction:g} of {n_points} points leaves {n_keep} kept and {n_points - n_keep} "
            "held out; both must be at least 1: change fraction",
            param="fraction",
        )
    if not specs:
        raise ModelSpecError("no models given: list at least one, e.g. paper,full", param="models")
    masks = [_mask_of(s) for s in specs]
    for spec, mask in zip(specs, masks):
        if n_keep < mask.sum() + 2:
            raise DataError(
                f"model {_model_name(spec)!r} has {int(mask.sum())} free parameters but each trial keeps "
                f"only {n_keep} points; it needs at least {int(mask.sum()) + 2}: raise fraction",
                param="fraction",
            )
    return n_keep, masks


def _reference_rms(u: np.ndarray, d: np.ndarray, specs, masks, init, max_iter: int) -> np.ndarray:
    """Reference RMS of each model: all points, best of the centre, pixel, zero and requested starts
    (a :class:`StartedModel`: its own start)."""
    named = ("auto", "pixel", "zero")
    starts = list(named) + ([init] if not (isinstance(init, str) and init in named) else [])
    out = np.full(len(masks), np.inf)
    # one batch per family: every model with each of its starts
    families = [_family_of(spec) for spec in specs]
    for family in sorted({f.name: f for f in families}.values(), key=lambda f: f.n_params):
        rows = [(j, _starts_of(spec, s, u, d, masks[j]))
                for j, spec in enumerate(specs) if families[j] is family
                for s in ([spec] if isinstance(spec, StartedModel) else starts)]  # fmt: skip
        owner = np.array([j for j, _ in rows])
        ref = fit_batch(u, d, np.stack([masks[j] for j in owner]), np.stack([p for _, p in rows]),
                        covariance=False, max_iter=max_iter, family=family,
                        prior=_stacked_priors([specs[j] for j in owner], family.n_params))  # fmt: skip
        np.minimum.at(out, owner, np.where(ref.converged, ref.rss, np.inf))
    return np.sqrt(out / len(u))


def _stacked_priors(specs, n_params: int):
    """The priors of a batch of models, ``(mean, sigma)`` of ``(B, P)`` (inf: none for a
    model without priors), or None when none has priors (the fit exactly as without)."""
    priors = [_prior_of(s) for s in specs]
    if all(p is None for p in priors):
        return None
    none = (np.zeros(n_params), np.full(n_params, np.inf))
    pairs = [none if p is None else tuple(np.broadcast_to(np.asarray(a, float), (n_params,)) for a in p)
             for p in priors]  # fmt: skip
    return np.stack([m for m, _ in pairs]), np.stack([w for _, w in pairs])


def _draw_subsets(seed: int, trials: int, n_points: int, n_keep: int) -> tuple[np.ndarray, np.ndarray]:
    """The sorted indices each trial keeps and holds out, ``(trials, n_keep)`` and the rest."""
    rng = np.random.default_rng(seed)
    perm = np.argsort(rng.random((trials, n_points)), axis=1)
    keep = np.ascontiguousarray(np.sort(perm[:, :n_keep], axis=1))
    held = np.ascontiguousarray(np.sort(perm[:, n_keep:], axis=1))
    return keep, held


class _Trials:
    """The outcome of every trial of every model: its reason code (0 = converged, else 1 +
    index in REASONS), parameters, held-out mean error and held-out points not inverted."""

    def __init__(self, u, d, masks, families, ref_rms, wrong_minimum_ratio, n_keep, trials):
        self.u, self.d, self.masks, self.families, self.ref_rms = u, d, masks, families, ref_rms
        self.wrong_minimum_ratio, self.n_keep = wrong_minimum_ratio, n_keep
        self.atol = 1e-9 * float(np.ptp(d[:, 1]))
        self.fold_points = hull_grid(u)
        n_models = len(masks)
        self.reason_code = np.zeros((n_models, trials), dtype=np.int64)
        self.params = [np.zeros((trials, len(m))) for m in masks]
        self.heldout = np.full((n_models, trials), np.nan)
        self.held_bad = np.zeros((n_models, trials), dtype=np.int64)

    def classify(self, j: int, fits) -> np.ndarray:
        """The reason code of each fit of model ``j``: status, non-finite, folded, wrong minimum."""
        n_sl = len(fits.rss)
        code = np.zeros(n_sl, dtype=np.int64)
        finite = np.isfinite(fits.params).all(axis=1) & np.isfinite(fits.rss)
        for s, name in _STATUS_REASON.items():
            code[(code == 0) & (fits.status == s)] = 1 + REASONS.index(name)
        code[(code == 0) & ~finite] = 1 + REASONS.index("non_finite")
        todo = code == 0
        min_det = np.full(n_sl, np.nan)
        if todo.any():
            family = self.families[j]
            min_det[todo] = min_jacobian_determinant(fits.params[todo], self.fold_points, family=family)
        code[todo & ~(min_det > 0)] = 1 + REASONS.index("folded")
        rms = np.sqrt(fits.rss / self.n_keep)
        ref = self.ref_rms[j]
        wrong = (rms > self.wrong_minimum_ratio * ref) & (rms - ref > self.atol)
        code[(code == 0) & wrong] = 1 + REASONS.index("wrong_minimum")
        return code

    def record(self, j: int, sl: slice, fits, held: np.ndarray) -> None:
        """Classify the fits of model ``j`` for trials ``sl`` and measure their held-out points."""
        code = self.classify(j, fits)
        ok = code == 0
        if ok.any():
            inv = undistort(self.d[held[ok]], fits.params[ok], family=self.families[j])
            conv = inv.converged
            err = np.hypot(*np.moveaxis(inv.xy - self.u[held[ok]], -1, 0))
            n_ok = conv.sum(axis=1)
            with np.errstate(invalid="ignore", divide="ignore"):
                h = np.where(n_ok > 0, np.where(conv, err, 0.0).sum(axis=1) / np.maximum(n_ok, 1), np.nan)
            rows = np.arange(sl.start, sl.stop)[ok]
            self.heldout[j, rows] = h
            self.held_bad[j, rows] = (~conv).sum(axis=1)
        self.reason_code[j, sl] = code
        self.params[j][sl] = fits.params

    def summary(self, j: int, spec, scale_u: float) -> ModelRobustness:
        """Model ``j`` over all trials: failures by reason, parameter spread, held-out error."""
        codes = self.reason_code[j]
        conv = codes == 0
        names = self.families[j].param_names
        free = tuple(n for n, m in zip(names, self.masks[j]) if m)
        std = {}
        for name in free:
            i = names.index(name)
            std[name] = float(np.std(self.params[j][conv, i], ddof=1)) if conv.sum() >= 2 else None
        h = self.heldout[j, conv]
        h = h[np.isfinite(h)]
        return ModelRobustness(
            name=_model_name(spec),
            free=free,
            trials=len(codes),
            not_converged=int((~conv).sum()),
            by_reason={r: int((codes == 1 + i).sum()) for i, r in enumerate(REASONS)},
            param_std=std,
            heldout_mean_error=float(h.mean() / scale_u) if h.size else float("nan"),
            heldout_failed=int(self.held_bad[j, conv].sum()),
            reference_rms=float(self.ref_rms[j]),
            trial_codes=codes,
        )
