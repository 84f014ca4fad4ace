"""``oapcal report``: one self-contained HTML page about a calibration."""

from __future__ import annotations

import click

from oapcal.cli._common import (
    check_output,
    file_option,
    json_option,
    load_pairs,
    out_option,
    print_json,
    progress_bar,
    sanitize,
)


@click.command("report")
@click.argument("calib", type=click.Path(dir_okay=False))
@file_option("--points", help="Landmark pairs (CSV x_u,y_u,x_d,y_d): residual vectors and Table 1 from them.")
@file_option("--image", help="A distorted image of a bar target: before/after, straightness, aspect, ESF.")
@file_option(
    "--selection",
    help="Model-selection JSON to tabulate: of 'oapcal select --json', or of 'oapcal select --families "
    "... --json' (the families compared).",
)
@file_option("--robustness", help="Robustness JSON (per model: trials, not_converged, ...) to tabulate.")
@click.option(
    "--expected-ratios",
    default="5,1",
    show_default=True,
    help="Known aspect ratios (long/short side) of the target's bars and squares.",
)
@click.option("--title", default=None, help="Title of the page.")
@out_option("The HTML file to write.", dash=False)
@json_option("Print the report's numbers as one JSON object.")
# one parameter per command-line option (click)
def report_command(calib, points, image, selection, robustness, expected_ratios, title, out, as_json):
    """Write an HTML report of a calibration (self-contained: images embedded)."""  # fmt: skip
    check_output(out, calib, points, image, selection, robustness)
    if not out.lower().endswith((".html", ".htm")):
        raise click.BadParameter(f"{out!r} must end in .html", param_hint="--out")
    ratios = _parse_ratios(expected_ratios)
    from oapcal.io.calibration import load_calibration
    from oapcal.io.results import load_any_selection, load_robustness
    from oapcal.report import build_report, write_report

    cal = load_calibration(calib)
    pairs = load_pairs(points) if points else None
    img = _read_image(image, cal, calib) if image else None
    sel = load_any_selection(selection) if selection else None
    rob = load_robustness(robustness) if robustness else None
    bar, update = progress_bar("report")
    with bar:
        html_text, data = build_report(
            cal, points=None if pairs is None else (pairs.xy_u, pairs.xy_d), image=img, image_name=image,
            selection=sel, robustness=rob, selection_source=selection, robustness_source=robustness,
            expected_ratios=ratios, title=title, progress=update,
        )  # fmt: skip
    write_report(out, html_text)
    if as_json:
        esf = None if data.esf is None else {k: v for k, v in data.esf.items() if k != "edges"}
        print_json({"out": out, "residuals": data.residuals, "uncertainty": data.uncertainty,
                    "checks": data.checks, "esf": esf, "model": data.model,
                    "selfcal": getattr(cal, "selfcal", None)})  # fmt: skip
        return 0
    _echo_summary(out, data)
    return 0


def _parse_ratios(expected_ratios: str) -> tuple:
    """The ``--expected-ratios`` comma list, each ratio at least 1."""
    try:
        ratios = tuple(float(v) for v in expected_ratios.split(",") if v.strip())
        if any(not r >= 1 for r in ratios):
            raise ValueError
    except ValueError:
        raise click.BadParameter(
            f"{expected_ratios!r} is not a comma list of ratios >= 1 such as 5,1",
            param_hint="--expected-ratios",
        ) from None
    return ratios


def _read_image(image, cal, calib):
    """The grey target image of ``--image``, checked against the calibration's image size
    and model region (as correct does)."""
    from oapcal.errors import InputFileError
    from oapcal.io.imagefile import read_image_grey

    try:
        img = read_image_grey(image)
    except InputFileError as exc:  # the reader's limit is correct's --max-pixels; report has none
        if exc.param != "max_pixels":
            raise
        raise InputFileError(
            str(exc).split("; raise max_pixels")[0] + "; the report takes images up to that size: "
            "crop the image to the target or bin it"
        ) from None
    from oapcal.io.calibration import check_model_region
    from oapcal.records import ImageSize

    size = ImageSize.of(img)
    if cal.image_size and tuple(cal.image_size) != size:  # as correct does
        raise InputFileError(
            f"{image}: is {size.width}x{size.height} px but the calibration is for "
            f"{cal.image_size[0]}x{cal.image_size[1]} px images; give an image of that camera"
        )
    check_model_region(cal, size, source=calib)
    return img


def _echo_summary(out, data) -> None:
    """The one line written without ``--json``: the residuals and, with an image, the ESF."""
    r = data.residuals
    click.echo(
        f"wrote {sanitize(out)}: residual mean {r['mean_px']:.4g} px, max {r['max_px']:.4g} px", nl=False
    )
    if data.esf is not None and data.esf["sigma_mean_px"] is not None:
        click.echo(
            f"; ESF sigma mean {data.esf['sigma_mean_px']:.3g} px, max {data.esf['sigma_max_px']:.3g} px",
            nl=False,
        )
    click.echo("")
