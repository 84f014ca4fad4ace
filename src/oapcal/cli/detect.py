"""``oapcal detect``: find, match and refine the landmarks of a target in a camera image."""

from __future__ import annotations

import click

from oapcal.cli._common import (
    check_output,
    choice_option,
    console,
    file_option,
    json_option,
    out_option,
    positive_option,
    print_json,
    with_flag_hint,
    write_detected_points,
)

#: ``auto`` and the keys of ``oapcal.imaging.usaf.ORIENTATIONS`` (written out so that this
#: module imports only click; a test checks that they agree).
ORIENTATION_CHOICES = (
    "auto", "none", "rot90", "rot180", "rot270", "flip-x", "flip-y", "transpose", "anti-transpose",
)  # fmt: skip


@click.command("detect")
@click.argument("image", type=click.Path(dir_okay=False))
@choice_option(
    "--target",
    choices=["usaf", "dots", "chessboard"],
    default="usaf",
    help="The target in the image (dots, chessboard: docs/detection.md, 'Dot grids and chessboards').",
)
@click.option("--groups", default="4-5", show_default=True, help="USAF groups in the image, e.g. 4-5.")
@click.option(
    "--um-per-px",
    type=click.FloatRange(min=1e-4, max=1e4),
    default=None,
    help="The camera's object-space pixel size (um per px), to within 30 % (6 % decides the element "
    "when one element alone is in view); also the scale of x_u,y_u.  Leave it out to find the scale.",
)
@out_option("Point-pair CSV: id,x_u,y_u,x_d,y_d.")
@file_option("--truth", help="Ground truth of a simulated image (id,x_d,y_d,visible) to score against.")
@file_option("--plot", "plot", help="Save a PNG of the image with the detected corners.")
@click.option(
    "--max-stderr-px",
    type=click.FloatRange(min=0, min_open=True),
    default=0.3,
    show_default=True,
    help="Drop triplets whose corners are less certain than this.",
)
@choice_option(
    "--orientation",
    choices=ORIENTATION_CHOICES,
    default="auto",
    help="The target's orientation in the image (turned about the image centre; "
    "docs/detection.md); auto: find it.",
)
@choice_option(
    "--mirror",
    choices=["auto", "yes", "no"],
    default="auto",
    help="Whether the image is mirrored (auto: find it; a single element in view cannot tell).",
)
@click.option(
    "--anchor",
    "anchors",
    multiple=True,
    metavar="GgEe[H|V][@X,Y]",
    help="An element you can read on the target, e.g. G6E3 (group 6, element 3), optionally with "
    "where it is in the image, G6E3@512,300 (camera px), or one triplet, G6E3V.  It decides the "
    "scale and the element that the bars alone may leave open; repeat for more elements.",
)
@json_option("Print one JSON object instead of a table.")
@positive_option("--pitch-um", help="--target dots: the dot pitch (um).")
@positive_option("--dot-um", help="--target dots: the dot diameter (um), optional.")
@positive_option("--square-um", help="--target chessboard: the square's side (um).")
@click.option(
    "--rows",
    type=click.IntRange(min=2),
    default=None,
    help="Dots (or chessboard squares) per column of the target, optional: a check, and ids from "
    "the grid's own corner when all are in view.",
)
@click.option(
    "--cols", type=click.IntRange(min=2), default=None, help="Dots (or squares) per row, with --rows."
)
@click.option(
    "--target-spec",
    default=None,
    help="A named grid target (its kind, pitch, dot and size), e.g. thorlabs-r2l2s3p3 (docs/detection.md).",
)
@choice_option("--polarity", choices=["auto", "dark", "bright"], default="auto",
               help="--target dots: dark dots on a bright field, bright on dark, or find out.")  # fmt: skip
