"""Bottom-up search for bar triplets: bars as thresholded blobs, triplets as three parallel bars.

Independent of the target's layout, scale, rotation, mirror and contrast polarity: every
blob that looks like a bar (a filled rectangle about 5 times as long as wide, in any
direction) is kept, and three bars of the same size side by side, one bar period apart,
make a triplet.  The threshold is the local midpoint between a local minimum and maximum
(so uneven illumination does not matter) at several window sizes (so bars of any size are
found); both polarities are tried.  Dust, digits and squares give blobs that are not bars
or bars that make no triplet; they are dropped here or left unmatched by the pose search.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Bar aspect (length / width) accepted from a thresholded blob (the target's is 5; blur
#: and the threshold change it somewhat).
ASPECT_RANGE = (2.8, 8.5)
#: Fraction of the blob's minimum-area rectangle its pixels must fill.
MIN_FILL = 0.72
#: A triplet's thresholded bar length per bar width (half its period; the target's is 5).
#: Why up to 8: blur lengthens a bright bar at a local threshold by a few px whatever its
#: width, and a relay stretches the bars' direction against their period: the LAB-UMK
#: micrograph through the relay gives group 4's horizontal triplets 6.6-7.1 (6.6 refused
#: them, and the target with them).  Why down to 2.8: the same relay, misaligned, squeezes
#: the other direction's bars along their length (local scales down to 0.75) while blur and
#: the threshold round off their ends: G4E2's vertical triplet through the misaligned relay
#: (seed 2) measured 3.04, and with 6-7 of group 4's triplets left the target was refused.
LENGTH_PER_WIDTH = (2.8, 8.0)
#: A triplet's outer bar's thresholded width per its middle bar's (the triplet's width is its
#: period, not these).  Why this wide: a blurred bar's thresholded width depends on the window
#: and pyramid level that found it (the widths come in steps of 1.6 px on the coarser levels)
#: and on its neighbours; G4E1's vertical triplet of the LAB-UMK micrograph through the
#: misaligned relay (seed 2) measured 9.0, 5.1 and 7.7 px at a period of 13.6 px.
NEIGHBOUR_WIDTH_RATIO = (1 / 1.8, 1.8)
#: Smallest bar width (px) looked for: narrower bars are not resolved reliably.
MIN_BAR_PX = 1.6


@dataclass(frozen=True)
class Triplets:
    """Triplets found in an image, one row each.

    ``centre`` ``(n, 2)`` px; ``angle`` of the bars' long axis in radians in ``[0, pi)``
    (x right, y down); ``width`` the bar width w in px (half the bar period); ``length``
    the bars' mean length in px; ``polarity`` +1 bright bars, -1 dark bars; ``bars``
    ``(n, 3, 2)`` the three bar centres, ordered along the normal.
    """

    centre: np.ndarray
    angle: np.ndarray
    width: np.ndarray
    length: np.ndarray
    polarity: np.ndarray
    bars: np.ndarray

    def __len__(self) -> int:
        return len(self.centre)

    def take(self, k) -> Triplets:
        return Triplets(
            *(getattr(self, f)[k] for f in ("centre", "angle", "width", "length", "polarity", "bars"))
        )


def _bars_in_mask(mask: np.ndarray, min_w: float, max_w: float) -> np.ndarray:
    """Bar-like blobs of a binary mask: rows ``cx, cy, w, l, angle, w_moments`` (angle of
    the long axis; ``w`` the width of the blob's minimum-area rectangle, ``w_moments`` its
    width from its second moments, :func:`find_bars`)."""
    import cv2

    contours, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_LIST, cv2.CHAIN_APPROX_SIMPLE)
    out = []
    for c in contours:
        if len(c) < 4:
            continue
        area = cv2.contourArea(c)
        if area < ASPECT_RANGE[0] * min_w * min_w * 0.7:
            continue
        (cx, cy), (a, b), ang = cv2.minAreaRect(c)
        w, length = (a, b) if a <= b else (b, a)
        if w < min_w or w > max_w or length < ASPECT_RANGE[0] * w or length > ASPECT_RANGE[1] * w:
            continue
        # contourArea measures the polygon through the boundary pixel centres: add half a
        # pixel all round before comparing with the rectangle.
        if (area + 0.5 * cv2.arcLength(c, True)) < MIN_FILL * (w + 1) * (length + 1):
            continue
        m = cv2.moments(c)
        var = 0.5 * (m["mu20"] + m["mu02"]) - np.hypot(0.5 * (m["mu20"] - m["mu02"]), m["mu11"])
        w_mom = min(w, float(np.sqrt(12.0 * var / m["m00"]))) if m["m00"] > 0 and var > 0 else w
        theta = np.deg2rad(ang) if a >= b else np.deg2rad(ang + 90.0)
        out.append((cx, cy, w, length, theta % np.pi, w_mom))
    return np.array(out, float).reshape(-1, 6)


def find_bars(img: np.ndarray, *, max_bar_px: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Bars of both polarities in a float image scaled to about ``[0, 1]``.

    Returns ``(bars, polarity)``: rows ``cx, cy, w, l, angle, w_moments`` and +1 (bright)
    or -1 (dark).  Two widths, both in the rectangle's convention (a filled ``W`` px wide
    bar measures ``W - 1``): ``w`` the minimum-area rectangle's, ``w_moments`` the blob's
    from its second moments (``sqrt(12 var)`` across its length, at most ``w``).  A bar
    turned off the pixel axes has staircase edges, and the rectangle round them is up to
    1.1 px wider than the bar unturned (the LAB-UMK micrograph turned by 30 degrees: 8.1 px,
    unturned 7.0; moments 7.1 and 6.9); a blurred bar's thresholded blob narrows towards its
    ends, and its moments' width is then the narrower (through a misaligned relay, turned by
    45 degrees: the rectangle's fitted a triplet's spacing, the moments' did not).
    """
    import cv2

    h, w = img.shape
    f = cv2.GaussianBlur(img.astype(np.float32), (0, 0), 0.7)
    noise = float(np.median(np.abs(f[1:, :] - f[:-1, :]))) * 1.5 + 1e-6
    max_bar = float(max_bar_px) if max_bar_px else max(h, w) / 5.0
    rows, pols = [], []
    # Windows of 9, 15 and 25 px on the image, then 25 px on ever smaller copies (a
    # pyramid): the cost stays that of a few full-size passes whatever the bar size.
    plan = [(9, 1.0), (15, 1.0), (25, 1.0)]
    factor = 1.0
    while 25 * factor * 1.6 <= max(25.0, min(4 * max_bar, 2 * max(h, w))):
        factor *= 1.6
        plan.append((25, factor))
    for win, factor in plan:
        g = (
            f
            if factor == 1.0
            else cv2.resize(f, None, fx=1 / factor, fy=1 / factor, interpolation=cv2.INTER_AREA)
        )
        k = cv2.getStructuringElement(cv2.MORPH_RECT, (win, win))
        sm = max(1.0, win / 4)
        lo = cv2.GaussianBlur(cv2.erode(g, k), (0, 0), sm)
        hi = cv2.GaussianBlur(cv2.dilate(g, k), (0, 0), sm)
        mid = 0.5 * (lo + hi)
        contrast = (hi - lo) > max(8 * noise / np.sqrt(factor), 0.08)
        min_w = max(MIN_BAR_PX, win / 14.0)
        max_w = win / 2.0
        for pol in (1.0, -1.0):
            found = _bars_in_mask(((g - mid) * pol > 0) & contrast, min_w, max_w)
            if factor != 1.0:
                found[:, :2] = (found[:, :2] + 0.5) * factor - 0.5
                found[:, [2, 3, 5]] *= factor
            rows.append(found)
            pols.append(np.full(len(found), pol))
    bars = np.concatenate(rows) if rows else np.zeros((0, 6))
    pol = np.concatenate(pols) if pols else np.zeros(0)
    return _dedupe_bars(bars, pol)


