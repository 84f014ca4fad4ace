"""Point-pair CSV files: ``x_u,y_u,x_d,y_d`` and an optional ``id`` column.

``x_u, y_u`` are the reference (undistorted) points and ``x_d, y_d`` the observed
(distorted) ones, in px (or any unit used consistently), origin at the centre of the
top-left pixel, x = column, y = row (``docs/conventions.md``).  Other columns are kept
(``correct-points`` copies them) but otherwise ignored.

Every problem raises :class:`~oapcal.errors.InputFileError` or
:class:`~oapcal.errors.DataError` with a message that names the file, the line (as a
text editor counts them, header = line 1) and the column.
"""

from __future__ import annotations

import csv
import difflib
import io
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from oapcal.errors import DataError, InputFileError
from oapcal.io.atomic import atomic_write
from oapcal.io.userfile import checked_coordinate, parse_number, read_text
from oapcal.validate import point_pairs

PAIR_COLUMNS = ("x_u", "y_u", "x_d", "y_d")
#: Coordinates beyond this magnitude are refused: no image is that large, and the model's
#: powers of r would overflow.
MAX_COORD = 1.0e12


@dataclass(frozen=True)
class PointPairs:
    """Point pairs read from a file.

    ``xy_u`` and ``xy_d`` are ``(N, 2)`` float arrays (NaN-filled when a column set was not
    required and is absent); ``ids`` the ``id`` column or None; ``rows`` the raw rows (for
    copying columns through) with ``fieldnames``; ``lines`` the file line of each row.
    ``warnings`` lists what was read but not used (landmark files: unpaired or disabled
    landmarks); ``where_u``/``where_d`` name each point's origin for messages (landmark
    files; empty for point-pair CSVs, whose ``lines`` say it).
    """

    xy_u: np.ndarray
    xy_d: np.ndarray
    ids: tuple[str, ...] | None
    rows: tuple[dict, ...]
    fieldnames: tuple[str, ...]
    lines: tuple[int, ...]
    source: str
    warnings: tuple[str, ...] = ()
    where_u: tuple[str, ...] = ()
    where_d: tuple[str, ...] = ()

    def __len__(self) -> int:
        return len(self.xy_d)


def _parse_float(text: str, name: str, line: int, column: str) -> float:
    try:
        value = parse_number(text)
    except (TypeError, ValueError, AttributeError):
        shown = "an empty cell" if not (text or "").strip() else repr(text)
        raise InputFileError(
            f"{name}: line {line}, column {column!r}: {shown} is not a number (give ASCII decimal or "
            "scientific notation, e.g. 47.5 or 4.75e1)"
        ) from None
    at = f"{name}: line {line}, column {column!r}"
    return checked_coordinate(value, MAX_COORD, at, text.strip(), "remove or fix this row")


def read_points(
    path: str | Path,
    require: tuple[str, ...] = PAIR_COLUMNS,
    *,
    check_geometry: bool = True,
) -> PointPairs:
    """Read a point-pair CSV (or TSV) file.

    ``require`` names the columns that must be present (``correct-points`` needs only
    ``x_d, y_d``).  With ``check_geometry``, duplicated points and collinear point sets
    are rejected (:func:`check_geometry`).
    """
    name = str(path)
    text = read_text(path, "point file")
    if "\x00" in text:
        raise InputFileError(f"{name}: contains binary data (NUL bytes); give a CSV text file")
    if not text.strip():
        raise InputFileError(f"{name}: is empty; expected a CSV header line {','.join(PAIR_COLUMNS)}")
    first = text.splitlines()[0]
    delimiter = "\t" if first.count("\t") > first.count(",") else ","
    reader = csv.reader(io.StringIO(text), delimiter=delimiter)
    try:
        header = [h.strip() for h in next(reader)]
    except csv.Error as exc:
        raise InputFileError(f"{name}: line 1: malformed CSV header ({exc})") from None
    _check_header(header, require, name)
    col = {h: i for i, h in enumerate(header)}
    present = [c for c in PAIR_COLUMNS if c in col]
    rows, lines, values = _data_rows(reader, header, present, name)
    if not rows:
        raise InputFileError(f"{name}: has a header but no data rows; add point pairs")
    arr = np.full((len(rows), 4), np.nan)
    for j, c in enumerate(present):
        arr[:, PAIR_COLUMNS.index(c)] = np.array(values)[:, j]
    ids = tuple(r["id"].strip() for r in rows) if "id" in col else None
    pairs = PointPairs(
        xy_u=arr[:, :2],
        xy_d=arr[:, 2:],
        ids=ids,
        rows=tuple(rows),
        fieldnames=tuple(header),
        lines=tuple(lines),
        source=name,
    )
    if ids is not None:
        _check_unique_ids(ids, lines, name)
    if check_geometry:
        check_geometry_of(pairs)
    return pairs


