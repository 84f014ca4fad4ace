"""The error a calibration's covariance cannot see, measured on its own landmarks.

The fit's covariance (:mod:`oapcal.uncertainty`) is the error of the parameters *if the
model were exact*.  Two things it misses, both measured here and kept in the calibration
as an :class:`~oapcal.uncertainty.ErrorModel`:

* **The model floor** ``F``: what the model cannot fit.  A landmark's residual is its own
  noise (independent from landmark to landmark) plus the misfit of the model (smooth, so
  neighbouring landmarks share it).  The mean dot product of each landmark's residual
  vector with those of its :data:`NEIGHBOURS` nearest neighbours estimates the misfit's
  mean squared length ``F^2`` (noise does not correlate); the rest of the residual
  variance is noise.  A correction error that the covariance cannot see is then ``F`` per
  point, not ``F / sqrt(n)``.
* **Extrapolation**: beyond the landmarks the error grows faster than the propagated
  uncertainty says (the terms the model lacks grow faster than those it has).  The
  landmarks are refitted :data:`SIDES` times, each time without the outermost
  :data:`HOLDOUT_FRACTION` of them in one direction, and the held-out landmarks are
  predicted: per side, the factor ``kappa^2 = (sum |h|^2 - m (F^2 + noise^2)) / sum sigma^2``
  (``h`` the held-out residuals, ``sigma`` the refit's propagated uncertainty there,
  ``m`` points) says by how much the propagated uncertainty underestimates the
  extrapolation error; a series model (Eq. 1 and its variants) keeps the worst side
  (``kappa >= 1``), because the terms it lacks act more on some sides than on others and
  the side a user extrapolates to may be the worst one.  The refits extrapolate by up to
  ``t_p`` hull radii (:data:`PROBED_QUANTILE` of the held-out landmarks' distances); beyond,
  the factor grows as ``((1 + d / R) / (1 + t_p))^g``, :data:`GROWTH_EXPONENT` ``g = 2``:
  the terms a model lacks are of higher order than those it has (for Eq. 1, the radial
  ``r^5`` beyond the fitted ``r^3``: two orders).
* **A physical model** (the relay families, :data:`oapcal.model.RELAY_FAMILIES`) lacks no
  terms of a series: the optics it traces are the distortion's own cause, and what it
  cannot fit (mirror figure, sensor) is in the floor ``F``.  Its sides' factors are then
  noisy estimates of one factor, and the worst of 8 of them is biased high (it made the
  relay's predicted error 2-3x too large beyond the landmarks: 84-99 % of the field within
  1 sigma, docs/benchmarks.md); it keeps their mean and grows
  beyond the probed distance as the field, ``g = 1`` (:data:`PHYSICAL_GROWTH_EXPONENT`).

``benchmarks/uncertainty.py`` measures the coverage this gives (docs/benchmarks.md).
"""

from __future__ import annotations

import numpy as np

from oapcal.uncertainty import ErrorModel, hull_distance, hull_radius, position_covariance

#: Neighbours whose residuals each landmark's is compared with (the floor estimate).
NEIGHBOURS = 4
#: Refits, each leaving out one side of the landmarks (directions evenly spread).
SIDES = 8
#: Share of the landmarks each refit leaves out (the outermost along its direction).
HOLDOUT_FRACTION = 0.25
#: Quantile over the sides' factors kept as the extrapolation factor: 1, the worst side
#: (the upper quartile left the demo's far extrapolation 3x optimistic: docs/benchmarks.md).
SIDE_QUANTILE = 1.0
#: Exponent ``g`` of the growth of the extrapolation factor with the distance ``d`` beyond
#: the hull, ``(1 + d / R)^g`` (``R`` the hull's radius): the model's missing terms grow
#: faster than its fitted ones (set from benchmarks/uncertainty.py and the demo).
GROWTH_EXPONENT = 2.0
#: The growth exponent ``g`` of a physical model's extrapolation factor beyond the probed
#: distance: out-of-model effects that grow with the field, not missing terms of higher order
#: (set from benchmarks/uncertainty.py: docs/benchmarks.md#uncertainty-coverage-and-the-trust-region).
PHYSICAL_GROWTH_EXPONENT = 1.0
#: Quantile of the held-out landmarks' distances (over the reduced hull's radius) up to
#: which the extrapolation factor counts as measured.
PROBED_QUANTILE = 0.9
#: Fewest landmarks for which the floor and the extrapolation are measured.
MIN_POINTS = 12


