"""``oapcal detect --target dots|chessboard``: the grid targets' side of the ``detect`` command
(its options are declared in :mod:`oapcal.cli.detect`)."""

from __future__ import annotations

import click

from oapcal.cli._common import check_output, console, print_json, with_flag_hint, write_detected_points

#: Options of ``detect`` that belong to the USAF target only.
USAF_ONLY = ("groups", "orientation", "mirror", "max_stderr_px")
#: Options of ``detect`` that belong to the grid targets only.
GRID_ONLY = ("pitch_um", "dot_um", "square_um", "rows", "cols", "target_spec", "polarity")


def check_usaf_options() -> None:
    """``--target usaf`` with a grid option given: a usage error naming it."""
    ctx = click.get_current_context()
    for name in GRID_ONLY:
        if ctx.get_parameter_source(name) not in (None, click.core.ParameterSource.DEFAULT):
            flag = "--" + name.replace("_", "-")
            raise click.UsageError(
                f"{flag} applies to --target dots or chessboard: drop it or choose that target"
            )


def _resolve(target, options):
    """The grid's kind, pitch, dot, rows and cols from the options (and ``--target-spec``)."""
    from oapcal.imaging.detect.grid import grid_spec

    ctx = click.get_current_context()
    for name in USAF_ONLY:
        if ctx.get_parameter_source(name) not in (None, click.core.ParameterSource.DEFAULT):
            flag = "--" + name.replace("_", "-")
            raise click.UsageError(f"{flag} applies to --target usaf only: drop it")
    spec = grid_spec(options["target_spec"]) if options.get("target_spec") else None
    if spec is not None and ctx.get_parameter_source("target") == click.core.ParameterSource.DEFAULT:
        target = spec.kind
    if spec is not None and spec.kind != target:
        raise click.UsageError(
            f"--target-spec {spec.name} is a {spec.kind} target, not {target}: drop --target"
        )
    if target == "dots":
        if options.get("square_um") is not None:
            raise click.UsageError("--square-um is for --target chessboard; a dot grid takes --pitch-um")
        pitch = options.get("pitch_um") or (spec.pitch_um if spec else None)
        if pitch is None:
            raise click.UsageError(
                "--target dots needs the dot pitch: give --pitch-um (or --target-spec NAME)"
            )
        dot = options.get("dot_um") if options.get("dot_um") is not None else (spec.dot_um if spec else None)
    else:
        if options.get("pitch_um") is not None or options.get("dot_um") is not None:
            raise click.UsageError(
                "--pitch-um and --dot-um are for --target dots; a chessboard takes --square-um"
            )
        pitch = options.get("square_um") or (spec.pitch_um if spec else None)
        if pitch is None:
            raise click.UsageError(
                "--target chessboard needs the square's side: give --square-um (or --target-spec NAME)"
            )
        dot = None
    rows, cols = options.get("rows"), options.get("cols")
    if rows is None and cols is None and spec is not None:
        rows, cols = spec.rows, spec.cols
    if (rows is None) != (cols is None):
        raise click.UsageError("give both --rows and --cols, or neither")
    if dot is not None and not dot < pitch:
        raise click.UsageError(f"--dot-um {dot:g} must be smaller than the pitch {pitch:g} um")
    return target, float(pitch), (float(dot) if dot is not None else None), rows, cols


def detect_grid_command(image, target, um_per_px, out, truth, plot, as_json, options) -> int:
    """Detect a dot grid or chessboard in ``image`` and write the point pairs (``oapcal detect``)."""
    from oapcal.cli.detect_inputs import check_image_size
    from oapcal.imaging.detect.grid import detect_grid, score_grid
    from oapcal.io.digest import file_sha256
    from oapcal.io.imagefile import read_image_grey

    target, pitch, dot, rows, cols = _resolve(target, options)
    check_output(out, image, truth)
    check_output(plot, image, truth, out)
    check_image_size(image)
    img = read_image_grey(image)
    truth_data = _read_grid_truth(truth) if truth else None
    det = detect_grid(img, target, pitch_um=pitch, dot_um=dot, rows=rows, cols=cols, um_per_px=um_per_px,
                      polarity=options.get("polarity") or "auto")  # fmt: skip
    summary = det.summary()
    summary["image"] = str(image)
    summary["image_sha256"] = file_sha256(image)
    summary["pitch_um"] = pitch
    if dot is not None:
        summary["dot_um"] = dot
    if truth_data is not None:
        summary["truth"] = score_grid(det, *truth_data)
    if not det.ok:
        if plot:
            _plot(img, det, plot)
        click.echo(with_flag_hint(f"oapcal: detection failed: {image}: {det.message}", det.param), err=True)
        if as_json:
            print_json(summary)
        return 3
    write_detected_points(out, det, plot, lambda path: _plot(img, det, path))
    if as_json:
        print_json(summary)
    elif out != "-":
        _print_summary(summary)
    return 0


