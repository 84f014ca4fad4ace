"""Edge spread functions: how blurred the image is, as a Gaussian point spread function.

Across a straight edge, an image blurred by a Gaussian PSF of standard deviation
``sigma`` has the profile of an error function (the edge spread function, ESF)::

    I(d) = low + (high - low) * Phi(d / sigma),    Phi(t) = (1 + erf(t / sqrt 2)) / 2

where ``d`` is the signed distance from the edge line.  Each edge, given as a rectangle
(region of interest, ROI) that contains one straight edge, is fitted with this profile and
a free, possibly slanted, line ``x = a + b y`` (or ``y = a + b x``), using every pixel of
the ROI (the slanted-edge method: a slanted edge samples the profile at many sub-pixel
distances).  The fit is :func:`scipy.optimize.least_squares`; ``sigma`` is perpendicular
to the edge.  The paper reports the largest and the mean ``sigma`` over the edges.

The fitted ``sigma`` is that of the ESF as the pixels sample it; a camera whose pixels
integrate light over their area adds its own box blur (variance 1/12 px^2 along a pixel
axis), which is not removed.

ROIs are ``(x0, y0, x1, y1)`` in px, inclusive pixel indices (x = column, y = row):
pixels ``x0 <= col <= x1`` and ``y0 <= row <= y1``.  :func:`find_edge_rois` finds them
automatically on a target of bright (or dark) bars and squares.

>>> import numpy as np
>>> from scipy.special import ndtr
>>> yy, xx = np.mgrid[0:30, 0:20]
>>> d = (xx - 9.3 - 0.05 * yy) / np.hypot(1.0, 0.05)   # distance from a slanted edge
>>> img = 10 + 80 * ndtr(d / 1.2)
>>> fit = fit_edge(img, (0, 0, 19, 29))
>>> fit.orientation, round(fit.sigma_px, 3)
('vertical', 1.2)
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field

import numpy as np

from oapcal.errors import DataError
from oapcal.records import finite_or_none

#: Most edges one :func:`analyse_edges` call fits (an ROI file longer than this is refused
#: while it is read, before any fit): about 1-30 ms an edge, so minutes at most.
MAX_EDGES = 10_000
#: Largest ROI (px): a fit holds about 10 float arrays of its size.
MAX_ROI_PIXELS = 2**20
#: Largest sum of the ROIs' sizes of one call (px).
MAX_TOTAL_ROI_PIXELS = 2**26


@dataclass(frozen=True)
class EdgeFit:
    """The error-function fit of one edge.

    ``orientation`` is the direction of the edge line (``vertical``: the intensity changes
    along x).  ``sigma_px`` and its standard error ``sigma_err_px`` are perpendicular to the
    edge; ``sigma_um`` is filled when a scale is known.  ``angle_deg`` is the edge's tilt
    from its orientation axis; ``centre`` the point of the edge line in the middle of the
    ROI; ``low``/``high`` the fitted levels; ``rms`` the RMS of the fit residuals (image
    units).  ``ok`` is False when the fit failed or is not trustworthy, with the reason in
    ``message``.  ``distance``/``values`` are the samples (signed distance from the fitted
    line in px, intensity) for plots.
    """

    roi: tuple[int, int, int, int]
    orientation: str
    sigma_px: float
    sigma_err_px: float
    angle_deg: float
    centre: tuple[float, float]
    low: float
    high: float
    rms: float
    ok: bool
    message: str
    um_per_px: float | None = None
    label: str = ""
    distance: np.ndarray = field(default=None, repr=False, compare=False)
    values: np.ndarray = field(default=None, repr=False, compare=False)

    @property
    def sigma_um(self) -> float | None:
        return None if self.um_per_px is None else self.sigma_px * self.um_per_px

    def to_dict(self) -> dict:
        out = {
            "label": self.label,
            "roi": list(self.roi),
            "orientation": self.orientation,
            "sigma_px": finite_or_none(self.sigma_px),
            "sigma_err_px": finite_or_none(self.sigma_err_px),
            "angle_deg": finite_or_none(self.angle_deg),
            "centre": [finite_or_none(v) for v in self.centre],
            "low": finite_or_none(self.low),
            "high": finite_or_none(self.high),
            "rms": finite_or_none(self.rms),
            "ok": bool(self.ok),
            "message": self.message,
        }
        if self.um_per_px is not None:
            out["sigma_um"] = finite_or_none(self.sigma_um)
        return out


def erf_edge(d, low, high, sigma):
    """The ESF model ``low + (high - low) Phi(d / sigma)``."""
    from scipy.special import ndtr

    return low + (high - low) * ndtr(np.asarray(d, float) / sigma)


def check_roi(roi, shape, label: str = "ROI") -> tuple[int, int, int, int]:
    """Validate an ROI against an image shape ``(rows, cols)``; returns it as ints."""
    try:
        x0, y0, x1, y1 = (int(round(float(v))) for v in roi)
    except (TypeError, ValueError):
        raise DataError(f"{label}: {roi!r} is not four numbers x0,y0,x1,y1") from None
    rows, cols = shape
    if not (0 <= x0 < x1 < cols and 0 <= y0 < y1 < rows):
        raise DataError(
            f"{label}: ({x0}, {y0}, {x1}, {y1}) is not a rectangle inside the {cols} x {rows} px image "
            "(need 0 <= x0 < x1 < width and 0 <= y0 < y1 < height)"
        )
    if min(x1 - x0, y1 - y0) < 3:
        raise DataError(
            f"{label}: ({x0}, {y0}, {x1}, {y1}) is too thin; give at least 4 x 4 px around the edge"
        )
    if (x1 - x0 + 1) * (y1 - y0 + 1) > MAX_ROI_PIXELS:
        raise DataError(
            f"{label}: ({x0}, {y0}, {x1}, {y1}) covers {(x1 - x0 + 1) * (y1 - y0 + 1):,} px, more than "
            f"{MAX_ROI_PIXELS:,}; give a rectangle around one edge (tens of px across it)"
        )
    return x0, y0, x1, y1


def check_rois(rois, shape, labels=None) -> list[tuple[int, int, int, int]]:
    """Validate every ROI (:func:`check_roi`), their number (at most :data:`MAX_EDGES`) and
    their total size (at most :data:`MAX_TOTAL_ROI_PIXELS`), before any fit."""
    try:
        n = len(rois)
    except TypeError:
        raise DataError(f"rois must be a list of rectangles (x0, y0, x1, y1), got {type(rois).__name__}",
                        param="rois") from None  # fmt: skip
    if n > MAX_EDGES:
        raise DataError(f"{n:,} ROIs is more than {MAX_EDGES:,} edges; give fewer ROIs", param="rois")
    if labels is not None and len(labels) != n:
        raise DataError(
            f"labels has {len(labels)} entries for {n} ROIs; give one label per ROI", param="labels"
        )
    out = [
        check_roi(roi, shape, labels[i] if labels is not None else f"edge {i + 1}")
        for i, roi in enumerate(rois)
    ]
    total = sum((x1 - x0 + 1) * (y1 - y0 + 1) for x0, y0, x1, y1 in out)
    if total > MAX_TOTAL_ROI_PIXELS:
        raise DataError(
            f"the {n:,} ROIs cover {total:,} px together, more than {MAX_TOTAL_ROI_PIXELS:,}; give fewer or "
            "smaller ROIs",
            param="rois",
        )
    return out


def _edge_start(data: np.ndarray) -> tuple[float, float, float, float, float]:
    """Start of the fit of an edge varying along axis 1 of ``data``: the levels from the two
    ends of the profile, the line from the gradient centroid of every line (a straight-line
    fit through them), and a blur from the steepest gradient."""
    n_v, n_u = data.shape
    profile = data.mean(axis=0)
    q = max(1, n_u // 4)
    low0, high0 = float(profile[:q].mean()), float(profile[-q:].mean())
    grad = np.abs(np.diff(data, axis=1))
    grad = np.where(grad >= 0.2 * grad.max(axis=1, keepdims=True), grad, 0.0)
    weight = grad.sum(axis=1)
    good = weight > 0
    centres = (grad * (np.arange(n_u - 1) + 0.5)).sum(axis=1)[good] / weight[good]
    if good.sum() >= 2:
        b0, a0 = np.polyfit(np.arange(n_v)[good], centres, 1)
    else:
        b0, a0 = 0.0, (n_u - 1) / 2
    sigma0 = max(0.5, min(abs(high0 - low0) / max(grad.max(), 1e-12) * 0.4, n_u / 4))
    return low0, high0, a0, b0, sigma0


def _erf_fit(data: np.ndarray, uu: np.ndarray, vv: np.ndarray, start):
    """Least-squares fit of ``low + (high - low) * Phi(d / sigma)`` (``d`` the distance from
    the line ``u = a + b v``) to ``data``: the parameters ``(low, high, a, b, sigma)``, the
    standard error of sigma, the residual variance and the solver's verdict and message."""
    from scipy.optimize import least_squares
    from scipy.special import ndtr

    def residuals(p):
        low, high, a, b, sigma = p
        d = (uu - a - b * vv) / math.sqrt(1.0 + b * b)
        return (low + (high - low) * ndtr(d / sigma) - data).ravel()

    n_u = data.shape[1]
    lo_b = [-np.inf, -np.inf, -1.0, -1.0, 0.05]
    hi_b = [np.inf, np.inf, float(n_u), 1.0, float(n_u)]
    p0 = np.clip(np.array(start), np.array(lo_b) + 1e-9, np.array(hi_b) - 1e-9)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        sol = least_squares(residuals, p0, bounds=(lo_b, hi_b), x_scale="jac", method="trf")
    res = sol.fun
    dof = max(res.size - 5, 1)
    s2 = float(res @ res) / dof
    try:
        jtj = sol.jac.T @ sol.jac
        cov = np.linalg.inv(jtj) * s2
        sigma_err = float(math.sqrt(max(cov[4, 4], 0.0)))
    except np.linalg.LinAlgError:
        sigma_err = float("nan")
    return tuple(float(v) for v in sol.x), sigma_err, s2, bool(sol.success), str(sol.message)


