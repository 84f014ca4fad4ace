"""The USAF-1951 resolution target: its true layout, bar-corner table and an area-sampled renderer.

Numbers of the standard (MIL-STD-150A, the 1951 USAF resolving power test target):

* an element of group ``g``, element ``e`` (1..6) has ``2 ** (g + (e - 1) / 6)`` line pairs
  per mm, so its bar width is ``w = 1000 / (2 * lp_per_mm)`` um (one line pair = one bar and
  one gap);
* each element is a horizontal and a vertical *triplet*: three bars ``w`` wide and ``5 w``
  long separated by gaps ``w`` wide (a triplet is a ``5 w x 5 w`` square);
* groups come in pairs (even ``g``, odd ``g + 1``), called *layers*; each layer is the next
  larger one scaled by 1/4 and nested inside it.

The layout of a layer, in units of ``w1`` (bar width of the even group's element 1), as
measured on real targets (``docs/usaf.md``); the numbers are those of the default
``"compact"`` layout:

* the even group's elements 2-6 form the *left column*, left-aligned, drawn "digit,
  horizontal bars, vertical bars" from left to right, the two triplets ``2 w`` apart;
* the odd group's elements 1-6 form the *right column*, right-aligned, drawn "vertical bars,
  horizontal bars, digit"; both columns start at the top of the layer and each element is
  ``2 w`` (of the element above) below the one above, i.e. element tops are ``7 w`` apart;
* the even group's element 1 is drawn like the right column ("vertical, horizontal,
  digit"), right-aligned and bottom-aligned with the left column: the layer is a square of
  side ``S = 7 (F + F^2 + F^3 + F^4) + 5 F^5 = 23.96 w1``, ``F = 2^(-1/6)``;
* the reference square fills the gap between the left column's element 2 (``2 w2`` from
  it) and the right column's element 1 (``2 w`` of that element from it), top-aligned;
* the next layer (scaled 1/4) sits below the square, between the columns, at
  ``(11.95, 8.98) w1`` (its top-left corner; measured, see ``docs/usaf.md``);
* group numbers stand above the columns, element numbers beside each element (the
  boxes :attr:`UsafTarget.labels` are approximate: they are for masking, not landmarks).

Makers differ in the gaps between triplets and between elements (3.5 w on one target),
in the width of the layer, the size of the square and the position and mirroring of the
nested layers; :data:`LAYOUTS` holds the layouts measured on real targets (``"compact"``
is the default).

Coordinates: object space in um, x to the right and y *down* (as in the image), origin at
the centre of the nested spiral of layers.  Every bar corner has an id such as
``G4E1H0C2``: group 4, element 1, horizontal triplet (``H``; ``V`` for vertical bars), bar 0
(top or left bar of the triplet), corner 2; corners are numbered 0 top-left, 1 top-right,
2 bottom-right, 3 bottom-left.

>>> t = usaf_target((4, 5))
>>> len(t.bars), len(t.corner_ids), len(t.squares)
(72, 288, 1)
>>> round(bar_width_um(4, 1), 4), round(line_pairs_per_mm(5, 6), 2)
(31.25, 57.02)
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

import numpy as np

from oapcal.errors import DataError
from oapcal.records import ImageSize

#: Gap between the two triplets of an element and between consecutive elements of a column,
#: in bar widths of the element (of the upper element between elements).  MIL-STD-150A layout.
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


#: The groups of the standard target (MIL-STD-150A), lowest and highest.
LOWEST_GROUP, HIGHEST_GROUP = -2, 9
#: One part of a groups text: a group or a range ``lo-hi`` (ASCII digits; a leading ``-`` a sign).
_GROUPS_PART = re.compile(r"(-?[0-9]+)(?:-(-?[0-9]+))?")


def parse_groups(text: str | tuple | list) -> tuple[int, ...]:
    """``"4-5"`` -> ``(4, 5)``; ``"4"`` -> ``(4,)``; ``"2,4-5"`` or a sequence of whole
    numbers also work.  Every group lies in -2 ... 9 (checked before a range is expanded, so
    ``4-99999999999999999999`` is one line, not an overflow); a range is written low to high;
    only ASCII digits are read (``4_5`` and other scripts' digits are refused, not 45).
    Anything else raises :class:`~oapcal.errors.DataError` naming ``groups``.

    >>> parse_groups("2, 4-5"), parse_groups("-2--1"), parse_groups([5, 4])
    ((2, 4, 5), (-2, -1), (4, 5))
    >>> parse_groups("9-3")
    Traceback (most recent call last):
    oapcal.errors.DataError: groups '9-3': the range 9-3 is reversed; write it low to high, 3-9
    """
    shown = repr(text)
    shown = shown if len(shown) <= 60 else shown[:50] + "..."
    how = "write e.g. 4-5 (groups 4 and 5) or 2,4-5"
    span = f"the standard target has groups {LOWEST_GROUP} to {HIGHEST_GROUP}"
    groups: list[int] = []
    if isinstance(text, str):
        for part in "".join(text.split()).split(","):
            if not part:
                continue
            match = _GROUPS_PART.fullmatch(part)
            if match is None:
                raise DataError(f"groups {shown}: not a group range ({part!r}); {how}", param="groups")
            for g in (match[1], match[2]):
                # the digits are looked at before int(): a number of thousands of digits is
                # out of range, not Python's int() error
                if g is not None and (len(g.lstrip("-0")) > 2 or not LOWEST_GROUP <= int(g) <= HIGHEST_GROUP):
                    raise DataError(
                        f"groups {shown}: {span}, not {g if len(g) <= 24 else g[:20] + '...'}", param="groups"
                    )
            lo = int(match[1])
            hi = lo if match[2] is None else int(match[2])
            if hi < lo:
                raise DataError(
                    f"groups {shown}: the range {part} is reversed; write it low to high, {hi}-{lo}",
                    param="groups",
                )
            groups.extend(range(lo, hi + 1))
    else:
        try:
            items = list(text) if len(text) <= 10 * (HIGHEST_GROUP - LOWEST_GROUP + 1) else None
        except (TypeError, OverflowError):
            items = None
        if items is None:
            raise DataError(
                f"groups {shown}: give a text such as '4-5' or a short list of groups", param="groups"
            )
        for g in items:
            if isinstance(g, (bool, np.bool_)) or not isinstance(g, (int, np.integer)):
                raise DataError(f"groups {shown}: {g!r} is not a whole number; {how}", param="groups")
            if not LOWEST_GROUP <= g <= HIGHEST_GROUP:
                raise DataError(f"groups {shown}: {span}, not {g}", param="groups")
            groups.append(int(g))
    if not groups:
        raise DataError(f"groups {shown}: no group given; {how}", param="groups")
    if len(set(groups)) != len(groups):
        twice = sorted({g for g in groups if groups.count(g) > 1})
        raise DataError(f"groups {shown}: group {twice[0]} is listed twice", param="groups")
    return tuple(sorted(groups))


# --------------------------------------------------------------------------- layout

#: Ratio of the bar widths of consecutive elements.
F = 2.0 ** (-1.0 / 6.0)
#: Side of a layer (height of the left column), in w1 = bar width of the even group's element 1.
LAYER_SIZE_W1 = 7.0 * (F + F**2 + F**3 + F**4) + 5.0 * F**5


@dataclass(frozen=True)
class UsafLayout:
    """Where a maker's target puts what the standard leaves open, in units of ``w1``.

    ``triplet_gap_w``: gap between the two triplets of an element, in its bar widths;
    ``element_gap_w``: gap between consecutive elements of a column, in bar widths of the
    upper one (both 2 on the compact target, so that element tops are ``7 w`` apart);
    ``extra_width_w1``: added to the layer's width between the square and the right column
    (0: the layer is as wide as it is high, :attr:`size_w1`); ``square_x_w1``: left and right
    edge of the reference square (None: it fills the gap between the columns' top elements,
    a triplet gap from each); ``square_height_w1``: its height (None: as high as wide);
    ``inner_offset_w1``: top-left corner of the next layer inside a layer;
    ``mirrored_layers``: even groups whose layer is drawn mirrored left-right (odd group on
    the left), as some whole-target prints do.
    """

    name: str
    inner_offset_w1: tuple[float, float]
    extra_width_w1: float = 0.0
    square_height_w1: float | None = None
    mirrored_layers: tuple[int, ...] = ()
    triplet_gap_w: float = GAP_W
    element_gap_w: float = GAP_W
    square_x_w1: tuple[float, float] | None = None

    @property
    def size_w1(self) -> float:
        """Height of the layer (of its left column), w1."""
        pitch = 5.0 + self.element_gap_w
        return pitch * (F + F**2 + F**3 + F**4) + 5.0 * F**5

    @property
    def width_w1(self) -> float:
        """Width of the layer (left edge of the left column to right edge of the right one), w1."""
        return self.size_w1 + self.extra_width_w1


#: Layouts measured on real targets (``docs/usaf.md``, :func:`oapcal.imaging.usaf_check.measure_layout`).
#: ``compact`` (default): 2 w gaps, square layer; the Fourier-ptychography target (and the
#: high-magnification one, as far as it shows).  ``spaced``: 3.5 w between elements, a smaller square (the
#: LAB-UMK target).  ``whole-target``: the digitised whole target with the header "RESOLVING
#: POWER TEST TARGET" (wider layer, tall square, layer 0-1 mirrored left-right).
LAYOUTS: dict[str, UsafLayout] = {
    "compact": UsafLayout("compact", inner_offset_w1=(11.95, 8.98)),
    "spaced": UsafLayout(
        "spaced",
        inner_offset_w1=(12.99, 10.42),
        triplet_gap_w=1.85,
        element_gap_w=3.49,
        extra_width_w1=-1.10,
        square_x_w1=(14.2, 18.9),
    ),
    "whole-target": UsafLayout(
        "whole-target",
        inner_offset_w1=(11.16, 9.14),
        triplet_gap_w=1.96,
        element_gap_w=2.04,
        extra_width_w1=1.83,
        square_height_w1=7.4,
        mirrored_layers=(0,),
    ),
}

# Approximate label boxes (measured on the compact target), w1 units: digit heights and the
# gap between a digit and its triplet.  Labels are for masking only.
_DIGIT_H_EVEN, _DIGIT_H_ODD, _GROUP_H = 2.4, 1.45, 2.95
_CHAR_W = 0.62  # width of one character per unit of height


def layout(name_or_layout: str | UsafLayout | None = None) -> UsafLayout:
    """A :class:`UsafLayout` from its name in :data:`LAYOUTS` (None: ``"compact"``)."""
    if isinstance(name_or_layout, UsafLayout):
        return name_or_layout
    key = "compact" if name_or_layout is None else name_or_layout
    try:
        return LAYOUTS[key]
    except KeyError:
        raise DataError(f"layout {key!r}: use one of {', '.join(LAYOUTS)}") from None


def _label_box(text: str, height: float, *, cx=None, x_left=None, x_right=None, cy=None, bottom=None):
    wd = _CHAR_W * height * len(text)
    if cx is not None:
        x0 = cx - wd / 2
    elif x_left is not None:
        x0 = x_left
    else:
        x0 = x_right - wd
    y0 = cy - height / 2 if cy is not None else bottom - height
    return (x0, y0, x0 + wd, y0 + height)


def _layer_local(lay: UsafLayout, g_even: int):
    """One unmirrored layer in units of ``w1``, origin at its top-left corner.

    Returns triplets ``(group, element, "H"|"V", w, x0, y0)`` (the triplet's ``5 w`` square),
    squares ``(x0, y0, x1, y1)`` and labels ``(kind, group, element, text, box)``.
    """
    size, width = lay.size_w1, lay.width_w1
    pitch, tw = 5.0 + lay.element_gap_w, 10.0 + lay.triplet_gap_w  # element pitch, element width (w)
    trip, labels = [], []
    y = 0.0
    for e in range(2, 7):  # even group, left column: digit, H, V
        w = F ** (e - 1)
        trip += [(g_even, e, "H", w, 0.0, y), (g_even, e, "V", w, (5.0 + lay.triplet_gap_w) * w, y)]
        labels.append(
            ("element", g_even, e, str(e), _label_box(str(e), _DIGIT_H_EVEN, x_right=-1.55, cy=y + 2.5 * w))
        )
        y += pitch * w
    y = 0.0
    for e in range(1, 7):  # odd group, right column: V, H, digit
        w = 0.5 * F ** (e - 1)
        trip += [(g_even + 1, e, "V", w, width - tw * w, y), (g_even + 1, e, "H", w, width - 5.0 * w, y)]
        labels.append(
            (
                "element",
                g_even + 1,
                e,
                str(e),
                _label_box(str(e), _DIGIT_H_ODD, x_left=width + 0.75, cy=y + 2.5 * w),
            )
        )
        y += pitch * w
    y1 = size - 5.0  # even group, element 1: V, H, digit, bottom right
    trip += [(g_even, 1, "V", 1.0, width - tw, y1), (g_even, 1, "H", 1.0, width - 5.0, y1)]
    labels.append(
        ("element", g_even, 1, "1", _label_box("1", _DIGIT_H_EVEN, x_left=width + 1.5, cy=size - 2.5))
    )
    labels.append(
        (
            "group",
            g_even,
            1,
            str(g_even),
            _label_box(str(g_even), _GROUP_H, x_left=width + 1.5, bottom=y1 - 0.15),
        )
    )
    labels.append(
        ("group", g_even, 2, str(g_even), _label_box(str(g_even), _GROUP_H, cx=0.5 * tw * F, bottom=-1.35))
    )
    labels.append(
        (
            "group",
            g_even + 1,
            1,
            str(g_even + 1),
            _label_box(str(g_even + 1), _GROUP_H, cx=width - 0.25 * tw, bottom=-1.35),
        )
    )
    gap = lay.triplet_gap_w  # the square is a triplet gap from its neighbours
    sq_x0, sq_x1 = (tw + gap) * F, width - 0.5 * (tw + gap)
    if lay.square_x_w1 is not None:
        sq_x0, sq_x1 = lay.square_x_w1
    sq_h = lay.square_height_w1 if lay.square_height_w1 is not None else sq_x1 - sq_x0
    return trip, [(sq_x0, 0.0, sq_x1, sq_h)], labels


def _layer_origins(lay: UsafLayout, groups) -> dict[int, tuple[np.ndarray, bool]]:
    """Top-left corner (um, spiral centre at 0) and mirroring of the layer of every even group."""
    pos, out, mirrored = np.zeros(2), {}, False
    g_hi = max(40, max(groups) + 2)
    for g in range(-2, g_hi + 1, 2):
        s = bar_width_um(g, 1)
        mirrored = g in lay.mirrored_layers
        out[g] = (pos.copy(), mirrored)
        ox, oy = lay.inner_offset_w1
        if mirrored:
            ox = lay.width_w1 - ox - lay.width_w1 / 4
        pos = pos + s * np.array([ox, oy])
    limit = pos  # the spiral's centre (layers beyond g_hi are far below a nm)
    return {g: (p - limit, m) for g, (p, m) in out.items()}


def _triplet_bars(orient: str, w: float, x0: float, y0: float) -> list[tuple[float, float, float, float]]:
    if orient == "H":
        return [(x0, y0 + 2 * b * w, x0 + 5 * w, y0 + (2 * b + 1) * w) for b in range(3)]
    return [(x0 + 2 * b * w, y0, x0 + (2 * b + 1) * w, y0 + 5 * w) for b in range(3)]


@dataclass(frozen=True)
class UsafTarget:
    """The bars of some groups of the USAF-1951 target, in object-space um (y down).

    ``bars`` ``(n, 4)`` rectangles ``x0, y0, x1, y1``; ``bar_group``, ``bar_element``,
    ``bar_orientation`` (``"H"`` or ``"V"``), ``bar_index`` (0..2) describe each bar and
    ``bar_width`` its width w in um.  ``corners_um`` ``(4 n, 2)`` lists the 4 corners of each
    bar in order (corner index 0..3, see :data:`CORNER_NAMES`) with ids ``corner_ids``.

    Not landmarks, but part of the target (for masking or matching): ``squares`` ``(m, 4)``
    the reference squares of the layers of ``groups`` (``square_group``: the layer's even
    group); ``labels`` ``(k, 4)`` approximate boxes of the printed numbers with
    ``label_text``, ``label_kind`` (``"element"`` digit beside an element or ``"group"``
    number) and ``label_group``, ``label_element`` (for a group number: the element it stands
    above, 1 or 2 for the even group, 1 for the odd group).
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
    squares: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)), repr=False)
    square_group: np.ndarray = field(default_factory=lambda: np.zeros(0, int), repr=False)
    labels: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)), repr=False)
    label_text: tuple[str, ...] = field(default=(), repr=False)
    label_kind: tuple[str, ...] = field(default=(), repr=False)
    label_group: np.ndarray = field(default_factory=lambda: np.zeros(0, int), repr=False)
    label_element: np.ndarray = field(default_factory=lambda: np.zeros(0, int), repr=False)
    layout: str = "compact"

    @property
    def bbox_um(self) -> np.ndarray:
        """``(x0, y0, x1, y1)`` of all bars."""
        return np.array([*self.bars[:, :2].min(axis=0), *self.bars[:, 2:].max(axis=0)])

    @property
    def digits(self) -> np.ndarray:
        """Boxes ``(k, 4)`` um of all printed numbers (element and group numbers): :attr:`labels`."""
        return self.labels

    @property
    def full_bbox_um(self) -> np.ndarray:
        """``(x0, y0, x1, y1)`` of the bars, squares and labels."""
        r = np.concatenate([self.bars, self.squares, self.labels])
        return np.array([*r[:, :2].min(axis=0), *r[:, 2:].max(axis=0)])

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

    def triplet_boxes(self) -> np.ndarray:
        """The ``5 w x 5 w`` square of each triplet of :meth:`triplets` (same order), ``(t, 4)`` um."""
        return np.array(
            [[*self.bars[b, :2].min(axis=0), *self.bars[b, 2:].max(axis=0)] for b in self.triplets()]
        )

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

    def boxes_px(
        self, boxes_um, um_per_px: float, image_size: tuple[int, int], orientation: str = "none"
    ) -> np.ndarray:
        """Any ``(n, 4)`` um boxes (e.g. :attr:`squares`, :attr:`labels`) as rectangles
        ``x0, y0, x1, y1`` (``x0 < x1``, ``y0 < y1``) in reference px (see :meth:`reference_px`)."""
        boxes_um = np.asarray(boxes_um, float).reshape(-1, 4)
        a = self.to_reference_px(boxes_um[:, :2], um_per_px, image_size, orientation)
        b = self.to_reference_px(boxes_um[:, 2:], um_per_px, image_size, orientation)
        return np.concatenate([np.minimum(a, b), np.maximum(a, b)], axis=1)

    def rectangles_px(
        self, um_per_px: float, image_size: tuple[int, int], orientation: str = "none"
    ) -> np.ndarray:
        """Bars as ``(n, 4)`` rectangles ``x0, y0, x1, y1`` (``x0 < x1``, ``y0 < y1``) in
        reference px (see :meth:`reference_px`)."""
        return self.boxes_px(self.bars, um_per_px, image_size, orientation)


