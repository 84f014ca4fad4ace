"""Automatic detection of USAF-1951 bar corners in a distorted, blurred camera image.

The detector never looks for corners one by one and then guesses which is which;
instead it registers the whole known target to the image, so every detected corner is
matched by construction, and then refines and checks each bar triplet locally
(``docs/detection.md``):

1. **Find the target and its orientation.** Normalised cross-correlation
   (``cv2.matchTemplate``) of the blurred image with the rendered target at scales 0.7-1.4,
   in each of the 8 orientations of :data:`oapcal.imaging.usaf.ORIENTATIONS` (quarter
   turns, with and without a mirror flip), gives the orientation, a similarity transform
   and the polarity (bright or dark bars).  An orientation whose runner-up scores at least
   :data:`ORIENTATION_RATIO` of it is ambiguous: the detection fails.  From here on the
   reference target is the one turned into this orientation about the image centre, so
   the output ``x_u, y_u`` share the camera's axes.
2. **Register the target densely, coarse to fine.** A polynomial warp ``u = W(x)`` from
   camera px ``x`` to reference px ``u`` is fitted by Gauss-Newton to every pixel around
   the target, the model image being ``a + b * R(W(x))`` with ``R`` the area-sampled target
   blurred by a Gaussian.  Blur and polynomial degree go 6 px / affine, 3 px / quadratic,
   1.5 px / cubic, then the image's own blur (fitted) / degree 4.  Using whole images
   rather than points lets 40 px of distortion be found without knowing it in advance.
3. **Refine each triplet.** Around each three-bar triplet, a local affine correction
   ``u = W(x) + d0 + D (x - x_t)`` with its own ``a, b`` and blur is fitted to the pixels;
   the triplet's 12 corners are the camera points that this local warp sends to the
   reference corners (Newton).
4. **Drop what is not certain.** A triplet's corners are dropped, and counted, when the
   local fit did not converge, the fitted contrast disagrees with the target's, the
   refined corners moved by more than half a bar width from the registration (so they
   could belong to a neighbouring bar), a copy of the fit shifted by one bar period fits
   almost as well (``ambiguous``), a corner's standard error exceeds ``max_stderr_px``,
   or a corner is not fully inside the image.
5. **Check the global alignment.** A smooth model (``full``, Eq. 1) is fitted to all
   matched pairs; pairs off it by more than a robust limit are dropped
   (``inconsistent``), and the whole detection is refused when a quarter of them are,
   when the fit fails, or when fewer than :data:`MIN_KEPT_FRACTION` of the expected
   corners survive (:func:`check_consistency`).

Coordinates follow ``docs/conventions.md``; reference px are the target at ``um_per_px``
with its bounding-box centre at the image centre (``oapcal.imaging.usaf``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from oapcal.errors import DataError
from oapcal.imaging.usaf import ORIENTATIONS, orientation_matrix, render_rectangles, usaf_target

#: (Gaussian blur of both images in px, polynomial degree) of the registration levels;
#: the last level (blur None) uses the image as it is and fits the blur.
LEVELS = ((6.0, 1), (3.0, 2), (1.5, 3), (None, 4))
#: Reference raster cells per reference px.
RASTER_OVERSAMPLE = 2
#: Reason keys of dropped triplets, in the order they are checked.
DROP_REASONS = ("not_converged", "contrast", "moved", "ambiguous", "uncertain", "outside", "inconsistent")
#: The orientation is ambiguous when the second-best orientation's correlation reaches
#: this fraction of the best (measured on relay images: about 0.6).
ORIENTATION_RATIO = 0.9
#: Consistency check (:func:`check_consistency`): residual limit ``max(SIGMAS * s, FLOOR)``
#: px, capped at half a bar width; refuse the alignment above MAX_FRACTION flagged pairs.
CONSISTENCY_FLOOR_PX = 0.5
CONSISTENCY_SIGMAS = 5.0
CONSISTENCY_MAX_FRACTION = 0.25
#: ... and above this rms residual (px) of the consistent pairs: an empirical limit between
#: a right detection through the relay at 94 px distortion (0.39 px, the model's own misfit)
#: and a wrong alignment at 161 px that was smooth enough to fit (0.93 px).
CONSISTENCY_MAX_RMS_PX = 0.75
#: The registration is refused when fewer than this fraction of the corners it expects
#: inside the image pass the local checks (a wrong orientation keeps none).
MIN_KEPT_FRACTION = 0.25


@dataclass(frozen=True)
class Detection:
    """Detected and matched corners of one image.

    ``ids``, ``xy_u`` (reference px), ``xy_d`` (detected camera px) and ``stderr_px``
    (1-sigma position uncertainty from the local fit) of every kept corner;
    ``n_expected`` reference corners that the registration puts fully inside the image;
    ``dropped`` the number of those dropped, by reason (:data:`DROP_REASONS`);
    ``status`` 0 when the target was found (else the message says why); ``polarity``,
    ``sigma_px`` (fitted blur of the image, camera px) and ``ncc`` (correlation of the
    registered model with the image) describe the registration.
    """

    ids: tuple[str, ...]
    xy_u: np.ndarray
    xy_d: np.ndarray
    stderr_px: np.ndarray
    n_expected: int
    dropped: dict = field(default_factory=dict)
    status: int = 0
    message: str = "ok"
    polarity: str = "bright"
    sigma_px: float = float("nan")
    ncc: float = float("nan")
    orientation: str = "none"
    orientation_scores: dict = field(default_factory=dict)
    consistency: dict = field(default_factory=dict)
    predicted: dict = field(default_factory=dict, repr=False)

    @property
    def coverage(self) -> float:
        """Kept corners / corners expected fully inside the image."""
        return len(self.ids) / self.n_expected if self.n_expected else 0.0

    def summary(self) -> dict:
        return {
            "status": self.status,
            "message": self.message,
            "found": len(self.ids),
            "expected": self.n_expected,
            "coverage": self.coverage,
            "dropped": dict(self.dropped),
            "polarity": self.polarity,
            "sigma_px": self.sigma_px,
            "ncc": self.ncc,
            "orientation": self.orientation,
            "orientation_matrix": orientation_matrix(self.orientation).tolist(),
            "orientation_scores": dict(self.orientation_scores),
            "consistency": dict(self.consistency),
        }


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
    """The target's area-sampled raster in reference px and its blurred versions."""

    def __init__(self, rects: np.ndarray, margin: float = 40.0):
        self.step = 1.0 / RASTER_OVERSAMPLE
        lo = rects[:, :2].min(axis=0) - margin
        hi = rects[:, 2:].max(axis=0) + margin
        self.start = np.floor(lo)
        n = np.ceil((hi - self.start) / self.step).astype(int) + 1
        self.lo, self.hi = lo + margin / 2, hi - margin / 2
        self.cover = render_rectangles(rects, (n[1], n[0]), start=tuple(self.start), step=self.step)
        self.cover = self.cover.astype(np.float32)
        self._cache: dict = {}

    def rasters(self, sigma: float):
        key = round(float(sigma), 4)
        if key not in self._cache:
            import cv2

            s = max(sigma, 0.05) / self.step
            r = cv2.GaussianBlur(self.cover, (0, 0), sigmaX=s, borderType=cv2.BORDER_CONSTANT)
            gv, gu = np.gradient(r, self.step)
            if len(self._cache) > 8:
                self._cache.clear()
            self._cache[key] = (r, gu.astype(np.float32), gv.astype(np.float32))
        return self._cache[key]

    def sample(self, u: np.ndarray, sigma: float, with_sigma: bool = False):
        """R, dR/du, dR/dv (and dR/dsigma) at reference points ``u`` ``(N, 2)``."""
        from scipy.ndimage import map_coordinates

        coords = [(u[:, 1] - self.start[1]) / self.step, (u[:, 0] - self.start[0]) / self.step]
        out = [map_coordinates(a, coords, order=1, cval=0.0) for a in self.rasters(sigma)]
        if with_sigma:
            h = 0.05 * max(sigma, 0.2)
            hi = map_coordinates(self.rasters(sigma + h)[0], coords, order=1, cval=0.0)
            lo = map_coordinates(self.rasters(max(sigma - h, 0.05))[0], coords, order=1, cval=0.0)
            out.append((hi - lo) / (sigma + h - max(sigma - h, 0.05)))
        return out


