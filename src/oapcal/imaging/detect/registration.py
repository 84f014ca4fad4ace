"""Registration of the whole target: a polynomial warp camera px -> reference px fitted to
the pixels (Levenberg-Marquardt on ``a + b R_sigma(W(x))``), its reference
raster, and the correlation search that places a target of known scale (8 orientations).

Every fitted parameter is bounded: the blur ``sigma`` stays in ``[SIGMA_MIN, sigma_max]``
(a step outside is rejected like a step that raises the cost), and the reference raster
and the pixels used per level are capped (:data:`MAX_RASTER_CELLS`, :data:`MAX_FIT_PIXELS`),
so the memory a registration needs is known before it starts.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from oapcal.imaging.detect.warp import PolyWarp
from oapcal.imaging.usaf import render_rectangles

#: Reference raster cells per reference px (fewer when the raster would exceed
#: :data:`MAX_RASTER_CELLS`).
RASTER_OVERSAMPLE = 2
#: Largest reference raster (cells); with its 3 float32 derivatives and at most
#: :data:`RASTER_CACHE` blurred copies this bounds the raster memory (about 0.6 GB).
MAX_RASTER_CELLS = 12_000_000
RASTER_CACHE = 3
#: Largest number of pixels one fit uses (a regular subsample beyond).
MAX_FIT_PIXELS = 250_000
#: Raster cells per blur sigma that a triplet's refinement needs at least: the cells are
#: area-sampled, so a coarser cell of size h only adds variance (its box and the bilinear
#: sampling: about h^2 / 4, here sigma^2 / 64, a blur 0.8 % wider, which the fitted blur
#: absorbs); what is left is 0.1-0.3 % of the contrast and no edge moves
#: (tests/imaging/test_detect_raster_cells.py).  A soft high-magnification image (sigma of
#: 8 reference px) was blurred cell by cell at half a reference px, its largest cost.
CELLS_PER_SIGMA = 4.0
#: A fit of the blur rebuilds its raster with cells of ``1 / CELLS_PER_SIGMA`` of the blur it
#: reached once that is this many times the raster's cells (:meth:`_PixelProblem.follow_blur`).
FOLLOW_BLUR_FACTOR = 2.0
#: Blur sigma (raster cells) from which :meth:`Reference._blurred` blurs on coarser cells
#: (at least this many per sigma: values within 0.1 % of the contrast of the direct blur).
COARSE_BLUR_CELLS = 12.0
#: Smallest blur sigma a fit may reach (reference px).
SIGMA_MIN = 0.05
#: Blur sigma (raster cells) from which :meth:`Reference.sigma_derivative` takes the
#: Laplacian of the blurred raster (error under 1.2 %) instead of a difference of two blurs.
LAPLACIAN_MIN_CELLS = 1.5
#: Second derivative, fourth order, unit spacing: (-1, 16, -30, 16, -1) / 12.
_D2_KERNEL = np.array([-1.0, 16.0, -30.0, 16.0, -1.0], np.float32) / 12.0


# -------------------------------------------------------------------------- reference


class Reference:
    """The target's area-sampled raster in reference px and its blurred versions.

    ``window`` ``(lo, hi)`` (reference px) limits the raster to a region (e.g. the part of
    the target that the image shows, or one triplet); the cell size grows beyond
    ``1 / RASTER_OVERSAMPLE`` px when the raster would exceed ``max_cells``, and to
    ``min_step`` when given (a raster blurred by many cells needs no finer cells than a
    fraction of its blur: :data:`CELLS_PER_SIGMA`).
    """

    def __init__(
        self, rects, margin: float = 40.0, window=None, max_cells: int = MAX_RASTER_CELLS, masks=None,
        min_step: float = 0.0,
    ):  # fmt: skip
        rects = np.asarray(rects, float).reshape(-1, 4)
        self._inputs = (rects, margin, window, max_cells, masks)
        lo = rects[:, :2].min(axis=0) - margin
        hi = rects[:, 2:].max(axis=0) + margin
        if window is not None:
            lo = np.maximum(lo, np.asarray(window[0], float))
            hi = np.minimum(hi, np.asarray(window[1], float))
            hi = np.maximum(hi, lo + 1.0)
        area = float(np.prod(hi - lo))
        self.step = max(1.0 / RASTER_OVERSAMPLE, float(np.sqrt(area / max_cells)), float(min_step))
        self.start = np.floor(lo)
        n = np.ceil((hi - self.start) / self.step).astype(int) + 1
        self.lo, self.hi = lo + margin / 2, hi - margin / 2
        if window is not None:
            self.lo, self.hi = np.maximum(self.lo, lo), np.minimum(self.hi, hi)
        near = (
            (rects[:, 2] >= lo[0]) & (rects[:, 0] <= hi[0]) & (rects[:, 3] >= lo[1]) & (rects[:, 1] <= hi[1])
        )
        cover = render_rectangles(rects[near], (n[1], n[0]), start=tuple(self.start), step=self.step)
        self.cover = cover.astype(np.float32)
        self._cache: dict = {}
        #: reference-px boxes (x0, y0, x1, y1) whose pixels no fit uses (the printed numbers)
        self.masks = np.zeros((0, 4)) if masks is None else np.asarray(masks, float).reshape(-1, 4)

    def with_min_step(self, min_step: float) -> Reference:
        """The same reference (its region ``lo``/``hi`` too) with cells of at least
        ``min_step`` (itself when its cells are that large already)."""
        if min_step <= self.step:
            return self
        rects, margin, window, max_cells, masks = self._inputs
        out = Reference(rects, margin, window, max_cells, masks, min_step=min_step)
        out.lo, out.hi = self.lo.copy(), self.hi.copy()
        return out

    def for_blur(self, sigma: float) -> Reference:
        """The same reference with cells no finer than a blur of ``sigma`` needs
        (:data:`CELLS_PER_SIGMA` per sigma; :meth:`with_min_step`)."""
        return self.with_min_step(sigma / CELLS_PER_SIGMA)

    @property
    def nbytes(self) -> int:
        return int(self.cover.nbytes * (1 + 3 * RASTER_CACHE))

    def _blurred(self, sigma: float) -> np.ndarray:
        """The raster blurred by ``sigma``; a blur of ``f >= 2`` times :data:`COARSE_BLUR_CELLS`
        cells is done on cells ``f`` times larger (area-averaged; ``f`` whole) and
        interpolated back, as :data:`CELLS_PER_SIGMA` says cells of a
        fraction of the blur suffice: a blur's cost grows with its width in cells, and a fit
        that wanders to a wide blur (a triplet in a turned canvas's fill reached 15.5
        reference px, 31 cells, against the image's 1.1) blurred a raster of 1.8 M cells for
        every trial step."""
        import cv2

        s = max(sigma, SIGMA_MIN) / self.step
        f = int(s // COARSE_BLUR_CELLS)
        if f < 2:
            return cv2.GaussianBlur(self.cover, (0, 0), sigmaX=s, borderType=cv2.BORDER_CONSTANT)
        h, w = self.cover.shape
        hh, ww = -(-h // f) * f, -(-w // f) * f
        padded = cv2.copyMakeBorder(self.cover, 0, hh - h, 0, ww - w, cv2.BORDER_CONSTANT, value=0.0)
        small = cv2.resize(padded, (ww // f, hh // f), interpolation=cv2.INTER_AREA)
        small = cv2.GaussianBlur(small, (0, 0), sigmaX=s / f, borderType=cv2.BORDER_CONSTANT)
        # cv2's resize keeps pixel centres aligned: fine cell j from coarse (j + 1/2) / f - 1/2
        return np.ascontiguousarray(cv2.resize(small, (ww, hh), interpolation=cv2.INTER_LINEAR)[:h, :w])

    def rasters(self, sigma: float, gradients: bool = True):
        """The raster blurred by ``sigma`` and, with ``gradients``, its two derivatives
        (computed once a caller needs them: a rejected step of a fit needs the raster alone)."""
        key = round(float(sigma), 4)
        if key not in self._cache:
            if len(self._cache) >= RASTER_CACHE:
                self._cache.pop(next(iter(self._cache)))
            self._cache[key] = [self._blurred(sigma)]
        entry = self._cache[key]
        if gradients and len(entry) == 1:
            entry += list(_gradient(entry[0], self.step))
        return tuple(entry) if gradients else (entry[0],)

    def sample(self, u: np.ndarray, sigma: float, with_sigma: bool = False, derivatives: bool = True):
        """R, dR/du, dR/dv (and dR/dsigma) at reference points ``u`` ``(N, 2)``; R alone
        without ``derivatives``."""
        r = [_bilinear(self.rasters(sigma, gradients=False)[0], self._coords(u))]
        return r + self.derivatives(u, sigma, with_sigma) if derivatives else r

    def derivatives(self, u: np.ndarray, sigma: float, with_sigma: bool = False):
        """dR/du, dR/dv (and dR/dsigma) at ``u``: :meth:`sample`'s entries after R."""
        coords = self._coords(u)
        out = [_bilinear(a, coords) for a in self.rasters(sigma)[1:]]
        if with_sigma:
            out.append(self.sigma_derivative(coords, sigma))
        return out

    def sigma_derivative(self, coords, sigma: float) -> np.ndarray:
        """dR/dsigma at raster coordinates ``coords``.

        A Gaussian blur solves the heat equation, ``dR_sigma/dsigma = sigma * Laplacian(R_sigma)``:
        from the raster already blurred by ``sigma`` and a fourth-order Laplacian (two cv2
        filters, a tenth of one blur's time) where the blur spans at least
        :data:`LAPLACIAN_MIN_CELLS` cells.  It replaces the central difference of two more
        blurs of the whole raster, a quarter of the detection time of a 3 Mpx image (10 of
        36 s); the two agree within 1.2 %, within 0.5 % from 2 cells
        (tests/imaging/test_detect_raster_cells.py).  Below, the blurred raster is too rough
        for a stencil and the difference of two blurs (cheap at that width) is used.
        """
        import cv2

        if sigma / self.step >= LAPLACIAN_MIN_CELLS:
            r = self.rasters(sigma, gradients=False)[0]
            one = np.ones(1, np.float32)
            lap = cv2.sepFilter2D(r, cv2.CV_32F, _D2_KERNEL, one, borderType=cv2.BORDER_CONSTANT)
            lap += cv2.sepFilter2D(r, cv2.CV_32F, one, _D2_KERNEL, borderType=cv2.BORDER_CONSTANT)
            return _bilinear(lap, coords) * (sigma / self.step**2)
        h = 0.05 * max(sigma, 0.2)
        lo_s = max(sigma - h, SIGMA_MIN)
        hi = _bilinear(self._blurred(sigma + h), coords)
        lo = _bilinear(self._blurred(lo_s), coords)
        return (hi - lo) / (sigma + h - lo_s)

    def _coords(self, u: np.ndarray):
        return [(u[:, 1] - self.start[1]) / self.step, (u[:, 0] - self.start[0]) / self.step]


def _gradient(raster: np.ndarray, step: float):
    """``(d/du, d/dv)`` of a float32 raster with cells of ``step``: ``np.gradient``'s central
    differences inside and one-sided differences at the edges, computed by cv2 (a tenth of
    ``np.gradient``'s time on a raster of a million cells; a large image's registration
    takes the gradient of every blurred raster it fits; tests/imaging/test_detect_raster_cells.py
    compares the two)."""
    import cv2

    out = []
    for dx, dy, axis in ((1, 0, 1), (0, 1, 0)):
        g = cv2.Sobel(raster, cv2.CV_32F, dx, dy, ksize=1, borderType=cv2.BORDER_REPLICATE)
        g /= np.float32(2.0 * step)  # as np.gradient rounds: the difference, then the division
        if raster.shape[axis] > 1:
            first, last = (np.s_[:, 0], np.s_[:, -1]) if axis == 1 else (np.s_[0], np.s_[-1])
            second, before = (np.s_[:, 1], np.s_[:, -2]) if axis == 1 else (np.s_[1], np.s_[-2])
            g[first] = (raster[second] - raster[first]) / np.float32(step)
            g[last] = (raster[last] - raster[before]) / np.float32(step)
        out.append(g)
    return tuple(out)


def _bilinear(raster: np.ndarray, coords) -> np.ndarray:
    """``raster`` interpolated bilinearly at ``coords`` (rows, columns), 0 outside."""
    from scipy.ndimage import map_coordinates

    return map_coordinates(raster, coords, order=1, cval=0.0)


@dataclass(frozen=True)
class PixelData:
    """What a registration fit models: ``values ~ a + b R_sigma(base_u + basis @ coef)`` at the
    pixels, with ``R_sigma`` the blurred reference raster ``ref``."""

    values: np.ndarray
    base_u: np.ndarray
    basis: np.ndarray
    ref: Reference


@dataclass(frozen=True)
class FitStart:
    """The start of a fit: the warp coefficients ``(nb, 2)``, background, contrast and blur."""

    coef: np.ndarray
    a: float
    b: float
    sigma: float


@dataclass(frozen=True)
class FitOptions:
    """Bounds and stopping rule of :func:`fit_pixels` (its docstring)."""

    fit_sigma: bool
    max_iter: int = 40
    tol: float = 1e-3
    sigma_max: float = np.inf
    max_shift: float = np.inf


@dataclass
class LMResult:
    coef: np.ndarray
    a: float
    b: float
    sigma: float
    cost: float
    cov: np.ndarray
    converged: bool
    n_iter: int
    ncc: float


class _PixelProblem:
    """Residuals and Jacobian of :func:`fit_pixels` in the packed parameters
    ``theta = (coef[:, 0], coef[:, 1], a, b[, sigma])``."""

    def __init__(self, data: PixelData, start: FitStart, options: FitOptions):
        self.data, self.options, self.sigma = data, options, start.sigma
        self.nb = data.basis.shape[1]
        self.start_u = data.base_u + data.basis @ start.coef

    def pack(self, start: FitStart) -> np.ndarray:
        c, extra = start.coef, [start.sigma] if self.options.fit_sigma else []
        return np.concatenate([c[:, 0], c[:, 1], [start.a, start.b], extra])

    def unpack(self, t):
        nb = self.nb
        c = np.stack([t[:nb], t[nb : 2 * nb]], -1)
        s = t[2 * nb + 2] if self.options.fit_sigma else self.sigma
        return c, t[2 * nb], t[2 * nb + 1], s

    def evaluate(self, t):
        """``(residuals, raster samples (R alone), b, (u, sigma))`` at ``t``, or None outside the bounds."""
        d, o = self.data, self.options
        c, a_, b_, s = self.unpack(t)
        if not SIGMA_MIN < s <= o.sigma_max:
            return None
        u = d.base_u + d.basis @ c
        if np.isfinite(o.max_shift) and np.abs(u - self.start_u).max() > o.max_shift:
            return None
        smp = d.ref.sample(u, s, derivatives=False)  # a step may be rejected: the raster's derivatives later
        model = a_ + b_ * smp[0]
        return d.values - model, smp, b_, (u, s)

    def follow_blur(self, theta) -> bool:
        """Rebuild the raster with cells of :data:`CELLS_PER_SIGMA` per the blur at ``theta``
        when that is :data:`FOLLOW_BLUR_FACTOR` times its cells or more (True: rebuilt).  A
        fit starts from a blur hint (1 px) and climbs to the image's own; a soft image's
        (7.8 px in a 2048 px canvas) was climbed on cells of half a px, every blur of a 6 M-cell
        raster 16 cells wide (8-10 s of its finest level).  A sharp image's fit never reaches
        the factor, so its path is the same bit for bit."""
        if not self.options.fit_sigma:
            return False
        s = float(self.unpack(theta)[3])
        ref = self.data.ref
        if s / CELLS_PER_SIGMA < FOLLOW_BLUR_FACTOR * ref.step:
            return False
        self.data = replace(self.data, ref=ref.for_blur(s))
        return True

    def jacobian(self, cur) -> np.ndarray:
        res, smp, b_, (u, s) = cur
        deriv = self.data.ref.derivatives(u, s, with_sigma=self.options.fit_sigma)
        basis = self.data.basis
        cols = [
            b_ * deriv[0][:, None] * basis,
            b_ * deriv[1][:, None] * basis,
            np.ones((len(res), 1)),
            smp[0][:, None],
        ]
        if self.options.fit_sigma:
            cols.append(b_ * deriv[2][:, None])
        return np.concatenate(cols, axis=1)


def fit_pixels(data: PixelData, start: FitStart, options: FitOptions) -> LMResult:
    """Fit ``values ~ a + b R_sigma(base_u + basis @ coef)`` (Levenberg-Marquardt).

    Parameters: ``coef`` ``(nb, 2)``, ``a``, ``b`` and optionally ``sigma``, bounded: a
    step that takes ``sigma`` out of ``[SIGMA_MIN, sigma_max]`` or moves any pixel's
    reference point by more than ``max_shift`` from the start is rejected like a step that
    raises the cost.  Converged when the largest change of ``u`` at any pixel is below
    ``tol`` reference px.

    Written out rather than ``scipy.optimize.least_squares``: the shift bound
    ``|basis @ (coef - coef0)| <= max_shift`` at every pixel is not a box on the parameters
    (``method="trf"`` takes boxes only, ``"lm"`` no bounds at all), the convergence test is
    on the largest pixel shift, and the cost is a bilinearly interpolated raster whose
    Jacobian is the raster's own gradient, not the interpolant's; least_squares stops
    elsewhere on the same problem (tests/imaging/test_detect_solver.py compares the two).
    """
    problem = _PixelProblem(data, start, options)
    theta, cur, cost, jtj, converged, n_iter = _lm_iterate(problem, problem.pack(start))
    c, a_, b_, s = problem.unpack(theta)
    values = data.values
    dof = max(len(values) - len(theta), 1)
    try:
        cov = np.linalg.inv(jtj) * cost / dof if jtj is not None else np.full((len(theta),) * 2, np.nan)
    except np.linalg.LinAlgError:
        cov = np.full((len(theta),) * 2, np.nan)
    model = values - cur[0]
    # a flat patch (e.g. the uniform fill of a turned image's canvas) has no correlation to report
    ncc = float(np.corrcoef(values, model)[0, 1]) if np.std(model) > 0 and np.std(values) > 0 else 0.0
    return LMResult(c, float(a_), float(b_), float(s), cost, cov, converged, n_iter, ncc)


def _lm_iterate(problem: _PixelProblem, theta: np.ndarray):
    """The Levenberg-Marquardt loop of :func:`fit_pixels`: ``(theta, residuals at theta,
    cost, J^T J, converged, iterations)``."""
    nb, basis, options = problem.nb, problem.data.basis, problem.options
    lam = 1e-3
    cur = problem.evaluate(theta)
    cost = float(cur[0] @ cur[0])
    converged = False
    n_iter = 0
    jtj = None
    for n_iter in range(1, options.max_iter + 1):  # noqa: B007  (n_iter is reported)
        jm = problem.jacobian(cur)
        jtj = jm.T @ jm
        g = jm.T @ cur[0]
        d = np.diag(jtj).copy()
        d[d <= 0] = 1.0
        improved = False
        for _ in range(12):
            try:
                step = np.linalg.solve(jtj + lam * np.diag(d), g)
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            trial = problem.evaluate(theta + step)
            if trial is not None and np.isfinite(trial[0]).all():
                new_cost = float(trial[0] @ trial[0])
                if new_cost <= cost:
                    theta = theta + step
                    cur, cost = trial, new_cost
                    lam = max(lam / 3, 1e-7)
                    improved = True
                    if problem.follow_blur(theta):  # the cost on the new raster
                        cur = problem.evaluate(theta)
                        cost = float(cur[0] @ cur[0])
                    break
            lam *= 10
        if not improved:
            converged = True  # no step reduces the cost: at a minimum (or stuck)
            break
        du = np.abs(basis @ np.stack([step[:nb], step[nb : 2 * nb]], -1)).max()
        if du < options.tol:
            converged = True
            break
    return theta, cur, cost, jtj, converged, n_iter


def find_target(img: np.ndarray, rects: np.ndarray, centre: np.ndarray):
    """Similarity by multi-scale NCC at half resolution: returns (scale, shift, ncc, sign)
    with ``camera = scale * u + shift``."""
    import cv2

    small = cv2.resize(cv2.GaussianBlur(img, (0, 0), 3.0), None, fx=0.5, fy=0.5, interpolation=cv2.INTER_AREA)
    small = small.astype(np.float32)
    # Pad with the median so that a target partly outside the image can still be placed.
    pad = (np.ceil(np.ptp(rects.reshape(-1, 2), axis=0) * 1.4 / 4) + 8).astype(int)
    small = cv2.copyMakeBorder(
        small, pad[1], pad[1], pad[0], pad[0], cv2.BORDER_CONSTANT, value=float(np.median(small))
    )
    best = (-1.0, None)
    for s in np.geomspace(0.7, 1.4, 15):
        r = centre + s * (rects.reshape(-1, 2, 2) - centre)
        r = r.reshape(-1, 4)
        lo = r[:, :2].min(axis=0) - 12
        hi = r[:, 2:].max(axis=0) + 12
        n = np.ceil((hi - lo) / 2).astype(int) + 1
        if n[0] >= small.shape[1] or n[1] >= small.shape[0]:
            continue
        templ = render_rectangles(r, (n[1], n[0]), start=tuple(lo), step=2.0).astype(np.float32)
        templ = cv2.GaussianBlur(templ, (0, 0), 1.5)
        score = cv2.matchTemplate(small, templ, cv2.TM_CCOEFF_NORMED)
        k = int(np.argmax(np.abs(score)))
        yx = np.unravel_index(k, score.shape)
        val = float(abs(score[yx]))
        if val > best[0]:
            sign = 1.0 if score[yx] > 0 else -1.0
            # Template cell (0, 0) is the scaled reference point ``lo``, and half-res pixel
            # (X, Y) is camera point (2X + 0.5, 2Y + 0.5); the scaled reference point of
            # u is centre + s (u - centre), so camera = s u + centre (1 - s) - lo + (2X + .5, 2Y + .5).
            pix = np.array([2 * (yx[1] - pad[0]) + 0.5, 2 * (yx[0] - pad[1]) + 0.5])
            best = (val, (float(s), centre * (1 - s) - lo + pix, sign))
    if best[1] is None:
        return None
    s, shift, sign = best[1]
    return s, shift, best[0], sign


def camera_sigma(warp: PolyWarp, sigma_ref: float) -> float:
    """PSF sigma in camera px from the fitted blur in reference px (which includes the
    pixel's own box, variance 1/12 px^2), at the centre of the target."""
    scale = float(np.sqrt(abs(np.linalg.det(warp.jacobian(warp.centre[None, :])[0]))))
    total = sigma_ref / scale
    return float(np.sqrt(max(total**2 - 1 / 12, 0.0)))


def initial_warp(s, shift, rects) -> PolyWarp:
    """The affine camera -> reference warp of the similarity ``camera = s u + shift``."""
    lo = rects[:, :2].min(axis=0)
    hi = rects[:, 2:].max(axis=0)
    mid = 0.5 * (lo + hi)
    centre = s * mid + shift
    scale = 0.5 * s * float(max(hi - lo))
    coef = np.zeros((3, 2))
    coef[0] = mid  # u at the centre
    coef[1] = [scale / s, 0.0]  # d u / d xi
    coef[2] = [0.0, scale / s]
    return PolyWarp(centre, scale, coef, 1)


def region_pixels(warp: PolyWarp, ref: Reference, size, lo=None, hi=None, max_pixels=None) -> np.ndarray:
    """Integer camera pixels of an image of ``size`` (w, h) whose reference point lies in
    ``[lo, hi]`` (default: the target's extent plus a margin); a regular subsample of them (every k-th row and
    column) when there would be more than ``max_pixels``."""
    lo = ref.lo if lo is None else lo
    hi = ref.hi if hi is None else hi
    corners = np.array([[lo[0], lo[1]], [hi[0], lo[1]], [hi[0], hi[1]], [lo[0], hi[1]]])
    w, h = size
    xc = warp.inverse(corners)
    pad = 3
    c0 = int(max(0, np.floor(np.nanmin(xc[:, 0])) - pad))
    c1 = int(min(w - 1, np.ceil(np.nanmax(xc[:, 0])) + pad))
    r0 = int(max(0, np.floor(np.nanmin(xc[:, 1])) - pad))
    r1 = int(min(h - 1, np.ceil(np.nanmax(xc[:, 1])) + pad))
    if c1 < c0 or r1 < r0:
        return np.zeros((0, 2))
    step = 1
    if max_pixels is not None:
        step = max(1, int(np.ceil(np.sqrt((c1 - c0 + 1) * (r1 - r0 + 1) / max_pixels))))
    gx, gy = np.meshgrid(np.arange(c0, c1 + 1, step), np.arange(r0, r1 + 1, step))
    xs = np.stack([gx.ravel(), gy.ravel()], -1).astype(float)
    u = warp(xs)
    sel = (u[:, 0] >= lo[0]) & (u[:, 0] <= hi[0]) & (u[:, 1] >= lo[1]) & (u[:, 1] <= hi[1])
    for x0, y0, x1, y1 in ref.masks:
        sel &= ~((u[:, 0] >= x0) & (u[:, 0] <= x1) & (u[:, 1] >= y0) & (u[:, 1] <= y1))
    return xs[sel]