def usaf_target(groups=(4, 5), layout_name: str | UsafLayout | None = None) -> UsafTarget:
    """The bars, bar corners, squares and labels of ``groups`` (module docstring for the
    layout) in the layout ``layout_name`` (:data:`LAYOUTS`, default ``"compact"``)."""
    groups = parse_groups(groups)
    lay = layout(layout_name)
    origins = _layer_origins(lay, groups)
    width = lay.width_w1
    rows, squares, square_group, labels = [], [], [], []
    for g_even in sorted({g - (g % 2) for g in groups}):
        s = bar_width_um(g_even, 1)
        origin, mirrored = origins[g_even]
        trip, sq, lab = _layer_local(lay, g_even)

        def place(box, _o=origin, _s=s, _m=mirrored):
            x0, y0, x1, y1 = box
            if _m:
                x0, x1 = width - x1, width - x0
            return (_o[0] + _s * x0, _o[1] + _s * y0, _o[0] + _s * x1, _o[1] + _s * y1)

        for g, e, orient, w, x0, y0 in trip:
            if g not in groups:
                continue
            bx0, by0, _, _ = place((x0, y0, x0 + 5 * w, y0 + 5 * w))
            for b, rect in enumerate(_triplet_bars(orient, s * w, bx0, by0)):
                rows.append((g, e, orient, b, s * w, rect))
        for box in sq:
            squares.append(place(box))
            square_group.append(g_even)
        for kind, g, e, text, box in lab:
            if g in groups:
                labels.append((kind, g, e, text, place(box)))
    # bars in a fixed order: by group, element, orientation, bar
    rows.sort(key=lambda r: (r[0], r[1], r[2], r[3]))
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
        squares=np.array(squares, float).reshape(-1, 4),
        square_group=np.array(square_group, int),
        labels=np.array([r[4] for r in labels], float).reshape(-1, 4),
        label_text=tuple(r[3] for r in labels),
        label_kind=tuple(r[0] for r in labels),
        label_group=np.array([r[1] for r in labels], int),
        label_element=np.array([r[2] for r in labels], int),
        layout=lay.name,
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


