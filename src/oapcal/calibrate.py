"""From point pairs to a :class:`~oapcal.io.calibration.Calibration`: normalize, fit,
score the correction as in the paper's Table 1, record the calibrated region.

>>> from oapcal.synthetic import synthetic_pairs
>>> data = synthetic_pairs(seed=0)
>>> cal = calibrate(data.xy_u, data.xy_d, model="paper")
>>> cal.fit["converged"], cal.residuals["mean_px"] < 1.0
(True, True)
"""

from __future__ import annotations

import numpy as np

from oapcal.io.calibration import Calibration
from oapcal.normalize import normalize
from oapcal.stats import correction_residuals


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
    **fit_options,
) -> Calibration:
    """Fit ``model`` to reference points ``xy_u`` and distorted points ``xy_d`` ``(N, 2)``.

    ``um_per_px`` is the object-space size of one unit of the reference points *as given*;
    with ``normalization="experiment"`` it is converted through the normalization scale.
    The residual statistics are those of :func:`oapcal.stats.correction_residuals`.
    """
    from scipy.spatial import ConvexHull, QhullError

    from oapcal.fit import fit

    norm = normalize(normalization, xy_u, xy_d)
    result = fit(norm.xy_u, norm.xy_d, model, init=init, **fit_options)
    scale = None if um_per_px is None else float(um_per_px) / norm.scale_u
    residuals = correction_residuals(result.params, norm.xy_u, norm.xy_d, scale)
    try:
        hull = norm.xy_u[ConvexHull(norm.xy_u).vertices]
    except QhullError:
        hull = None
    lo = norm.xy_u.min(axis=0)
    hi = norm.xy_u.max(axis=0)
    init_name = init if isinstance(init, str) else "user"
    return Calibration(
        free=result.free,
        params=np.array(result.params),
        stderr=np.array(result.stderr),
        covariance=np.array(result.covariance),
        fit={
            "n_points": len(norm.xy_u),
            "n_residuals": result.n,
            "k": result.k,
            "rss": result.rss,
            "aic": result.aic,
            "aicc": result.aicc,
            "bic": result.bic,
            "converged": result.converged,
            "status": result.status,
            "message": result.message,
            "n_iter": result.n_iter,
            "init": init_name,
            "normalize": normalization,
        },
        residuals=residuals.to_dict(),
        um_per_px=scale,
        image_size=tuple(int(v) for v in image_size) if image_size else None,
        bounds=(float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])),
        hull=hull,
        name=name,
        source=source,
    )
