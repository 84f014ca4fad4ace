"""Tables of points to correct: particle tracks (trackpy, TrackMate) and any CSV, TSV or
parquet table with an x and a y column.

``oapcal correct-points`` corrects such a table row by row and writes it back with every
column kept, in order, and three columns added: ``x_c, y_c`` (the corrected point, in the
table's own units and pixel convention) and ``converged``.  A row without a point (an
empty cell or ``NaN`` in x or y, as trackers write for a lost particle) is kept, with
``x_c, y_c`` empty (NaN) and ``converged`` empty; nothing is dropped.

* **Presets** name the columns of the trackers' own files (:data:`PRESETS`): trackpy's
  ``x, y`` (with ``frame, particle``), TrackMate's ``POSITION_X, POSITION_Y`` (with
  ``TRACK_ID, FRAME``).  TrackMate's CSV export writes three more header rows under the
  column names (the features' names, their short names and their units, e.g.
  ``(micron)``): they are recognised, kept in the output (extended for the new columns),
  and the units row says whether positions are in px or um.
* **Units**: ``px`` (camera pixels, origin at the centre of the top-left pixel unless
  ``origin="corner"``) or ``um``: the table's um are converted to camera px with
  ``table_um_per_px`` (the pixel size the tracker was given; by default the
  calibration's ``um_per_px``), and ``x_c, y_c`` come out in the calibration's object-space
  um (its ``um_per_px`` times the corrected reference px).
* CSV and TSV cells are copied through as text, byte for byte; parquet tables (and the
  Python form, :func:`correct_points_frame`) go through pandas (the ``tables`` extra).
"""

from __future__ import annotations

import csv
import math
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from oapcal.errors import DataError, InputFileError
from oapcal.io.landmarks._base import MAX_COORD, csv_rows, first_row, read_text, sniff_delimiter
from oapcal.io.userfile import checked_coordinate, parse_number

#: Suffixes read as parquet (through pandas and pyarrow).
PARQUET_SUFFIXES = (".parquet", ".pq")
#: The columns added to a corrected table.
ADDED_COLUMNS = ("x_c", "y_c", "converged")
#: Cells that mean "no value" in an x or y column (case ignored).
MISSING = ("", "nan", "na", "n/a", "null", "none")
UNITS = ("px", "um")
#: How trackers spell their units (TrackMate's units row, in brackets).
_UNIT_WORDS = {"pixel": "px", "pixels": "px", "px": "px", "micron": "um", "microns": "um", "um": "um",
               "\u00b5m": "um", "\u03bcm": "um"}  # fmt: skip


@dataclass(frozen=True)
class TablePreset:
    """The columns a tracker writes: the point's ``x_column, y_column`` and the columns that
    identify it (``keys``, for the docs and messages; all columns are kept anyway)."""

    name: str
    x_column: str
    y_column: str
    keys: tuple[str, ...] = ()


PRESETS: dict[str, TablePreset] = {
    "trackpy": TablePreset("trackpy", "x", "y", ("frame", "particle")),
    "trackmate": TablePreset("trackmate", "POSITION_X", "POSITION_Y", ("TRACK_ID", "FRAME")),
}


@dataclass(frozen=True)
class PointTable:
    """A table read by :func:`read_point_table`.

    ``columns`` are the column names in order; ``header_rows`` the rows between the names
    and the data (TrackMate's three), kept for the output; ``cells`` each data row's cells
    as text (CSV/TSV) or ``frame`` the pandas DataFrame (parquet); ``xy`` the ``(N, 2)``
    values of the x and y columns as given (NaN where a row has none); ``lines`` the file
    line of each row (for messages); ``units`` what the file itself says (TrackMate's units
    row: ``px``, ``um``) or None.
    """

    source: str
    columns: tuple[str, ...]
    x_column: str
    y_column: str
    xy: np.ndarray
    lines: tuple[int, ...]
    delimiter: str = ","
    header_rows: tuple[tuple[str, ...], ...] = ()
    cells: tuple[tuple[str, ...], ...] | None = field(default=None, repr=False)
    frame: object = field(default=None, repr=False)
    units: str | None = None

    def __len__(self) -> int:
        return len(self.xy)