@dataclass
class _GNResult:
    coef: np.ndarray
    a: float
    b: float
    sigma: float
    cost: float
    cov: np.ndarray
    converged: bool
    n_iter: int
    ncc: float


def _gauss_newton(
    values, base_u, basis, ref: _Reference, coef, a, b, sigma, *, fit_sigma, max_iter=40, tol=1e-3
) -> _GNResult:
    """Fit ``values ~ a + b R_sigma(base_u + basis @ coef)`` (Levenberg-Marquardt).

    Parameters: ``coef`` ``(nb, 2)``, ``a``, ``b`` and optionally ``sigma``.  Converged when
    the largest change of ``u`` at any pixel is below ``tol`` reference px.
    """
    nb = basis.shape[1]
    theta = np.concatenate([coef[:, 0], coef[:, 1], [a, b], [sigma] if fit_sigma else []])

    def unpack(t):
        c = np.stack([t[:nb], t[nb : 2 * nb]], -1)
        s = t[2 * nb + 2] if fit_sigma else sigma
        return c, t[2 * nb], t[2 * nb + 1], s

    def evaluate(t):
        c, a_, b_, s = unpack(t)
        if s <= 0.05:
            return None
        u = base_u + basis @ c
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
    return _GNResult(c, float(a_), float(b_), float(s), cost, cov, converged, n_iter, ncc)


