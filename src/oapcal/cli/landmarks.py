"""``oapcal landmarks``: landmark files from labelling tools (``convert``)."""

from __future__ import annotations

import click

from oapcal.cli._common import (
    check_output,
    json_option,
    landmark_options,
    load_pairs,
    out_option,
    print_json,
    sanitize,
)


@click.group("landmarks")
def landmarks_group():
    """Landmark files from VIA, napari, BigWarp or plain CSV/TSV."""


@landmarks_group.command("convert")
@landmark_options
@out_option("Output point-pair CSV (id,x_u,y_u,x_d,y_d); '-' for stdout.")
@json_option("Print a one-object JSON summary.")
def convert_command(source, out, as_json):
    """Pair the landmarks of a distorted and a reference image into a point-pair CSV.

    \b
      oapcal landmarks convert --distorted camera.json --reference target.json \\
          --pair-by corner --out points.csv

    The id column holds each pair's pairing value (the --pair-by attribute, the BigWarp
    landmark name, or the position with --pair-by-order).  Coordinates are converted to
    oapcal's convention (origin at the centre of the top-left pixel).
    """
    from oapcal.io.points import write_point_pairs

    check_output(out, source)
    if out == "-" and as_json:
        raise click.UsageError(
            "--out - writes the CSV to stdout; --json would print there too: give --out FILE"
        )
    pairs = load_pairs(source, require=("x_u", "y_u", "x_d", "y_d"))
    write_point_pairs(out, pairs.xy_u, pairs.xy_d, ids=pairs.ids)
    summary = {"pairs": len(pairs), "source": pairs.source, "out": out, "not_used": list(pairs.warnings)}
    if as_json:
        print_json(summary)
    elif out != "-":
        click.echo(sanitize(f"wrote {len(pairs)} point pairs to {out} (from {pairs.source})"))
    return 0