def preset_columns(preset: str | None, x_column: str = "x", y_column: str = "y") -> tuple[str, str]:
    """The x and y column names of ``preset`` (or ``x_column, y_column`` without one).

    >>> preset_columns("trackmate")
    ('POSITION_X', 'POSITION_Y')
    """
    if preset is None:
        return x_column, y_column
    if preset not in PRESETS:
        raise DataError(f"preset {preset!r} is unknown; use one of {', '.join(PRESETS)}", param="preset")
    return PRESETS[preset].x_column, PRESETS[preset].y_column


def is_parquet(path: str | Path) -> bool:
    return Path(path).suffix.lower() in PARQUET_SUFFIXES


def read_point_table(
    path: str | Path, *, x_column: str = "x", y_column: str = "y", preset: str | None = None
) -> PointTable:
    """Read a CSV, TSV or parquet table of points (see the module doc).

    Every problem raises :class:`~oapcal.errors.InputFileError` naming the file, the line
    (CSV: as an editor counts them) and the column: a missing column (the nearest name is
    suggested), a cell in x or y that is neither a number nor empty/NaN, an infinite or
    absurdly large coordinate, rows with too few cells.
    """
    x_column, y_column = preset_columns(preset, x_column, y_column)
    if is_parquet(path):
        return _read_parquet(path, x_column, y_column)
    name = str(path)
    text = read_text(path, "table of points (CSV or TSV)")
    delimiter = sniff_delimiter(text)
    rows = csv_rows(text, name, delimiter)
    _, header = first_row(rows, name)
    header = [h.strip() for h in header]
    ix = _column(header, x_column, name, "x_column")
    iy = _column(header, y_column, name, "y_column")
    rows = list(rows)
    n_extra = _extra_header_rows(header, rows, ix, iy)
    header_rows = tuple(tuple(cells) + ("",) * (len(header) - len(cells)) for _, cells in rows[:n_extra])
    units = _units_of(header_rows, ix, iy, name)
    cells, lines, xy = [], [], []
    for line, row in rows[n_extra:]:
        if len(row) < len(header):
            raise InputFileError(
                f"{name}: line {line}: {len(row)} cells but the header has {len(header)} columns; "
                "fill in the missing cells"
            )
        if len(row) > len(header) and any(c.strip() for c in row[len(header) :]):
            raise InputFileError(
                f"{name}: line {line}: {len(row)} cells but the header has {len(header)} columns; "
                "name every column in the header"
            )
        row = row[: len(header)]
        xy.append((_value(row[ix], name, line, header[ix]), _value(row[iy], name, line, header[iy])))
        cells.append(tuple(row))
        lines.append(line)
    if not cells:
        raise InputFileError(f"{name}: has a header but no data rows")
    return PointTable(
        name, tuple(header), header[ix], header[iy], np.array(xy, float).reshape(-1, 2), tuple(lines),
        delimiter, header_rows, tuple(cells), None, units,
    )  # fmt: skip


def _extra_header_rows(header, rows, ix: int, iy: int) -> int:
    """How many rows under the column names are more header (TrackMate's export: feature
    names, short names, units): only in a table with TrackMate's POSITION_X and POSITION_Y,
    the leading rows (at most 3) whose x and y cells are text, not numbers nor empty."""
    if not {"POSITION_X", "POSITION_Y"} <= set(header):
        return 0
    n = 0
    for _, cells in rows[:3]:
        texts = [cells[i].strip() if i < len(cells) else "" for i in (ix, iy)]
        if all(t and t.lower() not in MISSING and not _is_number(t) for t in texts):
            n += 1
        else:
            break
    return n


def _is_number(text: str) -> bool:
    try:
        parse_number(text)
    except ValueError:
        return False
    return True


