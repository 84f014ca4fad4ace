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
   orthogonal to the offsets), in a window of about 0.8 squares: an X-junction is
   point-symmetric, so this is unbiased.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from oapcal.imaging.detect.dots import image_noise

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
    import cv2
    from scipy.ndimage import map_coordinates

    a = np.asarray(img, np.float32)
    noise = image_noise(a)
    s = float(square_px)
    sigma = float(np.clip(s / 5.0, 1.0, 8.0))
    g = cv2.GaussianBlur(a, (0, 0), sigma)
    gxx = cv2.Sobel(g, cv2.CV_32F, 2, 0, ksize=3)
    gyy = cv2.Sobel(g, cv2.CV_32F, 0, 2, ksize=3)
    gxy = cv2.Sobel(g, cv2.CV_32F, 1, 1, ksize=3) / 4.0
    resp = gxy**2 - gxx * gyy
    k = max(3, int(round(s)) | 1)
    kern = cv2.getStructuringElement(cv2.MORPH_RECT, (k, k))
    contrast = cv2.GaussianBlur(cv2.dilate(a, kern) - cv2.erode(a, kern), (0, 0), max(1.0, s / 2))
    norm = resp / np.maximum(contrast, 1e-6) ** 2
    km = max(3, int(round(0.5 * s)) | 1)
    peak = norm == cv2.dilate(norm, cv2.getStructuringElement(cv2.MORPH_RECT, (km, km)))
    strong = contrast > 10.0 * max(noise, 1e-6)
    cand = peak & strong & (norm > 0)
    ys, xs = np.nonzero(cand)
    if len(xs) == 0:
        return _empty(noise)
    vals = norm[ys, xs]
    thr = 0.2 * float(np.percentile(vals, 95))
    sel = vals > thr
    xs, ys, vals = xs[sel], ys[sel], vals[sel]
    h, w = a.shape
    rho = max(2.0, 0.3 * s)
    inside = (xs > rho + 1) & (ys > rho + 1) & (xs < w - rho - 2) & (ys < h - rho - 2)
    xs, ys, vals = xs[inside], ys[inside], vals[inside]
    if len(xs) == 0:
        return _empty(noise)
    # X test on a ring (step 2), on a lightly smoothed image
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
    xs, ys, vals, amp = xs[ok], ys[ok], vals[ok], amp[ok]
    if len(xs) == 0:
        return _empty(noise)
    # corner kind (step 3): the direction of upward curvature, doubled, against the mean axis
    hxx, hyy, hxy = gxx[ys, xs], gyy[ys, xs], gxy[ys, xs]
    phi = 0.5 * np.arctan2(2 * hxy, hxx - hyy)  # eigen-direction of the larger eigenvalue
    axis = np.angle(np.mean(np.exp(4j * phi))) / 2.0
    parity = np.where(np.cos(2 * phi - axis) >= 0, 1, -1)
    # sub-pixel (step 4)
    win = int(np.clip(round(0.4 * s), 2, 15))
    pts = np.stack([xs, ys], axis=1).astype(np.float32).reshape(-1, 1, 2)
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 50, 1e-4)
    ref = cv2.cornerSubPix(a, pts.copy(), (win, win), (-1, -1), crit).reshape(-1, 2).astype(float)
    moved = np.hypot(*(ref - np.stack([xs, ys], axis=1)).T)
    keep = moved < 0.35 * s
    return Saddles(ref[keep], parity[keep].astype(int), vals[keep], amp[keep], noise)


__all__ = ["Saddles", "find_saddles"]