def _edge_verdict(ok: bool, message: str, contrast: float, noise: float, centre_u: float, n_u: int,
                  sigma: float) -> tuple[bool, str]:  # fmt: skip
    """Whether a converged fit is trustworthy, and the message saying why not (or ``ok``)."""
    if ok and not contrast > 5 * noise:
        return False, f"no clear edge: contrast {contrast:.3g} is below 5x the noise {noise:.3g}"
    if ok and not (0 <= centre_u <= n_u - 1):
        return False, "the fitted edge lies outside the ROI"
    if ok and 3 * sigma > max(centre_u, n_u - 1 - centre_u):
        return False, "the ROI is too narrow for this blur: widen it to at least 3 sigma each side"
    if ok and sigma <= 0.051:
        return False, "sigma hit its lower bound (0.05 px): the edge is not resolved by the pixels"
    return ok, "ok" if ok else message


def fit_edge(image: np.ndarray, roi, *, um_per_px: float | None = None, label: str = "") -> EdgeFit:
    """Fit the error-function ESF to the one straight edge inside ``roi`` (module docstring).

    Never raises on numerical failure: a failed or untrustworthy fit has ``ok = False``.
    Raises :class:`~oapcal.errors.DataError` when the ROI does not fit in the image.
    """
    image = np.asarray(image, float)
    x0, y0, x1, y1 = check_roi(roi, image.shape, label or "ROI")
    sub = image[y0 : y1 + 1, x0 : x1 + 1]
    # Orientation: the axis along which the mean profile changes most.
    span_x = float(np.ptp(sub.mean(axis=0)))
    span_y = float(np.ptp(sub.mean(axis=1)))
    vertical = span_x >= span_y
    data = sub if vertical else sub.T  # the edge now varies along axis 1 (u), lines along axis 0 (v)
    n_v, n_u = data.shape
    vv, uu = np.mgrid[0:n_v, 0:n_u].astype(float)
    start = _edge_start(data)
    low0, high0 = start[0], start[1]
    contrast = abs(high0 - low0)
    orientation = "vertical" if vertical else "horizontal"
    # Noise from differences along the edge (robust: median absolute deviation).
    noise0 = 1.4826 * float(np.median(np.abs(np.diff(data, axis=0)))) / math.sqrt(2.0) if n_v > 1 else 0.0
    if not contrast > 5 * noise0:
        nan = float("nan")
        return EdgeFit(
            roi=(x0, y0, x1, y1), orientation=orientation, sigma_px=nan, sigma_err_px=nan,
            angle_deg=nan, centre=(nan, nan), low=min(low0, high0), high=max(low0, high0), rms=noise0,
            ok=False, message=f"no clear edge: contrast {contrast:.3g} is below 5x the noise {noise0:.3g}",
            um_per_px=um_per_px, label=label, distance=np.zeros(0), values=np.zeros(0),
        )  # fmt: skip
    (low, high, a, b, sigma), sigma_err, s2, ok, message = _erf_fit(data, uu, vv, start)
    noise = math.sqrt(s2)
    centre_v = (n_v - 1) / 2
    centre_u = a + b * centre_v
    ok, message = _edge_verdict(ok, message, contrast, noise, centre_u, n_u, sigma)
    distance = ((uu - a - b * vv) / math.sqrt(1.0 + b * b)).ravel()
    if high < low:  # a falling edge: report levels as dark/bright with a positive sigma
        distance = -distance
    centre = (x0 + centre_u, y0 + centre_v) if vertical else (x0 + centre_v, y0 + centre_u)
    return EdgeFit(
        roi=(x0, y0, x1, y1), orientation=orientation, sigma_px=sigma, sigma_err_px=sigma_err,
        angle_deg=math.degrees(math.atan(b)), centre=(float(centre[0]), float(centre[1])),
        low=min(low, high), high=max(low, high), rms=noise, ok=ok, message=message,
        um_per_px=um_per_px, label=label, distance=distance, values=data.ravel(),
    )  # fmt: skip