# (one parameter per option of the command, as click passes them)
def detect_command(
    image,
    target,
    groups,
    um_per_px,
    out,
    truth,
    plot,
    max_stderr_px,
    orientation,
    mirror,
    anchors,
    as_json,
    **grid_options,
):
    """Detect the bar corners of a USAF-1951 target and match them to the reference target.

    Exit 0 with the points written, or exit 3 with the reason (and, with --plot, a picture
    of what was found) when the target is not found or its identity is not certain.
    --target dots / chessboard: a dot grid or chessboard, ids R<row>C<col>."""
    if target != "usaf" or grid_options.get("target_spec"):
        from oapcal.cli.detect_grid import detect_grid_command

        if anchors:
            raise click.BadParameter("names an element of a USAF-1951 target: drop it for a grid target",
                                     param_hint="--anchor")  # fmt: skip

        return detect_grid_command(image, target, um_per_px, out, truth, plot, as_json, grid_options)
    from oapcal.cli.detect_grid import check_usaf_options

    check_usaf_options()
    check_output(out, image, truth)
    check_output(plot, image, truth, out)
    img, group_list, anchor_list, score = _read_inputs(image, groups, anchors, truth)
    det = _detect(image, img, group_list, anchor_list, um_per_px, as_json, orientation=orientation,
                  mirror=mirror, max_stderr_px=max_stderr_px)  # fmt: skip
    summary = det.summary()
    if score is not None:
        from oapcal.imaging.detect import evaluate_detection

        summary["truth"] = evaluate_detection(det, *score)

    def draw(path):
        from oapcal.report.detect_plots import plot_detection

        plot_detection(img, det, path, groups=groups)

    if det.status != 0:
        return _failed(image, det, summary, plot, draw, as_json, scored=score is not None)
    # All outputs or none: the picture is drawn to a temporary file first, then the points
    # are written, then the picture is moved into place.
    write_detected_points(out, det, plot, draw)
    if as_json:
        print_json(summary)
    elif out != "-":
        _print_summary(summary)
    return 0


def _read_inputs(image, groups, anchors, truth):
    """``detect_command``'s inputs read and checked before detection starts: the grey
    image, the groups and anchors parsed, and the truth to score against (None without
    --truth), which must have every corner of the groups."""
    from oapcal.cli.detect_inputs import check_image_size, read_truth
    from oapcal.imaging.detect.anchor import parse_anchors
    from oapcal.imaging.usaf import parse_groups
    from oapcal.io.imagefile import read_image_grey

    group_list = parse_groups(groups)
    anchor_list = parse_anchors(anchors)
    group_list = _anchored_groups(group_list, anchor_list)
    check_image_size(image)
    img = read_image_grey(image)
    score = read_truth(truth) if truth else None
    if score is not None:
        from oapcal.errors import DataError
        from oapcal.imaging.usaf import usaf_target

        known = set(score[0])
        missing = [i for i in usaf_target(group_list).corner_ids if i not in known]
        if missing:
            raise DataError(
                f"{truth}: has no row with id {missing[0]!r}; is it the truth of this image and these groups?"
            )
    return img, group_list, anchor_list, score


def _detect(image, img, group_list, anchor_list, um_per_px, as_json: bool, **options):
    """:func:`~oapcal.imaging.detect.detect_usaf` on ``img`` (``options``: orientation,
    mirror, max_stderr_px) behind a progress bar (none with --json), with the digest of the
    ``image`` file."""
    from dataclasses import replace

    from oapcal.cli._common import progress_bar
    from oapcal.imaging.detect import detect_usaf
    from oapcal.io.digest import file_sha256

    bar, update = progress_bar("detecting corners", enabled=not as_json)
    with bar:
        det = detect_usaf(img, group_list, um_per_px, **options, progress=update, anchors=anchor_list)
    return replace(det, image_sha256=file_sha256(image))


def _failed(image, det, summary: dict, plot, draw, as_json: bool, scored: bool) -> int:
    """Exit 3 for a target not found or not certain: with --plot the picture of what was
    found (``draw(plot)``), the reason on stderr, then the summary with --json, or as a
    table when scored against --truth."""
    if plot:
        draw(plot)
    click.echo(with_flag_hint(f"oapcal: detection failed: {image}: {_cli_words(det.message)}", det.param),
               err=True)  # fmt: skip
    if scored and not as_json:
        _print_summary(summary)
    if as_json:
        print_json(summary)
    return 3


def _anchored_groups(group_list: tuple, anchor_list) -> tuple:
    """The groups to search: with --anchor and --groups left at its default, the anchors'
    own groups (a user who reads G7E1 on screen has group 7 in view, not the default 4-5)."""
    from click.core import ParameterSource

    ctx = click.get_current_context(silent=True)
    if not anchor_list or ctx is None or ctx.get_parameter_source("groups") is not ParameterSource.DEFAULT:
        return group_list
    named = tuple(sorted({a.group for a in anchor_list}))
    if set(named) - set(group_list):
        plural = "s" if len(named) > 1 else ""
        listed = ", ".join(map(str, named))
        click.echo(f"note: --groups not given: searching the --anchor's group{plural} {listed} "
                   "(give --groups to search others too)", err=True)  # fmt: skip
        return named
    return group_list


