"""Fitting Eq. (1) to point pairs: the batched Levenberg-Marquardt solver, ``BatchFit``
and ``FitResult``.

The fit minimises the forward residuals ``distort(xy_u; p) - xy_d`` (in the units of the
distorted points) over the free parameters of a model, the others held at 0.

:func:`fit_batch` is the one solver: it fits B models at once (each with its own mask,
start and, optionally, its own points or subset of points), one model per thread in
compiled code (``oapcal._kernels.lm_batch``, blocks of items on all cores); :func:`fit`, model selection,
cross-validation and the robustness test all call it.  It returns values and never
raises on numerical failure: every item has a ``status`` and ``message``.  A model family
other than Eq. (1) plugs in through ``family`` (:class:`oapcal.model.ModelFamily`,
``docs/architecture.md``).

Conditioning: pixel-scale data make the normal equations badly scaled (``r^4`` terms of
order 1e10).  The solver therefore works in coordinates divided by a factor ``f`` (the
largest absolute coordinate), with parameters reparametrized exactly by
:func:`oapcal.model.scale_params`, and scales the columns of the Jacobian (Marquardt's
scaling, as MINPACK does).  Results are reported in the data's own units.

>>> import numpy as np
>>> from oapcal.model import distort, params_from_dict
>>> g = np.stack(np.meshgrid(np.linspace(-1, 1, 9), np.linspace(-1, 1, 9)), -1).reshape(-1, 2)
>>> truth = params_from_dict({"k1": 0.05, "c_x": 0.1, "m": 1.2})
>>> result = fit(g, distort(g, truth), "k1,c_x")
>>> result.converged, round(result.value("k1"), 6)
(True, 0.05)
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from oapcal.errors import DataError, ModelSpecError
from oapcal.model import (
    N_PARAMS,
    TILT_NAMES,
    Model,
    ModelFamily,
    family_named,
    family_of,
    family_of_spec,
    identity_params,
    kernel_array,
    names_from_mask,
    params_from_dict,
    parse_any_model,
)
from oapcal.stats import information_criteria
from oapcal.validate import point_pairs

# Status codes of a fit (positive = converged).
STATUS_MESSAGES: dict[int, str] = {
    1: "converged: gradient orthogonal to the residuals (gtol)",
    2: "converged: relative reduction of the cost below ftol",
    3: "converged: relative step below xtol",
    4: "converged: residuals are zero",
    0: "not converged: iteration cap reached",
    -1: "not converged: a parameter or residual became non-finite",
    -2: "not converged: the damping grew without bound (no step reduces the cost)",
}


def _readonly(a) -> np.ndarray:
    a = np.array(a, dtype=float)
    a.setflags(write=False)
    return a


@dataclass(frozen=True)
class FitResult:
    """The immutable record of one fit.

    ``params`` holds all 13 values (fixed ones 0) and ``stderr`` all 13 standard errors
    (NaN for fixed ones), from ``cov = s^2 (J^T J)^-1`` with ``s^2 = RSS / (n - k)``;
    ``covariance`` is that ``k x k`` matrix over the free parameters in ``free`` order.
    ``rss`` is the sum of squared forward residuals, ``n`` the number of residuals (two
    per point) and ``k`` the number of free parameters; ``aic``, ``aicc`` and ``bic``
    follow :mod:`oapcal.stats` (with ``K = k + 1``).

    Fitted with priors (``fit_batch(prior=...)``): ``params`` is the maximum a posteriori
    estimate, ``rss`` the data's residuals alone (not the prior rows), ``covariance`` the
    posterior ``s^2 (J^T J + W^2)^-1`` and ``k_eff`` the effective number of parameters,
    the trace of the hat matrix ``tr((J^T J + W^2)^-1 J^T J)``, which replaces ``k`` in
    ``s^2 = RSS / (n - k_eff)`` and in AIC, AICc and BIC (``K = k_eff + 1``); None without
    priors.
    """

    free: tuple[str, ...]
    params: np.ndarray
    stderr: np.ndarray
    covariance: np.ndarray
    rss: float
    n: int
    k: int
    aic: float
    aicc: float
    bic: float
    converged: bool
    status: int
    message: str
    n_iter: int
    k_eff: float | None = None
    family: ModelFamily | str | None = None

    def __post_init__(self):
        # the family by name (fit_batch knows it); a record made without one names the
        # family of its vector's length, as before the family was carried
        family = family_of(self.params) if self.family is None else family_named(self.family)
        object.__setattr__(self, "family", family)

    @property
    def model(self) -> Model:
        """The fitted model as a value (:class:`oapcal.model.Model`)."""
        return Model(self.family, self.params, self.free)

    def value(self, name: str) -> float:
        """The fitted value of one parameter."""
        return float(self.params[self.family.param_names.index(name)])

    @property
    def params_dict(self) -> dict[str, float]:
        return self.model.params_dict

    @property
    def stderr_dict(self) -> dict[str, float]:
        """Standard errors of the free parameters, by name."""
        names = self.family.param_names
        return {name: float(self.stderr[names.index(name)]) for name in self.free}

    @property
    def mask(self) -> np.ndarray:
        return self.model.mask


@dataclass(frozen=True)
class BatchFit:
    """Results of :func:`fit_batch` for B models; every array has B as its first axis.

    ``params (B, P)`` in the data's units (fixed entries 0), ``covariance (B, P, P)``
    (zero rows and columns for fixed parameters; None when not requested), ``rss (B,)``
    the sum of squared forward residuals over each item's points, ``n (B,)`` the number of
    residuals of each item (two per point), ``n_iter (B,)`` Jacobian evaluations,
    ``status (B,)`` (see :data:`STATUS_MESSAGES`; positive = converged) and ``masks``.
    ``item(i)`` is item ``i`` as a :class:`FitResult`.  ``k_eff (B,)``: with priors, each
    item's effective number of parameters (:class:`FitResult`; ``rss`` is then the data's
    alone); None without.  ``family`` the model family fitted (by name; None: the family
    of the masks' length).
    """

    masks: np.ndarray
    params: np.ndarray
    covariance: np.ndarray | None
    rss: np.ndarray
    n: np.ndarray
    n_iter: np.ndarray
    status: np.ndarray
    k_eff: np.ndarray | None = None
    family: ModelFamily | str | None = None
    converged: np.ndarray = field(init=False)

    def __post_init__(self):
        object.__setattr__(self, "converged", self.status > 0)
        family = family_of(self.masks) if self.family is None else family_named(self.family)
        object.__setattr__(self, "family", family)
        for name in ("masks", "params", "covariance", "rss", "n", "n_iter", "status", "converged", "k_eff"):
            value = getattr(self, name)
            if value is not None:
                value.setflags(write=False)

    def __len__(self) -> int:
        return len(self.params)

    def item(self, i: int) -> FitResult:
        """Item ``i`` as a :class:`FitResult` (needs the covariance)."""
        if self.covariance is None:
            raise ModelSpecError("this batch was fitted without covariance; use fit_batch(covariance=True)")
        mask = self.masks[i]
        k = int(mask.sum())
        cov = self.covariance[i][np.ix_(mask, mask)]
        stderr = np.full(mask.shape[0], np.nan)
        stderr[mask] = np.sqrt(np.clip(np.diag(cov), 0, None))
        n = int(self.n[i])
        k_eff = None if self.k_eff is None else float(self.k_eff[i])
        ic = information_criteria(self.rss[i], n, k if k_eff is None else k_eff)
        status = int(self.status[i])
        return FitResult(
            free=names_from_mask(mask),
            params=_readonly(self.params[i]),
            stderr=_readonly(stderr),
            covariance=_readonly(cov),
            rss=float(self.rss[i]),
            n=n,
            k=k,
            aic=ic.aic,
            aicc=ic.aicc,
            bic=ic.bic,
            converged=status > 0,
            status=status,
            message=STATUS_MESSAGES[status],
            n_iter=int(self.n_iter[i]),
            k_eff=k_eff,
            family=self.family,
        )


#: The start every fit, selection and robustness test uses unless told otherwise
#: (``oapcal fit``, ``select``, ``robustness``, the demo and napari): :func:`centre_start`.
DEFAULT_INIT = "auto"

#: The named starts of :func:`initial_params`.
NAMED_STARTS = ("auto", "centre", "pixel", "zero")


def centre_start(xy_u: np.ndarray, xy_d: np.ndarray, rotation: bool = False) -> np.ndarray:
    """The data's own start: Eq. (1) with no distortion, its centre at the centroid of the
    points and the scale (and, with ``rotation``, the turn) of the best similarity.

    ``m = |s|`` (or ``Re s`` without the rotation) and ``theta = arg s`` from the complex
    least-squares similarity ``s = sum conj(u') d' / sum |u'|^2`` of the centred points
    (``u' = u - c_u``, ``d' = d - c_d``, ``c`` each set's centroid, where the least-squares
    similarity maps one onto the other);
    ``x_off, y_off = -R(theta) c_u`` and ``c_x, c_y = c_d`` so that the start maps
    ``c_u`` onto ``c_d``.  Returns ``(13,)``, or ``(14,)`` with the rotation (deg) last.
    On points already centred at 0 with equal scales it is the zero start; on pixel data
    it puts the distortion centre where the paper's pixel guesses do, the middle of the
    points, and never needs the data's units.

    >>> u = np.array([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0], [10.0, 10.0]])
    >>> d = 2.0 * u[:, ::-1] * [-1, 1] + 5.0          # turned by 90 deg, scaled by 2
    >>> np.round(centre_start(u, d, rotation=True)[[8, 9, 10, 11, 12, 13]], 6)
    array([ 5., -5., -5., 15.,  2., 90.])
    """
    from oapcal.normalize import similarity

    xy_u = np.asarray(xy_u, float)
    xy_d = np.asarray(xy_d, float)
    c_u = xy_u.mean(axis=0)
    c_d = xy_d.mean(axis=0)
    s = complex(similarity(xy_u, xy_d)[0])
    if not np.isfinite(s) or s == 0:
        s = 1.0 + 0.0j
    theta = float(np.angle(s)) if rotation else 0.0
    m = abs(s) if rotation else s.real
    if not m > 0:  # a reflection or a turn beyond 90 deg that Eq. (1) alone cannot start from
        m = abs(s)
    cos, sin = np.cos(theta), np.sin(theta)
    off = -np.array([cos * c_u[0] - sin * c_u[1], sin * c_u[0] + cos * c_u[1]])
    p = params_from_dict({"x_off": off[0], "y_off": off[1], "c_x": c_d[0], "c_y": c_d[1], "m": m})
    return np.append(p, np.degrees(theta)) if rotation else p


def initial_params(init, xy_u: np.ndarray, xy_d: np.ndarray, mask: np.ndarray, *,
                   family: ModelFamily | None = None) -> np.ndarray:  # fmt: skip
    """Starting values ``(13,)`` for a fit (``(14,)`` for the rotation family, ``(16,)`` for
    the tilt family: ``family``, or without it a mask of that length); fixed parameters are
    always 0 (``m`` is free), the tilt terms start at 0 (or their ``tilt_x=`` values).

    ``init`` is ``"auto"`` (:data:`DEFAULT_INIT`) or ``"centre"``: :func:`centre_start`,
    the data's own centre, scale and turn; ``"zero"`` (the paper's start for normalized
    data: all 0, m = 1), ``"pixel"`` (the paper's
    pixel-scale guesses: k1 = 1e-6, p1 = 1e-4, s3 = 1e-4, x_off = -W/2, y_off = -H/2,
    c_x = W/2, c_y = H/2, m = 1, where W/2 and H/2 are the middle of the x and y range
    spanned by all points, i.e. W = x_min + x_max), a mapping of name -> value over the
    zero start, a string ``"k1=1e-6,m=1"`` of the same, or a ``(13,)`` array.  The
    rotation starts from the similarity's turn with ``auto``/``centre``, else at 0 (or
    its ``rotation=`` value).
    """
    mask = np.asarray(mask, bool)
    # the entries after Eq. (1)'s 13: none, the rotation, or the rotation and the tilt terms
    n_extra = (family.n_params if family is not None else mask.shape[0]) - N_PARAMS
    rotation = n_extra > 0 and bool(mask[N_PARAMS])
    extra = 0.0
    tilt = [0.0] * len(TILT_NAMES)
    if isinstance(init, str) and init in ("auto", "centre"):
        p = centre_start(xy_u, xy_d, rotation=rotation)
        if rotation:
            p, extra = p[:N_PARAMS], float(p[N_PARAMS])
    elif isinstance(init, str) and init == "zero":
        p = identity_params()
    elif isinstance(init, str) and init == "pixel":
        pts = np.concatenate([np.asarray(xy_u, float), np.asarray(xy_d, float)])
        half_w = 0.5 * (pts[:, 0].min() + pts[:, 0].max())
        half_h = 0.5 * (pts[:, 1].min() + pts[:, 1].max())
        p = params_from_dict(
            {"k1": 1e-6, "p1": 1e-4, "s3": 1e-4, "x_off": -half_w, "y_off": -half_h,
             "c_x": half_w, "c_y": half_h, "m": 1.0}
        )  # fmt: skip
    else:
        values = _parse_assignments(init) if isinstance(init, str) else init
        if isinstance(values, Mapping):
            values = dict(values)
            extra = float(values.pop("rotation", 0.0))
            tilt = [float(values.pop(n, 0.0)) for n in TILT_NAMES]
            p = params_from_dict(values)
        else:
            p = np.array(values, dtype=float)
            if p.shape != (N_PARAMS,):
                raise ModelSpecError(f"initial values must have {N_PARAMS} entries, got shape {p.shape}")
    p = np.where(mask[:N_PARAMS], p, 0.0)
    if n_extra <= 0:
        return p
    tilt = np.where(mask[N_PARAMS + 1 :], tilt[: n_extra - 1], 0.0)
    return np.concatenate([p, [extra if rotation else 0.0], tilt])


def initial_params_many(init, xy_u: np.ndarray, xy_d: np.ndarray, masks: np.ndarray, *,
                        family: ModelFamily | None = None) -> np.ndarray:  # fmt: skip
    """Starting values ``(B, 13)`` (or ``(B, 14)`` for the rotation family) for the models
    ``masks`` from one ``init`` (as in :func:`initial_params`, with its ``family``, evaluated
    once for the full model, fixed entries 0)."""
    masks = np.atleast_2d(np.asarray(masks, bool))
    full = initial_params(init, xy_u, xy_d, np.ones(masks.shape[1], bool), family=family)
    if masks.shape[1] > N_PARAMS + 1 and not masks[:, N_PARAMS].all():  # the tilt family, rotation fixed
        unturned = np.ones(masks.shape[1], bool)
        unturned[N_PARAMS] = False
        plain = initial_params(init, xy_u, xy_d, unturned, family=family)
        full = np.where(masks[:, N_PARAMS : N_PARAMS + 1], full, plain)
    return np.where(masks, full, 0.0)


def _parse_assignments(text: str) -> dict[str, float]:
    values = {}
    for item in text.split(","):
        if not item.strip():
            continue
        name, sep, value = item.partition("=")
        if not sep:
            raise ModelSpecError(
                f"bad initial value {item.strip()!r}: use 'auto', 'centre', 'zero', 'pixel' or "
                "name=value pairs such as 'k1=1e-6,m=1'"
            )
        try:
            values[name.strip()] = float(value)
        except ValueError:
            raise ModelSpecError(f"initial value of {name.strip()!r} is not a number: {value!r}") from None
    return values


def _point_subsets(points, n_points: int, n_items: int) -> tuple[np.ndarray, np.ndarray]:
    """Point indices ``(1 or B, nmax)`` and counts from ``points``: None (all), integer
    indices ``(n,)``, ``(1, n)`` or ``(B, n)``, or a boolean mask ``(N,)`` or ``(B, N)``."""
    if points is None:
        return np.arange(n_points, dtype=np.int64)[None], np.array([n_points], dtype=np.int64)
    points = np.asarray(points)
    if points.dtype == bool:
        sel = np.atleast_2d(points)
        if sel.shape[1] != n_points or sel.shape[0] not in (1, n_items):
            raise ModelSpecError(f"a point mask must have shape ({n_points},) or ({n_items}, {n_points})")
        counts = sel.sum(axis=1).astype(np.int64)
        idx = np.argsort(~sel, axis=1, kind="stable")[:, : max(int(counts.max()), 1)]
        return kernel_array(idx, np.int64), counts
    idx = kernel_array(np.atleast_2d(points), np.int64)
    if idx.ndim != 2 or idx.shape[0] not in (1, n_items):
        raise ModelSpecError(f"point indices must have 1 or {n_items} rows, got shape {points.shape}")
    if idx.size and (idx.min() < 0 or idx.max() >= n_points):
        raise ModelSpecError(f"point indices must lie in 0..{n_points - 1}")
    return idx, np.full(idx.shape[0], idx.shape[1], dtype=np.int64)


# fit_batch's keywords are the solver's documented options (MINPACK's tolerances, the
# iteration cap, priors, subsets): the contract of the one solver, kept as keywords.
def fit_batch(
    xy_u: np.ndarray,
    xy_d: np.ndarray,
    masks: np.ndarray,
    p0: np.ndarray,
    *,
    points: np.ndarray | None = None,
    covariance: bool = True,
    max_iter: int = 200,
    ftol: float = 1e-12,
    xtol: float = 1e-12,
    gtol: float = 1e-12,
    scale: float | None = None,
    family: ModelFamily | None = None,
    prior=None,
) -> BatchFit:
    """Fit B models at once by Levenberg-Marquardt (the one solver of oapcal).

    Parameters
    ----------
    xy_u, xy_d : reference and distorted points, each ``(N, 2)`` (shared by all items) or
        ``(B, N, 2)`` (each item's own).
    masks : ``(B, P)`` bool, the free parameters of each model (the family's
        ``always_free`` ones, ``m`` for Eq. (1), must be free).
    p0 : ``(B, P)`` or ``(P,)`` starting values (fixed entries are forced to 0).
    points : which points each item is fitted to: None (all), integer indices ``(n,)``,
        ``(1, n)`` or ``(B, n)``, or a boolean mask ``(N,)`` or ``(B, N)``.
    covariance : also compute ``cov = s^2 (J^T J)^-1`` at each solution, with
        ``s^2 = RSS / (n - k)`` (pseudo-inverse of the column-scaled matrix).
    max_iter : cap on Jacobian evaluations per item.
    ftol, xtol, gtol : MINPACK-style tolerances: relative cost reduction (actual and
        predicted), relative scaled step, and the largest cosine between the residual
        vector and a Jacobian column.
    scale : the coordinate factor ``f`` (default: the largest absolute coordinate).
    family : the model family (default Eq. (1)).
    prior : Gaussian priors, a pair ``(mean, sigma)`` of ``(P,)`` or ``(B, P)`` arrays in
        the parameters' units: the fit is then the maximum a posteriori estimate, least
        squares on the residuals with one row ``(p_i - mean_i) / sigma_i`` appended per free
        parameter (in the compiled solver; ``sigma`` in the units of the distorted points
        per unit of the parameter, so a row weighs like a residual).  ``sigma`` inf: no
        row (that parameter free as without priors); 0: the parameter is fixed at its
        mean (removed from the free ones; for a family whose fixed parameters are 0 the
        mean must then be 0).  The covariance is the posterior one and ``k_eff`` the
        effective number of parameters (:class:`FitResult`).  None (default): no priors,
        the fit exactly as without this argument.

    Each item stops when it meets a tolerance, fails, or hits ``max_iter``, and its
    status says which.  Items are independent: a batch gives the same results as a loop of
    single-item calls with the same ``scale``.
    """
    xy_u = np.asarray(xy_u, dtype=float)
    xy_d = np.asarray(xy_d, dtype=float)
    masks = kernel_array(np.atleast_2d(np.asarray(masks, dtype=bool)), bool)
    family = family_of(masks, family)
    _check_batch(xy_u, xy_d, masks, family)
    idx, counts = _point_subsets(points, xy_u.shape[-2], masks.shape[0])
    p0 = np.broadcast_to(np.asarray(p0, dtype=float), masks.shape)
    if prior is not None:
        masks, p0, mean, sigma = _priors(prior, masks, p0, family)
        prior = (mean, sigma)  # checked, and broadcast to the masks
    want_jtj = bool(covariance) or prior is not None  # priors: J^T J for k_eff as well
    solver = {"max_iter": max_iter, "ftol": ftol, "xtol": xtol, "gtol": gtol, "want_jtj": want_jtj}
    f = _solver_scale(family, xy_u, xy_d, scale)
    return _solve_scaled(family, f, (xy_u, xy_d, idx, counts), masks, p0, solver, covariance, prior)


def _solve_scaled(family, f, points, masks, p0, solver: dict, covariance: bool, prior) -> BatchFit:
    """:func:`fit_batch`'s solve: in the solver's coordinates (the points ``(xy_u, xy_d,
    idx, counts)`` divided by ``f``, parameters ``p' = p f**e``), then back in the data's
    units; ``prior`` the checked ``(mean, sigma)`` or None."""
    xy_u, xy_d, idx, counts = points
    n_models, n_params = masks.shape
    exps = family.scale_exponents
    u = kernel_array((xy_u / f).reshape((-1,) + xy_u.shape[-2:]))
    d = kernel_array((xy_d / f).reshape((-1,) + xy_d.shape[-2:]))
    p = p0
    if exps is not None:
        p = p * f**exps
    fixed = 0.0 if family.zero_when_fixed else p
    p = kernel_array(np.where(masks, p, fixed))
    n_res = 2 * np.broadcast_to(counts, (n_models,)).astype(np.int64)
    cov = None
    k_eff = None
    if prior is None:
        status, n_iter, cost, jtj = _run_lm(family, u, d, idx, counts, masks, p, solver)
        rss_scaled = 2.0 * cost
        if covariance:
            cov = _covariance(jtj, masks, rss_scaled, n_res)
    else:
        mean_s, w_s = _prior_rows(*prior, exps, f, n_params)
        status, n_iter, cost, jtj = _run_lm(family, u, d, idx, counts, masks, p, solver, (mean_s, w_s, True))
        w2 = np.broadcast_to(np.where(masks, w_s**2, 0.0), masks.shape)
        penalty = (w2 * (p - mean_s) ** 2).sum(axis=1)
        rss_scaled = 2.0 * (cost - 0.5 * penalty)  # the data's part of the cost
        cov_s, k_eff = _posterior_covariance(jtj, w2, masks, rss_scaled, n_res)
        cov = cov_s if covariance else None
    # Back to the data's units: p = p' * f**-e, cov = D cov' D with D = f**-e.
    back = np.ones(n_params) if exps is None else f ** (-exps)
    params = np.where(masks, p * back, fixed) if family.zero_when_fixed else p * back
    if cov is not None:
        cov = cov * back[None, :, None] * back[None, None, :]
    return BatchFit(masks=masks.copy(), params=params, covariance=cov, rss=rss_scaled * f * f, n=n_res,
                    n_iter=n_iter, status=status, k_eff=k_eff, family=family)  # fmt: skip


def _solver_scale(family, xy_u, xy_d, scale) -> float:
    """The coordinate factor ``f`` of :func:`fit_batch` (1 for a family that is not
    reparametrized by scale; else ``scale``, or the largest absolute coordinate)."""
    if family.scale_exponents is None:
        return 1.0
    if scale:
        return float(scale)
    return float(max(np.abs(xy_u).max(initial=0), np.abs(xy_d).max(initial=0), 1e-300))


def _prior_rows(prior_mean, prior_sigma, exps, f: float, n_params: int):
    """The priors' rows in the solver's coordinates, ``(mean', w')``: with ``p' = p f**e``
    and residuals divided by ``f``, a row ``(p - mean) / sigma`` of the data's objective is
    ``w' (p' - mean')`` with ``w' = 1 / (sigma f**(e + 1))`` (0 for an infinite width)."""
    e = np.zeros(n_params) if exps is None else exps
    mean_s = kernel_array(prior_mean * f**e)
    with np.errstate(divide="ignore"):
        w_s = kernel_array(np.where(np.isfinite(prior_sigma), 1.0 / (prior_sigma * f ** (e + 1)), 0.0))
    return mean_s, w_s


def _check_batch(xy_u, xy_d, masks, family) -> None:
    """``fit_batch``'s masks and points checked against the family (a named
    :class:`~oapcal.errors.ModelSpecError`)."""
    n_models, n_params = masks.shape
    if n_params != family.n_params:
        raise ModelSpecError(f"model masks must have {family.n_params} entries, got {n_params}")
    for name in family.always_free:
        if not masks[:, family.param_names.index(name)].all():
            raise ModelSpecError(f"the parameter {name!r} must be free in every model")
    for name in family.never_free:
        if masks[:, family.param_names.index(name)].any():
            raise ModelSpecError(
                f"the parameter {name!r} is a constant of the {family.name} model: it cannot be fitted"
            )
    for xy in (xy_u, xy_d):
        if xy.shape[-1:] != (2,) or xy.ndim not in (2, 3) or xy.shape[-2] != xy_u.shape[-2]:
            raise ModelSpecError(f"points must be (N, 2) or (B, N, 2), got {xy_u.shape} and {xy_d.shape}")
        if xy.ndim == 3 and xy.shape[0] not in (1, n_models):
            raise ModelSpecError(f"per-item points must have {n_models} rows, got {xy.shape[0]}")


def _run_lm(family, u, d, idx, counts, masks, p, solver: dict, prior_rows=()):
    """The compiled solver over all items in blocks (``p`` is updated in place), in the
    solver's coordinates: ``(status, n_iter, cost, jtj)``; ``prior_rows`` the kernel's
    ``(mean, weight, True)`` of a fit with priors."""
    from oapcal import _kernels

    n_models, n_params = masks.shape
    status = np.zeros(n_models, dtype=np.int64)
    n_iter = np.zeros(n_models, dtype=np.int64)
    cost = np.zeros(n_models)
    want_jtj = solver["want_jtj"]
    jtj = np.zeros((n_models if want_jtj else 1, n_params, n_params))
    fd = None if family.analytic_jacobian else float(family.fd_step)
    _kernels.run_blocks(_kernels.lm_batch, n_models, _kernels.CHUNK, family.code, u, d, idx, counts, masks,
                        family.half, p, int(solver["max_iter"]), float(solver["ftol"]), float(solver["xtol"]),
                        float(solver["gtol"]), fd, want_jtj, status, n_iter, cost, jtj,
                        *prior_rows)  # fmt: skip
    return status, n_iter, cost, jtj


def _priors(prior, masks, p0, family):
    """``fit_batch``'s priors checked: ``(masks, p0, mean, sigma)`` with each zero-width
    prior's parameter fixed at its mean (removed from ``masks``, its start the mean)."""
    try:
        mean, sigma = (np.asarray(a, dtype=float) for a in prior)
        mean, sigma = np.broadcast_to(mean, masks.shape), np.broadcast_to(sigma, masks.shape)
    except (TypeError, ValueError):
        raise ModelSpecError(
            f"prior must be a pair (mean, sigma) of ({masks.shape[1]},) or {masks.shape} arrays"
        ) from None
    if np.isnan(mean).any() or np.isinf(mean).any() or np.isnan(sigma).any() or (sigma < 0).any():
        raise ModelSpecError("prior means must be finite and prior widths (sigma) 0 ... inf")
    zero = masks & (sigma == 0)
    if zero.any():
        for name in family.always_free:
            if zero[:, family.param_names.index(name)].any():
                raise ModelSpecError(f"the parameter {name!r} is always free: it takes no zero-width prior")
        if family.zero_when_fixed and (mean[zero] != 0).any():
            raise ModelSpecError(
                f"a zero-width prior fixes its parameter, and fixed parameters of the {family.name} "
                "model are 0: give it mean 0"
            )
        masks = kernel_array(masks & ~zero, bool)
        p0 = np.where(zero, mean, p0)
    return masks, p0, mean, sigma


def _posterior_covariance(jtj, w2, masks, rss, n_res):
    """The posterior covariance ``s^2 (J^T J + W^2)^-1`` over each item's free parameters
    (zero rows and columns for the fixed ones) and the effective number of parameters
    ``k_eff = tr((J^T J + W^2)^-1 J^T J)`` (the hat matrix's trace), with
    ``s^2 = RSS / (n - k_eff)``.  Without rows (``W = 0``) it is :func:`_covariance`'s."""
    n_models, n_params = masks.shape
    cov = np.zeros((n_models, n_params, n_params))
    k_eff = np.full(n_models, np.nan)
    for b in range(n_models):
        free = np.flatnonzero(masks[b])
        a = jtj[b][np.ix_(free, free)]
        post = a + np.diag(w2[b][free])
        if not np.isfinite(post).all():
            cov[b][np.ix_(free, free)] = np.nan
            continue
        d = np.sqrt(np.diag(post))
        d = np.where(d > 0, d, 1.0)
        inv = np.linalg.pinv(post / np.outer(d, d)) / np.outer(d, d)
        # tr(P^-1 J^T J) = k - tr(P^-1 W^2) for P = J^T J + W^2: the second form is exactly
        # k without rows even where the pseudo-inverse drops a near-degenerate direction
        k_eff[b] = float(len(free) - np.sum(np.diag(inv) * w2[b][free]))
        dof = n_res[b] - k_eff[b]
        s2 = rss[b] / dof if dof > 0 else np.nan
        cov[b][np.ix_(free, free)] = inv * s2
    return cov, k_eff


def _covariance(jtj: np.ndarray, masks: np.ndarray, rss: np.ndarray, n_res: np.ndarray) -> np.ndarray:
    """``s^2 (J^T J)^-1`` over each item's free parameters (pseudo-inverse of the matrix
    scaled to a unit diagonal); zero rows and columns for the fixed ones."""
    n_params = masks.shape[1]
    dof = n_res - masks.sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        s2 = np.where(dof > 0, rss / np.maximum(dof, 1), np.nan)
        diag = np.sqrt(np.einsum("bii->bi", jtj))
        dsub = np.where(masks & (diag > 0), diag, 1.0)
        scaled = jtj / (dsub[:, :, None] * dsub[:, None, :])
    # Fixed parameters get an identity block: the pseudo-inverse of a block-diagonal
    # matrix is block-diagonal, so the free block is unchanged.
    both = masks[:, :, None] & masks[:, None, :]
    scaled = np.where(both, scaled, 0.0) + np.eye(n_params) * ~masks[:, :, None]
    cov = np.full(scaled.shape, np.nan)
    finite = np.isfinite(scaled).all(axis=(1, 2))
    if finite.any():
        cov[finite] = np.linalg.pinv(scaled[finite])
    cov = cov / (dsub[:, :, None] * dsub[:, None, :]) * s2[:, None, None]
    return np.where(both, cov, 0.0)


def check_enough_points(n_points: int, k_free: int, source: str = "the point data") -> None:
    """Raise :class:`DataError` unless there are at least ``k_free + 2`` points."""
    if n_points < k_free + 2:
        raise DataError(
            f"{source}: {n_points} point pairs are too few for a model with {k_free} free "
            f"parameters; give at least {k_free + 2} pairs or choose a smaller model"
        )


def fit(
    xy_u: np.ndarray,
    xy_d: np.ndarray,
    model="paper",
    init=DEFAULT_INIT,
    **options,
) -> FitResult:
    """Fit one model (a spec for :func:`oapcal.model.parse_any_model`: Eq. 1, with
    ``+rotation`` the target's rotation too, or a mask of another family) to point pairs
    ``(N, 2)``.  A relay model (mask ``(36,)``) needs ``init``, its design's vector.

    ``init`` is as in :func:`initial_params`.  With ``"auto"`` (:data:`DEFAULT_INIT`) the
    fit starts from :func:`centre_start` and also from the paper's ``pixel`` and ``zero``
    starts, and keeps the converged fit with the lowest RSS (the centre start on a tie:
    the paper model has an exact two-fold ambiguity, docs/models.md, and the centre start
    puts the distortion centre in the middle of the points).  Trying all three costs two
    more fits; model selection and the robustness test use the centre start alone.
    ``options`` go to :func:`fit_batch`.
    Raises :class:`~oapcal.errors.DataError` when there are fewer points than the free
    parameters + 2; otherwise returns a :class:`FitResult` whether or not it converged.
    """
    mask = parse_any_model(model)
    family = family_of_spec(model)
    xy_u, xy_d = point_pairs(xy_u, xy_d)  # finite (N, 2) pairs, or a named DataError
    check_enough_points(len(xy_u), int(mask.sum()))
    if family.zero_when_fixed:  # Eq. (1), with or without the rotation (which starts at 0)
        starts = ["auto", "pixel", "zero"] if isinstance(init, str) and init == "auto" else [init]
        p0 = np.stack([initial_params(s, xy_u, xy_d, mask, family=family) for s in starts])
    else:  # a design-based family starts from its design's vector
        p0 = np.asarray(init, float)
        if isinstance(init, str) or p0.shape != (family.n_params,):
            raise ModelSpecError(
                f"a {family.name} model starts from its design: give init as its ({family.n_params},) "
                "parameter vector (oapcal.optics.relay_model.relay_params)"
            )
        p0 = p0[None]
    batch = fit_batch(xy_u, xy_d, np.repeat(mask[None], len(p0), 0), p0, **{"family": family, **options})
    rss = np.where(batch.converged & np.isfinite(batch.rss), batch.rss, np.inf)
    if not np.isfinite(rss).any():
        return batch.item(0)
    # Equivalent minima (same RSS to 1e-9 relative; the paper model has an exact two-fold
    # ambiguity, docs/models.md) go to the first start: the centre start, whose
    # distortion centre is the middle of the points.
    best = int(np.flatnonzero(rss <= rss.min() * (1 + 1e-9) + 1e-300)[0])
    return batch.item(best)