@dataclass(frozen=True)
class EsfSummary:
    """Edge fits and the paper's statistics over the good ones (``sigma_max``, ``sigma_mean``)."""

    edges: tuple[EdgeFit, ...]
    um_per_px: float | None = None

    @property
    def good(self) -> tuple[EdgeFit, ...]:
        return tuple(e for e in self.edges if e.ok)

    def _stat(self, fn) -> float:
        values = [e.sigma_px for e in self.good]
        return float(fn(values)) if values else float("nan")

    @property
    def sigma_max_px(self) -> float:
        return self._stat(np.max)

    @property
    def sigma_mean_px(self) -> float:
        return self._stat(np.mean)

    def to_dict(self) -> dict:
        out = {
            "n_edges": len(self.edges),
            "n_ok": len(self.good),
            "sigma_max_px": finite_or_none(self.sigma_max_px),
            "sigma_mean_px": finite_or_none(self.sigma_mean_px),
        }
        if self.um_per_px is not None:
            out["um_per_px"] = self.um_per_px
            out["sigma_max_um"] = finite_or_none(self.sigma_max_px * self.um_per_px)
            out["sigma_mean_um"] = finite_or_none(self.sigma_mean_px * self.um_per_px)
        out["edges"] = [e.to_dict() for e in self.edges]
        return out


