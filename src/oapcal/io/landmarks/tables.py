"""Landmark tables: napari Points CSV, BigWarp landmarks CSV, plain CSV/TSV.

Pixel conventions (see ``docs/file-formats.md``):

* **napari** puts pixel centres at integer coordinates, as oapcal does; its columns are
  ``index,axis-0,axis-1`` with axis-0 the row (y) and axis-1 the column (x).  With more
  axes (a stack) the last two are y and x and the others must be the same for every
  point.  Other columns are the layer's features.
* **BigWarp** (ImgLib2) also puts pixel centres at integer coordinates, in the image's
  calibrated units (px when the image is uncalibrated).  No header; each row is
  ``"name","enabled",moving x,moving y[,moving z],fixed x,fixed y[,fixed z]``.  The
  *moving* image is the distorted one, the *fixed* image the reference.
* **plain** CSV/TSV: columns named by the caller, origin at the pixel centre unless the
  caller says ``origin="corner"`` (e.g. ImageJ's Measure of point selections, whose
  centre of the top-left pixel is (0.5, 0.5)).
"""

from __future__ import annotations

import difflib
import math
import re

from oapcal.errors import InputFileError
from oapcal.io.landmarks._base import (
    Landmark,
    LandmarkSet,
    coordinate,
    csv_rows,
    first_row,
    read_text,
    sniff_delimiter,
)
from oapcal.io.userfile import parse_number

_AXIS = re.compile(r"^axis-(\d+)$")
#: Plane coordinates (BigWarp z, napari's leading axes) closer than this, relative to their
#: size (and absolutely, near 0), are the same plane: tools write float noise such as
#: 126.86263579832789 and 126.8626357983279 for one plane.
PLANE_TOLERANCE = 1e-9


def same_plane(a: float, b: float) -> bool:
    """Whether two plane coordinates are equal up to float noise (:data:`PLANE_TOLERANCE`).

    >>> same_plane(126.86263579832789, 126.8626357983279), same_plane(130.0, 130.5)
    (True, False)
    """
    return math.isclose(a, b, rel_tol=PLANE_TOLERANCE, abs_tol=PLANE_TOLERANCE)


def is_napari_header(first_line: str) -> bool:
    cells = [c.strip().strip('"') for c in first_line.split(",")]
    return "axis-0" in cells and "axis-1" in cells


def is_bigwarp_row(first_line: str) -> bool:
    """A header-less first line like ``"Pt-0","true",...``, or of 6 or 8 cells whose
    coordinates are numbers (a plain CSV's header line has names there)."""
    cells = [c.strip().strip('"').lower() for c in first_line.split(",")]
    if len(cells) >= 3 and cells[1] in ("true", "false"):
        return True
    if len(cells) not in (6, 8):
        return False
    try:
        [parse_number(c) for c in cells[2:]]
    except ValueError:
        return False
    return True


def read_napari(path, *, text: str | None = None) -> LandmarkSet:
    """Read a napari Points layer saved as CSV."""
    name = str(path)
    text = read_text(path, "napari points CSV") if text is None else text
    rows = csv_rows(text, name)
    _, header = first_row(rows, name)
    header = [h.strip() for h in header]
    axes = sorted((int(m.group(1)), i) for i, h in enumerate(header) if (m := _AXIS.match(h)))
    if [a for a, _ in axes] != list(range(len(axes))) or len(axes) < 2:
        raise InputFileError(
            f"{name}: line 1: a napari points CSV needs columns axis-0, axis-1, ... (axis-0 = row, "
            f"the last = column); found {', '.join(header[:8])}"
        )
    iy, ix = axes[-2][1], axes[-1][1]
    leading = [i for _, i in axes[:-2]]
    plane = None
    landmarks = []
    for line, cells in rows:
        where = f"line {line}"
        if len(cells) < len(header):
            raise InputFileError(f"{name}: {where}: {len(cells)} cells but the header has {len(header)}")
        y = coordinate(cells[iy], name, where, header[iy])
        x = coordinate(cells[ix], name, where, header[ix])
        here = tuple(coordinate(cells[i], name, where, header[i]) for i in leading)
        if plane is None:
            plane = here
        elif not all(same_plane(a, b) for a, b in zip(here, plane)):
            raise InputFileError(
                f"{name}: {where}: the point is in plane {here} but earlier ones are in {plane}; "
                "export the landmarks of one 2-D plane"
            )
        attrs = {h: cells[i].strip() for i, h in enumerate(header) if i not in (ix, iy) and i not in leading}
        landmarks.append(Landmark(x, y, attrs, where))
    if not landmarks:
        raise InputFileError(f"{name}: has a header but no points")
    return LandmarkSet(name, tuple(landmarks))


