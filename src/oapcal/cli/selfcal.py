"""``oapcal selfcal``: a calibration from frames of a moved, textured sample (docs/selfcal.md)."""

from __future__ import annotations

import click

from oapcal.cli._common import (
    check_output,
    console,
    file_option,
    json_option,
    out_option,
    positive_option,
    print_json,
    progress_bar,
    range_option,
)
from oapcal.cli._relay import (
    check_relay_spec,
    design_from_options,
    is_relay,
    model_option,
    relay_design_options,
)


@click.command("selfcal")
@click.argument("frames", nargs=-1, required=True)
@out_option("Write the calibration file (JSON) here; 'oapcal correct' and the others use it.", dash=False)
@model_option(
    "'+rotation' for Eq. (1) with a rotation term.",
    " The relay model is recommended where its design is known.",
)
@positive_option(
    "--um-per-px",
    help="Object um per corrected px (Eq. 1 models with --steps; the relay takes it from its design).",
)
@file_option(
    "--steps",
    "steps_file",
    help="Known stage positions: a CSV with columns frame,x_um,y_um (frame = the index of the frame in "
    "the order given, from 0). A positive x_um moves the sample's image towards larger columns, a "
    "positive y_um towards larger rows (docs/selfcal.md). They fix the scale and aspect.",
)
@click.option(
    "--stage-rotation/--no-stage-rotation",
    default=True,
    show_default=True,
    help="With --steps: fit the stage's turn against the camera's axes.",
)
@file_option("--residuals", "residuals_out", help="Write every match and its residual (CSV) here.")
@file_option(
    "--plot",
    "plot_out",
    help="Write a picture of the matches here (PNG); the residual field goes beside it (NAME-residuals.png).",
)
@range_option(
    "--max-matches-per-pair",
    type=click.IntRange(20, 5000),
    default=150,
    help="At most this many matches per overlapping pair of frames.",
)
@range_option(
    "--min-overlap",
    type=click.FloatRange(0.05, 0.95),
    default=0.2,
    help="Frames overlap when they share at least this fraction of the frame.",
)
@positive_option(
    "--max-rms",
    default=0.3,
    show_default=True,
    help="Refuse (a moving sample) when the inlier matches' RMS is above this, px.",
)
@range_option(
    "--min-inliers",
    type=click.FloatRange(0, 1),
    default=0.9,
    help="Refuse (a moving sample) when fewer of the matches than this fraction agree with "
    "one model and set of moves.",
)
@click.option(
    "--progress/--no-progress", default=True, show_default=True, help="A progress bar on a terminal."
)
@json_option("Print one JSON object instead of text.")
@relay_design_options
def selfcal_command(
    frames,
    out,
    model,
    um_per_px,
    steps_file,
    stage_rotation,
    residuals_out,
    plot_out,
    max_matches_per_pair,
    min_overlap,
    max_rms,
    min_inliers,
    progress,
    as_json,
    relay_design,
):
    """Calibrate from FRAMES (images, directories of images, or stacks) of one static, textured
    sample, each taken after a stage move; unknown moves unless --steps gives them."""
    from oapcal.io.calibration import save_calibration

    for path in (out, residuals_out, plot_out):
        check_output(path, *frames, *([steps_file] if steps_file else []))
    design = _checked_model(model, relay_design)
    images, names = _frames_from(frames)
    steps = _read_steps(steps_file, len(images))
    source = names[0] if len(names) == 1 else f"{names[0]} .. {names[-1]} ({len(images)} frames)"
    result = _match_and_calibrate(
        images, model, design, steps, source,
        show_progress=progress and not as_json, max_matches_per_pair=max_matches_per_pair,
        min_overlap=min_overlap, um_per_px=um_per_px, stage_rotation=stage_rotation, max_rms=max_rms,
        min_inliers=min_inliers,
    )  # fmt: skip
    _check_usable(result.calibration, source)
    save_calibration(result.calibration, out)
    if residuals_out is not None:
        _write_residuals(residuals_out, result)
    if plot_out is not None:
        _write_plots(plot_out, result, images)
    if as_json:
        print_json(summary(result))
    else:
        print_summary(result)
    return 0


def _checked_model(model: str, relay_design):
    """The relay's design for a relay ``model`` (None for Eq. 1); a bad spec fails here,
    before the frames are read."""
    if is_relay(model):
        check_relay_spec(model)
        return design_from_options(relay_design)
    from oapcal.model import parse_any_model

    parse_any_model(model)  # a bad spec fails before the frames are read
    return None


def _frames_from(frames):
    """The frames named by the FRAMES arguments and their names (the first input that names
    nothing usable is a usage error)."""
    from oapcal.batch.stack import expand_inputs

    files, failures, _ = expand_inputs(frames)
    if failures:
        raise click.BadParameter(failures[0].message, param_hint="FRAMES")
    return _read_frames(files)


def _read_steps(steps_file, n_frames: int):
    """The known stage positions of ``--steps`` (None without)."""
    if steps_file is None:
        return None
    from oapcal.io.userfile import read_text
    from oapcal.selfcal import parse_steps

    return parse_steps(read_text(steps_file, "steps file"), n_frames, steps_file)