def estimate_error_model(xy_u, xy_d, params, mask=None, *, family=None, **fit_options) -> ErrorModel | None:
    """The :class:`~oapcal.uncertainty.ErrorModel` of the model ``params`` fitted to
    reference points ``xy_u`` and distorted points ``xy_d`` ``(N, 2)``, in the fit's
    coordinates (module docstring).  ``params`` is a :class:`~oapcal.model.Model` (its free
    parameters are the fitted ones unless ``mask`` is given) or a parameter vector of
    ``family`` with the free-parameter ``mask`` (a legacy call without ``family``: the
    built-in family of its length).  ``fit_options`` are the fit's own (passed to
    :func:`oapcal.fitting.fit_batch` for the refits).  None with fewer than
    :data:`MIN_POINTS` landmarks whose correction converges.
    """
    from scipy.spatial import cKDTree

    from oapcal.model import RELAY_FAMILIES, Model, as_model

    xy_u = np.asarray(xy_u, float)
    xy_d = np.asarray(xy_d, float)
    model = as_model(params, family)
    if mask is not None:
        model = Model.from_mask(model.family, model.params, mask)
    k = len(model.free)
    inv = model.inverse(xy_d)
    ok = inv.converged & np.isfinite(inv.xy).all(axis=1)
    xy_u, xy_d, resid = xy_u[ok], xy_d[ok], inv.xy[ok] - xy_u[ok]
    n = len(xy_u)
    if n < max(MIN_POINTS, k + 2):
        return None
    # the residual variance per point (2-D), with the fit's degrees of freedom
    ms = float((resid * resid).sum() / max(n - k / 2, 1))
    tree = cKDTree(xy_u)
    dist, nb = tree.query(xy_u, min(NEIGHBOURS, n - 1) + 1)
    floor2 = max(0.0, float((resid[:, None, :] * resid[nb[:, 1:]]).sum(-1).mean()))
    noise2 = max(ms - floor2, 0.0)
    spacing = float(np.median(dist[:, 1]))
    ratios, reach = _side_ratios(xy_u, xy_d, model, floor2 + noise2, fit_options)
    physical = model.family in RELAY_FAMILIES
    if not ratios:
        kappa2 = 1.0
    elif physical:  # one factor, estimated on every side: their mean
        kappa2 = max(1.0, float(np.mean(ratios)))
    else:
        kappa2 = max(1.0, float(np.quantile(ratios, SIDE_QUANTILE)))
    return ErrorModel(
        floor_px=float(np.sqrt(floor2)),
        noise_px=float(np.sqrt(noise2)),
        extrapolation=float(np.sqrt(kappa2)),
        ramp_px=spacing if spacing > 0 else 1.0,
        sides=SIDES,
        sides_used=len(ratios),
        holdout_fraction=HOLDOUT_FRACTION,
        growth_exponent=PHYSICAL_GROWTH_EXPONENT if physical else GROWTH_EXPONENT,
        probed_distance=float(np.quantile(np.concatenate(reach), PROBED_QUANTILE)) if reach else 0.0,
        method="leave-side-out-mean" if physical else "leave-side-out",
    )


def _side_ratios(xy_u, xy_d, model, point_var: float, fit_options: dict) -> tuple[list, list]:
    """Refit without each side of the landmarks (:func:`_sides`) and predict the held-out
    ones: per converged side, the factor ``kappa^2`` (module docstring; ``point_var`` is
    ``F^2 + noise^2``) and the held-out landmarks' distances beyond the refit's hull (in
    hull radii)."""
    import inspect

    from oapcal.fitting import fit_batch

    mask = model.mask
    k = int(mask.sum())
    keep = _sides(xy_u)
    keep = keep[keep.sum(axis=1) >= k + 2]
    ratios, reach = [], []
    if not len(keep):
        return ratios, reach
    # the fit's own options, as far as the batched solver takes them (covariance: always)
    accepted = set(inspect.signature(fit_batch).parameters) - {"covariance", "points", "family"}
    fit_options = {key: v for key, v in fit_options.items() if key in accepted}
    masks = np.repeat(mask[None], len(keep), 0)
    starts = np.repeat(np.asarray(model.params)[None], len(keep), 0)
    batch = fit_batch(xy_u, xy_d, masks, starts, points=keep, family=model.family, **fit_options)
    idx = np.flatnonzero(mask)
    for b in range(len(keep)):
        if not batch.converged[b]:
            continue
        out = ~keep[b]
        side = model.with_params(batch.params[b])
        cov_b = batch.covariance[b][np.ix_(idx, idx)]
        inv_b = side.inverse(xy_d[out])
        good = inv_b.converged & np.isfinite(inv_b.xy).all(axis=1)
        if not good.any():
            continue
        h = inv_b.xy[good] - xy_u[out][good]
        cv = position_covariance(xy_u[out][good], side, cov_b)
        sp2 = cv[:, 0, 0] + cv[:, 1, 1]
        sp2 = np.where(np.isfinite(sp2), sp2, 0.0)
        hull_b = _hull(xy_u[keep[b]])
        reach.append(hull_distance(xy_u[out][good], hull_b) / max(hull_radius(hull_b), 1e-300))
        if sp2.sum() <= 0:
            continue
        excess = (h * h).sum() - good.sum() * point_var
        ratios.append(float(excess / sp2.sum()))
    return ratios, reach


def _hull(xy: np.ndarray) -> np.ndarray:
    from scipy.spatial import ConvexHull

    return xy[ConvexHull(xy).vertices]


def _sides(xy_u: np.ndarray) -> np.ndarray:
    """``(SIDES, N)`` bool: the landmarks each refit keeps (all but the outermost
    :data:`HOLDOUT_FRACTION` along its direction)."""
    centre = xy_u.mean(axis=0)
    keep = []
    for j in range(SIDES):
        theta = 2 * np.pi * j / SIDES
        proj = (xy_u - centre) @ np.array([np.cos(theta), np.sin(theta)])
        keep.append(proj < np.quantile(proj, 1 - HOLDOUT_FRACTION))
    return np.array(keep)