def read_bigwarp(path, *, text: str | None = None) -> tuple[LandmarkSet, LandmarkSet]:
    """Read a BigWarp landmarks CSV: ``(moving, fixed)`` landmark sets.

    Each landmark's ``name`` attribute pairs it with its partner.  Disabled rows and rows
    whose point is missing in one image (BigWarp writes ``Infinity``/``NaN`` there) are not
    used; they are listed in ``ignored``.
    """
    name = str(path)
    text = read_text(path, "BigWarp landmarks CSV") if text is None else text
    moving, fixed, ignored = [], [], []
    width = None
    plane_z: list[float | None] = [None, None]
    for line, cells in csv_rows(text, name):
        where = f"line {line}"
        cells = [c.strip() for c in cells]
        if width is None:
            if len(cells) not in (6, 8):
                raise InputFileError(
                    f"{name}: {where}: {len(cells)} cells; a BigWarp row has 6 (2-D) or 8 (3-D): "
                    '"name","true",moving x,y[,z],fixed x,y[,z]'
                )
            width = len(cells)
        elif len(cells) != width:
            raise InputFileError(f"{name}: {where}: {len(cells)} cells but line 1 has {width}")
        label, enabled = cells[0], cells[1].lower()
        if enabled not in ("true", "false"):
            raise InputFileError(f"{name}: {where}: enabled flag is {cells[1]!r}, expected true or false")
        if enabled == "false":
            ignored.append(f"{where}: landmark {label!r} is disabled")
            continue
        nd = (width - 2) // 2
        halves = (cells[2 : 2 + nd], cells[2 + nd :])
        _check_placed(halves, f"{name}: {where}: landmark {label!r}")
        if any(_missing(v) for half in halves for v in half):
            ignored.append(f"{where}: landmark {label!r} is placed in only one image")
            continue
        points = []
        for side, half in zip(("moving", "fixed"), halves):
            points.append([coordinate(v, name, where, f"{side} {ax}") for v, ax in zip(half, "xyz")])
        if nd == 3:
            _check_plane(points, plane_z, f"{name}: {where}")
        moving.append(Landmark(points[0][0], points[0][1], {"name": label}, where))
        fixed.append(Landmark(points[1][0], points[1][1], {"name": label}, where))
    if width is None:
        raise InputFileError(f"{name}: has no landmark rows")
    if not moving:
        raise InputFileError(f"{name}: no enabled landmark is placed in both images")
    return (
        LandmarkSet(f"{name} [moving]", tuple(moving), tuple(ignored)),
        LandmarkSet(f"{name} [fixed]", tuple(fixed), ()),
    )


def _check_placed(halves, at: str) -> None:
    """Refuse a point with some coordinates missing and others numbers (BigWarp writes every
    coordinate of an unplaced point)."""
    for side, half in zip(("moving", "fixed"), halves):
        gone = [_missing(v) for v in half]
        if any(gone) and not all(gone):
            ax = "xyz"[gone.index(True)]
            raise InputFileError(
                f"{at} has {side} {ax} = {half[gone.index(True)]!r} but "
                f"its other {side} coordinates are numbers; give a finite {ax}, or disable the landmark"
            )


def _check_plane(points, plane_z: list, at: str) -> None:
    """Refuse a 3-D landmark off the plane of the earlier ones (``plane_z``: the moving and
    fixed planes so far, None before the first; set here)."""
    for k, side in enumerate(("moving", "fixed")):
        z = points[k][2]
        if plane_z[k] is None:
            plane_z[k] = z
        elif not same_plane(z, plane_z[k]):
            raise InputFileError(
                f"{at}: {side} z = {z:.15g} differs from earlier landmarks "
                f"(z = {plane_z[k]:.15g}); oapcal needs landmarks of one 2-D plane"
            )


def _missing(text: str) -> bool:
    try:
        return not math.isfinite(parse_number(text))
    except ValueError:
        return False


def read_table(path, *, x_column: str = "x", y_column: str = "y", origin: str = "center",
               text: str | None = None) -> LandmarkSet:  # fmt: skip
    """Read landmarks from a CSV or TSV with a header; ``x_column``/``y_column`` name the
    coordinate columns (matched exactly, then ignoring case).  ``origin="corner"``
    subtracts 0.5 px (files whose top-left pixel centre is at (0.5, 0.5))."""
    if origin not in ("center", "corner"):
        raise InputFileError(f"pixel origin {origin!r}: expected 'center' or 'corner'")
    name = str(path)
    text = read_text(path, "landmark CSV") if text is None else text
    rows = csv_rows(text, name, sniff_delimiter(text))
    _, header = first_row(rows, name)
    header = [h.strip() for h in header]
    ix = find_column(header, x_column, name, "x_column")
    iy = find_column(header, y_column, name, "y_column")
    offset = 0.5 if origin == "corner" else 0.0
    landmarks = []
    for line, cells in rows:
        where = f"line {line}"
        if len(cells) < len(header):
            raise InputFileError(
                f"{name}: {where}: {len(cells)} cells but the header has {len(header)} columns; "
                "fill in the missing cells"
            )
        x = coordinate(cells[ix], name, where, f"column {header[ix]!r}") - offset
        y = coordinate(cells[iy], name, where, f"column {header[iy]!r}") - offset
        attrs = {h: cells[i].strip() for i, h in enumerate(header) if i not in (ix, iy) and h}
        landmarks.append(Landmark(x, y, attrs, where))
    if not landmarks:
        raise InputFileError(f"{name}: has a header but no data rows")
    return LandmarkSet(name, tuple(landmarks))


def find_column(header: list[str], wanted: str, name: str, param: str) -> int:
    if wanted in header:
        if header.count(wanted) > 1:
            raise InputFileError(f"{name}: line 1: column {wanted!r} appears more than once; keep one")
        return header.index(wanted)
    folded = [h.lower() for h in header]
    if folded.count(wanted.lower()) == 1:
        return folded.index(wanted.lower())
    close = difflib.get_close_matches(wanted, header, n=1, cutoff=0.5)
    hint = f" (did you mean {close[0]!r}?)" if close else ""
    from oapcal.io.points import delimiter_hint

    raise InputFileError(
        f"{name}: line 1: no column {wanted!r}{hint}; name the coordinate column with {param} "
        f"(columns: {', '.join(header[:8])}){delimiter_hint(header)}",
        param=param,
    )