def _units_of(header_rows, ix: int, iy: int, name: str) -> str | None:
    """The units a TrackMate units row gives the x and y columns (``(micron)``, ``(pixel)``)."""
    for row in header_rows:
        cx, cy = row[ix].strip(), row[iy].strip()
        if cx.startswith("(") and cx.endswith(")"):
            word = cx[1:-1].strip().lower()
            unit = _UNIT_WORDS.get(word)
            if unit is None:
                raise InputFileError(
                    f"{name}: the units row gives the positions in {cx}; oapcal corrects positions in "
                    "pixels or microns: export the table in one of those"
                )
            if cy != cx:
                raise InputFileError(f"{name}: the units row gives x in {cx} but y in {cy}")
            return unit
    return None


def _value(text: str, name: str, line: int, column: str) -> float:
    stripped = text.strip()
    if stripped.lower() in MISSING:
        return math.nan
    try:
        value = parse_number(stripped)
    except ValueError:
        shown = repr(stripped) if len(stripped) <= 30 else repr(stripped[:27] + "...")
        raise InputFileError(
            f"{name}: line {line}, column {column!r}: {shown} is not a number (give ASCII decimal or "
            "scientific notation, or leave the cell empty / NaN where a row has no point)"
        ) from None
    return _finite(value, name, f"line {line}", column)


def _finite(value: float, name: str, where: str, column: str) -> float:
    # str(value) of nan and inf is value:g
    fix = "give a number, or leave the cell empty / NaN where a row has no point"
    return checked_coordinate(value, MAX_COORD, f"{name}: {where}, column {column!r}", f"{value:g}", fix,
                              "fix or remove the row")  # fmt: skip


def _column(header, wanted: str, name: str, param: str) -> int:
    from oapcal.io.landmarks.tables import find_column

    return find_column(list(header), wanted, name, param)


def _pandas():
    from oapcal.extras import require

    return require("pandas", "tables")


def _read_parquet(path, x_column: str, y_column: str) -> PointTable:
    from oapcal.extras import require
    from oapcal.io.userfile import check_input_file

    pd = _pandas()
    require("pyarrow", "tables")
    checked = check_input_file(path, "parquet table", PARQUET_SUFFIXES)
    try:
        frame = pd.read_parquet(checked)
    except Exception as exc:  # pyarrow raises ArrowInvalid, OSError, ... for a bad file
        raise InputFileError(
            f"{path}: cannot be read as a parquet table ({type(exc).__name__}: {exc})"
        ) from None
    return _table_from_frame(frame, str(path), x_column, y_column)


def _table_from_frame(frame, name: str, x_column: str, y_column: str) -> PointTable:
    pd = _pandas()
    columns = [str(c) for c in frame.columns]
    ix = _column(columns, x_column, name, "x_column")
    iy = _column(columns, y_column, name, "y_column")
    xy = np.empty((len(frame), 2))
    for k, i in enumerate((ix, iy)):
        column = frame.iloc[:, i]
        if not (pd.api.types.is_numeric_dtype(column) and not pd.api.types.is_bool_dtype(column)):
            raise InputFileError(
                f"{name}: column {columns[i]!r} holds {column.dtype} values, not numbers; give the "
                "coordinates as numbers"
            )
        xy[:, k] = column.to_numpy(dtype=float, na_value=np.nan)
        bad = np.flatnonzero(~np.isnan(xy[:, k]) & (~np.isfinite(xy[:, k]) | (np.abs(xy[:, k]) > MAX_COORD)))
        if bad.size:
            _finite(float(xy[bad[0], k]), name, f"row {bad[0]}", columns[i])
    return PointTable(name, tuple(columns), columns[ix], columns[iy], xy, tuple(range(len(frame))),
                      frame=frame)  # fmt: skip


# ------------------------------------------------------------------- the correction


def table_scale(calibration, units: str, table_um_per_px: float | None) -> tuple[float, float]:
    """``(in_scale, out_scale)``: table units per camera px of the input, and per reference
    px of the output (1, 1 for px)."""
    if units not in UNITS:
        raise DataError(f"units {units!r}: give 'px' or 'um'", param="units")
    if units == "px":
        if table_um_per_px is not None:
            raise DataError("table_um_per_px applies to tables in um only", param="table_um_per_px")
        return 1.0, 1.0
    cal_um = getattr(calibration, "um_per_px", None)
    if not cal_um:
        raise DataError(
            "the calibration has no um_per_px, so corrected positions cannot be given in um; refit it "
            "with um_per_px, or give the table in px",
            param="units",
        )
    if table_um_per_px is not None and not (math.isfinite(table_um_per_px) and table_um_per_px > 0):
        raise DataError(f"table_um_per_px must be a positive number, got {table_um_per_px}",
                        param="table_um_per_px")  # fmt: skip
    return float(table_um_per_px or cal_um), float(cal_um)


