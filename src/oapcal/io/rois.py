"""Region-of-interest files for edge analysis: CSV with columns ``x0,y0,x1,y1`` and an
optional ``label``.

Each row is a rectangle in px (x = column, y = row, origin at the centre of the top-left
pixel) holding one straight edge: the pixels ``x0 <= col <= x1``, ``y0 <= row <= y1``.
Problems raise :class:`~oapcal.errors.InputFileError` naming the file, line and column.

>>> import tempfile, pathlib
>>> p = pathlib.Path(tempfile.mkdtemp()) / "rois.csv"
>>> _ = p.write_text("label,x0,y0,x1,y1\\nleft edge,10,20,30,60\\n")
>>> read_rois(p)
([(10, 20, 30, 60)], ['left edge'])
"""

from __future__ import annotations

import csv
import io
import math

from oapcal.errors import InputFileError
from oapcal.io.userfile import parse_number

ROI_COLUMNS = ("x0", "y0", "x1", "y1")
#: Largest pixel index accepted in an ROI file.
MAX_INDEX = 10_000_000


def read_rois(path) -> tuple[list[tuple[int, int, int, int]], list[str]]:
    """Rectangles and labels (``"roi N"`` where the file has no ``label`` column).  A file of
    more than :data:`oapcal.imaging.esf.MAX_EDGES` rectangles is refused at the first row
    past the limit, before any fit."""
    name = str(path)
    from oapcal.imaging.esf import MAX_EDGES
    from oapcal.io.userfile import read_text

    text = read_text(path, "ROI file", missing="no such ROI file; check the path")
    reader = csv.reader(io.StringIO(text))
    header = [h.strip() for h in next(reader, [])]
    missing = [c for c in ROI_COLUMNS if c not in header]
    if missing:
        raise InputFileError(
            f"{name}: line 1: missing column {missing[0]!r}; the header must contain {','.join(ROI_COLUMNS)}"
        )
    col = {h: i for i, h in enumerate(header)}
    rois, labels = [], []
    for row in reader:
        line = reader.line_num
        if not row or all(not c.strip() for c in row):
            continue
        if len(rois) == MAX_EDGES:
            raise InputFileError(
                f"{name}: line {line}: more than {MAX_EDGES:,} rectangles (an edge takes 1-30 ms to fit); "
                f"give at most {MAX_EDGES:,}, e.g. split the file"
            )
        if len(row) < len(header):
            raise InputFileError(f"{name}: line {line}: {len(row)} cells but the header has {len(header)}")
        values = []
        for c in ROI_COLUMNS:
            cell = row[col[c]].strip()
            try:
                v = parse_number(cell)
            except ValueError:
                raise InputFileError(f"{name}: line {line}, column {c!r}: {cell!r} is not a number") from None
            if not math.isfinite(v) or abs(v) > MAX_INDEX:
                raise InputFileError(
                    f"{name}: line {line}, column {c!r}: {cell!r} is not a pixel index (a whole number "
                    f"between -{MAX_INDEX} and {MAX_INDEX})"
                )
            if v != int(v):
                raise InputFileError(f"{name}: line {line}, column {c!r}: {cell} is not a whole pixel index")
            values.append(int(v))
        x0, y0, x1, y1 = values
        if not (x1 > x0 and y1 > y0):
            raise InputFileError(f"{name}: line {line}: need x1 > x0 and y1 > y0, got {x0},{y0},{x1},{y1}")
        rois.append((x0, y0, x1, y1))
        labels.append(row[col["label"]].strip() if "label" in col else f"roi {len(rois)}")
    if not rois:
        raise InputFileError(f"{name}: has no rectangles; add rows x0,y0,x1,y1")
    return rois, labels
