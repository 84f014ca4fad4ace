"""Registration of the whole target: a polynomial warp camera px -> reference px fitted to
the pixels (Levenberg-Marquardt on ``a + b R_sigma(W(x))``), its reference
raster, and the correlation search that places a target of known scale (8 orientations).

Every fitted parameter is bounded: the blur ``sigma`` stays in ``[SIGMA_MIN, sigma_max]``
(a step outside is rejected like a step that raises the cost), and the reference raster
and the pixels used per level are capped (:data:`MAX_RASTER_CELLS`, :data:`MAX_FIT_PIXELS`),
so the memory a registration needs is known before it starts.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

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
#: Smallest blur sigma a fit may reach (reference px).
SIGMA_MIN = 0.05


# ------------------------------------------------------------------------ polynomial warp


def _exponents(degree: int) -> list[tuple[int, int]]:
    return [(i, t - i) for t in range(degree + 1) for i in range(t, -1, -1)]


@dataclass
class _Warp:
    """``u = sum_k coef[k] * xi^i eta^j`` with ``xi = (x - centre) / scale`` (camera -> ref)."""

    centre: np.ndarray
    scale: float
    coef: np.ndarray  # (nb, 2)
    degree: int

    def basis(self, x: np.ndarray) -> np.ndarray:
        z = (np.asarray(x, float) - self.centre) / self.scale
        return np.stack([z[:, 0] ** i * z[:, 1] ** j for i, j in _exponents(self.degree)], -1)

    def __call__(self, x):
        return self.basis(x) @ self.coef

    def jacobian(self, x) -> np.ndarray:
        """``du/dx`` ``(N, 2, 2)``."""
        z = (np.asarray(x, float) - self.centre) / self.scale
        dx, dy = [], []
        for i, j in _exponents(self.degree):
            dx.append(i * z[:, 0] ** max(i - 1, 0) * z[:, 1] ** j if i else np.zeros(len(z)))
            dy.append(j * z[:, 0] ** i * z[:, 1] ** max(j - 1, 0) if j else np.zeros(len(z)))
        dbx = np.stack(dx, -1) / self.scale
        dby = np.stack(dy, -1) / self.scale
        return np.stack([dbx @ self.coef, dby @ self.coef], -1)  # [n, u/v, x/y]

    def with_degree(self, degree: int) -> _Warp:
        new = np.zeros((len(_exponents(degree)), 2))
        old = _exponents(self.degree)
        for k, e in enumerate(_exponents(degree)):
            if e in old:
                new[k] = self.coef[old.index(e)]
        return _Warp(self.centre, self.scale, new, degree)


def _invert(func, jac, u_target: np.ndarray, x0: np.ndarray, n_iter: int = 30) -> np.ndarray:
    """Solve ``func(x) = u_target`` for x by Newton from ``x0`` (rows independent)."""
    x = np.array(x0, float)
    for _ in range(n_iter):
        r = func(x) - u_target
        jm = jac(x)
        step = np.linalg.solve(jm, r[..., None])[..., 0]
        x = x - step
        if np.nanmax(np.abs(step), initial=0.0) < 1e-9:
            break
    return x


# -------------------------------------------------------------------------- reference


class _Reference:
    """The target's area-sampled raster in reference px and its blurred versions.

    ``window`` ``(lo, hi)`` (reference px) limits the raster to a region (e.g. the part of
    the target that the image shows, or one triplet); the cell size grows beyond
    ``1 / RASTER_OVERSAMPLE`` px when the raster would exceed ``max_cells``.
    """

    def __init__(
        self, rects, margin: float = 40.0, window=None, max_cells: int = MAX_RASTER_CELLS, masks=None
    ):
        rects = np.asarray(rects, float).reshape(-1, 4)
        lo = rects[:, :2].min(axis=0) - margin
        hi = rects[:, 2:].max(axis=0) + margin
        if window is not None:
            lo = np.maximum(lo, np.asarray(window[0], float))
            hi = np.minimum(hi, np.asarray(window[1], float))
            hi = np.maximum(hi, lo + 1.0)
        area = float(np.prod(hi - lo))
        self.step = max(1.0 / RASTER_OVERSAMPLE, float(np.sqrt(area / max_cells)))
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

    @property
    def nbytes(self) -> int:
        return int(self.cover.nbytes * (1 + 3 * RASTER_CACHE))

    def _blurred(self, sigma: float) -> np.ndarray:
        import cv2

        s = max(sigma, SIGMA_MIN) / self.step
        return cv2.GaussianBlur(self.cover, (0, 0), sigmaX=s, borderType=cv2.BORDER_CONSTANT)

    def rasters(self, sigma: float):
        key = round(float(sigma), 4)
        if key not in self._cache:
            r = self._blurred(sigma)
            gv, gu = np.gradient(r, self.step)
            if len(self._cache) >= RASTER_CACHE:
                self._cache.pop(next(iter(self._cache)))
            self._cache[key] = (r, gu.astype(np.float32), gv.astype(np.float32))
        return self._cache[key]

    def sample(self, u: np.ndarray, sigma: float, with_sigma: bool = False):
        """R, dR/du, dR/dv (and dR/dsigma) at reference points ``u`` ``(N, 2)``."""
        from scipy.ndimage import map_coordinates

        coords = [(u[:, 1] - self.start[1]) / self.step, (u[:, 0] - self.start[0]) / self.step]
        out = [map_coordinates(a, coords, order=1, cval=0.0) for a in self.rasters(sigma)]
        if with_sigma:
            h = 0.05 * max(sigma, 0.2)
            lo_s = max(sigma - h, SIGMA_MIN)
            hi = map_coordinates(self._blurred(sigma + h), coords, order=1, cval=0.0)
            lo = map_coordinates(self._blurred(lo_s), coords, order=1, cval=0.0)
            out.append((hi - lo) / (sigma + h - lo_s))
        return out


@dataclass
class _LMResult:
    coef: np.ndarray
    a: float
    b: float
    sigma: float
    cost: float
    cov: np.ndarray
    converged: bool
    n_iter: int
    ncc: float


def _levenberg_marquardt(
    values,
    base_u,
    basis,
    ref: _Reference,
    coef,
    a,
    b,
    sigma,
    *,
    fit_sigma,
    max_iter=40,
    tol=1e-3,
    sigma_max=np.inf,
    max_shift=np.inf,
) -> _LMResult:
    """Fit ``values ~ a + b R_sigma(base_u + basis @ coef)`` (Levenberg-Marquardt).

    Parameters: ``coef`` ``(nb, 2)``, ``a``, ``b`` and optionally ``sigma``, bounded: a
    step that takes ``sigma`` out of ``[SIGMA_MIN, sigma_max]`` or moves any pixel's
    reference point by more than ``max_shift`` from the start is rejected like a step that
    raises the cost.  Converged when the largest change of ``u`` at any pixel is below
    ``tol`` reference px.
    """  # fmt: skip
    nb = basis.shape[1]
    theta = np.concatenate([coef[:, 0], coef[:, 1], [a, b], [sigma] if fit_sigma else []])

    def unpack(t):
        c = np.stack([t[:nb], t[nb : 2 * nb]], -1)
        s = t[2 * nb + 2] if fit_sigma else sigma
        return c, t[2 * nb], t[2 * nb + 1], s

    start_u = base_u + basis @ coef

    def evaluate(t):
        c, a_, b_, s = unpack(t)
        if not SIGMA_MIN < s <= sigma_max:
            return None
        u = base_u + basis @ c
        if np.isfinite(max_shift) and np.abs(u - start_u).max() > max_shift:
            return None
        smp = ref.sample(u, s, with_sigma=fit_sigma)
        model = a_ + b_ * smp[0]
        return values - model, smp, b_

    lam = 1e-3
    cur = evaluate(theta)
    cost = float(cur[0] @ cur[0])
    converged = False
    n_iter = 0
    jtj = None
    for n_iter in range(1, max_iter + 1):  # noqa: B007  (n_iter is reported)
        res, smp, b_ = cur
        cols = [
            b_ * smp[1][:, None] * basis,
            b_ * smp[2][:, None] * basis,
            np.ones((len(res), 1)),
            smp[0][:, None],
        ]
        if fit_sigma:
            cols.append(b_ * smp[3][:, None])
        jm = np.concatenate(cols, axis=1)
        jtj = jm.T @ jm
        g = jm.T @ res
        d = np.diag(jtj).copy()
        d[d <= 0] = 1.0
        improved = False
        for _ in range(12):
            try:
                step = np.linalg.solve(jtj + lam * np.diag(d), g)
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            trial = evaluate(theta + step)
            if trial is not None and np.isfinite(trial[0]).all():
                new_cost = float(trial[0] @ trial[0])
                if new_cost <= cost:
                    theta = theta + step
                    cur, cost = trial, new_cost
                    lam = max(lam / 3, 1e-7)
                    improved = True
                    break
            lam *= 10
        if not improved:
            converged = True  # no step reduces the cost: at a minimum (or stuck)
            break
        du = np.abs(basis @ np.stack([step[:nb], step[nb : 2 * nb]], -1)).max()
        if du < tol:
            converged = True
            break
    c, a_, b_, s = unpack(theta)
    dof = max(len(values) - len(theta), 1)
    try:
        cov = np.linalg.inv(jtj) * cost / dof if jtj is not None else np.full((len(theta),) * 2, np.nan)
    except np.linalg.LinAlgError:
        cov = np.full((len(theta),) * 2, np.nan)
    model = values - cur[0]
    ncc = float(np.corrcoef(values, model)[0, 1]) if np.std(model) > 0 else 0.0
    return _LMResult(c, float(a_), float(b_), float(s), cost, cov, converged, n_iter, ncc)


def _find_target(img: np.ndarray, rects: np.ndarray, centre: np.ndarray):
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


def _camera_sigma(warp: _Warp, sigma_ref: float) -> float:
    """PSF sigma in camera px from the fitted blur in reference px (which includes the
    pixel's own box, variance 1/12 px^2), at the centre of the target."""
    scale = float(np.sqrt(abs(np.linalg.det(warp.jacobian(warp.centre[None, :])[0]))))
    total = sigma_ref / scale
    return float(np.sqrt(max(total**2 - 1 / 12, 0.0)))


def _initial_warp(s, shift, ref_centre, rects, w, h) -> _Warp:
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
    return _Warp(centre, scale, coef, 1)


def _initial_inverse(warp: _Warp, u: np.ndarray) -> np.ndarray:
    """Camera points from the affine part of ``warp`` (Newton's start)."""
    jac = warp.jacobian(warp.centre[None, :])[0]
    u0 = warp(warp.centre[None, :])[0]
    return warp.centre + np.linalg.solve(jac, (u - u0).T).T


def _region(warp: _Warp, ref: _Reference, w: int, h: int, lo=None, hi=None, max_pixels=None) -> np.ndarray:
    """Integer camera pixels whose reference point lies in ``[lo, hi]`` (default: the
    target's extent plus a margin); a regular subsample of them (every k-th row and
    column) when there would be more than ``max_pixels``."""
    lo = ref.lo if lo is None else lo
    hi = ref.hi if hi is None else hi
    corners = np.array([[lo[0], lo[1]], [hi[0], lo[1]], [hi[0], hi[1]], [lo[0], hi[1]]])
    x0 = _initial_inverse(warp, corners)
    xc = _invert(warp, warp.jacobian, corners, x0)
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
