"""Chessboard corners: saddle points of the image, verified and refined (``docs/detection.md``).

1. **Saddle response**: with ``g`` the image smoothed at about a fifth of a square,
   ``R = g_xy^2 - g_xx g_yy`` (positive only where the image curves up one way and down the
   other: the X-junction of four squares), divided by the square of the local contrast
   (so uneven light does not matter); its local maxima are the candidates.
2. **X test**: on a ring of 0.3 squares around the candidate the image crosses its ring
   mean exactly four times, with opposite arcs alike: an X-junction, not an edge, the
   board's outer L-corners or a printing flaw.
3. **Corner type**: the direction of the saddle's upward curvature; the two kinds of
   corner of a chessboard differ by 90 degrees, and neighbouring corners are of different
   kinds, which the lattice growth checks (``parity``).
4. **Sub-pixel**: ``cv2.cornerSubPix`` (the point where the gradients in a window are
   orthogonal to the offsets, a window of about 0.8 squares), then the saddle point of a
   quadratic fitted to the smoothed image around it (:func:`saddle_points`): an X-junction
   is point-symmetric, so both are unbiased, and the fit has no pixel-phase error.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from oapcal.imaging.detect.dots import image_noise
from oapcal.records import ImageSize

#: Ring samples of the X test.
RING_SAMPLES = 32


@dataclass(frozen=True)
class Saddles:
    """Chessboard-corner candidates: ``xy`` (px, refined), ``parity`` (+1 / -1: the corner's
    kind), ``strength`` (the normalised saddle response), ``contrast`` (the ring's
    amplitude, image units), ``noise`` (the image's)."""

    xy: np.ndarray
    parity: np.ndarray
    strength: np.ndarray
    contrast: np.ndarray
    noise: float


def _empty(noise):
    z = np.zeros(0)
    return Saddles(np.zeros((0, 2)), np.zeros(0, int), z, z, noise)


def find_saddles(img: np.ndarray, square_px: float) -> Saddles:
    """Chessboard-corner candidates in ``img`` for squares of about ``square_px`` (module docstring)."""
    a = np.asarray(img, np.float32)
    noise = image_noise(a)
    s = float(square_px)
    sigma = float(np.clip(s / 5.0, 1.0, 8.0))
    gxx, gyy, gxy, norm, contrast = _saddle_response(a, s, sigma)
    found = _candidates(norm, contrast, noise, s)
    if found is None:
        return _empty(noise)
    xs, ys, vals, rho = found
    xs, ys, vals, amp = _x_test(a, xs, ys, vals, rho, s, noise)
    if len(xs) == 0:
        return _empty(noise)
    parity = _corner_parity(gxx, gyy, gxy, xs, ys)
    ref, keep = _subpixel(a, xs, ys, s)
    return Saddles(ref[keep], parity[keep].astype(int), vals[keep], amp[keep], noise)


def _saddle_response(a: np.ndarray, s: float, sigma: float):
    """The second derivatives of ``a`` smoothed by ``sigma`` (``gxx``, ``gyy``, ``gxy``),
    the saddle response over the local contrast squared, and the local contrast."""
    import cv2

    g = cv2.GaussianBlur(a, (0, 0), sigma)
    gxx = cv2.Sobel(g, cv2.CV_32F, 2, 0, ksize=3)
    gyy = cv2.Sobel(g, cv2.CV_32F, 0, 2, ksize=3)
    gxy = cv2.Sobel(g, cv2.CV_32F, 1, 1, ksize=3) / 4.0
    resp = gxy**2 - gxx * gyy
    k = max(3, int(round(s)) | 1)
    kern = cv2.getStructuringElement(cv2.MORPH_RECT, (k, k))
    contrast = cv2.GaussianBlur(cv2.dilate(a, kern) - cv2.erode(a, kern), (0, 0), max(1.0, s / 2))
    norm = resp / np.maximum(contrast, 1e-6) ** 2
    return gxx, gyy, gxy, norm, contrast


def _candidates(norm: np.ndarray, contrast: np.ndarray, noise: float, s: float):
    """The strong local maxima of the response ``norm`` whose ring fits in the image:
    ``(xs, ys, values, ring radius)``; None when there is none."""
    import cv2

    km = max(3, int(round(0.5 * s)) | 1)
    peak = norm == cv2.dilate(norm, cv2.getStructuringElement(cv2.MORPH_RECT, (km, km)))
    strong = contrast > 10.0 * max(noise, 1e-6)
    cand = peak & strong & (norm > 0)
    ys, xs = np.nonzero(cand)
    if len(xs) == 0:
        return None
    vals = norm[ys, xs]
    thr = 0.2 * float(np.percentile(vals, 95))
    sel = vals > thr
    xs, ys, vals = xs[sel], ys[sel], vals[sel]
    h, w = norm.shape
    rho = max(2.0, 0.3 * s)
    inside = (xs > rho + 1) & (ys > rho + 1) & (xs < w - rho - 2) & (ys < h - rho - 2)
    xs, ys, vals = xs[inside], ys[inside], vals[inside]
    if len(xs) == 0:
        return None
    return xs, ys, vals, rho


def _x_test(a: np.ndarray, xs, ys, vals, rho: float, s: float, noise: float):
    """Step 2: the candidates whose ring of radius ``rho`` (on a lightly smoothed image)
    changes sign 4 times, point-symmetrically and above the noise: ``(xs, ys, vals, amplitude)``."""
    import cv2
    from scipy.ndimage import map_coordinates

    ring_img = cv2.GaussianBlur(a, (0, 0), max(0.7, 0.1 * s))
    t = np.arange(RING_SAMPLES) * 2 * np.pi / RING_SAMPLES
    rx = xs[:, None] + rho * np.cos(t)[None, :]
    ry = ys[:, None] + rho * np.sin(t)[None, :]
    ring = map_coordinates(ring_img, [ry.ravel(), rx.ravel()], order=1).reshape(rx.shape)
    ring -= ring.mean(axis=1, keepdims=True)
    sign = np.sign(ring)
    changes = (sign != np.roll(sign, 1, axis=1)).sum(axis=1)
    half = RING_SAMPLES // 2
    opposite = (ring * np.roll(ring, half, axis=1)).mean(axis=1) / np.maximum((ring**2).mean(axis=1), 1e-12)
    amp = np.sqrt((ring**2).mean(axis=1))
    ok = (changes == 4) & (opposite > 0.5) & (amp > 5.0 * max(noise, 1e-6))
    return xs[ok], ys[ok], vals[ok], amp[ok]


def _corner_parity(gxx, gyy, gxy, xs, ys) -> np.ndarray:
    """Step 3, the corner kind (+1/-1): the direction of upward curvature, doubled, against
    the mean axis."""
    hxx, hyy, hxy = gxx[ys, xs], gyy[ys, xs], gxy[ys, xs]
    phi = 0.5 * np.arctan2(2 * hxy, hxx - hyy)  # eigen-direction of the larger eigenvalue
    axis = np.angle(np.mean(np.exp(4j * phi))) / 2.0
    return np.where(np.cos(2 * phi - axis) >= 0, 1, -1)


def _subpixel(a: np.ndarray, xs, ys, s: float):
    """Step 4: the corners refined to sub-pixel (``cornerSubPix``, then
    :func:`saddle_points`) and which to keep (converged, moved less than 0.35 square)."""
    import cv2

    win = int(np.clip(round(0.4 * s), 2, 15))
    pts = np.stack([xs, ys], axis=1).astype(np.float32).reshape(-1, 1, 2)
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 50, 1e-4)
    ref = cv2.cornerSubPix(a, pts.copy(), (win, win), (-1, -1), crit).reshape(-1, 2).astype(float)
    ref, conv = saddle_points(a, ref, sigma=float(np.clip(s / 7.0, 1.0, 6.0)))
    moved = np.hypot(*(ref - np.stack([xs, ys], axis=1)).T)
    keep = conv & (moved < 0.35 * s)
    return ref, keep


