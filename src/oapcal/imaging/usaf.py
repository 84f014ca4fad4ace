"""The USAF-1951 resolution target: geometry, bar-corner table and an area-sampled renderer.

Numbers of the standard (MIL-STD-150A, the 1951 USAF resolving power test target):

* an element of group ``g``, element ``e`` (1..6) has ``2 ** (g + (e - 1) / 6)`` line pairs
  per mm, so its bar width is ``w = 1000 / (2 * lp_per_mm)`` um (one line pair = one bar and
  one gap);
* each element is a horizontal and a vertical *triplet*: three bars ``w`` wide and ``5 w``
  long separated by gaps ``w`` wide (a triplet is a ``5 w x 5 w`` square);
* groups come in pairs (even ``g``, odd ``g + 1``), called *layers*; each layer is the next
  larger one scaled by 1/4 and nested in its centre.  Within a layer the odd group's
  elements 1-6 run down the right side from the upper right corner; the even group's
  element 1 is at the lower right and its elements 2-6 run down the left side.

oapcal's layout choices where the standard's drawing gives dimensions we do not reproduce
(``docs/usaf.md``): inside an element the horizontal-bar triplet is on the left, the
vertical-bar triplet on the right, ``2 w`` apart; consecutive elements in a column are
``2 w`` apart (``w`` of the lower element); the two columns of a layer leave a ``2 w1`` gap
(``w1`` = bar width of the even group's element 1) around the hole that holds the next
layer.  Digits and the reference squares are not drawn: only bars carry landmarks.

Coordinates: object space in um, x to the right and y *down* (as in the image), origin at
the centre of the nested spiral of layers.  Every bar corner has an id such as
``G4E1H0C2``: group 4, element 1, horizontal triplet (``H``; ``V`` for vertical bars), bar 0
(top or left bar of the triplet), corner 2; corners are numbered 0 top-left, 1 top-right,
2 bottom-right, 3 bottom-left.

>>> t = usaf_target((4, 5))
>>> len(t.bars), len(t.corner_ids)
(72, 288)
>>> round(bar_width_um(4, 1), 4), round(line_pairs_per_mm(5, 6), 2)
(31.25, 57.02)
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from oapcal.errors import DataError

#: Gap between the triplets of an element, between elements and around the nested layer,
#: in bar widths (oapcal's layout choice, see the module docstring).
GAP_W = 2.0
#: Corner order of a bar: top-left, top-right, bottom-right, bottom-left (y down).
CORNER_NAMES = ("top-left", "top-right", "bottom-right", "bottom-left")

#: The 8 orientations of the target in an image (the dihedral group of the square): the
#: 2x2 matrix ``T`` that maps a reference offset ``(dx, dy)`` from the image centre to
#: ``T @ (dx, dy)``, in image px (x right, y *down*).  Turns are as seen on the displayed
#: image: ``rot90`` turns the target 90 degrees counter-clockwise (its right side goes up),
#: ``rot270`` clockwise; ``flip-x`` mirrors left-right (x -> -x), ``flip-y`` top-bottom,
#: ``transpose`` swaps x and y, ``anti-transpose`` swaps them with both signs changed.
ORIENTATIONS: dict[str, tuple[tuple[int, int], tuple[int, int]]] = {
    "none": ((1, 0), (0, 1)),
    "rot90": ((0, 1), (-1, 0)),
    "rot180": ((-1, 0), (0, -1)),
    "rot270": ((0, -1), (1, 0)),
    "flip-x": ((-1, 0), (0, 1)),
    "flip-y": ((1, 0), (0, -1)),
    "transpose": ((0, 1), (1, 0)),
    "anti-transpose": ((0, -1), (-1, 0)),
}


def orientation_matrix(name: str) -> np.ndarray:
    """The 2x2 integer matrix of an orientation in :data:`ORIENTATIONS`.

    >>> orientation_matrix("rot90") @ [1, 0]   # the target's +x (right) points up (-y)
    array([ 0, -1])
    """
    try:
        return np.array(ORIENTATIONS[name], dtype=int)
    except KeyError:
        raise DataError(f"orientation {name!r}: use one of {', '.join(ORIENTATIONS)}") from None


def nearest_orientation(matrix) -> str:
    """The orientation whose matrix is nearest (Frobenius norm) to ``matrix / sqrt(|det|)``:
    e.g. the orientation of an image made through a linear map with magnification.

    >>> nearest_orientation([[-0.21, 0.0], [0.0, -0.2]])
    'rot180'
    """
    m = np.asarray(matrix, float)
    m = m / np.sqrt(abs(np.linalg.det(m)))
    return min(ORIENTATIONS, key=lambda k: float(np.sum((m - np.array(ORIENTATIONS[k])) ** 2)))


def orient_px(xy, orientation: str, image_size: tuple[int, int]) -> np.ndarray:
    """Apply an orientation about the image centre ``c = ((w - 1) / 2, (h - 1) / 2)``:
    ``c + T (xy - c)`` for points ``(..., 2)``.

    >>> orient_px([[0.0, 0.0]], "rot180", (640, 480)).tolist()
    [[639.0, 479.0]]
    """
    centre = (np.asarray(image_size, float) - 1.0) / 2.0
    t = orientation_matrix(orientation)
    return centre + (np.asarray(xy, float) - centre) @ t.T


def line_pairs_per_mm(group: int, element: int) -> float:
    """The standard's resolution of an element: ``2 ** (group + (element - 1) / 6)`` lp/mm."""
    return float(2.0 ** (group + (element - 1) / 6.0))