def _cli_words(message: str) -> str:
    """The library's advice in this command's words: ``in anchors, e.g. 'G4E2@x,y'`` is
    ``with --anchor, e.g. --anchor G4E2@x,y``."""
    import re

    message = re.sub(r"in anchors, e\.g\. '([^']+)'", r"with --anchor, e.g. --anchor \1", message)
    message = message.replace("the anchors given", "the --anchor given")
    return message.replace(" in anchors", " with --anchor")


def _print_pixel_size(out, s: dict) -> None:
    """The pixel-size answer: um per px with its uncertainty, the field of view, the digest."""
    ps = s.get("pixel_size")
    fov = s.get("field_of_view_um")
    if not s.get("found"):
        return
    if s.get("um_per_px_sigma") is not None:
        line = f"pixel size {s['um_per_px']:.5g} +/- {s['um_per_px_sigma']:.2g} um/px (found)"
    else:
        line = f"pixel size {s['um_per_px']:.5g} um/px (given)"
        if ps:
            line += f", measured {ps['um_per_px']:.5g} um/px"
    if ps:
        line += (
            f" from {ps['corners']} corners (statistical {ps['statistical']:.2g}, anisotropy "
            f"{ps['anisotropy']:.2g}, over the field {ps['field']:.2g} um/px)"
        )
    if fov:
        line += f"; field of view {fov[0]:.5g} x {fov[1]:.5g} um"
    out.print(line)
    if s.get("image_sha256"):
        out.print(f"image sha256 {s['image_sha256']}")


def _print_summary(s: dict) -> None:
    out = console()
    m = s["orientation_matrix"]
    scores = list(s["orientation_scores"].items())
    runner_up = f", next {scores[1][0]} {scores[1][1]:.3f}" if len(scores) > 1 else ""
    if not s["found"] and not s.get("truth"):
        return
    pose = s.get("pose", {}).get("best")
    if pose:
        out.print(
            f"target found: {pose['um_per_px']:.4g} um/px, turned {pose['rotation_deg']:.1f} degrees"
            f"{', mirrored' if pose['mirrored'] else ''}; {pose['matched_triplets']} bar triplets matched"
        )
    if scores:
        out.print(
            f"target orientation {s['orientation']} (x_u,y_u = centre + [[{m[0][0]}, {m[0][1]}], "
            f"[{m[1][0]}, {m[1][1]}]] (reference - centre); correlation {scores[0][1]:.3f}{runner_up})"
        )
    else:
        out.print(
            f"target orientation {s['orientation']} (x_u,y_u = centre + [[{m[0][0]}, {m[0][1]}], "
            f"[{m[1][0]}, {m[1][1]}]] (reference - centre)), x_u,y_u at {s['um_per_px']:.4g} um/px"
        )
    out.print(
        f"found {s['found']} of {s['expected']} corners expected fully inside the image "
        f"(coverage {100 * s['coverage']:.1f} %); {s['polarity']} bars, "
        f"fitted blur sigma {s['sigma_px']:.2f} px, model-image correlation {s['ncc']:.3f}"
    )
    _print_pixel_size(out, s)
    c = s["consistency"]
    if c.get("model"):
        out.print(
            f"consistency: {c['model']} model fitted to the matched corners, rms residual "
            f"{c['rms_px']:.3f} px, max {c['max_px']:.3f} px, {c['inconsistent']} inconsistent dropped"
        )
    if s["dropped"]:
        out.print("dropped: " + ", ".join(f"{k} {v}" for k, v in s["dropped"].items()))
    t = s.get("truth")
    if t:
        out.print(
            f"against the truth: {t['found']} of {t['visible']} fully visible corners found "
            f"({100 * t['coverage']:.1f} %), error median {t['median_error_px']:.3f} px, "
            f"rms {t['rms_error_px']:.3f} px, max {t['max_error_px']:.3f} px, mismatches {t['mismatches']}"
        )