# ---------------------------------------------------------------------------- detection


def _to_float_image(image: np.ndarray) -> np.ndarray:
    img = np.asarray(image)
    if img.ndim == 3:
        img = img[..., :3].mean(axis=-1)
    if img.ndim != 2:
        raise DataError(f"image has shape {img.shape}: expected a 2-D grey or colour image")
    img = img.astype(np.float64)
    lo, hi = np.percentile(img, [0.5, 99.9])
    if not hi > lo:
        raise DataError("the image is uniform: there is no target to detect")
    return (img - lo) / (hi - lo)


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


def detect_usaf(
    image: np.ndarray,
    groups=(4, 5),
    um_per_px: float = 4.8,
    *,
    orientation: str = "auto",
    sigma_hint_px: float = 1.0,
    max_stderr_px: float = 0.3,
    ambiguity_ratio: float = 1.5,
    orientation_ratio: float = ORIENTATION_RATIO,
    consistency_model: str | None = "auto",
    progress: bool = False,
) -> Detection:
    """Find, match and refine the bar corners of USAF ``groups`` in ``image`` (module docstring).

    ``um_per_px`` is the scale of the reference points (object um per reference px); it
    should be close to the object-space size of a camera pixel (within the 0.7-1.4 range
    searched).  ``orientation`` is the target's orientation in the image (a key of
    :data:`oapcal.imaging.usaf.ORIENTATIONS`), or ``"auto"`` to find it: the one of the 8
    whose rendered target correlates best with the image; when the second best reaches
    ``orientation_ratio`` of the best score the orientation is ambiguous and the detection
    fails.  The reference points ``xy_u`` are the target turned into that orientation
    about the image centre (:meth:`~oapcal.imaging.usaf.UsafTarget.reference_px`), so a
    model fitted to the pairs has ``m`` close to +1.

    ``consistency_model`` is the model (``"full"``, ``"paper"``, ...) fitted to the matched
    pairs to check the global alignment (:func:`check_consistency`); ``"auto"`` uses
    ``full`` from 40 corners, ``paper`` from 16, and skips the check below; ``None`` skips it.

    Returns a :class:`Detection`; a target that cannot be found, an ambiguous orientation
    or an inconsistent alignment is a ``status != 0`` result, not an exception.
    """
    from threadpoolctl import threadpool_limits

    # Detection does many small dense solves; a multithreaded BLAS only adds contention on
    # them (measured on 2 cores: 1.2-1.9 s with one BLAS thread, 12-14 s at random with two).
    with threadpool_limits(limits=1, user_api="blas"):
        if not um_per_px > 0:
            raise DataError(f"um_per_px {um_per_px}: must be positive")
        if orientation != "auto":
            orientation_matrix(orientation)  # raises for an unknown name
        img = _to_float_image(image)
        h, w = img.shape
        target = usaf_target(groups)
        ref_centre = (np.asarray((w, h), float) - 1) / 2
        empty = Detection((), np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0), 0, {}, 1, "")

        candidates = list(ORIENTATIONS) if orientation == "auto" else [orientation]
        scores = {}
        for name in candidates:
            found = _find_target(img, target.rectangles_px(um_per_px, (w, h), name), ref_centre)
            scores[name] = (found[2], found) if found is not None else (-1.0, None)
        ranked = sorted(scores, key=lambda k: -scores[k][0])
        best = ranked[0]
        score_table = {k: round(float(scores[k][0]), 4) for k in ranked}
        found = scores[best][1]
        empty = _replace(empty, orientation=best, orientation_scores=score_table)
        if found is None or found[2] < 0.2:
            msg = (
                "the target was not found (no correlation with the rendered groups); "
                "check --groups and --um-per-px"
            )
            return _replace(empty, message=msg)
        if len(ranked) > 1 and scores[ranked[1]][0] >= orientation_ratio * scores[best][0]:
            msg = (
                f"the target's orientation is ambiguous: {best} scores {scores[best][0]:.3f} and "
                f"{ranked[1]} {scores[ranked[1]][0]:.3f}; give the orientation (--orientation)"
            )
            return _replace(empty, message=msg)
        rects = target.rectangles_px(um_per_px, (w, h), best)
        corners_u = target.reference_px(um_per_px, (w, h), best)
        swap_axes = orientation_matrix(best)[0, 0] == 0  # a quarter turn: H bars run vertically
        ref = _Reference(rects)
        s, shift, score, sign = found  # camera = s u + shift
        warp = _initial_warp(s, shift, ref_centre, rects, w, h)

        sigma = float(np.hypot(sigma_hint_px, np.sqrt(1 / 12)))
        a, b = (0.05, 0.9) if sign > 0 else (0.95, -0.9)
        import cv2

        with _Progress(progress, len(LEVELS) + len(target.triplets()) + 1) as bar:
            for blur, degree in LEVELS:
                warp = warp.with_degree(degree)
                values_img = img if blur is None else cv2.GaussianBlur(img, (0, 0), blur)
                xs = _region(warp, ref, w, h)
                if len(xs) < 50:
                    return _replace(empty, message="the registered target falls outside the image")
                model_sigma = sigma if blur is None else float(np.hypot(blur, sigma))
                res = _gauss_newton(
                    values_img[xs[:, 1].astype(int), xs[:, 0].astype(int)],
                    np.zeros((len(xs), 2)),
                    warp.basis(xs),
                    ref,
                    warp.coef,
                    a,
                    b,
                    model_sigma,
                    fit_sigma=blur is None,
                )
                warp = _Warp(warp.centre, warp.scale, res.coef, degree)
                a, b = res.a, res.b
                if res.ncc < 0.3:
                    msg = f"registration failed (model-image correlation {res.ncc:.2f} at blur {blur} px)"
                    return _replace(empty, message=msg, ncc=res.ncc)
                if blur is None:
                    sigma = res.sigma
                bar.advance()
            global_ncc = res.ncc
            if global_ncc < 0.5:
                return _replace(
                    empty,
                    message=f"registration failed (model-image correlation {global_ncc:.2f} < 0.5)",
                    ncc=global_ncc,
                )
            x0 = _initial_inverse(warp, corners_u)
            pred = _invert(warp, warp.jacobian, corners_u, x0)
            m = 3.0
            inside = np.isfinite(pred).all(axis=1) & (pred[:, 0] >= m) & (pred[:, 0] <= w - 1 - m)
            inside &= (pred[:, 1] >= m) & (pred[:, 1] <= h - 1 - m)
            n_expected = int(inside.sum())

            keep_idx, keep_xy, keep_se = [], [], []
            dropped = dict.fromkeys(DROP_REASONS, 0)
            for bars in target.triplets():
                idx = np.concatenate([4 * bars + c for c in range(4)])
                idx.sort()
                n_in = int(inside[idx].sum())
                if n_in == 0:
                    bar.advance()
                    continue
                reason, xy, se = _refine_triplet(
                    img, warp, ref, target, bars, idx, corners_u, pred, a, b, sigma, um_per_px,
                    max_stderr_px=max_stderr_px, ambiguity_ratio=ambiguity_ratio, swap_axes=swap_axes,
                )  # fmt: skip
                bar.advance()
                if reason is not None:
                    dropped[reason] += n_in
                    continue
                ok = (xy[:, 0] >= m) & (xy[:, 0] <= w - 1 - m) & (xy[:, 1] >= m) & (xy[:, 1] <= h - 1 - m)
                dropped["outside"] += int((inside[idx] & ~ok).sum())
                for k, i in enumerate(idx):
                    if ok[k] and inside[i]:
                        keep_idx.append(i)
                        keep_xy.append(xy[k])
                        keep_se.append(se[k])
            order = np.argsort(keep_idx)
            keep_idx = np.asarray(keep_idx, int)[order]
            keep_xy = np.asarray(keep_xy, float).reshape(-1, 2)[order]
            keep_se = np.asarray(keep_se, float)[order]
            width_px = target.corner_width_um[keep_idx] / um_per_px
            check = check_consistency(corners_u[keep_idx], keep_xy, width_px, consistency_model)
            bar.advance()
        common = dict(
            n_expected=n_expected,
            polarity="bright" if b > 0 else "dark",
            sigma_px=_camera_sigma(warp, sigma),
            ncc=global_ncc,
            orientation=best,
            orientation_scores=score_table,
            consistency=check.summary(),
        )
        if check.status != 0:
            dropped["inconsistent"] = len(keep_idx)
            return _replace(
                empty, dropped={k: v for k, v in dropped.items() if v}, message=check.message, **common
            )
        keep = check.consistent
        dropped["inconsistent"] = int((~keep).sum())
        keep_idx = keep_idx[keep]
        if len(keep_idx) < MIN_KEPT_FRACTION * n_expected:
            msg = (
                f"the registration is unreliable: only {len(keep_idx)} of {n_expected} expected corners "
                f"passed the checks (model-image correlation {global_ncc:.2f}); nothing was kept"
            )
            return _replace(empty, dropped={k: v for k, v in dropped.items() if v}, message=msg, **common)
        return Detection(
            ids=tuple(target.corner_ids[i] for i in keep_idx),
            xy_u=corners_u[keep_idx],
            xy_d=keep_xy[keep],
            stderr_px=keep_se[keep],
            dropped={k: v for k, v in dropped.items() if v},
            status=0,
            message="ok",
            predicted={target.corner_ids[i]: pred[i] for i in np.flatnonzero(inside)},
            **common,
        )


