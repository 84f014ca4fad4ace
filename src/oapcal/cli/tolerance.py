"""``oapcal tolerance``: how misalignment changes a relay's distortion and the error of a
calibration made on the aligned relay (sensitivities per unit and a Monte Carlo)."""

from __future__ import annotations

import click

from oapcal.cli._common import (
    PointsUsageError,
    check_output,
    check_plot_suffix,
    choice_option,
    console,
    file_option,
    flag_option,
    json_option,
    print_json,
    progress_bar,
)
from oapcal.cli._relay import design_option, design_options, field_option

#: Smallest camera pixel (um): below it a grid of a mm spans over 1e7 px and the aligned
#: calibration cannot be fitted in px.
MIN_PIXEL_UM = 1e-3
#: Most Monte Carlo trials (``oapcal.optics.tolerance.MAX_TRIALS``; a copy, so that ``--help``
#: imports nothing heavy).
MAX_TRIALS = 500_000

#: Tolerance options: group (``oapcal.optics.tolerance.GROUPS``) -> (flag, unit, help).
TOLERANCE_OPTIONS = {
    "tilt": ("--tilt", "deg", "tip and tilt of both mirrors"),
    "decentre": ("--decentre", "mm", "decentre of both mirrors along both axes"),
    "clock": ("--clock", "deg", "clocking of both mirrors"),
    "focal_length": ("--focal-length-error", "mm", "focal length of both mirrors"),
    "d1": ("--d1-error", "mm", "collimated path length"),
    "stop_decentre": ("--stop-decentre", "mm", "aperture stop position"),
    "camera_tilt": ("--camera-tilt", "deg", "camera tilt about both axes"),
    "defocus": ("--defocus", "mm", "camera position along its normal"),
    "object_tilt": ("--object-tilt", "deg", "target tilt about both axes"),
}


class OneLineCommand(click.Command):
    """A command whose usage errors (a bad number, an unknown option) are one line."""

    def parse_args(self, ctx, args):
        try:
            return super().parse_args(ctx, args)
        except click.UsageError as exc:
            raise PointsUsageError(exc.format_message()) from None


def _tolerance_options(func):
    import functools

    @functools.wraps(func)
    def wrapper(*args, **kwargs):
        groups = {name: kwargs.pop(f"tol_{name}") for name in TOLERANCE_OPTIONS}
        return func(*args, groups=groups, **kwargs)

    for name, (flag, unit, text) in reversed(TOLERANCE_OPTIONS.items()):
        text = f"Monte Carlo tolerance (+/-) of the {text}, {unit}."
        kind = click.FloatRange(max=45.0) if unit == "deg" else float  # >= 0 checked with a clearer message
        option = click.option(flag, f"tol_{name}", type=kind, default=0.0, metavar=unit.upper(), help=text)
        wrapper = option(wrapper)
    return wrapper


#: The relay's design options, shared with ``oapcal simulate relay`` (the same definitions:
#: :func:`oapcal.cli._relay.design_options`, style ``simulate``).
DESIGN_OPTIONS = ("setup", "d1", "orientation", "stop_distance", "focal_length", "focal_length_2")


@click.command("tolerance", cls=OneLineCommand)
@design_options(
    "simulate", "setup", "d1_mm", "orientation", "stop_distance_mm", "focal_length_mm", "focal_length_2_mm"
)
@click.option("--grid", "n", type=int, default=17, show_default=True, help="Grid points per side.")
@field_option("Full width of the square object field, mm (as simulate relay).")
@design_option("simulate", "pixel_size_um", low=MIN_PIXEL_UM, low_open=False)
@click.option(
    "--model",
    default="paper",
    show_default=True,
    help="Brown-Conrady model of the aligned calibration (preset or parameter list).",
)
@_tolerance_options
@click.option("--tol", "tol", multiple=True, metavar="NAME=VALUE",
              help="Tolerance of one parameter (e.g. m2_tilt_x=0.02), overriding its group; "
              "repeatable.")  # fmt: skip
@click.option("--trials", type=int, default=500, show_default=True,
              help=f"Monte Carlo trials (at most {MAX_TRIALS:,}).")  # fmt: skip
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of the Monte Carlo.")
@choice_option(
    "--distribution",
    choices=["uniform", "normal"],
    default="uniform",
    help="uniform in +/- tolerance, or normal with sigma = tolerance / 2.",
)
@click.option("--percentiles", default="50,90,95", show_default=True,
              help="Percentiles of the Monte Carlo summary, comma-separated.")  # fmt: skip