#: Height (px) of the box in which a text's glyphs are drawn before they are area-sampled
#: down to their box: the ink's share of the box is then the same at every resolution.
_GLYPH_REF_PX = 96


def _text_ink(text: str, box_h: float, box_w: float) -> np.ndarray:
    """The ink ``[0, 1]`` of ``text`` in OpenCV's Hershey simplex font, cropped to its own
    bounding box and scaled to fill ``box_h x box_w`` (px) with its aspect kept, stroke about
    0.14 of the height. Drawn at a reference size and area-sampled down (``cv2.INTER_AREA``),
    and measured on the drawn ink, not from ``cv2.getTextSize``, whose box differs between
    OpenCV 4 and 5 (OpenCV 5 draws the glyphs smaller within it)."""
    import cv2

    font = cv2.FONT_HERSHEY_SIMPLEX
    ref_h = float(_GLYPH_REF_PX)
    ref_w = ref_h * box_w / box_h
    thick = max(1, int(round(0.14 * ref_h)))

    def draw(scale: float) -> np.ndarray:
        (tw, th), base = cv2.getTextSize(text, font, scale, thick)
        pad = 2 * thick + 4
        canvas = np.zeros((th + base + 2 * pad, tw + 2 * pad), np.uint8)
        cv2.putText(canvas, text, (pad, pad + th), font, scale, 255, thick, cv2.LINE_AA)
        ys, xs = np.nonzero(canvas)
        if len(ys) == 0:
            return np.zeros((1, 1), np.float32)
        return canvas[ys.min() : ys.max() + 1, xs.min() : xs.max() + 1].astype(np.float32) / 255.0

    scale = 1.0
    for _ in range(3):  # the ink's size is nearly proportional to the scale: a few passes
        ink = draw(scale)
        scale *= min(ref_h / ink.shape[0], ref_w / ink.shape[1])
    ink = draw(scale * 0.999)
    f = min(box_h / ink.shape[0], box_w / ink.shape[1])  # never outside its box
    size = (max(1, int(round(ink.shape[1] * f))), max(1, int(round(ink.shape[0] * f))))
    return cv2.resize(ink, size, interpolation=cv2.INTER_AREA).astype(float)