@dataclass(frozen=True)
class Consistency:
    """The global consistency check of matched pairs (:func:`check_consistency`).

    ``consistent`` (bool per pair); ``model`` the fitted model (None: not checked);
    ``rms_px`` the rms residual of the consistent pairs, ``threshold_px`` the residual
    limit (per pair); ``status`` 0, or 1 when the alignment is refused (``message``).
    """

    consistent: np.ndarray
    model: str | None
    rms_px: float
    max_px: float
    n_inconsistent: int
    status: int = 0
    message: str = "ok"

    def summary(self) -> dict:
        return {
            "model": self.model,
            "rms_px": self.rms_px,
            "max_px": self.max_px,
            "inconsistent": self.n_inconsistent,
            "status": self.status,
            "message": self.message,
        }


def check_consistency(
    xy_u: np.ndarray,
    xy_d: np.ndarray,
    width_px: np.ndarray,
    model: str | None = "auto",
    *,
    floor_px: float = CONSISTENCY_FLOOR_PX,
    n_sigma: float = CONSISTENCY_SIGMAS,
    max_fraction: float = CONSISTENCY_MAX_FRACTION,
    max_rms_px: float = CONSISTENCY_MAX_RMS_PX,
) -> Consistency:
    """Check that matched pairs follow one smooth distortion: fit ``model``
    (:func:`oapcal.fit.fit`, the pixel start) to the pairs and flag every pair whose
    residual exceeds ``min(max(n_sigma * s, floor_px), width_px / 2)``, with ``s`` a
    robust rms of the residuals (1.2 x their median); refit without the flagged pairs
    until nothing changes (at most 8 times).

    A pair off by a whole bar (a mismatch) is at least ``width_px`` from its true position
    and cannot follow the smooth model; a correct pair is within the model's own error.
    The alignment is refused (``status`` 1) when the fit does not converge, when more than
    ``max_fraction`` of the pairs are flagged (then the model is fitted to wrong pairs
    as much as to right ones and nothing can be trusted), or when the rms residual of
    the rest exceeds ``max_rms_px`` (a wrong alignment can be smooth, but rarely as
    smooth as a real distortion; the limit is empirical, see :data:`CONSISTENCY_MAX_RMS_PX`).

    ``model="auto"``: ``full`` from 40 pairs, ``paper`` from 16, no check below
    (``model`` None in the result); ``None``: no check.
    """
    from oapcal.fit import fit
    from oapcal.model import distort

    n = len(xy_u)
    everything = np.ones(n, bool)
    if model == "auto":
        model = "full" if n >= 40 else "paper" if n >= 16 else None
    if model is None:
        return Consistency(everything, None, float("nan"), float("nan"), 0)
    keep = everything
    width_px = np.asarray(width_px, float)
    for _ in range(8):
        result = fit(xy_u[keep], xy_d[keep], model, init="pixel")
        if not result.converged:
            return Consistency(
                ~everything, model, float("nan"), float("nan"), n, 1,
                f"the global alignment could not be checked: the {model} model did not converge "
                f"on the matched corners ({result.message})",
            )  # fmt: skip
        r = np.hypot(*(distort(xy_u, result.params) - xy_d).T)
        s = 1.2 * float(np.median(r[keep]))
        limit = np.minimum(max(n_sigma * s, floor_px), 0.5 * width_px)
        new = r <= limit
        if (new == keep).all() or new.sum() < 0.5 * n:
            keep = new
            break
        keep = new
    n_bad = int((~keep).sum())
    rms = float(np.sqrt(np.mean(r[keep] ** 2))) if keep.any() else float("nan")
    worst = float(r[keep].max()) if keep.any() else float("nan")
    if n_bad > max_fraction * n:
        return Consistency(
            ~everything, model, rms, worst, n, 1,
            f"the global alignment is inconsistent: {n_bad} of {n} matched corners are off the "
            f"smooth {model} model (rms residual of the rest {rms:.2f} px); nothing was kept",
        )  # fmt: skip
    if not rms <= max_rms_px:
        return Consistency(
            ~everything, model, rms, worst, n, 1,
            f"the global alignment is doubtful: the {model} model fits the matched corners with an rms "
            f"residual of {rms:.2f} px (limit {max_rms_px:g} px); nothing was kept",
        )  # fmt: skip
    return Consistency(keep, model, rms, worst, n_bad)