def _dedupe_bars(bars: np.ndarray, pol: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One bar per place and polarity (the same bar is found at several window sizes)."""
    if len(bars) == 0:
        return bars, pol
    from scipy.spatial import cKDTree

    order = np.argsort(-bars[:, 3])  # longest first: keeps the largest fit of a bar
    bars, pol = bars[order], pol[order]
    keep = np.ones(len(bars), bool)
    tree = cKDTree(bars[:, :2])
    for i in range(len(bars)):
        if not keep[i]:
            continue
        for j in tree.query_ball_point(bars[i, :2], max(0.6 * bars[i, 2], 1.5)):
            if j > i and pol[j] == pol[i]:
                keep[j] = False
    return bars[keep], pol[keep]


def group_triplets(bars: np.ndarray, pol: np.ndarray) -> Triplets:
    """Triplets: a bar with one bar of the same size and direction on each side, one bar
    period away along the normal, in line.  The period (not the thresholded width, which
    depends on the threshold) gives the bar width.  ``bars`` rows ``cx, cy, w, l, angle``
    and optionally ``w_moments`` (:func:`find_bars`; default ``w``): the spacing's lower
    limit takes the narrower width, its upper limit the wider (each the more lenient)."""
    empty = Triplets(
        np.zeros((0, 2)), np.zeros(0), np.zeros(0), np.zeros(0), np.zeros(0), np.zeros((0, 3, 2))
    )
    if len(bars) < 3:
        return empty
    from scipy.spatial import cKDTree

    tree = cKDTree(bars[:, :2])
    out = []
    w_mom = bars[:, 5] if bars.shape[1] > 5 else bars[:, 2]
    for i, (cx, cy, w, length, th) in enumerate(bars[:, :5]):
        nrm = np.array([-np.sin(th), np.cos(th)])
        along = np.array([np.cos(th), np.sin(th)])
        near = [j for j in tree.query_ball_point((cx, cy), 3.2 * w + 2) if j != i and pol[j] == pol[i]]
        side = {-1: [], 1: []}
        for j in near:
            d = bars[j, :2] - (cx, cy)
            dn, da = float(d @ nrm), float(d @ along)
            dth = abs((bars[j, 4] - th + np.pi / 2) % np.pi - np.pi / 2)
            # the spacing may reach the wider bar's limit: a blurred middle bar between two
            # others thresholds narrower than they do (measured: 4.8 px between two of
            # 6.0 px at a 12.9 px spacing, where its own width allowed 12.8 px); the lower
            # limit stays the narrower bar's (the limits only widen), from its moments (a
            # turned bar's rectangle is too wide, find_bars)
            w_lo, w_hi = min(w_mom[i], w_mom[j]), max(w, bars[j, 2])
            if (
                dth < np.deg2rad(10)
                and abs(da) < 0.2 * length + 1
                and NEIGHBOUR_WIDTH_RATIO[0] < bars[j, 2] / w < NEIGHBOUR_WIDTH_RATIO[1]
                and 0.75 < bars[j, 3] / length < 1.33
                and 1.55 * w_lo - 0.5 < abs(dn) < 2.5 * w_hi + 0.8
            ):
                side[int(np.sign(dn))].append((abs(dn), j))
        for dl, jl in side[-1]:
            for dr, jr in side[1]:
                if abs(dl - dr) > 0.2 * max(dl, dr) + 0.7:
                    continue
                period = 0.5 * (dl + dr)
                wb = period / 2
                lengths = bars[[jl, i, jr], 3]
                if not LENGTH_PER_WIDTH[0] < lengths.mean() / wb < LENGTH_PER_WIDTH[1]:
                    continue
                pts = bars[[jl, i, jr], :2]
                # irregularity: unequal spacing, widths, lengths, offsets along the bars
                widths = bars[[jl, i, jr], 2]
                bad = (
                    abs(dl - dr) / period + np.ptp(widths) / widths.mean() + np.ptp(lengths) / lengths.mean()
                )
                out.append((cx, cy, th, wb, lengths.mean(), pol[i], pts, bad))
    if not out:
        return empty
    # one triplet per middle bar position: keep the most regular candidate
    out.sort(key=lambda o: o[7])
    res = Triplets(
        np.array([o[:2] for o in out]),
        np.array([o[2] for o in out]),
        np.array([o[3] for o in out]),
        np.array([o[4] for o in out]),
        np.array([o[5] for o in out]),
        np.array([o[6] for o in out]),
    )
    _, first = np.unique(np.round(res.centre, 0), axis=0, return_index=True)
    return res.take(np.sort(first))


def find_triplets(img: np.ndarray, *, max_bar_px: float | None = None) -> Triplets:
    """All bar triplets of ``img`` (:func:`find_bars`, :func:`group_triplets`)."""
    bars, pol = find_bars(img, max_bar_px=max_bar_px)
    return group_triplets(bars, pol)
