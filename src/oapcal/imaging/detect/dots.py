"""Dot candidates and their unbiased sub-pixel centres (``docs/detection.md``).

1. **Background**: the image without its dots, a grey-level closing (dark dots) or opening
   (bright dots) with a disc larger than a dot and smaller than the gap between dots,
   smoothed; the *signal* is the background minus the image (dark dots) or the reverse.
   Uneven light changes the background, not the signal's shape.
2. **Candidates**: connected components (``cv2.connectedComponentsWithStats``) of the signal
   above 40 % of its local peak level (a dilation over one pitch, smoothed), where that
   level stands clear of the noise; components of implausible area or elongation
   (dust, merged dots) are left out.
3. **Centres**: weighted moments of the signal in a soft-edged circular window centred on
   the current estimate, iterated to their fixed point.  For a dot symmetric about its
   centre the window is then symmetric about it too, so neither the window's truncation
   nor a constant error of the background shifts the centre (the window's first moment
   vanishes); no median filter or threshold enters the centre.  The standard error comes
   from the noise (the median absolute deviation of the image's fine detail).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: A component is a candidate when its signal exceeds this fraction of the local peak level.
THRESHOLD_FRACTION = 0.4
#: Iterations of the centroid's fixed point, and the shift (px) that ends them.
MAX_ITER, SHIFT_TOL = 100, 1e-4


@dataclass(frozen=True)
class Dots:
    """Dot candidates: ``xy`` centres (px), ``stderr_px``, ``area`` (px above threshold),
    ``ellipticity`` (1 - minor/major axis of the signal's second moments), ``amplitude``
    (peak signal), ``converged`` (the centroid's iteration), and ``polarity``
    (``dark`` or ``bright`` dots), ``noise`` (the image noise, same units as the image),
    ``window_px`` the radius of the centroid window, ``shading`` the background's change
    across the window over the dot's amplitude."""

    xy: np.ndarray
    stderr_px: np.ndarray
    area: np.ndarray
    ellipticity: np.ndarray
    amplitude: np.ndarray
    converged: np.ndarray
    polarity: str
    noise: float
    window_px: np.ndarray
    shading: np.ndarray = None


def image_noise(img: np.ndarray) -> float:
    """Robust noise of ``img``: 1.4826 x the median absolute deviation of the difference of
    horizontally neighbouring pixels, divided by sqrt(2)."""
    d = np.diff(np.asarray(img, np.float64), axis=1)
    mad = np.median(np.abs(d - np.median(d)))
    return float(1.4826 * mad / np.sqrt(2.0))


def guess_polarity(img: np.ndarray, pitch_px: float) -> str:
    """``dark`` or ``bright`` dots: the sign of the skewness of the image's detail at the
    pitch's scale (dots cover a minority of the area, so they make the tail)."""
    import cv2

    a = np.asarray(img, np.float32)
    hp = a - cv2.GaussianBlur(a, (0, 0), max(1.0, pitch_px))
    hp = hp - hp.mean()
    skew = float((hp**3).mean() / max((hp**2).mean(), 1e-30) ** 1.5)
    return "dark" if skew < 0 else "bright"


def _disc(d: int) -> np.ndarray:
    import cv2

    d = max(3, int(d) | 1)
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (d, d))


def dot_signal(
    img: np.ndarray, pitch_px: float, dot_px: float | None, polarity: str, *, with_background=False
):
    """Step 1: the background-subtracted signal (positive on the dots); with
    ``with_background`` also the background."""
    import cv2

    a = np.asarray(img, np.float32)
    size = 0.75 * pitch_px if dot_px is None else min(max(1.5 * dot_px + 2.0, 0.5 * pitch_px), 0.9 * pitch_px)
    k = _disc(round(size))
    if polarity == "dark":
        bg = cv2.morphologyEx(a, cv2.MORPH_CLOSE, k)
    else:
        bg = cv2.morphologyEx(a, cv2.MORPH_OPEN, k)
    bg = cv2.GaussianBlur(bg, (0, 0), max(1.0, 0.5 * pitch_px))
    sig = (bg - a) if polarity == "dark" else (a - bg)
    return (sig, bg) if with_background else sig


def find_dots(
    img: np.ndarray,
    pitch_px: float,
    *,
    dot_px: float | None = None,
    polarity: str = "auto",
) -> Dots:
    """Dot candidates in ``img`` (float, any scale) with their centres (module docstring).

    ``pitch_px`` the lattice period (e.g. from :func:`~oapcal.imaging.detect.lattice.lattice_period`),
    ``dot_px`` the dot diameter if known; ``polarity`` ``dark``, ``bright`` or ``auto``."""
    a = np.asarray(img, np.float32)
    if polarity == "auto":
        polarity = guess_polarity(a, pitch_px)
    sig, bg = dot_signal(a, pitch_px, dot_px, polarity, with_background=True)
    noise = image_noise(a)
    found = _components(a, sig, pitch_px, noise)
    if found is None:
        return _empty(polarity, noise)
    area, cents, keep, med = found
    radius, xy0 = _windows(area, cents, keep, med, pitch_px, dot_px)
    xy, se, conv, amp, ell = centroids(sig, xy0, radius, noise)
    ok = np.isfinite(xy).all(axis=1)
    shade = _shading(bg, xy, radius, amp)
    return Dots(
        xy=xy[ok], stderr_px=se[ok], area=area[keep][ok], ellipticity=ell[ok], amplitude=amp[ok],
        converged=conv[ok], polarity=polarity, noise=noise, window_px=np.broadcast_to(radius, (len(xy),))[ok],
        shading=shade[ok],
    )  # fmt: skip


def _components(a: np.ndarray, sig: np.ndarray, pitch_px: float, noise: float):
    """The connected components of the thresholded dot signal: ``(area, centres, keep,
    median area)``, ``keep`` the dot-sized ones clear of the image border; None when no
    component has 2 px."""
    import cv2

    kp = _disc(round(pitch_px))
    level = cv2.GaussianBlur(cv2.dilate(sig, kp), (0, 0), max(1.0, 0.5 * pitch_px))
    floor = max(8.0 * noise, 0.1 * float(np.percentile(level, 99.5)))
    mask = ((sig > THRESHOLD_FRACTION * level) & (level > floor)).astype(np.uint8)
    n, labels, stats, cents = cv2.connectedComponentsWithStats(mask, connectivity=8)
    area = stats[1:, cv2.CC_STAT_AREA].astype(float)
    cents = cents[1:]
    keep = area >= 2
    if keep.sum() == 0:
        return None
    med = float(np.median(area[keep]))
    keep &= (area <= 4.0 * med) & (area >= 0.2 * med)
    # no component touching the image border (its centre would be biased)
    x0, y0 = stats[1:, cv2.CC_STAT_LEFT], stats[1:, cv2.CC_STAT_TOP]
    ww, hh = stats[1:, cv2.CC_STAT_WIDTH], stats[1:, cv2.CC_STAT_HEIGHT]
    h, w = a.shape
    keep &= (x0 > 0) & (y0 > 0) & (x0 + ww < w) & (y0 + hh < h)
    return area, cents, keep, med


def _windows(area, cents, keep, med, pitch_px, dot_px):
    """The centroid window's radius (one, or one per dot) and the kept components' centres."""
    # the window: the dot's radius + the blur's reach, at most 0.45 pitch
    r_dot = 0.5 * dot_px if dot_px else np.sqrt(med / np.pi) / np.sqrt(THRESHOLD_FRACTION + 0.35)
    radius = float(min(r_dot + 2.5, 0.45 * pitch_px))
    radius = max(radius, 1.5)
    xy0 = cents[keep]
    # each dot's window stays clear of its nearest neighbour (whose blurred edge reaches
    # about r_dot + 2.5 px towards it): a compressed part of the field has a smaller pitch
    big = area[keep] >= 0.5 * med  # dust specks do not shrink a dot's window
    if big.sum() >= 2:
        from scipy.spatial import cKDTree

        d, i = cKDTree(xy0[big]).query(xy0, k=2)
        nn = np.where(d[:, 0] < 1e-9, d[:, 1], d[:, 0])  # the nearest other dot-sized candidate
        radius = np.clip(np.minimum(radius, nn - r_dot - 2.5), 1.5, None)
    return radius, xy0


def _shading(bg: np.ndarray, xy: np.ndarray, radius, amp: np.ndarray) -> np.ndarray:
    """Shading: the background's change across the window against the dot's amplitude (a
    steep vignette edge the background does not follow pulls the centre)."""
    import cv2

    h, w = bg.shape
    gx = cv2.Sobel(bg, cv2.CV_32F, 1, 0, ksize=3) / 8.0
    gy = cv2.Sobel(bg, cv2.CV_32F, 0, 1, ksize=3) / 8.0
    shade = np.full(len(xy), np.inf)
    ix = np.clip(np.rint(np.nan_to_num(xy[:, 0])).astype(int), 0, w - 1)
    iy = np.clip(np.rint(np.nan_to_num(xy[:, 1])).astype(int), 0, h - 1)
    rad = np.broadcast_to(radius, (len(xy),))
    with np.errstate(invalid="ignore", divide="ignore"):
        shade = np.hypot(gx[iy, ix], gy[iy, ix]) * rad / amp
    return shade


def _empty(polarity, noise):
    z = np.zeros(0)
    return Dots(np.zeros((0, 2)), np.zeros((0, 2)), z, z, z, np.zeros(0, bool), polarity, noise, z, z)


def centroids(sig: np.ndarray, xy0: np.ndarray, radius: float, noise: float):
    """Step 3 for all dots at once: ``(xy, stderr (N, 2), converged, amplitude, ellipticity)``.

    Vectorised over the dots: each iteration gathers the ``(2R + 3)^2`` patch around every
    current centre, weights it by ``clip(R + 0.5 - d, 0, 1)`` (a one-pixel soft edge, so the
    fixed point moves continuously with the data) and takes the first moments.  A dot whose
    window leaves the image is NaN."""
    sig = np.asarray(sig, np.float64)
    xy = np.asarray(xy0, float).copy()
    n = len(xy)
    radii = np.broadcast_to(np.asarray(radius, float), (n,)).copy()
    half = int(np.ceil(radii.max() if n else 1.0)) + 1
    off = np.arange(-half, half + 1)
    conv = np.zeros(n, bool)
    active = np.ones(n, bool)
    for _ in range(MAX_ITER):
        idx = np.flatnonzero(active)
        if len(idx) == 0:
            break
        _centroid_step(sig, xy, radii, idx, active, conv, half, off)
    se, amp, ell = _final_moments(sig, xy, radii, half, off, noise)
    return xy, se, conv, amp, ell


def _inside(c: np.ndarray, half: int, shape) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The pixel nearest to every centre ``c`` and whether its ``half`` window is inside
    an image of ``shape``."""
    h, w = shape
    ix0 = np.rint(c[:, 0]).astype(int)
    iy0 = np.rint(c[:, 1]).astype(int)
    inside = (ix0 - half >= 0) & (iy0 - half >= 0) & (ix0 + half < w) & (iy0 + half < h)
    return ix0, iy0, inside


def _weighted_patches(sig, c, ix0, iy0, off, radii):
    """The patches of ``sig`` around the centres ``c`` (m, k, k), the offsets from the
    centres ``dx``, ``dy`` and the soft-edged disc weights."""
    px = ix0[:, None] + off[None, :]  # (m, k)
    py = iy0[:, None] + off[None, :]
    patch = sig[py[:, :, None], px[:, None, :]]  # (m, k, k)
    dx = px[:, None, :] - c[:, 0, None, None]
    dy = py[:, :, None] - c[:, 1, None, None]
    wgt = np.clip(radii[:, None, None] + 0.5 - np.hypot(dx, dy), 0.0, 1.0)
    return patch, dx, dy, wgt


def _centroid_step(sig, xy, radii, idx, active, conv, half, off) -> None:
    """One iteration for the active dots ``idx``: move each to its window's first moment;
    updates ``xy``, ``active`` and ``conv`` in place."""
    c = xy[idx]
    ix0, iy0, inside = _inside(c, half, sig.shape)
    xy[idx[~inside]] = np.nan
    active[idx[~inside]] = False
    idx, c, ix0, iy0 = idx[inside], c[inside], ix0[inside], iy0[inside]
    patch, dx, dy, wgt = _weighted_patches(sig, c, ix0, iy0, off, radii[idx])
    m0 = (wgt * patch).sum(axis=(1, 2))
    good = m0 > 0
    sx = np.where(good, (wgt * patch * dx).sum(axis=(1, 2)) / np.where(good, m0, 1), 0)
    sy = np.where(good, (wgt * patch * dy).sum(axis=(1, 2)) / np.where(good, m0, 1), 0)
    step = np.hypot(sx, sy)
    xy[idx, 0] += sx
    xy[idx, 1] += sy
    bad = ~good | (step > radii[idx])
    xy[idx[bad]] = np.nan
    active[idx[bad]] = False
    done = (step < SHIFT_TOL) & ~bad
    conv[idx[done]] = True
    active[idx[done]] = False


def _final_moments(sig, xy, radii, half, off, noise):
    """The final moments at the fixed point: ``(stderr (N, 2), amplitude, ellipticity)``,
    NaN for the dots lost."""
    n = len(xy)
    se = np.full((n, 2), np.nan)
    amp = np.full(n, np.nan)
    ell = np.full(n, np.nan)
    ok = np.isfinite(xy).all(axis=1)
    idx = np.flatnonzero(ok)
    if len(idx):
        c = xy[idx]
        ix0, iy0, inside = _inside(c, half, sig.shape)
        idx, c, ix0, iy0 = idx[inside], c[inside], ix0[inside], iy0[inside]
        patch, dx, dy, wgt = _weighted_patches(sig, c, ix0, iy0, off, radii[idx])
        m0 = (wgt * patch).sum(axis=(1, 2))
        # d(centre) = sum w (p - c) noise / m0: its variance
        se[idx, 0] = noise * np.sqrt((wgt**2 * dx**2).sum(axis=(1, 2))) / m0
        se[idx, 1] = noise * np.sqrt((wgt**2 * dy**2).sum(axis=(1, 2))) / m0
        amp[idx] = patch.max(axis=(1, 2))
        pos = np.clip(patch, 0, None) * wgt
        mp = pos.sum(axis=(1, 2))
        mxx = (pos * dx**2).sum(axis=(1, 2)) / mp
        myy = (pos * dy**2).sum(axis=(1, 2)) / mp
        mxy = (pos * dx * dy).sum(axis=(1, 2)) / mp
        tr, det = mxx + myy, mxx * myy - mxy**2
        disc = np.sqrt(np.clip(tr**2 / 4 - det, 0, None))
        l1, l2 = tr / 2 + disc, np.clip(tr / 2 - disc, 1e-12, None)
        ell[idx] = 1.0 - np.sqrt(l2 / l1)
    return se, amp, ell


__all__ = ["Dots", "centroids", "dot_signal", "find_dots", "guess_polarity", "image_noise"]