def _camera_sigma(warp: _Warp, sigma_ref: float) -> float:
    """PSF sigma in camera px from the fitted blur in reference px (which includes the
    pixel's own box, variance 1/12 px^2), at the centre of the target."""
    scale = float(np.sqrt(abs(np.linalg.det(warp.jacobian(warp.centre[None, :])[0]))))
    total = sigma_ref / scale
    return float(np.sqrt(max(total**2 - 1 / 12, 0.0)))


def _replace(det: Detection, **changes) -> Detection:
    from dataclasses import replace

    return replace(det, **changes)


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


def _region(warp: _Warp, ref: _Reference, w: int, h: int, lo=None, hi=None) -> np.ndarray:
    """Integer camera pixels whose reference point lies in ``[lo, hi]`` (default: the
    target's extent plus a margin)."""
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
    gx, gy = np.meshgrid(np.arange(c0, c1 + 1), np.arange(r0, r1 + 1))
    xs = np.stack([gx.ravel(), gy.ravel()], -1).astype(float)
    u = warp(xs)
    sel = (u[:, 0] >= lo[0]) & (u[:, 0] <= hi[0]) & (u[:, 1] >= lo[1]) & (u[:, 1] <= hi[1])
    return xs[sel]


def _refine_triplet(
    img,
    warp,
    ref,
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
):
    """Local affine refinement of one triplet; returns (drop reason or None, xy, stderr)."""
    h, w = img.shape
    w_ref = float(target.bar_width[bars[0]]) / um_per_px  # bar width, reference px
    u_tri = corners_u[idx]
    margin = 1.5 * w_ref + 3.0 * sigma + 1.0
    lo = u_tri.min(axis=0) - margin
    hi = u_tri.max(axis=0) + margin
    xs = _region(warp, ref, w, h, lo, hi)
    if len(xs) < 20:
        return "outside", None, None
    values = img[xs[:, 1].astype(int), xs[:, 0].astype(int)]
    x_t = pred[idx].mean(axis=0)
    l_t = max(float(np.ptp(pred[idx], axis=0).max()) / 2, 1.0)
    basis = np.column_stack([np.ones(len(xs)), (xs - x_t) / l_t])
    base_u = warp(xs)
    res = _gauss_newton(values, base_u, basis, ref, np.zeros((3, 2)), a, b, sigma, fit_sigma=True)

    def local(x):
        return warp(x) + np.column_stack([np.ones(len(x)), (x - x_t) / l_t]) @ res.coef

    def local_jac(x):
        return warp.jacobian(x) + (res.coef[1:].T / l_t)[None]

    xy = _invert(local, local_jac, u_tri, pred[idx])
    if not (res.converged and np.isfinite(xy).all() and np.isfinite(res.cov).all()):
        return "not_converged", None, None
    if np.sign(res.b) != np.sign(b) or not 0.4 < res.b / b < 2.5:
        return "contrast", None, None
    if np.hypot(*(xy - pred[idx]).T).max() > 0.5 * w_ref:
        return "moved", None, None
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
        return "ambiguous", None, None
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
        return "uncertain", None, None
    return None, xy, se