def bar_width_um(group: int, element: int) -> float:
    """Bar (and gap) width in um: half of one line pair, ``1000 / (2 lp/mm)``."""
    return 1000.0 / (2.0 * line_pairs_per_mm(group, element))


def parse_groups(text: str | tuple | list) -> tuple[int, ...]:
    """``"4-5"`` -> ``(4, 5)``; ``"4"`` -> ``(4,)``; ``"2,4-5"`` or a sequence also work."""
    if not isinstance(text, str):
        groups = tuple(int(g) for g in text)
    else:
        groups = []
        try:
            for part in text.replace(" ", "").split(","):
                if not part:
                    continue
                head, sep, tail = part[1:].partition("-")  # a leading '-' is a sign
                if sep:
                    lo, hi = int(part[0] + head), int(tail)
                    groups.extend(range(lo, hi + 1))
                else:
                    groups.append(int(part))
        except ValueError:
            raise DataError(
                f"groups {text!r}: not a group range; write e.g. 4-5 (groups 4 and 5) or 2,4-5"
            ) from None
        groups = tuple(groups)
    if not groups:
        raise DataError(f"groups {text!r}: no group given; write e.g. 4-5")
    if len(set(groups)) != len(groups):
        raise DataError(f"groups {text!r}: a group is listed twice")
    if min(groups) < -2 or max(groups) > 9:
        raise DataError(f"groups {text!r}: the standard target has groups -2 to 9")
    return tuple(sorted(groups))


# --------------------------------------------------------------------------- layout