def render_digits(
    boxes: np.ndarray,
    texts,
    shape: tuple[int, int],
    *,
    start: tuple[float, float] = (0.0, 0.0),
    step: float = 1.0,
    supersample: int = 4,
) -> np.ndarray:
    """Coverage ``(rows, cols)`` of printed numbers: each text drawn upright in its box
    ``x0, y0, x1, y1`` (same cell convention as :func:`render_rectangles`) with OpenCV's
    Hershey simplex font, stroke about 0.14 of the height, ``supersample``-fold area sampling.

    The standard's digits are another font; these approximate their size, place and ink
    (about 35 % of the box), enough for masking and for realistic simulated images.

    >>> cov = render_digits(np.array([[2.0, 2.0, 8.0, 12.0]]), ["4"], (14, 10))
    >>> bool(cov[2:12, 2:8].sum() > 10 and cov[:, :2].sum() == 0)
    True
    """
    rows, cols = int(shape[0]), int(shape[1])
    out = np.zeros((rows, cols))
    ss = int(supersample)
    for (x0, y0, x1, y1), text in zip(np.asarray(boxes, float).reshape(-1, 4), texts):
        c0, r0 = (x0 - start[0]) / step + 0.5, (y0 - start[1]) / step + 0.5  # cell-edge units
        c1, r1 = (x1 - start[0]) / step + 0.5, (y1 - start[1]) / step + 0.5
        ic0, ir0 = max(0, int(np.floor(c0))), max(0, int(np.floor(r0)))
        ic1, ir1 = min(cols, int(np.ceil(c1))), min(rows, int(np.ceil(r1)))
        if ic0 >= ic1 or ir0 >= ir1 or (r1 - r0) * ss < 6:
            continue
        box_h, box_w = (r1 - r0) * ss, (c1 - c0) * ss
        glyph = _text_ink(text, box_h, box_w)
        gh, gw = glyph.shape
        # full cells ic0..ic1 at ss sub-cells each; the glyph centred on the box
        canvas = np.zeros((int(np.ceil(r1) - ir0) * ss + gh, int(np.ceil(c1) - ic0) * ss + gw))
        oy = int(round((r0 - ir0) * ss + (box_h - gh) / 2))
        ox = int(round((c0 - ic0) * ss + (box_w - gw) / 2))
        canvas[max(oy, 0) : max(oy, 0) + gh, max(ox, 0) : max(ox, 0) + gw] = glyph
        hi_h, hi_w = (ir1 - ir0) * ss, (ic1 - ic0) * ss
        block = canvas[:hi_h, :hi_w].reshape(ir1 - ir0, ss, ic1 - ic0, ss).mean(axis=(1, 3))
        out[ir0:ir1, ic0:ic1] += block
    return np.clip(out, 0.0, 1.0, out=out)


