"""Fitting Eq. (1) to point pairs: a batched Levenberg-Marquardt solver and ``FitResult``.

The fit minimises the forward residuals ``distort(xy_u; p) - xy_d`` (in the units of the
distorted points) over the free parameters of a model, the others held at 0.

:func:`fit_batch` fits B models at once (each with its own mask, start and, optionally,
its own points), all advancing together; :func:`fit` is one model.  Both return values,
never raise on numerical failure: every item has a ``status`` and ``message``.

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
    INDEX,
    N_PARAMS,
    PARAM_NAMES,
    SCALE_EXPONENTS,
    distort,
    identity_params,
    jacobian_params,
    names_from_mask,
    params_from_dict,
    parse_model,
    scale_params,
)
from oapcal.stats import information_criteria

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

    def value(self, name: str) -> float:
        """The fitted value of one parameter."""
        return float(self.params[INDEX[name]])

    @property
    def params_dict(self) -> dict[str, float]:
        return {name: float(v) for name, v in zip(PARAM_NAMES, self.params)}

    @property
    def stderr_dict(self) -> dict[str, float]:
        """Standard errors of the free parameters, by name."""
        return {name: float(self.stderr[INDEX[name]]) for name in self.free}

    @property
    def mask(self) -> np.ndarray:
        return parse_model(self.free)


@dataclass(frozen=True)
class BatchFit:
    """Results of :func:`fit_batch` for B models; every array has B as its first axis.

    ``params (B, 13)``, ``covariance (B, 13, 13)`` (zero rows and columns for fixed
    parameters), ``rss (B,)``, ``n_iter (B,)``, ``status (B,)`` (see
    :data:`STATUS_MESSAGES`), ``converged (B,)``; ``n`` residuals per item and ``masks``.
    """

    masks: np.ndarray
    params: np.ndarray
    covariance: np.ndarray
    rss: np.ndarray
    n: int
    n_iter: np.ndarray
    status: np.ndarray
    converged: np.ndarray = field(init=False)

    def __post_init__(self):
        object.__setattr__(self, "converged", self.status > 0)

    def __len__(self) -> int:
        return len(self.params)

    def item(self, i: int) -> FitResult:
        """Item ``i`` as a :class:`FitResult`."""
        mask = self.masks[i]
        k = int(mask.sum())
        cov_full = self.covariance[i]
        cov = cov_full[np.ix_(mask, mask)]
        stderr = np.full(N_PARAMS, np.nan)
        stderr[mask] = np.sqrt(np.clip(np.diag(cov), 0, None))
        ic = information_criteria(self.rss[i], self.n, k)
        status = int(self.status[i])
        return FitResult(
            free=names_from_mask(mask),
            params=_readonly(self.params[i]),
            stderr=_readonly(stderr),
            covariance=_readonly(cov),
            rss=float(self.rss[i]),
            n=self.n,
            k=k,
            aic=ic.aic,
            aicc=ic.aicc,
            bic=ic.bic,
            converged=status > 0,
            status=status,
            message=STATUS_MESSAGES[status],
            n_iter=int(self.n_iter[i]),
        )


def initial_params(init, xy_u: np.ndarray, xy_d: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Starting values ``(13,)`` for a fit; fixed parameters are always 0 (``m`` is free).

    ``init`` is ``"zero"`` (the paper's default: all 0, m = 1), ``"pixel"`` (the paper's
    pixel-scale guesses: k1 = 1e-6, p1 = 1e-4, s3 = 1e-4, x_off = -W/2, y_off = -H/2,
    c_x = W/2, c_y = H/2, m = 1, where W/2 and H/2 are the middle of the x and y range
    spanned by all points, i.e. W = x_min + x_max), a mapping of name -> value over the
    zero start, a string ``"k1=1e-6,m=1"`` of the same, or a ``(13,)`` array.
    """
    mask = np.asarray(mask, bool)
    if isinstance(init, str) and init == "zero":
        p = identity_params()
    elif isinstance(init, str) and init == "pixel":
        pts = np.concatenate([np.asarray(xy_u, float), np.asarray(xy_d, float)])
        half_w = 0.5 * (pts[:, 0].min() + pts[:, 0].max())
        half_h = 0.5 * (pts[:, 1].min() + pts[:, 1].max())
        p = params_from_dict(
            {"k1": 1e-6, "p1": 1e-4, "s3": 1e-4, "x_off": -half_w, "y_off": -half_h,
             "c_x": half_w, "c_y": half_h, "m": 1.0}
        )  # fmt: skip
    elif isinstance(init, str):
        p = params_from_dict(_parse_assignments(init))
    elif isinstance(init, Mapping):
        p = params_from_dict(init)
    else:
        p = np.array(init, dtype=float)
        if p.shape != (N_PARAMS,):
            raise ModelSpecError(f"initial values must have {N_PARAMS} entries, got shape {p.shape}")
    return np.where(mask, p, 0.0)


