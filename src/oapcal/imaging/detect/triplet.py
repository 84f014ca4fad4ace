"""Refinement of one bar triplet: a local affine correction of the registration with its own
contrast and blur, fitted to the pixels around the triplet; corners by Newton."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from oapcal.imaging.detect.registration import (
    CELLS_PER_SIGMA,
    FitOptions,
    FitStart,
    PixelData,
    Reference,
    fit_pixels,
    region_pixels,
)
from oapcal.imaging.detect.warp import PolyWarp, newton_invert

#: How far (bar widths) an element's registration (:func:`refine_element`) may move it: its
#: two triplets, a quarter turn to each other, leave no slip by one bar period.
ELEMENT_MAX_SHIFT = 2.0
#: ... and the largest blur (times the registration's) it may fit: the element pass corrects
#: where an element is, in the image's blur; a fit that blurs its pixels several times more
#: is not fitting that element's bars (measured: the real FPM micrograph turned by 30 degrees
#: and mirrored on a 3 Mpx canvas, G3E2 in the canvas's fill fitted 14.9 and 36.5 reference
#: px against the registration's 1.1, and blurring the raster that much took 38 s of the
#: detection's 90 s; the LAB-UMK renders' elements fit at most 1.8 times the registration's).
ELEMENT_MAX_BLUR = 4.0
#: ... and only where both its triplets show bars: a triplet whose pixels (the box of its
#: predicted corners) vary by less than this fraction of the registration's contrast
#: (standard deviation) lies outside what the image shows (a turned canvas's fill, a
#: saturated or dark region), and the other triplet alone does not pin a move of two bar
#: widths (measured: on the FPM micrograph turned by 30 degrees on a 3 Mpx canvas, four
#: group-3 elements with one triplet wholly in the fill took 3.8 s of the detection's 27 s
#: and none of their triplets was kept).  Sharp bars vary by about half their contrast.
FLAT_FRACTION = 0.05
#: Largest number of pixels one triplet's fit uses (a regular subsample beyond: a large
#: triplet has far more pixels than its 8 parameters need).
MAX_TRIPLET_PIXELS = 12_000
#: A triplet whose fitted blur exceeds this many bar widths is not resolved: its bars'
#: modulation (the contrast of the bar period, ``exp(-pi**2 sigma**2 / (2 w**2))``) is below
#: 2e-5 of their contrast, so the fit places its corners from the blurred blob of the three
#: bars and the drawn layout alone, not from its bars (measured: group 5 under a 5 px blur,
#: fitted blur 1.7-2.6 bar widths, corners 1-1.9 px off the truth with standard errors of
#: 0.06 px; every kept triplet of the real images is at most 0.95).
UNRESOLVED_BLUR = 1.5


@dataclass(frozen=True)
class TripletContext:
    """What the refinement of every triplet of one registration shares.

    ``img`` the normalised image, ``warp`` the registration (camera -> reference px),
    ``rects``/``masks`` the model's bars and the boxes no fit uses (reference px),
    ``target`` the target, ``corners_u`` its corners (reference px) and ``pred`` their
    predicted camera positions; ``a``, ``b``: the starting background and contrast, or ``a``
    None to take them from a linear fit of the pixels to the model at the start (uneven
    illumination), ``b`` then gives only the polarity (its sign) that the fitted contrast
    must have; ``sigma`` the starting blur (reference px), ``um_per_px`` the scale of the
    reference px, ``swap_axes`` a quarter turn (H bars run vertically); ``max_stderr_px``
    and ``ambiguity_ratio`` the limits of :func:`refine_triplet`.
    """

    img: np.ndarray
    warp: PolyWarp
    rects: np.ndarray
    masks: np.ndarray | None
    target: object
    corners_u: np.ndarray
    pred: np.ndarray
    a: float | None
    b: float
    sigma: float
    um_per_px: float
    max_stderr_px: float
    ambiguity_ratio: float
    swap_axes: bool = False


@dataclass(frozen=True)
class _Local:
    """One triplet's pixels and the local model around it."""

    data: PixelData
    x_t: np.ndarray  # centre and half size of the local affine correction's coordinates
    l_t: float
    w_ref: float  # bar width, reference px
    xs: np.ndarray | None = None  # the camera pixels (N, 2)

    def on(self, warp: PolyWarp) -> _Local:
        """The same pixels, raster and local coordinates, their reference points through
        ``warp`` (another base for the same fit: :func:`refine_element`)."""
        d = self.data
        return replace(self, data=PixelData(d.values, warp(self.xs), d.basis, d.ref))