def _layer_local() -> tuple[list[tuple[int, int, float, float, float]], np.ndarray, np.ndarray]:
    """One layer in units of ``w1`` (even group, element 1), origin at its top-left corner.

    Returns the elements as ``(group offset 0|1, element, w, x_left, y_top)``, the layer's
    bounding-box centre and the centre of its hole (where the next layer goes).
    """
    r = 2.0 ** (-1.0 / 6.0)
    w_even = {e: r ** (e - 1) for e in range(1, 7)}
    w_odd = {e: 0.5 * r ** (e - 1) for e in range(1, 7)}
    width = lambda w: (10.0 + GAP_W) * w  # noqa: E731  two 5w triplets and a gap
    height = lambda w: 5.0 * w  # noqa: E731
    left_w = max(width(w_even[e]) for e in range(2, 7))
    right_w = max(width(w_odd[e]) for e in range(1, 7))
    # Layer width W: left column, gap, hole (the next layer, W/4 wide), gap, right column.
    total_w = (left_w + 2 * GAP_W + right_w) / (1.0 - 0.25)
    elements = []
    y = 0.0
    for e in range(2, 7):  # even group elements 2-6 down the left side
        if e > 2:
            y += GAP_W * w_even[e]
        elements.append((0, e, w_even[e], 0.0, y))
        y += height(w_even[e])
    left_h = y
    y = 0.0
    for e in range(1, 7):  # odd group elements 1-6 down the right side from the upper right
        if e > 1:
            y += GAP_W * w_odd[e]
        elements.append((1, e, w_odd[e], total_w - width(w_odd[e]), y))
        y += height(w_odd[e])
    y += GAP_W * w_even[1]  # even group element 1 at the lower right
    elements.append((0, 1, w_even[1], total_w - width(w_even[1]), y))
    right_h = y + height(w_even[1])
    total_h = max(left_h, right_h)
    hole_top, hole_bottom = 0.0, y - GAP_W * w_even[1]
    hole = np.array([left_w + GAP_W + 0.5 * (total_w / 4), 0.5 * (hole_top + hole_bottom)])
    bbox_centre = np.array([total_w / 2, total_h / 2])
    return elements, bbox_centre, hole


@dataclass(frozen=True)
class UsafTarget:
    """The bars of some groups of the USAF-1951 target, in object-space um (y down).

    ``bars`` ``(n, 4)`` rectangles ``x0, y0, x1, y1``; ``bar_group``, ``bar_element``,
    ``bar_orientation`` (``"H"`` or ``"V"``), ``bar_index`` (0..2) describe each bar and
    ``bar_width`` its width w in um.  ``corners_um`` ``(4 n, 2)`` lists the 4 corners of each
    bar in order (corner index 0..3, see :data:`CORNER_NAMES`) with ids ``corner_ids``.
    """

    groups: tuple[int, ...]
    bars: np.ndarray
    bar_group: np.ndarray
    bar_element: np.ndarray
    bar_orientation: np.ndarray
    bar_index: np.ndarray
    bar_width: np.ndarray
    corner_ids: tuple[str, ...] = field(repr=False)
    corners_um: np.ndarray = field(repr=False)

    @property
    def bbox_um(self) -> np.ndarray:
        """``(x0, y0, x1, y1)`` of all bars."""
        return np.array([*self.bars[:, :2].min(axis=0), *self.bars[:, 2:].max(axis=0)])

    @property
    def centre_um(self) -> np.ndarray:
        """Centre of :attr:`bbox_um`; the point oapcal puts at the image centre."""
        b = self.bbox_um
        return np.array([(b[0] + b[2]) / 2, (b[1] + b[3]) / 2])

    @property
    def corner_bar(self) -> np.ndarray:
        """Index of the bar of each corner."""
        return np.repeat(np.arange(len(self.bars)), 4)

    @property
    def corner_width_um(self) -> np.ndarray:
        """Bar width w of each corner's bar (um)."""
        return np.repeat(self.bar_width, 4)

    def triplets(self) -> list[np.ndarray]:
        """Bar indices of each triplet (3 bars), largest first."""
        keys = {}
        for i in range(len(self.bars)):
            k = (self.bar_group[i], self.bar_element[i], self.bar_orientation[i])
            keys.setdefault(k, []).append(i)
        order = sorted(keys, key=lambda k: (-self.bar_width[keys[k][0]], k[2]))
        return [np.array(keys[k]) for k in order]

    def reference_px(
        self, um_per_px: float, image_size: tuple[int, int], orientation: str = "none"
    ) -> np.ndarray:
        """Corners in reference px at ``um_per_px``: :attr:`centre_um` at the image centre
        ``c = ((w - 1) / 2, (h - 1) / 2)``, turned by ``orientation`` about ``c``
        (:func:`orient_px`); the convention of ``detect`` and ``simulate image``."""
        return self.to_reference_px(self.corners_um, um_per_px, image_size, orientation)

    def to_reference_px(
        self, xy_um, um_per_px: float, image_size: tuple[int, int], orientation: str = "none"
    ) -> np.ndarray:
        """Object um -> reference px (see :meth:`reference_px`)."""
        centre_px = (np.asarray(image_size, float) - 1.0) / 2.0
        xy = (np.asarray(xy_um, float) - self.centre_um) / float(um_per_px) + centre_px
        return xy if orientation == "none" else orient_px(xy, orientation, image_size)

    def rectangles_px(
        self, um_per_px: float, image_size: tuple[int, int], orientation: str = "none"
    ) -> np.ndarray:
        """Bars as ``(n, 4)`` rectangles ``x0, y0, x1, y1`` (``x0 < x1``, ``y0 < y1``) in
        reference px (see :meth:`reference_px`)."""
        a = self.to_reference_px(self.bars[:, :2], um_per_px, image_size, orientation)
        b = self.to_reference_px(self.bars[:, 2:], um_per_px, image_size, orientation)
        return np.concatenate([np.minimum(a, b), np.maximum(a, b)], axis=1)