class _Progress:
    def __init__(self, enabled: bool, total: int):
        self.enabled, self.total = enabled, total

    def __enter__(self):
        if self.enabled:
            from rich.progress import Progress

            self._p = Progress(transient=True)
            self._p.__enter__()
            self._t = self._p.add_task("detecting corners", total=self.total)
        return self

    def advance(self):
        if self.enabled:
            self._p.update(self._t, advance=1)

    def __exit__(self, *exc):
        if self.enabled:
            self._p.__exit__(*exc)
        return False


# --------------------------------------------------------------------------- evaluation


def evaluate_detection(detection: Detection, ids, xy_d_true, visible) -> dict:
    """Compare a detection with ground truth (e.g. :class:`~oapcal.imaging.simulate.SimulatedImage`).

    Returns ``found`` (kept corners that are truly visible), ``visible`` (fully visible
    corners), ``coverage`` (found / visible), ``median_error_px``, ``max_error_px``,
    ``rms_error_px`` and ``mismatches``: kept corners farther from their true position than
    half the distance from that true position to the nearest other true corner (so nearer
    to another corner than to their own).
    """
    index = {i: k for k, i in enumerate(ids)}
    xy_true = np.asarray(xy_d_true, float)
    vis = np.asarray(visible, bool)
    k = np.array([index[i] for i in detection.ids], int)
    err = np.hypot(*(detection.xy_d - xy_true[k]).T) if len(k) else np.zeros(0)
    from scipy.spatial import cKDTree

    finite = np.isfinite(xy_true).all(axis=1)
    tree = cKDTree(xy_true[finite])
    nn = tree.query(xy_true[k], k=2)[0][:, 1] if len(k) else np.zeros(0)
    mismatches = int((err > 0.5 * nn).sum())
    found = int(vis[k].sum()) if len(k) else 0
    n_vis = int(vis.sum())
    return {
        "found": found,
        "visible": n_vis,
        "coverage": found / n_vis if n_vis else 0.0,
        "median_error_px": float(np.median(err)) if len(err) else float("nan"),
        "max_error_px": float(err.max()) if len(err) else float("nan"),
        "rms_error_px": float(np.sqrt(np.mean(err**2))) if len(err) else float("nan"),
        "mismatches": mismatches,
    }
