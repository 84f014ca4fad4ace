"""``oapcal correct-points``: correct point pairs, landmarks, or tables of tracks."""

from __future__ import annotations

import click

from oapcal.cli._common import (
    PointsUsageError,
    allow_unconverged_option,
    check_output,
    load_pairs,
    load_usable_calibration,
    out_option,
    points_options,
    positive_option,
)


@click.command("correct-points")
@click.argument("calib", type=click.Path(dir_okay=False))
@points_options
@out_option(
    "Output table: every input column (in order, TrackMate's header rows too) plus x_c,y_c,converged; "
    ".csv, .tsv or (from a parquet input) .parquet."
)
@click.option(
    "--preset",
    type=click.Choice(["trackpy", "trackmate"]),
    default=None,
    help="Columns of a tracker's table: trackpy x,y (frame, particle); TrackMate POSITION_X, "
    "POSITION_Y (TRACK_ID, FRAME; its CSV export's extra header rows are kept).",
)
@click.option(
    "--units",
    type=click.Choice(["px", "um"]),
    default=None,
    help="Units of a table's x,y (and of x_c,y_c): camera px, or um (converted with "
    "--table-um-per-px; x_c,y_c in the calibration's object-space um). Default: px, or what a "
    "TrackMate units row says.",
)
@positive_option(
    "--table-um-per-px",
    help="With --units um: the camera pixel size the tracker used (default: the calibration's um_per_px).",
)
@allow_unconverged_option
def correct_points_command(calib, points, out, preset, units, table_um_per_px, allow_unconverged):
    """Correct distorted points with a calibration: the x_d,y_d columns of POINTS, the
    landmarks of --distorted FILE (VIA, napari, BigWarp), or a table of tracks (--distorted
    or POINTS as CSV, TSV or parquet with --preset or --x-column/--y-column), every column kept."""
    check_output(out, calib, points)
    if units is None and table_um_per_px is not None:
        units = "um"
    if units != "um" and table_um_per_px is not None:
        raise PointsUsageError("--table-um-per-px applies to --units um")
    if _is_table(points, preset, units):
        return _correct_table(calib, points, out, preset, units, table_um_per_px, allow_unconverged)
    return _correct_pairs(calib, points, out, allow_unconverged)


def _is_table(points, preset, units) -> bool:
    """Whether the input is corrected as a table (every column kept, NaN rows kept): a
    preset or units asked for, a parquet file, or a plain CSV/TSV given as --distorted."""
    from oapcal.io.tables import is_parquet

    path = points.points if points.points is not None else points.distorted
    if preset is not None or units is not None or is_parquet(path):
        return True
    if points.points is not None:
        return False
    if points.fmt != "auto":
        return points.fmt == "csv"
    from oapcal.io.landmarks import detect_format

    return detect_format(points.distorted) == "csv"


def _correct_table(calib, points, out, preset, units, table_um_per_px, allow_unconverged) -> int:
    from oapcal.io.tables import check_units, correct_xy, read_point_table, write_point_table

    if points.points is not None:
        path, x_column, y_column, origin = points.points, "x_d", "y_d", "center"
    else:
        path, x_column, y_column, origin = (
            points.distorted,
            points.x_column,
            points.y_column,
            points.pixel_origin,
        )
        if points.reference is not None:
            raise PointsUsageError(
                "correct-points corrects the distorted points only: drop --reference for a table"
            )
        for flag, value in (("--distorted-image", points.distorted_image),
                            ("--reference-image", points.reference_image)):  # fmt: skip
            if value is not None:
                raise PointsUsageError(f"{flag} applies to VIA files, not to a table")
        if points.fmt not in ("auto", "csv"):
            raise PointsUsageError(f"--format {points.fmt} is not a table: drop --preset/--units for it")
    if preset is not None:
        from oapcal.io.tables import PRESETS

        own = PRESETS[preset]
        if (x_column, y_column) not in (("x", "y"), ("x_d", "y_d"), (own.x_column, own.y_column)):
            raise PointsUsageError(
                f"--preset {preset} names the columns {own.x_column},{own.y_column}: "
                "drop --x-column/--y-column"
            )
        x_column, y_column = own.x_column, own.y_column
    cal = load_usable_calibration(calib, allow_unconverged)
    table = read_point_table(path, x_column=x_column, y_column=y_column)
    if points.pair_by is not None and points.pair_by not in table.columns:
        raise PointsUsageError(
            f"{path}: --pair-by {points.pair_by}: no such column; every column of a table is kept, so "
            "--pair-by is not needed"
        )
    units = check_units(table, units)
    xy_c, converged, present = correct_xy(table.xy, cal, units=units, table_um_per_px=table_um_per_px,
                                          origin=origin)  # fmt: skip
    write_point_table(out, table, xy_c, converged, present)
    n_missing = int((~present).sum())
    if n_missing:
        click.echo(
            f"oapcal: note: {n_missing} of {len(table)} rows have no point (empty or NaN "
            f"{table.x_column}/{table.y_column}); they are kept with empty x_c,y_c,converged",
            err=True,
        )
    _warn_unconverged(int((present & ~converged).sum()), int(present.sum()), None)
    from oapcal.io.tables import table_scale

    _say_trust(cal, xy_c[present & converged] / table_scale(cal, units, table_um_per_px)[1]
               - (0.5 if origin == "corner" else 0.0))  # fmt: skip
    return 0


def _correct_pairs(calib, points, out, allow_unconverged) -> int:
    from oapcal.io.points import write_points
    from oapcal.model import as_model

    cal = load_usable_calibration(calib, allow_unconverged)
    pairs = load_pairs(points, require=("x_d", "y_d"))
    inverse = as_model(cal).inverse(pairs.xy_d)
    fields = [f for f in pairs.fieldnames if f not in ("x_c", "y_c", "converged")]
    fields += ["x_c", "y_c", "converged"]
    rows = []
    for row, xy, ok in zip(pairs.rows, inverse.xy, inverse.converged):
        row = dict(row)
        row["x_c"] = repr(float(xy[0])) if ok else ""
        row["y_c"] = repr(float(xy[1])) if ok else ""
        row["converged"] = int(bool(ok))
        rows.append(row)
    write_points(out, fields, rows)
    _warn_unconverged(int((~inverse.converged).sum()), len(rows), int(inverse.folded.sum()))
    _say_trust(cal, inverse.xy[inverse.converged])
    return 0


def _say_trust(cal, xy_c_px) -> None:
    """Say how far beyond the landmarks' hull the corrected points (px) lie, if any do."""
    from oapcal.cli.correct import points_trust_message

    line = points_trust_message(cal, xy_c_px)
    if line:
        click.echo(line, err=True)


def _warn_unconverged(n_bad: int, n: int, n_folded: int | None) -> None:
    if n_bad:
        folded = f" ({n_folded} where the map folds over)" if n_folded is not None else ""
        click.echo(
            f"oapcal: warning: {n_bad} of {n} points could not be corrected{folded}; their x_c,y_c are empty",
            err=True,
        )