def usaf_target(groups=(4, 5)) -> UsafTarget:
    """The bars and bar corners of ``groups`` (see the module docstring for the layout)."""
    groups = parse_groups(groups)
    local, bbox_centre, hole = _layer_local()
    d = hole - bbox_centre / 4.0
    rows = []
    for g in groups:
        g_even = g - (g % 2)
        s = bar_width_um(g_even, 1)  # um per layer unit
        origin = -(4.0 / 3.0) * s * d  # layer origin relative to the spiral centre
        for odd, e, w, x_left, y_top in local:
            if g_even + odd != g:
                continue
            w_um = s * w
            x0, y0 = origin + s * np.array([x_left, y_top])
            for orient, tx in (("H", x0), ("V", x0 + (5.0 + GAP_W) * w_um)):
                for b in range(3):
                    if orient == "H":
                        rect = (tx, y0 + 2 * b * w_um, tx + 5 * w_um, y0 + (2 * b + 1) * w_um)
                    else:
                        rect = (tx + 2 * b * w_um, y0, tx + (2 * b + 1) * w_um, y0 + 5 * w_um)
                    rows.append((g, e, orient, b, w_um, rect))
    bars = np.array([r[5] for r in rows], float)
    corners = np.stack([bars[:, [0, 1]], bars[:, [2, 1]], bars[:, [2, 3]], bars[:, [0, 3]]], axis=1).reshape(
        -1, 2
    )
    ids = tuple(f"G{g}E{e}{o}{b}C{c}" for g, e, o, b, _, _ in rows for c in range(4))
    return UsafTarget(
        groups=groups,
        bars=bars,
        bar_group=np.array([r[0] for r in rows]),
        bar_element=np.array([r[1] for r in rows]),
        bar_orientation=np.array([r[2] for r in rows]),
        bar_index=np.array([r[3] for r in rows]),
        bar_width=np.array([r[4] for r in rows]),
        corner_ids=ids,
        corners_um=corners,
    )


# ------------------------------------------------------------------------- rendering


def _coverage_1d(lo: float, hi: float, n: int, start: float, step: float) -> np.ndarray:
    """Length of ``[lo, hi]`` inside each cell ``[start + (i - 1/2) step, start + (i + 1/2) step]``,
    as a fraction of ``step``, for ``i = 0..n-1``."""
    centres = start + step * np.arange(n)
    left = np.maximum(centres - 0.5 * step, lo)
    right = np.minimum(centres + 0.5 * step, hi)
    return np.clip(right - left, 0.0, None) / step