def analyse_edges(image, rois, *, um_per_px=None, labels=None, progress=None) -> EsfSummary:
    """Fit every ROI.  The ROIs are checked first (:func:`check_rois`: inside the image, at
    most :data:`MAX_EDGES` of them, each at most :data:`MAX_ROI_PIXELS` and together at
    most :data:`MAX_TOTAL_ROI_PIXELS`).  ``progress(done, total)`` is called after each edge."""
    from oapcal.progress import progress_callback

    progress = progress_callback(progress)
    image = np.asarray(image, float)  # once, not per edge
    rois = check_rois(rois, image.shape[:2], labels)
    edges = []
    for i, roi in enumerate(rois):
        label = labels[i] if labels is not None else f"edge {i + 1}"
        edges.append(fit_edge(image, roi, um_per_px=um_per_px, label=label))
        if progress is not None:
            progress(i + 1, len(rois))
    return EsfSummary(tuple(edges), um_per_px)


# ------------------------------------------------------------------ finding edges


@dataclass(frozen=True)
class Components:
    """Bars and squares of a target image: a two-level segmentation (Otsu's threshold on
    the image, the minority class as foreground) and its connected components.

    ``labels`` ``(rows, cols)`` int (0 = background); ``boxes`` ``(n, 4)`` inclusive
    ``(x0, y0, x1, y1)`` of components 1..n; ``background`` and ``foreground`` the median
    intensities of the two classes (their plateaus); ``bright`` whether the foreground is
    brighter; ``touches`` ``(n, 4)`` bool, whether the left, top, right, bottom side touches
    the image border.
    """

    labels: np.ndarray
    boxes: np.ndarray
    areas: np.ndarray
    background: float
    foreground: float
    bright: bool
    touches: np.ndarray

    @property
    def level(self) -> float:
        """The half-way intensity between the two plateaus."""
        return 0.5 * (self.background + self.foreground)