def correct_xy(xy: np.ndarray, calibration, *, units: str = "px", table_um_per_px: float | None = None,
               origin: str = "center") -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """Correct the points ``xy (N, 2)`` of a table, in its units and pixel convention.

    Returns ``(xy_c, converged, present)``: the corrected points in the same units and
    convention (NaN where the row has no point or the inverse did not converge), whether
    each converged, and whether each row had a point.  The inverse is
    :func:`oapcal.model.undistort` of the calibration's model."""
    from oapcal.model import as_model

    if origin not in ("center", "corner"):
        raise DataError(f"pixel origin {origin!r}: expected 'center' or 'corner'", param="origin")
    in_scale, out_scale = table_scale(calibration, units, table_um_per_px)
    offset = 0.5 if origin == "corner" else 0.0
    xy = np.asarray(xy, float).reshape(-1, 2)
    present = np.isfinite(xy).all(axis=1)
    xy_c = np.full_like(xy, np.nan)
    converged = np.zeros(len(xy), bool)
    if present.any():
        inverse = as_model(calibration).inverse(xy[present] / in_scale - offset)
        ok = np.asarray(inverse.converged, bool)
        done = np.where(ok[:, None], (inverse.xy + offset) * out_scale, np.nan)
        xy_c[present] = done
        converged[present] = ok
    return xy_c, converged, present


def check_units(table: PointTable, units: str | None) -> str:
    """The units to correct ``table`` in: ``units`` if given (refused when the file's own
    units row says otherwise), else the file's, else px."""
    if units is not None and units not in UNITS:
        raise DataError(f"units {units!r}: give 'px' or 'um'", param="units")
    if table.units is not None and units is not None and units != table.units:
        raise InputFileError(
            f"{table.source}: its units row gives the positions in {table.units}, not {units}; give "
            f"units {table.units!r} (or leave it out)",
            param="units",
        )
    return units or table.units or "px"


def _text(value: float) -> str:
    return "" if math.isnan(value) else repr(float(value))


def write_point_table(path: str | Path, table: PointTable, xy_c, converged, present) -> None:
    """Write ``table`` with ``x_c, y_c, converged`` added (replacing columns of those
    names), atomically (``-`` is stdout).  The format follows ``path``'s suffix: ``.tsv``
    tab-separated, ``.csv`` comma-separated (any other the input's separator), parquet
    (a parquet input only: a CSV's cells are text)."""
    if is_parquet(path):
        if table.frame is None:
            raise InputFileError(
                f"{path}: a CSV/TSV table is written as CSV/TSV (its cells are kept as text); give a .csv "
                "or .tsv output, or a parquet input"
            )
        frame = add_columns(table.frame, xy_c, converged, present)
        from oapcal.io.atomic import atomic_path

        with atomic_path(Path(path)) as tmp:
            frame.to_parquet(tmp, index=False)
        return
    suffix = Path(str(path)).suffix.lower()
    delimiter = "\t" if suffix == ".tsv" else "," if suffix == ".csv" else table.delimiter
    keep = [i for i, c in enumerate(table.columns) if c not in ADDED_COLUMNS]
    header = [table.columns[i] for i in keep] + list(ADDED_COLUMNS)
    ix, iy = table.columns.index(table.x_column), table.columns.index(table.y_column)
    extra = []
    for k, row in enumerate(table.header_rows):
        last = k == len(table.header_rows) - 1
        cells = [row[i] for i in keep]
        if last and row[ix].strip().startswith("("):  # the units row: x_c, y_c in the same units
            cells += [row[ix], row[iy], ""]
        else:
            cells += [f"{row[ix]} corrected".strip(), f"{row[iy]} corrected".strip(), "Converged"]
        extra.append(cells)
    if table.cells is not None:
        body = ([cells[i] for i in keep] for cells in table.cells)
    else:
        body = ([_frame_cell(v) for v in row] for row in table.frame.iloc[:, keep].itertuples(index=False))

    def rows():
        for cells, (x, y), ok, has in zip(body, xy_c, converged, present):
            yield cells + [_text(x), _text(y), (str(int(bool(ok))) if has else "")]

    def emit(fh):
        writer = csv.writer(fh, delimiter=delimiter, lineterminator="\n")
        writer.writerow(header)
        writer.writerows(extra)
        writer.writerows(rows())

    if str(path) == "-":
        emit(sys.stdout)
        return
    from oapcal.io.atomic import atomic_write

    with atomic_write(path) as fh:
        emit(fh)


