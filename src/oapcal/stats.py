"""Statistics defined once: information criteria and the paper's Table-1 residuals.

Information criteria
--------------------
For a least-squares fit with Gaussian errors of unknown variance:

* ``n`` is the number of residuals: **two per point** (an x and a y residual).
* ``K`` is the number of estimated quantities: the free model parameters **plus one**
  for the error variance.
* ``AIC  = n ln(RSS / n) + 2 K``
* ``AICc = AIC + 2 K (K + 1) / (n - K - 1)``, undefined (NaN) when ``n - K - 1 <= 0``
* ``BIC  = n ln(RSS / n) + K ln(n)``

Table-1 residuals
-----------------
Observed distorted points are corrected through the fitted inverse and compared with
their reference points; with ``d_i`` the Euclidean distance of pair ``i`` over ``M``
pairs: ``max = max d_i``, ``mean = mean d_i``, ``rms = sqrt(mean d_i^2)`` and the paper's
``total = sqrt(sum d_i^2)``.

>>> ic = information_criteria(rss=2.0, n=100, k_free=3)
>>> round(ic.aicc - ic.aic, 6)   # 2*4*5/(100-4-1)
0.421053
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from oapcal.model import as_model


@dataclass(frozen=True)
class InformationCriteria:
    """AIC, AICc and BIC of one fit; see the module docstring for the formulas."""

    aic: float
    aicc: float
    bic: float


def information_criteria(rss, n, k_free):
    """AIC, AICc and BIC (module docstring); vectorized over ``rss`` and ``k_free``.

    Returns an :class:`InformationCriteria` of floats, or of arrays when the inputs are
    arrays.  AICc is NaN where ``n - K - 1 <= 0``; all three are NaN where ``rss`` is not
    finite.  An exact fit (``rss == 0``) gives ``-inf``.
    """
    rss = np.asarray(rss, dtype=float)
    k = np.asarray(k_free, dtype=float) + 1.0
    n = float(n)
    with np.errstate(divide="ignore", invalid="ignore"):
        loglik_term = n * np.log(rss / n)
        aic = loglik_term + 2.0 * k
        denom = n - k - 1.0
        aicc = np.where(denom > 0, aic + 2.0 * k * (k + 1.0) / np.where(denom > 0, denom, 1.0), np.nan)
        bic = loglik_term + k * np.log(n)
    if aic.ndim == 0:
        return InformationCriteria(float(aic), float(aicc), float(bic))
    return InformationCriteria(aic, aicc, bic)


def _in_um(px_field: str) -> property:
    """A property of :class:`ResidualStats`: the distance ``px_field`` times ``um_per_px``."""

    def get(self) -> float | None:
        value = getattr(self, px_field)
        return None if self.um_per_px is None else value * self.um_per_px

    return property(get, doc=f"``{px_field}`` in um (None without a scale).")


@dataclass(frozen=True)
class ResidualStats:
    """The paper's Table-1 statistics of corrected points against reference points.

    Distances in px (the units of the points); the ``*_um`` fields are filled when a
    scale (um per px of the reference points) is known.  ``n_points`` counts the pairs
    used; ``n_failed`` the points whose inverse did not converge (left out).
    """

    max_px: float
    mean_px: float
    rms_px: float
    total_px: float
    n_points: int
    n_failed: int = 0
    um_per_px: float | None = None

    max_um = _in_um("max_px")
    mean_um = _in_um("mean_px")
    rms_um = _in_um("rms_px")
    total_um = _in_um("total_px")

    def to_dict(self) -> dict:
        """Plain dict with ``max_px mean_px rms_px total_px`` and, with a scale, ``*_um``."""
        out = asdict(self)
        if self.um_per_px is None:
            out.pop("um_per_px")
        else:
            for key in ("max", "mean", "rms", "total"):
                out[f"{key}_um"] = getattr(self, f"{key}_um")
        return out


def residual_stats(xy_corrected, xy_ref, um_per_px: float | None = None) -> ResidualStats:
    """Table-1 statistics of corrected points ``(N, 2)`` against reference points ``(N, 2)``.

    Rows with a NaN corrected point (an inverse that did not converge) are left out and
    counted in ``n_failed``.
    """
    xy_corrected = np.asarray(xy_corrected, dtype=float)
    xy_ref = np.asarray(xy_ref, dtype=float)
    d = np.hypot(*(xy_corrected - xy_ref).T)
    ok = np.isfinite(d)
    d = d[ok]
    if d.size == 0:
        nan = float("nan")
        return ResidualStats(nan, nan, nan, nan, 0, int((~ok).sum()), um_per_px)
    return ResidualStats(
        max_px=float(d.max()),
        mean_px=float(d.mean()),
        rms_px=float(np.sqrt(np.mean(d * d))),
        total_px=float(np.sqrt(np.sum(d * d))),
        n_points=int(d.size),
        n_failed=int((~ok).sum()),
        um_per_px=um_per_px,
    )


def correction_residuals(params, xy_u, xy_d, um_per_px: float | None = None) -> ResidualStats:
    """Correct ``xy_d`` through the inverse of ``params`` (a :class:`~oapcal.model.Model`, a
    fitted record or a bare vector, :func:`~oapcal.model.as_model`) and compare with ``xy_u``
    (Table 1)."""
    inverse = as_model(params).inverse(xy_d)
    return residual_stats(inverse.xy, xy_u, um_per_px)