def _check_header(header: list[str], require, name: str) -> None:
    """Refuse a header without the ``require`` columns (suggesting a close name) or with a
    point column twice."""
    missing = [c for c in require if c not in header]
    if missing:
        hints = []
        spare = [h for h in header if h not in PAIR_COLUMNS]  # a close match must not be needed itself
        for col in missing:
            close = difflib.get_close_matches(col, spare, n=1, cutoff=0.6)
            hints.append(f"{col!r}" + (f" (found {close[0]!r}: rename it)" if close else ""))
        raise InputFileError(
            f"{name}: line 1: missing column{'s' if len(missing) > 1 else ''} {', '.join(hints)}; "
            f"the header must contain {','.join(require)}{delimiter_hint(header)}"
        )
    dupes = sorted({h for h in header if header.count(h) > 1 and h in PAIR_COLUMNS + ("id",)})
    if dupes:
        raise InputFileError(f"{name}: line 1: column {dupes[0]!r} appears more than once; keep one")


def _data_rows(reader, header: list[str], present: list[str], name: str):
    """The non-blank rows after the header: each as a dict, its line and the numbers of
    its ``present`` point columns."""
    col = {h: i for i, h in enumerate(header)}
    rows, lines, values = [], [], []
    try:
        for row in reader:
            line = reader.line_num
            if not row or all(not c.strip() for c in row):
                continue
            if len(row) < len(header):
                raise InputFileError(
                    f"{name}: line {line}: {len(row)} cells but the header has {len(header)} columns; "
                    "fill in the missing cells"
                )
            values.append([_parse_float(row[col[c]], name, line, c) for c in present])
            rows.append({h: row[i] for i, h in enumerate(header)})
            lines.append(line)
    except csv.Error as exc:
        raise InputFileError(f"{name}: line {reader.line_num}: malformed CSV ({exc})") from None
    return rows, lines, values


def _check_unique_ids(ids, lines, name: str) -> None:
    seen: dict[str, int] = {}
    for i, ident in enumerate(ids):
        if ident in seen:
            raise InputFileError(
                f"{name}: line {lines[i]}: id {ident!r} already used on line {seen[ident]}; "
                "ids must be unique"
            )
        seen[ident] = lines[i]


def delimiter_hint(header: list[str]) -> str:
    """A hint for a header read as one column because the file separates its columns by
    ``;`` or ``|`` (as spreadsheets set to a comma decimal separator write), else "".

    >>> delimiter_hint(["x_u;y_u;x_d;y_d"])
    "; the file separates its columns with ';': save it with ',' (or tabs)"
    """
    if len(header) == 1:
        for sep in (";", "|"):
            if sep in header[0]:
                return f"; the file separates its columns with {sep!r}: save it with ',' (or tabs)"
    return ""


def check_geometry_of(pairs: PointPairs) -> None:
    """Reject duplicated points and collinear point sets (raises :class:`DataError`)."""
    for label, xy in (("reference", pairs.xy_u), ("distorted", pairs.xy_d)):
        if np.isnan(xy).any():  # a column set that was not required (and may be partial)
            continue
        _check_duplicates(xy, label, pairs)
        _check_collinear(xy, label, pairs)


def _check_duplicates(xy: np.ndarray, label: str, pairs: PointPairs) -> None:
    order = np.lexsort((xy[:, 1], xy[:, 0]))
    s = xy[order]
    same = np.flatnonzero((s[1:] == s[:-1]).all(axis=1))
    if same.size:
        a, b = sorted((order[same[0]], order[same[0] + 1]))
        x, y = xy[a]
        raise DataError(
            f"{pairs.source}: lines {pairs.lines[a]} and {pairs.lines[b]} have the same {label} point "
            f"({x:g}, {y:g}); remove the duplicate"
        )


#: Smallest spread (max - min, in x and in y) of a point set, absolutely and relative to its
#: largest coordinate: below it the fit's arithmetic loses the points' layout.
MIN_SPREAD = 1e-6
MIN_RELATIVE_SPREAD = 1e-9