def refine_triplet(ctx: TripletContext, bars, idx):
    """Local affine refinement of the triplet of ``bars`` (corner indices ``idx``); returns
    (drop reason or None, xy, stderr, info) (:class:`TripletContext` for the start)."""
    # the local correction at most a bar width anywhere
    reason, local, res, b = _fit_local(ctx, bars, idx, widths=1.0, floor_px=2.0)
    if reason is not None:
        return reason, None, None, None
    w_ref = local.w_ref
    warp = _with_affine(ctx.warp, local, res.coef)
    pred = ctx.pred[idx]
    xy = newton_invert(warp, warp.jacobian, ctx.corners_u[idx], pred)
    if not (res.converged and np.isfinite(xy).all() and np.isfinite(res.cov).all()):
        return "not_converged", None, None, None
    if np.sign(res.b) != np.sign(b) or not 0.4 < res.b / b < 2.5:
        return "contrast", None, None, None
    if np.hypot(*(xy - pred).T).max() > 0.5 * w_ref:
        return "moved", None, None, None
    if res.sigma > UNRESOLVED_BLUR * w_ref:
        return "unresolved", None, None, None
    if _ambiguous(ctx, local, res, bars):
        return "ambiguous", None, None, None
    se = _corner_stderr(local, res, warp.jacobian, xy)
    if se.max() > ctx.max_stderr_px:
        return "uncertain", None, None, None
    return None, xy, se, {"ncc": res.ncc, "sigma": res.sigma, "b": res.b}


def refine_element(ctx: TripletContext, bars, idx) -> TripletContext | None:
    """``ctx`` with its registration corrected for one element (the ``bars`` of both its
    triplets, corner indices ``idx``): an affine correction fitted to the element's pixels,
    which may move it by up to :data:`ELEMENT_MAX_SHIFT` bar widths, added either to the
    registration or to its tangent at the element's predicted centre
    (:meth:`PolyWarp.tangent`, an affine map: the registration's curvature left out),
    whichever fits the same pixels with the lower cost; the element's corners predicted
    through it.  None when neither fit succeeds or its contrast is not the registration's
    (``core._refine_twice`` says why).

    Why the tangent: an element is registered again where the registration is off by more
    than half a bar width, mostly at the edge of what the image shows of the target, where
    its polynomial (degree up to 4) is least constrained, so its curvature there may be
    wrong too.  Measured on the LAB-UMK micrograph through misaligned relays: group 5's
    triplets refined on the registration plus the element's correction came 0.4-0.95 px
    (median) off the truth from every start (G5E2 then dropped); with the choice, G5E2
    0.15-0.23 px and G5E3 0.29-0.32 px (0.39-0.48 before).  Why
    not always the tangent: where the registration's curvature is right, the tangent
    leaves out the field's own (a simulated setup-1 field: G5E1's corners 0.16 px off on
    the tangent, 0.02 px on the registration).  None, without a fit, when one of the
    triplets shows no bars (:data:`FLAT_FRACTION`)."""
    if not all(_shows_bars(ctx, bars[ctx.target.bar_orientation[bars] == o]) for o in ("H", "V")):
        return None
    tangent = replace(ctx, warp=ctx.warp.tangent(ctx.pred[idx].mean(axis=0)))
    best = None
    shared = None
    for base in (tangent, ctx):
        reason, local, res, b = _fit_local(
            base, bars, idx, widths=ELEMENT_MAX_SHIFT, floor_px=0.0, max_blur=ELEMENT_MAX_BLUR,
            local=None if shared is None else shared.on(base.warp),
        )  # fmt: skip
        if local is not None:
            shared = local  # both bases judged on the same pixels, with one raster and its blurs
        if (
            reason is not None
            or not (res.converged and np.isfinite(res.coef).all())
            or np.sign(res.b) != np.sign(b)
        ):
            continue
        if best is None or res.cost < best[0]:
            best = (res.cost, _with_affine(base.warp, local, res.coef))
    if best is None:
        return None
    warp = best[1]
    pred = ctx.pred.copy()
    pred[idx] = warp.inverse(ctx.corners_u[idx], x0=ctx.pred[idx])
    if not np.isfinite(pred[idx]).all():
        return None
    return replace(ctx, warp=warp, pred=pred)