def render_rectangles(
    rects: np.ndarray,
    shape: tuple[int, int],
    *,
    start: tuple[float, float] = (0.0, 0.0),
    step: float = 1.0,
) -> np.ndarray:
    """Area-sampled rendering of axis-aligned rectangles ``(n, 4)`` (``x0, y0, x1, y1``).

    Cell ``[row, col]`` of the ``(rows, cols)`` output is centred on
    ``(start[0] + col * step, start[1] + row * step)`` and covers a ``step x step`` square;
    its value is the fraction of that square covered by the rectangles (exact for
    non-overlapping rectangles: the coverage of a rectangle is the product of its 1-D
    coverages).  ``float64`` in ``[0, 1]``.

    >>> render_rectangles(np.array([[0.0, 0.0, 1.5, 1.0]]), (2, 3))
    array([[0.25, 0.5 , 0.  ],
           [0.25, 0.5 , 0.  ]])
    """
    rows, cols = int(shape[0]), int(shape[1])
    out = np.zeros((rows, cols))
    for x0, y0, x1, y1 in np.asarray(rects, float).reshape(-1, 4):
        x0, x1 = min(x0, x1), max(x0, x1)
        y0, y1 = min(y0, y1), max(y0, y1)
        c0 = max(0, int(np.floor((x0 - start[0]) / step - 0.5)))
        c1 = min(cols, int(np.ceil((x1 - start[0]) / step + 0.5)) + 1)
        r0 = max(0, int(np.floor((y0 - start[1]) / step - 0.5)))
        r1 = min(rows, int(np.ceil((y1 - start[1]) / step + 0.5)) + 1)
        if c0 >= c1 or r0 >= r1:
            continue
        cx = _coverage_1d(x0, x1, c1 - c0, start[0] + c0 * step, step)
        cy = _coverage_1d(y0, y1, r1 - r0, start[1] + r0 * step, step)
        out[r0:r1, c0:c1] += np.outer(cy, cx)
    return np.clip(out, 0.0, 1.0, out=out)


def intensity(coverage: np.ndarray, polarity: str = "bright", background: float = 0.05) -> np.ndarray:
    """Relative intensity from bar coverage: bright bars (1) on a dark field (``background``)
    for ``polarity="bright"``, dark bars (``background``) on a bright field (1) for ``"dark"``."""
    if polarity == "bright":
        return background + (1.0 - background) * coverage
    if polarity == "dark":
        return 1.0 - (1.0 - background) * coverage
    raise DataError(f"polarity {polarity!r}: use 'bright' (bright bars) or 'dark' (dark bars)")


@dataclass(frozen=True)
class RenderedTarget:
    """A rendered target: ``image`` ``(h, w)`` float in ``[0, 1]`` and every bar corner in px."""

    image: np.ndarray
    corner_ids: tuple[str, ...]
    corners_px: np.ndarray
    um_per_px: float


def render_usaf(
    groups=(4, 5),
    *,
    um_per_px: float = 4.8,
    image_size: tuple[int, int] = (640, 480),
    polarity: str = "bright",
    background: float = 0.05,
) -> RenderedTarget:
    """Render ``groups`` at ``um_per_px`` into an ``image_size`` (w, h) image, area-sampled,
    with the target's bounding-box centre at the image centre (:meth:`UsafTarget.reference_px`).

    >>> r = render_usaf((4, 5), um_per_px=4.8)
    >>> r.image.shape, r.corners_px.shape
    ((480, 640), (288, 2))
    """
    if not um_per_px > 0:
        raise DataError(f"um_per_px {um_per_px}: must be positive")
    target = usaf_target(groups)
    w, h = (int(v) for v in image_size)
    cover = render_rectangles(target.rectangles_px(um_per_px, (w, h)), (h, w))
    return RenderedTarget(
        image=intensity(cover, polarity, background),
        corner_ids=target.corner_ids,
        corners_px=target.reference_px(um_per_px, (w, h)),
        um_per_px=float(um_per_px),
    )