@flag_option("--refit", help="Also refit the model to each Monte Carlo relay (its own floor; slower).")
@file_option("--plot", help="Figure (PNG): sensitivities, and the Monte Carlo distributions.")
@json_option()
# The command's options, one parameter each (click); the body calls helpers.
def tolerance_command(setup, d1, orientation, stop_distance, focal_length, focal_length_2, n, field_mm,
                      pixel_size, model, groups, tol, trials, seed, distribution, percentiles, refit, plot,
                      as_json):  # fmt: skip
    """Sensitivity of the relay's grid distortion, and of the error of the aligned relay's
    calibration, to each misalignment; Monte Carlo over tolerances (--tilt 0.05 ...)."""
    from oapcal.cli._relay import traced_relay

    pct, per_parameter = _check_options(n, trials, pixel_size, field_mm, percentiles, tol, groups, plot)
    from oapcal.model import parse_model
    from oapcal.optics.tolerance import Tolerancing, expand_tolerances

    parse_model(model)  # a bad model is a usage error before any work
    tolerances = expand_tolerances(groups, per_parameter)
    relay = traced_relay({"setup": setup, "d1_mm": d1, "orientation": orientation,
                          "stop_distance_mm": stop_distance, "focal_length_mm": focal_length,
                          "focal_length_2_mm": focal_length_2})  # fmt: skip
    if tolerances:  # the trials, their memory and each tolerance's extremes, before any tracing
        _check_monte_carlo(relay, tolerances, trials, distribution, n)
    bar, update = progress_bar("tolerancing")
    with bar:
        update(0, 1, "calibrating the aligned relay")
        tolerancing = Tolerancing(relay, n=n, field_mm=field_mm, pixel_size_um=pixel_size, model=model)
        if not tolerancing.calibration.converged:
            click.echo(
                f"oapcal: error: the {model} model did not converge on the aligned relay's grid "
                f"({tolerancing.calibration.message}); try another --model",
                err=True,
            )
            return 3
        update(0, 1, "sensitivities")
        rows = tolerancing.sensitivity(progress=update)
        mc = None
        if tolerances:
            update(0, trials, "Monte Carlo")
            mc = tolerancing.monte_carlo(
                tolerances, trials, seed=seed, distribution=distribution, percentiles=pct, refit=refit,
                progress=update,
            )  # fmt: skip
        result = _result(relay, tolerancing, pixel_size, model, rows, mc)
        if plot is not None:
            from oapcal.report.optics_plots import plot_tolerance

            update(0, 1, "plotting")
            plot_tolerance(result, plot)
    if as_json:
        print_json(result)
    else:
        print_tolerance(result)
    return 0


def _check_options(n, trials, pixel_size, field_mm, percentiles, tol, groups, plot):
    """Refuse bad option values before any work; returns the percentiles and the
    per-parameter tolerances (``--tol``) parsed."""
    from oapcal.errors import GeometrySpecError

    if n < 2:
        raise GeometrySpecError(f"--grid needs at least 2 points a side, got {n}")
    if n > 201:
        raise GeometrySpecError(f"--grid {n} is more than tolerancing needs: give at most 201")
    if trials < 1:
        raise GeometrySpecError(f"--trials must be at least 1, got {trials}")
    if trials > MAX_TRIALS:
        raise GeometrySpecError(f"--trials must be at most {MAX_TRIALS:,}, got {trials:,}")
    for value, name in ((pixel_size, "--pixel-size"), (field_mm, "--field")):
        if not value > 0:
            raise GeometrySpecError(f"{name} must be positive, got {value:g}")
    pct = _parse_percentiles(percentiles)
    per_parameter = dict(_parse_assignment(text) for text in tol)
    for name, value in groups.items():
        if not value >= 0:
            raise GeometrySpecError(f"{TOLERANCE_OPTIONS[name][0]} must be a tolerance >= 0, got {value:g}")
    if plot is not None:
        check_output(plot)
        check_plot_suffix(plot, "--plot")
    return pct, per_parameter


def _check_monte_carlo(relay, tolerances, trials, distribution, n) -> None:
    """:func:`oapcal.optics.tolerance.check_monte_carlo`, its error naming the flags that
    set the offending tolerance."""
    from oapcal.errors import GeometrySpecError
    from oapcal.optics.tolerance import GROUPS, check_monte_carlo

    try:
        check_monte_carlo(relay, tolerances, trials, distribution, n)
    except GeometrySpecError as exc:
        if not (isinstance(exc.param, tuple) and exc.param[0] == "tolerances"):
            raise
        name = exc.param[1]
        flags = [flag for group, (flag, _, _) in TOLERANCE_OPTIONS.items() if name in GROUPS[group]]
        raise GeometrySpecError(f"{exc} (set by {', '.join(flags + ['--tol'])})") from None


def _result(relay, tolerancing, pixel_size, model, rows, mc) -> dict:
    """The JSON-ready result of the command (``--json``; the tables print it)."""
    return {
        "relay": {
            "d1_mm": relay.d1_mm, "orientation": relay.orientation,
            "stop_distance_mm": relay.stop_distance_mm, "focal_length_mm": relay.focal_lengths_mm[0],
            "focal_length_2_mm": relay.focal_lengths_mm[1],
        },
        "grid": {"n": tolerancing.n, "field_mm": tolerancing.field_mm, "pixel_size_um": pixel_size},
        "model": model,
        "calibration": {"free": list(tolerancing.calibration.free),
                        "params": tolerancing.calibration.params_dict},
        "aligned": tolerancing.aligned,
        "sensitivity": rows,
        "monte_carlo": mc,
    }  # fmt: skip