def find_components(image: np.ndarray, min_area: int = 20) -> Components:
    """Segment a target image into bars and squares (see :class:`Components`)."""
    import cv2

    image = np.asarray(image, float)
    lo, hi = float(image.min()), float(image.max())
    if not hi > lo:
        raise DataError("the image is uniform: there are no edges to analyse")
    scaled = np.round((image - lo) / (hi - lo) * 255).astype(np.uint8)
    t, mask = cv2.threshold(scaled, 0, 1, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    bright = mask.mean() <= 0.5
    fg = (mask if bright else 1 - mask).astype(np.uint8)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(fg, connectivity=4)
    thr = lo + (hi - lo) * t / 255.0
    median_fg = float(np.median(image[fg == 1])) if fg.any() else thr
    median_bg = float(np.median(image[fg == 0])) if (fg == 0).any() else thr
    keep = [k for k in range(1, n) if stats[k, cv2.CC_STAT_AREA] >= min_area]
    remap = np.zeros(n, np.int32)
    remap[keep] = np.arange(1, len(keep) + 1)
    labels = remap[labels]
    x = stats[keep, cv2.CC_STAT_LEFT]
    y = stats[keep, cv2.CC_STAT_TOP]
    w = stats[keep, cv2.CC_STAT_WIDTH]
    h = stats[keep, cv2.CC_STAT_HEIGHT]
    boxes = np.stack([x, y, x + w - 1, y + h - 1], -1).reshape(-1, 4)
    rows, cols = image.shape
    touches = np.stack(
        [boxes[:, 0] == 0, boxes[:, 1] == 0, boxes[:, 2] == cols - 1, boxes[:, 3] == rows - 1], -1
    )
    return Components(
        labels=labels,
        boxes=boxes,
        areas=stats[keep, cv2.CC_STAT_AREA].astype(int),
        background=median_bg,
        foreground=median_fg,
        bright=bool(bright),
        touches=touches.reshape(-1, 4),
    )


SIDES = ("left", "top", "right", "bottom")


def find_edge_rois(
    image: np.ndarray,
    *,
    half_width: int = 10,
    min_length: int = 6,
    min_area: int = 20,
    valid: np.ndarray | None = None,
) -> tuple[list[tuple[int, int, int, int]], list[str]]:
    """ROIs around the straight sides of the bars and squares of a target image.

    For each component (:func:`find_components`) and each side not on the image border:
    the middle of the side (corners trimmed by a fifth of the side, at least 3 px) and,
    across it, up to ``half_width`` px each way but no more than half the component's
    thickness or half the gap to the next component, so one ROI holds one edge.  Returns
    ``(rois, labels)``; labels read like ``"bar 3 left"``.  With a boolean ``valid`` mask
    ``(rows, cols)``, ROIs that hold an invalid pixel are left out.
    """
    comp = find_components(image, min_area)
    fg = comp.labels > 0
    rois, labels = [], []
    for k, box in enumerate(comp.boxes):
        for side_index, side in enumerate(SIDES):
            if comp.touches[k, side_index]:
                continue
            roi = _side_roi(fg, box, side, half_width, min_length)
            if roi is None:
                continue
            if valid is not None and not valid[roi[1] : roi[3] + 1, roi[0] : roi[2] + 1].all():
                continue
            rois.append(tuple(int(v) for v in roi))
            labels.append(f"bar {k + 1} {side}")
    return rois, labels


def _side_roi(fg: np.ndarray, box, side: str, half_width: int, min_length: int):
    """The ROI ``(x0, y0, x1, y1)`` across one ``side`` of the component in ``box`` of the
    foreground ``fg`` (:func:`find_edge_rois`), or None when the side is too short or too
    close to the image border or the next component."""
    rows, cols = fg.shape
    bx0, by0, bx1, by1 = box
    w, h = bx1 - bx0 + 1, by1 - by0 + 1
    vertical = side in ("left", "right")
    length = h if vertical else w
    trim = max(3, length // 5)
    a0, a1 = (by0, by1) if vertical else (bx0, bx1)
    a0, a1 = a0 + trim, a1 - trim
    if a1 - a0 + 1 < min_length:
        return None
    thickness = w if vertical else h
    # The edge lies half-way between the last foreground and first background pixel.
    if side == "left":
        edge, outward = bx0, -1
    elif side == "right":
        edge, outward = bx1 + 1, 1
    elif side == "top":
        edge, outward = by0, -1
    else:
        edge, outward = by1 + 1, 1
    gap = half_width * 2
    for step in range(1, 2 * half_width + 1):
        pos = edge - 1 - (step - 1) if outward < 0 else edge + (step - 1)
        if not (0 <= pos < (cols if vertical else rows)):
            gap = step - 1
            break
        strip = fg[a0 : a1 + 1, pos] if vertical else fg[pos, a0 : a1 + 1]
        if strip.any():
            gap = step - 1
            break
    hw = int(min(half_width, thickness // 2, gap // 2 if gap < 2 * half_width else half_width))
    if hw < 2:
        return None
    c0, c1 = edge - hw, edge + hw - 1
    if c0 < 0 or c1 >= (cols if vertical else rows):
        return None
    return (c0, a0, c1, a1) if vertical else (a0, c0, a1, c1)