def _plot(img, det, path) -> None:
    """The image with the indexed landmarks (crosses) and every 5th id."""
    from oapcal.report.plots import new_figure, save_figure

    fig = new_figure(8, 8 * img.shape[0] / img.shape[1])
    ax = fig.add_subplot(111)
    ax.imshow(img, cmap="gray", interpolation="nearest")
    if len(det.xy_d):
        ax.plot(det.xy_d[:, 0], det.xy_d[:, 1], "+", color="tab:red", ms=4, mew=0.8)
        for rid, (r, c), p in zip(det.ids, det.rc, det.xy_d):
            if r % 5 == 0 and c % 5 == 0:
                ax.annotate(rid, p, color="yellow", fontsize=6, xytext=(2, -2), textcoords="offset points")
    ax.set_title(det.message if not det.ok else f"{len(det.ids)} landmarks, {det.summary()['grid_rows']} x "
                 f"{det.summary()['grid_cols']}", fontsize=9)  # fmt: skip
    ax.set_axis_off()
    save_figure(fig, path)


def _read_grid_truth(path):
    """A truth file ``id,x_d,y_d,visible`` with ids ``R{row}C{col}``: ``(rc, xy, visible)``."""
    import re

    import numpy as np

    from oapcal.cli.detect_inputs import read_truth
    from oapcal.errors import InputFileError

    ids, xy, visible = read_truth(path)
    rc = []
    for i in ids:
        m = re.fullmatch(r"R(\d+)C(\d+)", i)
        if m is None:
            raise InputFileError(
                f"{path}: id {i!r} is not a grid id R<row>C<col>; is it the truth of a grid target?"
            )
        rc.append((int(m.group(1)), int(m.group(2))))
    return np.array(rc, int), xy, visible


def _print_summary(s: dict) -> None:
    out = console()
    absolute = (
        "ids from the grid's own corner"
        if s["ids_absolute"]
        else "ids counted from the first row and column found"
    )
    out.print(
        f"{s['target']}: found {s['found']} of {s['expected']} landmarks expected in view "
        f"(coverage {100 * s['coverage']:.1f} %), grid {s['grid_rows']} x {s['grid_cols']}, {absolute}; "
        f"pitch {s['pitch_px']:.3f} px"
    )
    fov = s["field_of_view_um"]
    ps = s["pixel_size"]
    at = ps["at_px"]
    given = f"; x_u,y_u at the given {s['um_per_px']:.5g} um/px" if ps["given"] else ""
    out.print(
        f"pixel size {ps['um_per_px']:.5g} +/- {ps['um_per_px_sigma']:.2g} um/px (object space, measured at "
        f"({at[0]:.1f}, {at[1]:.1f}) px){given}; field of view {fov[0]:.1f} x {fov[1]:.1f} um"
    )
    out.print(f"image sha256 {s['image_sha256']}")
    c = s["counts"]
    dropped = {
        k: c[k]
        for k in (
            "loo_dropped",
            "dirty_dropped",
            "unconverged_dropped",
            "position_dropped",
            "ambiguous",
            "conflicts",
            "parity",
        )
        if c.get(k)
    }
    if dropped:
        out.print("left out: " + ", ".join(f"{k} {v}" for k, v in dropped.items()))
    t = s.get("truth")
    if t:
        med = "n/a" if t["median_error_px"] is None else f"{t['median_error_px']:.3f} px"
        mx = "n/a" if t["max_error_px"] is None else f"{t['max_error_px']:.3f} px"
        out.print(
            f"against the truth: {t['found_in_view']} of {t['in_view']} landmarks in view found "
            f"({100 * t['found_fraction']:.1f} %), wrong indices {t['wrong']}, error median {med}, max {mx}"
        )
