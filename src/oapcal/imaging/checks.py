"""Checks of a corrected image and of corrected landmarks, as in the paper's Figure 4.

* **Straightness**: along each side of each bar and square of a target image, the edge is
  located to a fraction of a pixel in every row (or column) as the point where the
  intensity crosses the half-way level between background and bars (linear interpolation
  between the two pixels that straddle it; the level is set per line between the
  background plateau and the line's peak); a straight line is fitted through these
  points and the RMS (and largest) perpendicular deviation from it is reported in px.
  A well-corrected image has straight edges (deviation near the noise floor); distortion
  bends them.
* **Aspect ratio**: the width and height of each bar or square, as the median distance
  between opposite edges over the middle rows (columns), and their ratio (long / short),
  compared with the nearest of the target's known ratios (5 for the bars of a USAF 1951
  target, 1 for its squares).  The half-way crossing of a blurred edge is at the true
  edge for a symmetric PSF, so blur does not bias the sizes of features much wider than it.
* **Residual vectors** of corrected landmarks: corrected minus reference position.

>>> import numpy as np
>>> from oapcal.imaging.bars import bar_target
>>> img, _ = bar_target((60, 80), bars=[(20.5, 10.5, 30.5, 50.5)], sigma=1.0)
>>> result = check_target(img)
>>> [round(s.rms_px, 3) for s in result.edges[:2]], round(result.shapes[0].aspect, 3)
([0.0, 0.0], 4.0)
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from oapcal.imaging.esf import SIDES, Components, find_components
from oapcal.records import finite_or_none


@dataclass(frozen=True)
class EdgeLine:
    """One side of one component: located edge points, the fitted line and its straightness."""

    component: int
    side: str
    points: np.ndarray = field(repr=False)  # (n, 2) x, y of the located edge
    rms_px: float
    max_px: float
    angle_deg: float
    ends: tuple[tuple[float, float], tuple[float, float]]

    def to_dict(self) -> dict:
        return {
            "component": self.component,
            "side": self.side,
            "n_points": len(self.points),
            "rms_px": self.rms_px,
            "max_px": self.max_px,
            "angle_deg": self.angle_deg,
            "ends": [list(self.ends[0]), list(self.ends[1])],
        }


@dataclass(frozen=True)
class ShapeCheck:
    """Size and aspect ratio of one bar or square (px); ``error_pct`` against ``expected``."""

    component: int
    box: tuple[int, int, int, int]
    width_px: float
    height_px: float
    aspect: float
    expected: float | None
    error_pct: float | None

    def to_dict(self) -> dict:
        return {
            "component": self.component,
            "box": list(self.box),
            "width_px": self.width_px,
            "height_px": self.height_px,
            "aspect": self.aspect,
            "expected": self.expected,
            "error_pct": self.error_pct,
        }


@dataclass(frozen=True)
class TargetCheck:
    """Straightness of every edge and shape of every component of one image."""

    edges: tuple[EdgeLine, ...]
    shapes: tuple[ShapeCheck, ...]
    level: float

    @property
    def straightness_rms_px(self) -> float:
        """RMS over all edges of their RMS deviations (NaN without edges)."""
        values = [e.rms_px for e in self.edges]
        return float(np.sqrt(np.mean(np.square(values)))) if values else float("nan")

    @property
    def straightness_max_px(self) -> float:
        values = [e.max_px for e in self.edges]
        return float(np.max(values)) if values else float("nan")

    @property
    def aspect_error_mean_pct(self) -> float:
        values = [abs(s.error_pct) for s in self.shapes if s.error_pct is not None]
        return float(np.mean(values)) if values else float("nan")

    @property
    def aspect_error_max_pct(self) -> float:
        values = [abs(s.error_pct) for s in self.shapes if s.error_pct is not None]
        return float(np.max(values)) if values else float("nan")

    def summary(self) -> dict:
        return {
            "n_edges": len(self.edges),
            "straightness_rms_px": finite_or_none(self.straightness_rms_px),
            "straightness_max_px": finite_or_none(self.straightness_max_px),
            "n_shapes": len(self.shapes),
            "aspect_error_mean_pct": finite_or_none(self.aspect_error_mean_pct),
            "aspect_error_max_pct": finite_or_none(self.aspect_error_max_pct),
        }


#: Components checked at most by :func:`check_target` (the largest ones).
MAX_COMPONENTS = 2000


def _crossings(image, labels, k, background, bright, side, a0, a1, b0=0, b1=None):
    """Sub-pixel edge positions of component ``k`` on ``side`` for lines ``a0..a1``.

    The level of each line is half-way between the background plateau and the line's own
    peak inside the component, so that a line near a corner or across a thin bar (whose
    peak the blur lowers) is still cut at the edge.

    For a left/right side the lines are rows and the positions x; for top/bottom they are
    columns and the positions y.  Returns ``(lines, positions)`` of the lines where the
    crossing exists.  ``b0..b1`` is the component's extent along the lines (its box): only
    that part of each line is searched, so the work grows with the component, not the image.
    """
    vertical = side in ("left", "right")
    img = image if vertical else image.T
    lab = labels if vertical else labels.T
    sign = 1.0 if bright else -1.0
    lines, positions = [], []
    b1 = img.shape[1] - 1 if b1 is None else b1
    for line in range(a0, a1 + 1):
        cols = np.flatnonzero(lab[line, b0 : b1 + 1] == k) + b0
        if cols.size == 0:
            continue
        if side in ("left", "top"):
            j = cols[0]
            i0, i1 = j - 1, j  # outside -> inside
        else:
            j = cols[-1]
            i0, i1 = j, j + 1  # inside -> outside
        if i0 < 0 or i1 >= img.shape[1]:
            continue
        inside = img[line, cols]
        level = 0.5 * (background + (inside.max() if bright else inside.min()))
        v0, v1 = sign * (img[line, i0] - level), sign * (img[line, i1] - level)
        if v0 == v1 or v0 * v1 > 0:
            continue
        positions.append(i0 + v0 / (v0 - v1))
        lines.append(line)
    return np.array(lines, float), np.array(positions, float)


def _line_fit(lines, positions):
    """Fit ``position = a + b line``; perpendicular deviations, angle, fitted end points."""
    b, a = np.polyfit(lines, positions, 1)
    dev = (positions - (a + b * lines)) / math.sqrt(1.0 + b * b)
    ends = [(float(a + b * t), float(t)) for t in (lines.min(), lines.max())]
    return dev, math.degrees(math.atan(b)), ends


def check_target(
    image: np.ndarray,
    expected_ratios=(5.0, 1.0),
    *,
    min_area: int = 20,
    min_points: int = 5,
    components: Components | None = None,
    valid: np.ndarray | None = None,
) -> TargetCheck:
    """Straightness of the sides and aspect ratios of the bars and squares of ``image``.

    Corners are left out (a fifth of each side, at least 2 px), as are sides on the image
    border and components touching it (for the aspect ratio).  With a boolean ``valid``
    mask ``(rows, cols)``, components within 2 px of an invalid pixel are left out.  Only
    the :data:`MAX_COMPONENTS` largest components are checked (an image of noise has
    hundreds of thousands).
    """
    image = np.asarray(image, float)
    comp = find_components(image, min_area) if components is None else components
    edges, shapes = [], []
    order = np.arange(len(comp.boxes))
    if len(order) > MAX_COMPONENTS:
        order = np.sort(np.argsort(-np.asarray(comp.areas), kind="stable")[:MAX_COMPONENTS])
    for index in order:
        bx0, by0, bx1, by1 = comp.boxes[index]
        if valid is not None:
            window = valid[max(by0 - 2, 0) : by1 + 3, max(bx0 - 2, 0) : bx1 + 3]
            if not window.all():
                continue
        extents = _component_edges(image, comp, index, min_points, edges)
        if comp.touches[index].any() or len(extents) < 4:
            continue
        shape = _shape_check(index + 1, comp.boxes[index], extents, expected_ratios)
        if shape is not None:
            shapes.append(shape)
    return TargetCheck(tuple(edges), tuple(shapes), comp.level)


def _component_edges(image: np.ndarray, comp: Components, index: int, min_points: int, edges: list) -> dict:
    """The straightness of each side of component ``index`` not on the image border,
    appended to ``edges`` (:class:`EdgeLine`); returns the sides located on at least 3
    lines, ``{side: (lines, positions)}``, for the aspect ratio."""
    bx0, by0, bx1, by1 = comp.boxes[index]
    k = index + 1
    extents = {}
    for side_index, side in enumerate(SIDES):
        if comp.touches[index, side_index]:
            continue
        vertical = side in ("left", "right")
        a0, a1 = (by0, by1) if vertical else (bx0, bx1)
        trim = max(2, (a1 - a0 + 1) // 5)
        b0, b1 = (bx0, bx1) if vertical else (by0, by1)
        lines, pos = _crossings(
            image, comp.labels, k, comp.background, comp.bright, side, a0 + trim, a1 - trim, b0, b1
        )
        if len(lines) >= 3:  # enough for a median width
            extents[side] = (lines, pos)
        if len(lines) < min_points:  # too few for a line fit
            continue
        dev, angle, ends = _line_fit(lines, pos)
        # Points and line ends back to (x, y).
        xy = np.stack([pos, lines], -1) if vertical else np.stack([lines, pos], -1)
        ends_xy = tuple(ends) if vertical else tuple((t, p) for p, t in ends)
        edges.append(
            EdgeLine(
                component=k,
                side=side,
                points=xy,
                rms_px=float(np.sqrt(np.mean(dev * dev))),
                max_px=float(np.max(np.abs(dev))),
                angle_deg=angle,
                ends=ends_xy,
            )
        )
    return extents


def _shape_check(k: int, box, extents: dict, expected_ratios) -> ShapeCheck | None:
    """The aspect ratio of component ``k`` from its four sides' ``extents``, against the
    nearest of ``expected_ratios``; None when its width or height is not positive."""
    bx0, by0, bx1, by1 = box
    width = _extent(extents["left"], extents["right"])
    height = _extent(extents["top"], extents["bottom"])
    if not (width > 0 and height > 0):
        return None
    aspect = max(width, height) / min(width, height)
    expected = None
    error = None
    if len(expected_ratios):
        expected = float(min(expected_ratios, key=lambda r: abs(math.log(aspect / r))))
        error = 100.0 * (aspect / expected - 1.0)
    return ShapeCheck(
        k,
        (int(bx0), int(by0), int(bx1), int(by1)),
        float(width),
        float(height),
        aspect,
        expected,
        error,
    )


def _extent(first, second) -> float:
    """Median distance between two opposite sides over the lines both located."""
    lines1, pos1 = first
    lines2, pos2 = second
    common, i1, i2 = np.intersect1d(lines1, lines2, return_indices=True)
    if common.size == 0:
        return float("nan")
    return float(np.median(pos2[i2] - pos1[i1]))


@dataclass(frozen=True)
class ResidualVectors:
    """Corrected landmarks against their references: ``xy_c``, ``dxy = xy_c - xy_u`` (NaN
    where the inverse did not converge) and the references ``xy_u``; all ``(N, 2)`` px."""

    xy_u: np.ndarray
    xy_c: np.ndarray
    dxy: np.ndarray

    @property
    def length(self) -> np.ndarray:
        return np.hypot(self.dxy[:, 0], self.dxy[:, 1])


def residual_vectors(model, xy_u, xy_d) -> ResidualVectors:
    """Correct ``xy_d`` through the inverse of ``model`` (a Model, a calibration or a
    parameter vector: :func:`oapcal.model.as_model`) and compare with ``xy_u``."""
    from oapcal.model import as_model

    xy_u = np.asarray(xy_u, float)
    xy_c = as_model(model).inverse(np.asarray(xy_d, float)).xy
    return ResidualVectors(xy_u, xy_c, xy_c - xy_u)