def target_coverage(
    target: UsafTarget,
    shape: tuple[int, int],
    *,
    start: tuple[float, float] = (0.0, 0.0),
    step: float = 1.0,
    squares: bool = True,
    digits: bool = True,
) -> np.ndarray:
    """Coverage of the whole target in object space (cells of ``step`` um, centre of cell
    ``[0, 0]`` at ``start`` um): bars and squares area-sampled (:func:`render_rectangles`),
    numbers drawn by :func:`render_digits`."""
    rects = target.bars if not squares else np.concatenate([target.bars, target.squares])
    cover = render_rectangles(rects, shape, start=start, step=step)
    if digits and len(target.labels):
        cover += render_digits(target.labels, target.label_text, shape, start=start, step=step)
        np.clip(cover, 0.0, 1.0, out=cover)
    return cover


def render_usaf(
    groups=(4, 5),
    *,
    um_per_px: float = 4.8,
    image_size: tuple[int, int] = (640, 480),
    polarity: str = "bright",
    background: float = 0.05,
    squares: bool = True,
    digits: bool = True,
    layout_name: str | UsafLayout | None = None,
) -> RenderedTarget:
    """Render ``groups`` at ``um_per_px`` into an ``image_size`` (w, h) image, area-sampled,
    with the bars' bounding-box centre at the image centre (:meth:`UsafTarget.reference_px`):
    bars, the reference squares (``squares``) and the printed numbers (``digits``) of the
    true layout ``layout_name``.

    >>> r = render_usaf((4, 5), um_per_px=4.8)
    >>> r.image.shape, r.corners_px.shape
    ((480, 640), (288, 2))
    """
    if not um_per_px > 0:
        raise DataError(f"um_per_px {um_per_px}: must be positive")
    target = usaf_target(groups, layout_name)
    size = ImageSize(*(int(v) for v in image_size))
    # reference px -> um: x_um = centre_um + (x_px - c) * S; cell (0, 0) is pixel (0, 0)
    start = tuple(target.centre_um - (np.array(size, float) - 1.0) / 2.0 * um_per_px)
    cover = target_coverage(
        target, size.shape, start=start, step=float(um_per_px), squares=squares, digits=digits
    )
    return RenderedTarget(
        image=intensity(cover, polarity, background),
        corner_ids=target.corner_ids,
        corners_px=target.reference_px(um_per_px, size),
        um_per_px=float(um_per_px),
    )
