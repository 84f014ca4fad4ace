"""``oapcal esf``: edge spread functions and the Gaussian PSF they imply."""

from __future__ import annotations

import click

from oapcal.cli._common import (
    check_output,
    console,
    count_option,
    file_option,
    flag_option,
    json_option,
    positive_option,
    print_json,
    progress_bar,
)


@click.command("esf")
@click.argument("image", type=click.Path(dir_okay=False))
@file_option(
    "--rois",
    "rois_file",
    help="CSV of rectangles x0,y0,x1,y1 (px, inclusive; optional label), one edge each.",
)
@flag_option(
    "--auto",
    "auto",
    help="Find the edges of the bars and squares of a target image (the default without --rois).",
)
@positive_option("--um-per-px", help="Object-space size of one image px (um), for sigma in um.")
@count_option(
    "--half-width", least=2, default=10, help="With --auto: at most this many px each side of an edge."
)
@file_option("--plot", "plot", help="Write a PNG of the sigma distribution and example fits here.")
@json_option()
def esf_command(image, rois_file, auto, um_per_px, half_width, plot, as_json):
    """Fit error functions to straight edges of IMAGE and report the Gaussian PSF sigma."""  # fmt: skip
    if rois_file is not None and auto:
        raise click.UsageError("give either --rois FILE or --auto, not both")
    from oapcal.errors import DataError
    from oapcal.imaging.esf import analyse_edges, find_edge_rois
    from oapcal.io.imagefile import read_image_grey

    check_output(plot, image, rois_file)
    if plot is not None and not plot.lower().endswith(".png"):
        raise click.BadParameter(f"{plot!r} must end in .png", param_hint="--plot")
    img = read_image_grey(image)
    if rois_file is not None:
        from oapcal.imaging.esf import check_rois
        from oapcal.io.rois import read_rois

        rois, labels = read_rois(rois_file)  # at most MAX_EDGES rows are read
        check_rois(rois, img.shape, [f"{rois_file}: {label}" for label in labels])  # before any fit
    else:
        try:
            rois, labels = find_edge_rois(img, half_width=half_width)
        except DataError as exc:
            msg = f"{image}: no straight edges found ({exc}); give the edges with --rois FILE"
            raise DataError(msg) from None
        if not rois:
            raise DataError(
                f"{image}: no straight edges found (no bars or squares with sides of 6 px or more); "
                "give the edges with --rois FILE"
            )
    summary = _fit_with_progress(analyse_edges, img, rois, labels, um_per_px)
    if plot is not None and summary.good:
        from oapcal.io.atomic import atomic_path
        from oapcal.report.plots import esf_figure

        with atomic_path(plot) as tmp:
            esf_figure(summary).savefig(tmp)
    result = {"image": image, **summary.to_dict()}
    if as_json:
        print_json(result)
    else:
        _print_table(summary)
    if not summary.good:
        click.echo("oapcal: warning: no edge could be fitted; see the messages per edge", err=True)
        return 3
    return 0


def _fit_with_progress(analyse_edges, img, rois, labels, um_per_px):
    bar, update = progress_bar(f"fitting {len(rois):,} edges")
    with bar:
        return analyse_edges(img, rois, labels=labels, um_per_px=um_per_px, progress=update)


def _print_table(summary) -> None:
    from rich.table import Table

    out = console()
    um = summary.um_per_px is not None
    table = Table(title="Edge spread functions (error-function fits)", title_justify="left")
    for name in [
        "edge",
        "orientation",
        "sigma [px]",
        "+-",
        *(["sigma [um]"] if um else []),
        "tilt [deg]",
        "fit",
    ]:
        table.add_column(name, justify="left" if name in ("edge", "orientation", "fit") else "right")
    for e in summary.edges:
        if e.ok:
            row = [e.label, e.orientation, f"{e.sigma_px:.3f}", f"{e.sigma_err_px:.3f}"]
            row += [f"{e.sigma_um:.3f}"] if um else []
            row += [f"{e.angle_deg:.2f}", "ok"]
        else:
            row = [e.label, e.orientation, "-", "-", *(["-"] if um else []), "-", f"[red]{e.message}[/red]"]
        table.add_row(*row)
    out.print(table)
    d = summary.to_dict()
    if summary.good:
        line = f"{d['n_ok']} of {d['n_edges']} edges: sigma max {d['sigma_max_px']:.3f} px, "
        line += f"mean {d['sigma_mean_px']:.3f} px"
        if um:
            line += f" (max {d['sigma_max_um']:.3f} um, mean {d['sigma_mean_um']:.3f} um)"
        out.print(line)
