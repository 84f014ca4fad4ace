"""Refinement of one bar triplet: a local affine correction of the registration with its own
contrast and blur, fitted to the pixels around the triplet; corners by Newton."""

from __future__ import annotations

import numpy as np

from oapcal.imaging.detect.registration import _invert, _levenberg_marquardt, _Reference, _region

#: Largest number of pixels one triplet's fit uses (a regular subsample beyond: a large
#: triplet has far more pixels than its 8 parameters need).
MAX_TRIPLET_PIXELS = 12_000


def _refine_triplet(
    img,
    warp,
    rects,
    target,
    bars,
    idx,
    corners_u,
    pred,
    a,
    b,
    sigma,
    um_per_px,
    *,
    max_stderr_px,
    ambiguity_ratio,
    swap_axes=False,
    masks=None,
):
    """Local affine refinement of one triplet; returns (drop reason or None, xy, stderr, info).

    ``a``, ``b``: the starting background and contrast, or ``a`` None to take them from a
    linear fit of the pixels to the model at the start (uneven illumination); ``b`` then
    gives only the polarity (its sign) that the fitted contrast must have.
    """
    h, w = img.shape
    w_ref = float(target.bar_width[bars[0]]) / um_per_px  # bar width, reference px
    u_tri = corners_u[idx]
    margin = 1.5 * w_ref + 3.0 * sigma + 1.0
    lo = u_tri.min(axis=0) - margin
    hi = u_tri.max(axis=0) + margin
    # A raster of this triplet's neighbourhood only (bounded, cheap to re-blur for every
    # trial sigma), holding every bar near it.
    pad = 3.0 * max(sigma, 1.0) + 2.0 * w_ref + 4.0
    ref = _Reference(rects, margin=pad, window=(lo - pad, hi + pad), masks=masks)
    xs = _region(warp, ref, w, h, lo, hi, max_pixels=MAX_TRIPLET_PIXELS)
    if len(xs) < 20:
        return "outside", None, None, None
    values = img[xs[:, 1].astype(int), xs[:, 0].astype(int)]
    x_t = pred[idx].mean(axis=0)
    l_t = max(float(np.ptp(pred[idx], axis=0).max()) / 2, 1.0)
    basis = np.column_stack([np.ones(len(xs)), (xs - x_t) / l_t])
    base_u = warp(xs)
    if a is None:
        r0 = ref.sample(base_u, sigma)[0]
        design = np.column_stack([np.ones_like(r0), r0])
        (a, b0), *_ = np.linalg.lstsq(design, values, rcond=None)
        if not (np.isfinite(b0) and np.sign(b0) == np.sign(b) and abs(b0) > 1e-6):
            return "contrast", None, None, None
        b = float(b0)
    # Bounds: the blur at most about a bar width (beyond, the bars are not resolved and the
    # corners are meaningless), the local correction at most a bar width anywhere.
    res = _levenberg_marquardt(
        values, base_u, basis, ref, np.zeros((3, 2)), a, b, sigma, fit_sigma=True,
        sigma_max=max(1.2 * w_ref, 1.5 * sigma, 1.0), max_shift=max(w_ref, 2.0),
    )  # fmt: skip

    def local(x):
        return warp(x) + np.column_stack([np.ones(len(x)), (x - x_t) / l_t]) @ res.coef

    def local_jac(x):
        return warp.jacobian(x) + (res.coef[1:].T / l_t)[None]

    xy = _invert(local, local_jac, u_tri, pred[idx])
    if not (res.converged and np.isfinite(xy).all() and np.isfinite(res.cov).all()):
        return "not_converged", None, None, None
    if np.sign(res.b) != np.sign(b) or not 0.4 < res.b / b < 2.5:
        return "contrast", None, None, None
    if np.hypot(*(xy - pred[idx]).T).max() > 0.5 * w_ref:
        return "moved", None, None, None
    # Ambiguity: the same fit shifted by one bar period (2 w) across the bars.
    orient = target.bar_orientation[bars[0]]
    axis = 1 if (orient == "H") != swap_axes else 0
    best = res.cost
    shifted = []
    for sgn in (-1.0, 1.0):
        shift = np.zeros(2)
        shift[axis] = sgn * 2 * w_ref
        u = base_u + basis @ res.coef + shift
        r = ref.sample(u, res.sigma)[0]
        design = np.column_stack([np.ones_like(r), r])
        coef, *_ = np.linalg.lstsq(design, values, rcond=None)
        resid = values - design @ coef
        shifted.append(float(resid @ resid))
    if min(shifted) < ambiguity_ratio * best:
        return "ambiguous", None, None, None
    # Corner standard errors from the covariance of the 6 local warp coefficients.
    cov = res.cov[:6, :6]  # order: coef[:,0] (3), coef[:,1] (3)
    jw = local_jac(xy)
    jinv = np.linalg.inv(jw)
    loc = np.column_stack([np.ones(len(xy)), (xy - x_t) / l_t])
    se = np.empty(len(xy))
    for k in range(len(xy)):
        du = np.zeros((2, 6))
        du[0, :3] = loc[k]
        du[1, 3:] = loc[k]
        dx = -jinv[k] @ du
        se[k] = float(np.sqrt(np.trace(dx @ cov @ dx.T) / 2))
    if se.max() > max_stderr_px:
        return "uncertain", None, None, None
    return None, xy, se, {"ncc": res.ncc, "sigma": res.sigma, "b": res.b}