def saddle_points(img: np.ndarray, xy: np.ndarray, sigma: float, iterations: int = 12):
    """Step 4's second stage: the stationary point of a quadratic fitted (least squares) to
    the image smoothed by a Gaussian of ``sigma`` px in a window of ``2 k + 1`` px around
    each estimate (``k = max(2, round(1.3 sigma))``, bicubic samples), Newton steps until they
    are below 1e-4 px.  An X-junction is point-symmetric, so its smoothed image is too and
    the stationary point is the corner (no pixel-phase error: 0.002 px median on a
    noise-free render, against 0.023 px for ``cornerSubPix`` alone).  Returns ``(xy, converged)``."""
    import cv2
    from scipy.ndimage import map_coordinates

    g = cv2.GaussianBlur(np.asarray(img, np.float32), (0, 0), sigma).astype(np.float64)
    k = max(2, int(round(1.3 * sigma)))
    off = np.arange(-k, k + 1, dtype=float)
    dx, dy = (v.ravel() for v in np.meshgrid(off, off))
    design = np.stack([np.ones_like(dx), dx, dy, dx * dx, dx * dy, dy * dy], axis=1)
    pinv = np.linalg.pinv(design)
    pts = np.asarray(xy, float).copy()
    conv = np.zeros(len(pts), bool)
    h, w = g.shape
    for _ in range(iterations):
        vals = map_coordinates(
            g, [pts[:, 1, None] + dy[None], pts[:, 0, None] + dx[None]], order=3, mode="nearest"
        )
        c = vals @ pinv.T
        hxx, hxy, hyy = 2 * c[:, 3], c[:, 4], 2 * c[:, 5]
        det = hxx * hyy - hxy**2
        saddle = det < 0
        det = np.where(saddle, det, -1.0)
        sx = -(hyy * c[:, 1] - hxy * c[:, 2]) / det
        sy = -(-hxy * c[:, 1] + hxx * c[:, 2]) / det
        step = np.stack([sx, sy], axis=1)
        step = np.where(saddle[:, None], np.clip(step, -1.0, 1.0), 0.0)
        pts += step
        conv = saddle & (np.hypot(sx, sy) < 1e-4)
        if conv.all():
            break
    inside = ImageSize(w, h).contains(pts, k)
    small = np.hypot(*step.T) < 1e-3  # oscillating at the 1e-3 px level is converged enough
    return pts, (conv | small) & saddle & inside


__all__ = ["Saddles", "find_saddles", "saddle_points"]