def check_spread(xy: np.ndarray, label: str, source: str) -> None:
    """Refuse degenerate coordinates (raises :class:`DataError`): spread over less than
    :data:`MIN_SPREAD` units in x or y, or less than :data:`MIN_RELATIVE_SPREAD`
    of their size (e.g. all near 1e-300, or 1e8 +- 1e-3).

    >>> try:
    ...     check_spread(np.array([[0, 0], [1e-300, 2e-300], [3e-300, 0]]), "reference", "p.csv")
    ... except DataError as e:
    ...     print(str(e)[:60])
    p.csv: the reference points spread over only 3e-300 x 2e-300
    """
    xy = np.asarray(xy, float)
    if len(xy) == 0 or not np.isfinite(xy).all():
        return
    if len(xy) == 1:  # no spread to speak of: say how many there are
        raise DataError(
            f"{source}: there is only one {label} point; a fit needs several, spread over the field in "
            "both x and y"
        )
    size = float(np.abs(xy).max())
    spread = xy.max(axis=0) - xy.min(axis=0)
    if spread.min() < max(MIN_SPREAD, MIN_RELATIVE_SPREAD * size):
        raise DataError(
            f"{source}: the {label} points spread over only {spread[0]:.3g} x {spread[1]:.3g} units; "
            f"a fit needs them spread over at least {MIN_SPREAD:g} units (and {MIN_RELATIVE_SPREAD:g} of "
            "their size) in both x and y; check the units and the columns"
        )


def _check_collinear(xy: np.ndarray, label: str, pairs: PointPairs) -> None:
    check_spread(xy, label, pairs.source)
    if len(xy) < 3:
        return
    centred = xy - xy.mean(axis=0)
    sv = np.linalg.svd(centred, compute_uv=False)
    if sv[0] == 0 or sv[1] <= 1e-9 * sv[0]:
        raise DataError(
            f"{pairs.source}: all {label} points lie on one line; the model needs points spread "
            "over the field in both x and y"
        )


def write_points(path: str | Path, fieldnames, rows) -> None:
    """Write rows (dicts) as CSV, atomically; ``-`` writes to stdout."""
    if str(path) == "-":
        writer = csv.DictWriter(sys.stdout, fieldnames=list(fieldnames), lineterminator="\n")
        writer.writeheader()
        writer.writerows(rows)
        return
    with atomic_write(path) as fh:
        writer = csv.DictWriter(fh, fieldnames=list(fieldnames), lineterminator="\n")
        writer.writeheader()
        writer.writerows(rows)


def write_point_pairs(path: str | Path, xy_u, xy_d, ids=None) -> None:
    """Write a point-pair file ``id,x_u,y_u,x_d,y_d`` (``id`` only when given).

    ``xy_u``, ``xy_d`` are ``(N, 2)`` arrays of finite numbers (what :func:`read_points`
    reads back) and ``ids`` has one id per point; anything else raises
    :class:`~oapcal.errors.DataError` before the file is touched."""
    xy_u, xy_d = point_pairs(xy_u, xy_d)
    if ids is not None:
        if isinstance(ids, (str, bytes)) or not hasattr(ids, "__len__"):
            raise DataError(
                f"ids must be a sequence of one id per point, got {type(ids).__name__}", param="ids"
            )
        if len(ids) != len(xy_u):
            raise DataError(
                f"ids has {len(ids)} entries but there are {len(xy_u)} points; give one id per point",
                param="ids",
            )
    fields = (["id"] if ids is not None else []) + list(PAIR_COLUMNS)
    rows = []
    for i in range(len(xy_u)):
        row = {"x_u": repr(float(xy_u[i, 0])), "y_u": repr(float(xy_u[i, 1])),
               "x_d": repr(float(xy_d[i, 0])), "y_d": repr(float(xy_d[i, 1]))}  # fmt: skip
        if ids is not None:
            row["id"] = str(ids[i])
        rows.append(row)
    write_points(path, fields, rows)


#: The columns of a simulated image's ground truth (``oapcal simulate image --truth``).
TRUTH_COLUMNS = ("id", "x_u", "y_u", "x_d", "y_d", "visible")


def write_truth(path: str | Path, sim) -> None:
    """Write the ground truth of a :class:`~oapcal.imaging.simulate.SimulatedImage` as the
    CSV ``id,x_u,y_u,x_d,y_d,visible`` (atomically; coordinates to full precision)."""
    rows = [
        {"id": i, "x_u": repr(float(u[0])), "y_u": repr(float(u[1])),
         "x_d": repr(float(d[0])), "y_d": repr(float(d[1])), "visible": int(v)}
        for i, u, d, v in zip(sim.ids, sim.xy_u, sim.xy_d, sim.visible)
    ]  # fmt: skip
    write_points(path, TRUTH_COLUMNS, rows)