def _frame_cell(value) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return ""
    try:
        import pandas as pd

        if pd.isna(value):
            return ""
    except (ImportError, TypeError, ValueError):
        pass
    return repr(value) if isinstance(value, float) else str(value)


def add_columns(frame, xy_c, converged, present):
    """A copy of the DataFrame ``frame`` with ``x_c, y_c`` (float, NaN where no point or not
    converged) and ``converged`` (pandas' nullable boolean: NA where the row had no point)
    added at the end (replacing columns of those names)."""
    pd = _pandas()
    out = frame.drop(columns=[c for c in ADDED_COLUMNS if c in frame.columns]).copy()
    out["x_c"] = np.asarray(xy_c)[:, 0]
    out["y_c"] = np.asarray(xy_c)[:, 1]
    out["converged"] = pd.array(np.asarray(converged, bool), dtype="boolean")
    out.loc[~np.asarray(present, bool), "converged"] = pd.NA
    return out


def correct_points_frame(
    frame,
    calibration,
    *,
    x_column: str = "x",
    y_column: str = "y",
    preset: str | None = None,
    units: str = "px",
    table_um_per_px: float | None = None,
    origin: str = "center",
):
    """Correct the points of a pandas DataFrame (a trackpy or TrackMate table, or any with
    an x and a y column): a copy with ``x_c, y_c, converged`` added, every other column and
    row kept (rows whose x or y is NaN get NaN and ``converged`` NA).

    ``calibration`` is a :class:`~oapcal.calibration.Calibration` (``load_calibration``);
    ``preset`` (``"trackpy"``, ``"trackmate"``) names the columns; ``units`` ``"px"`` or
    ``"um"`` (see the module doc); ``origin="corner"`` for tables whose top-left pixel
    centre is (0.5, 0.5) px.  Needs pandas (``pip install -e '.[tables]'``).  A DataFrame
    without the columns, or with coordinates that are not finite numbers, raises
    :class:`~oapcal.errors.DataError`.

    >>> import pandas as pd
    >>> from oapcal.model import params_from_dict
    >>> tracks = pd.DataFrame({"y": [10.0, float("nan")], "x": [20.0, 5.0], "frame": [0, 1],
    ...                        "particle": [3, 3]})
    >>> out = correct_points_frame(tracks, params_from_dict({"x_off": 1.0}), preset="trackpy")
    >>> out[["x", "x_c", "y_c"]].to_dict("list"), out["converged"].isna().tolist()
    ({'x': [20.0, 5.0], 'x_c': [19.0, nan], 'y_c': [10.0, nan]}, [False, True])
    """
    # 8 parameters: the frame, the calibration and the public keywords of ``correct-points``
    # (one per option: columns, preset, units, pixel size, origin).
    try:
        table = _table_from_frame(frame, "the DataFrame", *preset_columns(preset, x_column, y_column))
    except InputFileError as exc:  # a value in memory, not a file: the same message as a DataError
        raise DataError(str(exc), param=exc.param) from None
    xy_c, converged, present = correct_xy(table.xy, calibration, units=units,
                                          table_um_per_px=table_um_per_px, origin=origin)  # fmt: skip
    return add_columns(frame, xy_c, converged, present)