def _parse_assignments(text: str) -> dict[str, float]:
    values = {}
    for item in text.split(","):
        if not item.strip():
            continue
        name, sep, value = item.partition("=")
        if not sep:
            raise ModelSpecError(
                f"bad initial value {item.strip()!r}: use 'zero', 'pixel' or name=value pairs "
                "such as 'k1=1e-6,m=1'"
            )
        try:
            values[name.strip()] = float(value)
        except ValueError:
            raise ModelSpecError(f"initial value of {name.strip()!r} is not a number: {value!r}") from None
    return values


def fit_batch(
    xy_u: np.ndarray,
    xy_d: np.ndarray,
    masks: np.ndarray,
    p0: np.ndarray,
    *,
    max_iter: int = 200,
    ftol: float = 1e-12,
    xtol: float = 1e-12,
    gtol: float = 1e-12,
    scale: float | None = None,
) -> BatchFit:
    """Fit B models at once by Levenberg-Marquardt.

    Parameters
    ----------
    xy_u, xy_d : ``(N, 2)`` or ``(B, N, 2)`` reference and observed distorted points.
    masks : ``(B, 13)`` bool, the free parameters of each model (``m`` must be free).
    p0 : ``(B, 13)`` starting values (fixed entries are forced to 0).
    max_iter : cap on LM iterations (Jacobian evaluations) per item.
    ftol, xtol, gtol : MINPACK-style tolerances: relative cost reduction (actual and
        predicted), relative scaled step, and the largest cosine between the residual
        vector and a Jacobian column.
    scale : the coordinate factor ``f`` (default: the largest absolute coordinate).

    All items advance together; an item stops when it meets a tolerance, fails, or hits
    ``max_iter``, and its status says which.
    """
    xy_u = np.asarray(xy_u, dtype=float)
    xy_d = np.asarray(xy_d, dtype=float)
    masks = np.atleast_2d(np.asarray(masks, dtype=bool))
    p0 = np.atleast_2d(np.asarray(p0, dtype=float))
    n_models = masks.shape[0]
    if not masks[:, INDEX["m"]].all():
        raise ModelSpecError("the magnification m must be free in every model")
    n_res = 2 * xy_u.shape[-2]

    f = float(scale) if scale else float(max(np.abs(xy_u).max(), np.abs(xy_d).max(), 1e-300))
    u = xy_u / f
    d = xy_d / f
    p = np.where(masks, scale_params(np.broadcast_to(p0, masks.shape), f), 0.0)
    fixed = ~masks

    def residuals(params, active):
        uu = u if u.ndim == 2 else u[active]
        dd = d if d.ndim == 2 else d[active]
        return (distort(uu, params) - dd).reshape(len(params), -1)

    def normal_equations(params, active):
        uu = u if u.ndim == 2 else u[active]
        jac = jacobian_params(uu, params).reshape(len(params), -1, N_PARAMS)
        jac = np.where(fixed[active][:, None, :], 0.0, jac)
        return jac

    status = np.full(n_models, 0, dtype=np.int64)
    n_iter = np.zeros(n_models, dtype=np.int64)
    lam = np.full(n_models, 1e-3)
    nu = np.full(n_models, 2.0)
    with np.errstate(all="ignore"):
        r = residuals(p, np.arange(n_models))
        cost = 0.5 * np.einsum("bi,bi->b", r, r)
        status[~np.isfinite(cost)] = -1
        status[cost == 0] = 4
        running = status == 0
        need_jac = np.ones(n_models, dtype=bool)
        jtj = np.zeros((n_models, N_PARAMS, N_PARAMS))
        grad = np.zeros((n_models, N_PARAMS))
        eye = np.eye(N_PARAMS)
        for _ in range(max_iter * 4):  # outer cap; each item is capped at max_iter Jacobians
            if not running.any():
                break
            idx = np.flatnonzero(running & need_jac)
            if idx.size:
                jac = normal_equations(p[idx], idx)
                r_i = residuals(p[idx], idx)
                jtj[idx] = np.einsum("bni,bnj->bij", jac, jac)
                grad[idx] = np.einsum("bni,bn->bi", jac, r_i)
                n_iter[idx] += 1
                need_jac[idx] = False
                # gtol: largest cosine between residual vector and a Jacobian column.
                colnorm = np.sqrt(np.einsum("bii->bi", jtj[idx]))
                rnorm = np.sqrt(2.0 * cost[idx])
                with np.errstate(divide="ignore", invalid="ignore"):
                    cosine = np.where(colnorm > 0, np.abs(grad[idx]) / (colnorm * rnorm[:, None]), 0.0)
                hit = np.nanmax(cosine, axis=1) <= gtol
                status[idx[hit]] = 1
                running[idx[hit]] = False
            idx = np.flatnonzero(running)
            if not idx.size:
                break
            a = jtj[idx]
            g = grad[idx]
            fx = fixed[idx]
            dcol = np.sqrt(np.einsum("bii->bi", a))
            dcol = np.where(fx | ~(dcol > 0), 1.0, dcol)
            a_s = a / (dcol[:, :, None] * dcol[:, None, :])
            a_s = np.where(fx[:, :, None] | fx[:, None, :], 0.0, a_s) + eye * fx[:, :, None]
            g_s = np.where(fx, 0.0, g / dcol)
            lhs = a_s + lam[idx, None, None] * (eye * ~fx[:, :, None])
            try:
                step_s = -np.linalg.solve(lhs, g_s[..., None])[..., 0]
            except np.linalg.LinAlgError:
                step_s = -np.stack([np.linalg.lstsq(m_, v_, rcond=None)[0] for m_, v_ in zip(lhs, g_s)])
            step_s = np.where(fx, 0.0, step_s)
            step = step_s / dcol
            p_new = p[idx] + step
            r_new = residuals(p_new, idx)
            cost_new = 0.5 * np.einsum("bi,bi->b", r_new, r_new)
            predicted = -(
                np.einsum("bi,bi->b", g_s, step_s) + 0.5 * np.einsum("bi,bij,bj->b", step_s, a_s, step_s)
            )
            actual = cost[idx] - cost_new
            rho = np.where(predicted > 0, actual / predicted, -1.0)
            accept = np.isfinite(cost_new) & (actual > 0) & (rho > 1e-4)

            # Convergence tests on this trial step (MINPACK style).
            rel_actual = np.where(cost[idx] > 0, np.abs(actual) / cost[idx], 0.0)
            rel_pred = np.where(cost[idx] > 0, predicted / cost[idx], 0.0)
            f_conv = (rel_actual <= ftol) & (rel_pred <= ftol) & (rho <= 2.0)
            pnorm = np.linalg.norm(p[idx] * dcol, axis=1)
            x_conv = np.linalg.norm(step_s, axis=1) <= xtol * np.maximum(pnorm, 1e-300)

            acc = idx[accept]
            p[acc] = p_new[accept]
            cost[acc] = cost_new[accept]
            need_jac[acc] = True
            rho_a = rho[accept]
            lam[acc] *= np.maximum(1.0 / 3.0, 1.0 - (2.0 * rho_a - 1.0) ** 3)
            nu[acc] = 2.0
            rej = idx[~accept]
            lam[rej] *= nu[rej]
            nu[rej] *= 2.0

            done_f = idx[f_conv & (accept | (np.abs(actual) <= ftol * cost[idx]))]
            status[done_f] = np.where(status[done_f] == 0, 2, status[done_f])
            done_x = idx[x_conv]
            status[done_x] = np.where(status[done_x] == 0, 3, status[done_x])
            status[idx[~np.isfinite(p_new).all(axis=1) & ~accept & (lam[idx] > 1e16)]] = -1
            status[idx[(lam[idx] > 1e32) & (status[idx] == 0)]] = -2
            zero = idx[accept & (cost_new == 0)]
            status[zero] = 4
            capped = (n_iter >= max_iter) & need_jac & (status == 0)
            running = status == 0
            running &= ~capped
        status[~np.isfinite(p).all(axis=1)] = -1
        status[~np.isfinite(cost)] = -1

        # Covariance at the solution: s^2 (J^T J)^-1 over the free parameters.
        idx = np.arange(n_models)
        jac = normal_equations(p, idx)
        jtj = np.einsum("bni,bnj->bij", jac, jac)
        rss_scaled = 2.0 * cost
        dof = n_res - masks.sum(axis=1)
        s2 = np.where(dof > 0, rss_scaled / np.maximum(dof, 1), np.nan)
        cov = np.zeros((n_models, N_PARAMS, N_PARAMS))
        for i in range(n_models):
            mk = masks[i]
            sub = jtj[i][np.ix_(mk, mk)]
            dsub = np.sqrt(np.diag(sub))
            dsub = np.where(dsub > 0, dsub, 1.0)
            try:
                inv = np.linalg.pinv(sub / np.outer(dsub, dsub)) / np.outer(dsub, dsub)
            except np.linalg.LinAlgError:
                inv = np.full(sub.shape, np.nan)
            cov[i][np.ix_(mk, mk)] = inv * s2[i]

    # Back to the data's units: p = p' * f**-e, cov = D cov' D with D = f**-e.
    back = f ** (-SCALE_EXPONENTS)
    params = np.where(masks, p * back, 0.0)
    cov = cov * back[None, :, None] * back[None, None, :]
    return BatchFit(
        masks=masks,
        params=params,
        covariance=cov,
        rss=rss_scaled * f * f,
        n=n_res,
        n_iter=n_iter,
        status=status,
    )


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
    init="auto",
    **options,
) -> FitResult:
    """Fit one model (a spec for :func:`oapcal.model.parse_model`) to point pairs ``(N, 2)``.

    ``init`` is as in :func:`initial_params`, or ``"auto"`` (the default): fit from both
    the ``pixel`` and the ``zero`` start and keep the converged fit with the lower RSS
    (the pixel start on a tie).
    On pixel-scale data the zero start can stop in a wrong local minimum, and on
    normalized data the pixel start is far off; trying both costs one more fit.
    ``options`` go to :func:`fit_batch`.
    Raises :class:`~oapcal.errors.DataError` when there are fewer points than the free
    parameters + 2; otherwise returns a :class:`FitResult` whether or not it converged.
    """
    mask = parse_model(model)
    xy_u = np.asarray(xy_u, float)
    xy_d = np.asarray(xy_d, float)
    check_enough_points(len(xy_u), int(mask.sum()))
    starts = ["pixel", "zero"] if isinstance(init, str) and init == "auto" else [init]
    p0 = np.stack([initial_params(s, xy_u, xy_d, mask) for s in starts])
    batch = fit_batch(xy_u, xy_d, np.repeat(mask[None], len(starts), 0), p0, **options)
    rss = np.where(batch.converged & np.isfinite(batch.rss), batch.rss, np.inf)
    if not np.isfinite(rss).any():
        return batch.item(0)
    # Equivalent minima (same RSS to 1e-9 relative; the paper model has an exact two-fold
    # ambiguity, docs/models.md) go to the first start: the pixel start, whose
    # distortion centre is the middle of the points.
    best = int(np.flatnonzero(rss <= rss.min() * (1 + 1e-9) + 1e-300)[0])
    return batch.item(best)