def _parse_percentiles(text: str) -> list[float]:
    from oapcal.errors import GeometrySpecError

    try:
        values = [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        values = []
    if not values or not all(0 <= v <= 100 for v in values):
        raise GeometrySpecError(f"--percentiles {text!r} is not a list like 50,90,95 (each in 0..100)")
    return values


def _parse_assignment(text: str) -> tuple[str, float]:
    from oapcal.errors import GeometrySpecError

    name, sep, value = text.partition("=")
    try:
        number = float(value)
    except ValueError:
        number = None
    if not sep or number is None:
        raise GeometrySpecError(f"--tol {text!r} is not NAME=VALUE like m2_tilt_x=0.02")
    return name.strip(), number


def print_tolerance(s: dict) -> None:

    out = console()
    r, g, a = s["relay"], s["grid"], s["aligned"]
    out.print(
        f"OAP relay: d1 = {r['d1_mm']:g} mm, orientation {r['orientation']}, stop "
        f"{r['stop_distance_mm']:g} mm after the first mirror, f = {r['focal_length_mm']:g} / "
        f"{r['focal_length_2_mm']:g} mm; "
        f"{g['n']}x{g['n']} grid over {g['field_mm']:g} mm, {g['pixel_size_um']:g} um pixels"
    )
    out.print(
        f"Aligned: distortion max {a['max_px']:.2f} px, mean {a['mean_px']:.2f} px; the {s['model']} "
        f"calibration corrects it to mean {a['corrected_mean_px']:.3f} px, max {a['corrected_max_px']:.3f} px"
    )
    out.print(_sensitivity_table(s["sensitivity"]))
    mc = s["monte_carlo"]
    if mc is None:
        out.print("No tolerances given: add e.g. --tilt 0.05 --decentre 0.1 for a Monte Carlo.")
        return
    _print_monte_carlo(out, mc)


def _sensitivity_table(rows):
    """The table of first-order rates (rates below the resolution shown as 0)."""
    from rich import box
    from rich.table import Table

    from oapcal.optics.tolerance import RESOLUTION_PX

    def num(value, signed=False):
        if abs(value) < RESOLUTION_PX:
            return "0"
        return f"{value:+.3g}" if signed else f"{value:.3g}"

    table = Table(title="Sensitivity per unit of misalignment (first order, camera px per deg or mm)",
                  title_justify="left", box=box.SIMPLE_HEAD)  # fmt: skip
    for col in ("parameter", "unit", "max+", "max-", "mean+", "mean-", "err.mean", "err.max", "recentr.",
                "shift", "scale%"):  # fmt: skip
        left = col in ("parameter", "unit")
        table.add_column(col, justify="left" if left else "right", no_wrap=left)
    for row in rows:
        signed = [num(row[k], True) for k in ("max_plus_px", "max_minus_px", "mean_plus_px", "mean_minus_px")]
        plain = [
            num(row[k]) for k in ("corrected_mean_px", "corrected_max_px", "recentred_mean_px", "shift_px")
        ]
        scale = num(row["scale_ppm"] * 1e-4, True) if abs(row["scale_ppm"]) >= 1.0 else "0"
        table.add_row(row["parameter"], row["unit"], *signed, *plain, scale)
    return table


def _print_monte_carlo(out, mc) -> None:
    from rich.table import Table

    tol = ", ".join(f"{k} {v:g}" for k, v in mc["tolerances"].items())
    out.print(
        f"Monte Carlo: {mc['trials']} trials ({mc['distribution']}, seed {mc['seed']}) within +/- {tol}"
    )
    table = Table(title="Monte Carlo (camera px; scale error in %)", title_justify="left")
    keys = ["mean", "std"] + [f"p{q:g}" for q in mc["percentiles"]] + ["max"]
    table.add_column("metric")
    for key in keys:
        table.add_column(key, justify="right")
    for metric, stats in mc["summary"].items():
        factor = 1e-4 if metric == "scale_error_ppm" else 1.0
        name = "scale_error_%" if metric == "scale_error_ppm" else metric
        table.add_row(name, *("-" if stats[k] is None else f"{stats[k] * factor:.3g}" for k in keys))
    out.print(table)
    notes = []
    if mc["n_lost"]:
        notes.append(
            f"{mc['n_lost']} trials whose chief rays miss a mirror (left out): tolerances too large?"
        )
    if mc["n_failed"]:
        notes.append(f"{mc['n_failed']} trials where the aligned calibration could not correct every point")
    if mc["n_vignetted"]:
        notes.append(f"{mc['n_vignetted']} trials with a vignetted chief ray")
    for note in notes:
        out.print(f"[yellow]{note}[/yellow]")