def corner_indices(bars) -> np.ndarray:
    """The sorted indices of the four corners of each bar of ``bars``."""
    return np.sort(np.concatenate([4 * np.asarray(bars) + c for c in range(4)]))


def _shows_bars(ctx: TripletContext, bars) -> bool:
    """Whether the image varies over the box of the predicted corners of the triplet of
    ``bars`` by at least :data:`FLAT_FRACTION` of the registration's contrast (True when
    the context has no contrast of its own, ``ctx.a`` None)."""
    xy = ctx.pred[corner_indices(bars)]
    if ctx.a is None or not np.isfinite(xy).all():
        return True
    h, w = ctx.img.shape
    c0, r0 = np.maximum(np.floor(xy.min(axis=0)).astype(int), 0)
    c1, r1 = np.minimum(np.ceil(xy.max(axis=0)).astype(int), [w - 1, h - 1])
    if c1 < c0 or r1 < r0:
        return False
    return float(np.std(ctx.img[r0 : r1 + 1, c0 : c1 + 1])) >= FLAT_FRACTION * abs(ctx.b)


def _fit_local(ctx: TripletContext, bars, idx, *, widths: float, floor_px: float, max_blur=None, local=None):
    """The local affine correction of the registration fitted to the pixels around ``bars``
    (corner indices ``idx``; or to those of ``local``, :meth:`_Local.on`), moving no pixel
    by more than ``widths`` bar widths (at least ``floor_px``), for :func:`refine_triplet`
    and :func:`refine_element`: ``(drop reason or None, local pixels, fit, starting
    contrast)``.  The blur is bounded by about a bar width: beyond, the bars are not
    resolved and the corners are meaningless; and, given ``max_blur``, by that many times
    the registration's blur."""
    if local is None:
        local = _local_pixels(ctx, bars, idx)
    if local is None:
        return "outside", None, None, None
    a, b = ctx.a, ctx.b
    if a is None:
        a, b = _linear_contrast(local.data, ctx.sigma, b)
        if a is None:
            return "contrast", None, None, None
    w_ref, sigma = local.w_ref, ctx.sigma
    sigma_max = max(1.2 * w_ref, 1.5 * sigma, 1.0)
    if max_blur is not None:
        sigma_max = min(sigma_max, max(max_blur * sigma, 1.5 * sigma, 1.0))
    options = FitOptions(fit_sigma=True, sigma_max=sigma_max, max_shift=max(widths * w_ref, floor_px))
    res = fit_pixels(local.data, FitStart(np.zeros((3, 2)), a, b, sigma), options)
    return None, local, res, b


def _with_affine(warp: PolyWarp, local: _Local, coef: np.ndarray) -> PolyWarp:
    """``warp`` plus the local affine correction ``coef`` (in the basis ``1, (x - x_t) / l_t``
    of the local pixels, :func:`_local_pixels`) as one :class:`PolyWarp`: the same map, in
    ``warp``'s basis (``1, (x - centre) / scale, ...``)."""
    k = warp.scale / local.l_t
    shift = (warp.centre - local.x_t) / local.l_t
    out = warp.coef.copy()
    out[0] += coef[0] + shift[0] * coef[1] + shift[1] * coef[2]
    out[1] += k * coef[1]
    out[2] += k * coef[2]
    return warp.with_coef(out)