def _match_and_calibrate(
    images, model, design, steps, source, *, show_progress, max_matches_per_pair, min_overlap, um_per_px,
    stage_rotation, max_rms, min_inliers,
):  # fmt: skip
    """Match the frames and self-calibrate, under a progress bar; a refusal for a moving
    sample fails like a fit (nothing written)."""
    bar, update = progress_bar("self-calibration", enabled=show_progress)
    from oapcal.selfcal import SelfcalRefused, find_matches, self_calibrate

    try:
        with bar:
            prior = _prior(design, images[0].shape[:2])
            matches = find_matches(
                images,
                max_per_pair=max_matches_per_pair,
                min_overlap=min_overlap,
                prior=prior,
                progress=update,
            )
            return self_calibrate(
                matches,
                model,
                design=design,
                steps_um=steps,
                um_per_px=um_per_px,
                stage_rotation=stage_rotation,
                max_rms_px=max_rms,
                source=source,
                min_inlier_fraction=min_inliers,
                progress=update,
            )
    except SelfcalRefused as exc:
        if exc.reason == "frames":
            raise
        from oapcal.cli.fit import FitFailed

        raise FitFailed(f"{source}: {exc}; nothing written") from None


def _read_frames(files):
    """Every frame of every file, in order (a stack gives all its pages), and their names."""
    from oapcal.io.images import open_frames

    images, names = [], []
    for path in files:
        with open_frames(path) as (info, frames):
            for i, frame in enumerate(frames):
                images.append(frame)
                names.append(str(path) if info.n_frames == 1 else f"{path}[{i}]")
    return images, names


def _prior(design, shape):
    """The relay's design as the prior of the matching (None for Eq. 1)."""
    if design is None:
        return None
    from oapcal.optics.relay_model import default_centre, relay_params

    rows, cols = shape
    return relay_params(default_centre(design, None, (cols, rows)))


def _check_usable(cal, source: str) -> None:
    import numpy as np

    from oapcal.cli.fit import FitFailed
    from oapcal.errors import InputFileError
    from oapcal.io.calibration import check_model_region

    if not np.isfinite(cal.params).all():
        raise FitFailed(f"{source}: the self-calibration gave non-finite parameters; nothing written")
    try:
        check_model_region(cal, source=source)
    except InputFileError as exc:
        raise FitFailed(f"{exc}; nothing written (fit a smaller --model)") from None


def _write_residuals(path, result) -> None:
    from oapcal.io.points import write_points

    m = result.matches
    fields = ["frame_a", "frame_b", "x_a", "y_a", "x_b", "y_b", "weight", "e_x", "e_y", "e", "inlier"]
    rows = []
    for i in range(len(m)):
        e = result.residuals[i]
        rows.append(
            {
                "frame_a": int(m.frame_a[i]),
                "frame_b": int(m.frame_b[i]),
                "x_a": repr(float(m.xy_a[i, 0])),
                "y_a": repr(float(m.xy_a[i, 1])),
                "x_b": repr(float(m.xy_b[i, 0])),
                "y_b": repr(float(m.xy_b[i, 1])),
                "weight": f"{m.weight[i]:.6g}",
                "e_x": f"{e[0]:.6g}",
                "e_y": f"{e[1]:.6g}",
                "e": f"{float((e**2).sum()) ** 0.5:.6g}",
                "inlier": int(bool(result.inlier[i])),
            }
        )
    write_points(path, fields, rows)


def _write_plots(path, result, images) -> None:
    from pathlib import Path

    from oapcal.report.plots import save_figure
    from oapcal.report.selfcal_plots import matches_figure, residual_figure

    save_figure(matches_figure(result, images[0]), path)
    p = Path(path)
    save_figure(residual_figure(result), p.with_name(f"{p.stem}-residuals{p.suffix or '.png'}"))


def summary(result) -> dict:
    """The ``--json`` object of ``oapcal selfcal``."""
    from oapcal.io.jsonfile import finite_or_none as _finite

    cal = result.calibration
    r = cal.residuals
    return {
        "frames": int(result.matches.n_frames),
        "pairs": len(result.matches.pairs),
        "matches": len(result.matches),
        "inliers": int(result.inlier.sum()),
        "free": list(cal.free),
        "params": cal.params_dict,
        "translations_px": [[float(v) for v in t] for t in result.translations],
        "stage_rotation_deg": _finite(result.stage_rotation_deg),
        "um_per_px_centre": None if result.um_per_px_centre is None else list(result.um_per_px_centre),
        "residuals": {"rms_px": r.rms_px, "mean_px": r.mean_px, "max_px": r.max_px},
        "gauge": list(result.gauge),
        "gauge_left": result.gauge_left,
        "converged": bool(cal.fit.converged),
    }


def print_summary(result) -> None:
    cal = result.calibration
    out = console()
    m = result.matches
    out.print(
        f"[bold]Self-calibration[/bold] ({cal.family.name} model): {m.n_frames} frames, {len(m.pairs)} "
        f"overlapping pairs, {int(result.inlier.sum())} of {len(m)} matches inliers"
    )
    r = cal.residuals
    out.print(f"match residuals: RMS {r.rms_px:.4g} px, mean {r.mean_px:.4g} px, max {r.max_px:.4g} px")
    if cal.relay_design is not None:
        from oapcal.optics.relay_model import describe

        out.print("[bold]The relay as fitted[/bold] (pinned by the gauge: +/- 0)")
        for line in describe(cal):
            out.print("  " + line)
    else:
        names = cal.family.param_names
        out.print(
            "[bold]Parameters[/bold]: " + ", ".join(f"{n} {cal.params[names.index(n)]:.6g}" for n in cal.free)
        )
    if result.stage_rotation_deg is not None:
        out.print(f"stage turned against the camera by {result.stage_rotation_deg:+.4f} deg")
    if result.um_per_px_centre is not None:
        ux, uy = result.um_per_px_centre
        out.print(f"at the image centre: {ux:.5g} um per px along x, {uy:.5g} along y")
    out.print("[bold]Gauge[/bold]")
    for line in result.gauge:
        out.print("  " + line)