def _local_pixels(ctx: TripletContext, bars, idx) -> _Local | None:
    """The pixels around the triplet (None when fewer than 20) and a raster of its
    neighbourhood only (bounded, cheap to re-blur for every trial sigma), holding every bar
    near it."""
    img, sigma = ctx.img, ctx.sigma
    h, w = img.shape
    w_ref = float(ctx.target.bar_width[bars[0]]) / ctx.um_per_px
    u_tri = ctx.corners_u[idx]
    margin = 1.5 * w_ref + 3.0 * sigma + 1.0
    lo = u_tri.min(axis=0) - margin
    hi = u_tri.max(axis=0) + margin
    pad = 3.0 * max(sigma, 1.0) + 2.0 * w_ref + 4.0
    ref = Reference(ctx.rects, margin=pad, window=(lo - pad, hi + pad), masks=ctx.masks,
                    min_step=sigma / CELLS_PER_SIGMA)  # fmt: skip
    xs = region_pixels(ctx.warp, ref, (w, h), lo, hi, max_pixels=MAX_TRIPLET_PIXELS)
    if len(xs) < 20:
        return None
    values = img[xs[:, 1].astype(int), xs[:, 0].astype(int)]
    pred = ctx.pred[idx]
    x_t = pred.mean(axis=0)
    l_t = max(float(np.ptp(pred, axis=0).max()) / 2, 1.0)
    basis = np.column_stack([np.ones(len(xs)), (xs - x_t) / l_t])
    return _Local(PixelData(values, ctx.warp(xs), basis, ref), x_t, l_t, w_ref, xs)


def _linear_contrast(data: PixelData, sigma: float, b_sign: float):
    """``(a, b)`` of a linear fit of the pixels to the model at the start, or ``(None,
    None)`` when its contrast has not the sign of ``b_sign``."""
    r0 = data.ref.sample(data.base_u, sigma, derivatives=False)[0]
    design = np.column_stack([np.ones_like(r0), r0])
    (a, b0), *_ = np.linalg.lstsq(design, data.values, rcond=None)
    if not (np.isfinite(b0) and np.sign(b0) == np.sign(b_sign) and abs(b0) > 1e-6):
        return None, None
    return a, float(b0)


def _ambiguous(ctx: TripletContext, local: _Local, res, bars) -> bool:
    """Whether the same fit shifted by one bar period (2 w) across the bars explains the
    pixels nearly as well (``ambiguity_ratio``)."""
    orient = ctx.target.bar_orientation[bars[0]]
    axis = 1 if (orient == "H") != ctx.swap_axes else 0
    data = local.data
    shifted = []
    for sgn in (-1.0, 1.0):
        shift = np.zeros(2)
        shift[axis] = sgn * 2 * local.w_ref
        u = data.base_u + data.basis @ res.coef + shift
        r = data.ref.sample(u, res.sigma, derivatives=False)[0]
        design = np.column_stack([np.ones_like(r), r])
        coef, *_ = np.linalg.lstsq(design, data.values, rcond=None)
        resid = data.values - design @ coef
        shifted.append(float(resid @ resid))
    return min(shifted) < ctx.ambiguity_ratio * res.cost


def _corner_stderr(local: _Local, res, jac, xy) -> np.ndarray:
    """Corner standard errors from the covariance of the 6 local warp coefficients."""
    cov = res.cov[:6, :6]  # order: coef[:,0] (3), coef[:,1] (3)
    jinv = np.linalg.inv(jac(xy))
    loc = np.column_stack([np.ones(len(xy)), (xy - local.x_t) / local.l_t])
    se = np.empty(len(xy))
    for k in range(len(xy)):
        du = np.zeros((2, 6))
        du[0, :3] = loc[k]
        du[1, 3:] = loc[k]
        dx = -jinv[k] @ du
        se[k] = float(np.sqrt(np.trace(dx @ cov @ dx.T) / 2))
    return se
