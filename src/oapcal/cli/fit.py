"""``oapcal fit`` (``oapcal correct-points`` is in :mod:`oapcal.cli.correct_points`)."""

from __future__ import annotations

import click

from oapcal.cli._common import (
    INIT_HELP,
    check_output,
    choice_option,
    console,
    flag_option,
    json_option,
    load_pairs,
    out_option,
    parse_size,
    points_options,
    positive_option,
    print_json,
)
from oapcal.cli._priors import load_priors, priors_option
from oapcal.cli._relay import (
    check_relay_spec,
    design_from_options,
    is_relay,
    model_option,
    refuse_normalize,
    relay_design_options,
)


@click.command("fit")
@points_options
@model_option("'+rotation' (paper+rotation) to fit the target's in-plane rotation too.")
@click.option("--init", "init", default="auto", show_default=True, help=INIT_HELP)
@choice_option(
    "--normalize",
    "normalization",
    choices=["none", "experiment"],
    default="none",
    help="'experiment': scale and align the reference points onto the distorted ones as the paper did "
    "for points from another microscope.",
)
@positive_option("--um-per-px", help="Object-space size (um) of one unit of the reference points as given.")
@click.option("--image-size", default=None, help="Camera image size WxH in px, e.g. 640x480.")
@out_option("Write the calibration file (JSON) here.", required=False)
@json_option()
@choice_option(
    "--rotation",
    choices=["auto", "fit", "none"],
    default="auto",
    help="The target's in-plane rotation with an Eq. (1) model: 'auto' fits it too when the points need "
    "it (Eq. 1 alone does not converge, or AICc drops by > 10) and says so; 'fit' always; 'none' "
    "never.",
)
@flag_option(
    "--keep-unconverged",
    help="Write the calibration even when the fit did not converge (exit 3 still); 'oapcal correct' then "
    "needs --allow-unconverged to use it.",
)
@relay_design_options
@priors_option
# one parameter per command-line option (Click passes them so)
def fit_command(points, model, init, normalization, um_per_px, image_size, out, as_json, rotation,
                keep_unconverged, relay_design, priors="auto"):  # fmt: skip
    """Fit a distortion model to point pairs: a CSV with x_u,y_u,x_d,y_d (POINTS), or
    landmark files --distorted FILE --reference FILE (VIA, napari, BigWarp, CSV)."""
    from oapcal.calibration import UnusableFitError
    from oapcal.io.calibration import save_calibration

    check_output(out, points)
    size = parse_size(image_size)
    relay_priors = load_priors(priors, relay=is_relay(model))
    if relay_priors is not None and not is_relay(model):
        raise click.UsageError(f"--priors {priors} applies to a relay model (--model relay); drop it")
    try:
        if is_relay(model):
            cal, pairs = _fit_relay(points, model, normalization, um_per_px, size, relay_design, relay_priors)
        else:
            cal, pairs = _fit_eq1(points, model, init, normalization, um_per_px, size, rotation)
    except UnusableFitError as exc:
        raise _unusable(exc) from None
    _check_fit_usable(cal, pairs.source)
    for note in cal.notes:
        # the rotation policy's choice can be undone (not the fold beyond the landmarks)
        how = " (--rotation none fits the model as given)" if getattr(note, "kind", "") == "rotation" else ""
        click.echo(f"oapcal: note: {note}{how}", err=True)
    write = out is not None and (cal.fit.converged or keep_unconverged)
    if write:
        save_calibration(cal, out)
    if as_json:
        print_json(fit_summary(cal))
    elif out != "-" or not write:
        print_fit(cal)
    if not cal.fit.converged:
        what = "written anyway (--keep-unconverged)" if write else "nothing written"
        keep = "" if write else ", or give --keep-unconverged to write it anyway"
        click.echo(
            f"oapcal: error: {pairs.source}: the fit did not converge "
            f"({cal.fit.message.removeprefix('not converged: ')}{_runaway(cal)}); {what}. Try another "
            f"--model (e.g. {_suggestion(cal)}) or --init{keep}",
            err=True,
        )
        return 3
    return 0


def _fit_relay(points, model, normalization, um_per_px, size, relay_design, relay_priors):
    """``(calibration, pairs)`` of a relay model (``--model relay...``)."""
    from oapcal.entry import calibrate

    check_relay_spec(model)  # a bad spec fails before the file is read
    refuse_normalize(normalization, "the relay model fits the target's pose itself, in px")
    design = design_from_options(relay_design)
    pairs = load_pairs(points)
    cal = calibrate(pairs.xy_u, pairs.xy_d, model, design=design, um_per_px=um_per_px, image_size=size,
                    source=pairs.source, priors=relay_priors)  # fmt: skip
    return cal, pairs


def _fit_eq1(points, model, init, normalization, um_per_px, size, rotation):
    """``(calibration, pairs)`` of an Eq. (1) model (with or without the rotation)."""
    from oapcal.entry import calibrate
    from oapcal.fitting import check_enough_points
    from oapcal.model import parse_any_model

    parse_any_model(model)  # a bad spec fails before the file is read
    pairs = load_pairs(points)
    check_enough_points(len(pairs), int(parse_any_model(model).sum()), source=pairs.source)
    if rotation != "auto" and model.strip().endswith("+rotation"):
        raise click.UsageError(f"--model {model} fits the rotation already: drop --rotation {rotation}")
    cal = calibrate(
        pairs.xy_u, pairs.xy_d, model, init=init, normalization=normalization,
        um_per_px=um_per_px, image_size=size, source=pairs.source, rotation=rotation,
    )  # fmt: skip
    return cal, pairs


def _runaway(cal) -> str:
    """Why an Eq. (1) fit did not converge, when the distortion centre ran away."""
    if cal.relay_design is not None or cal.bounds is None:
        return ""
    x0, y0, x1, y1 = cal.bounds
    limit = 10 * max(x1 - x0, y1 - y0) + abs(x1) + abs(y1)
    names = cal.family.param_names
    far = [n for n in ("x_off", "y_off", "c_x", "c_y") if abs(cal.params[names.index(n)]) > limit]
    if not far:
        return ""
    values = ", ".join(f"{n} = {cal.params[names.index(n)]:.3g}" for n in far)
    return (
        f"; the distortion centre runs away: {values}, over 10 times the points' span, as when the "
        "points hold a turn, shear or aspect change that the model cannot represent"
    )


def _suggestion(cal) -> str:
    return "radial+rotation" if len(cal.params) > 13 else "paper+rotation"


class FitFailed(click.ClickException):
    """The fit ran but gave no usable model (exit 3, nothing written)."""

    exit_code = 3

    def show(self, file=None):
        from oapcal.cli._common import sanitize

        click.echo(f"oapcal: error: {sanitize(self.format_message())}", err=True)


#: ``oapcal fit``'s wording of the fix of each :class:`oapcal.calibration.UnusableFitError`
#: (its flags; the library's message names the Python parameters).
_UNUSABLE_ADVICE = {
    "non_finite": "Check the points, or fit a smaller --model",
    "negative_m": "Fit the rotation (--rotation auto, the default, or fit)",
}


def _check_fit_usable(cal, source: str) -> None:
    """The library's refusal of a fit that gives no usable model
    (:func:`oapcal.calibration.check_fit_usable`, :func:`oapcal.entry.check_relay_plausible`,
    which :func:`oapcal.calibrate` applies as well), as exit 3 with nothing written."""
    from oapcal.calibration import UnusableFitError, check_fit_usable
    from oapcal.entry import check_relay_plausible

    try:
        check_fit_usable(cal, source)
        check_relay_plausible(cal, source)
    except UnusableFitError as exc:
        raise _unusable(exc) from None


def _unusable(exc) -> FitFailed:
    """An :class:`~oapcal.calibration.UnusableFitError` as ``oapcal fit`` words it."""
    advice = _UNUSABLE_ADVICE.get(exc.code)
    problem = exc.problem.replace("the priors (priors 'default')", "--priors default")
    return FitFailed(f"{problem}; nothing written" + (f". {advice}" if advice else ""))


def fit_summary(cal) -> dict:
    """The ``--json`` object of ``oapcal fit``."""
    from oapcal.io.jsonfile import finite_or_none as _finite

    extra = {} if cal.priors is None else {"priors": cal.priors, "k_eff": _finite(cal.fit.k_eff)}
    if cal.notes:
        # what the fit decided for the user (the rotation fitted too, a fold beyond the
        # landmarks), as stderr says: only when there is something to say
        extra["notes"] = list(cal.notes)
    return {
        **extra,
        "free": list(cal.free),
        "params": cal.params_dict,
        "stderr": {n: _finite(cal.stderr[i]) for i, n in _free_index(cal)},
        "converged": bool(cal.fit.converged),
        "aicc": _finite(cal.fit.aicc),  # forward residuals; the key set is pinned (the file has both)
        "residuals": {
            k: v
            for k, v in cal.residuals.to_dict().items()
            if k.endswith(("_px", "_um")) and k != "um_per_px"
        },
    }


def _number(value) -> str:
    return "n/a" if value is None else f"{value:.6g}"


def _free_index(cal):
    names = cal.family.param_names
    return [(names.index(n), n) for n in cal.free]


def print_fit(cal) -> None:
    """Readable tables: parameters with errors, fit statistics, Table-1 residuals."""
    from rich.table import Table

    family = cal.family
    out = console()
    out.print(f"[bold]Fitted parameters[/bold] ({family.name} model)")
    table = Table()
    table.add_column("parameter")
    table.add_column("value", justify="right")
    table.add_column("std. error", justify="right")
    for i, name in enumerate(family.param_names):
        if name in family.never_free:
            continue
        if name in cal.free:
            table.add_row(name, f"{cal.params[i]:.6g}", f"{cal.stderr[i]:.3g}")
        else:
            table.add_row(f"[dim]{name}[/dim]", f"[dim]{cal.params[i]:.6g} (fixed)[/dim]", "")
    out.print(table)
    if cal.relay_design is not None:
        from oapcal.optics.relay_model import describe

        out.print("[bold]The relay as fitted[/bold]")
        for line in describe(cal):
            out.print("  " + line)
    f = cal.fit
    if cal.priors is not None:
        out.print(
            f"maximum a posteriori fit, priors {cal.priors.get('spec')} (noise "
            f"{cal.priors.get('noise_used_px', float('nan')):.3g} px; effective parameters "
            f"{f.k_eff:.3g} of {f.k})"
        )
    status = "converged" if f.converged else "NOT converged"
    out.print(
        f"{status} after {f.n_iter} iterations ({f.message}); {f.n_points} points, "
        f"RSS {f.rss:.6g}, AICc {f.aicc_forward:.6g} (forward residuals; "
        f"{_number(f.aicc_corrected)} after correction, as model selection scores it)"
    )
    r = cal.residuals.to_dict()
    out.print("[bold]Residuals after correction (paper's Table 1)[/bold]")
    res = Table()
    for col in ("", "max", "mean", "rms", "total"):
        res.add_column(col, justify="right")
    res.add_row("px", *(f"{r[f'{k}_px']:.4g}" for k in ("max", "mean", "rms", "total")))
    if "max_um" in r:
        res.add_row("um", *(f"{r[f'{k}_um']:.4g}" for k in ("max", "mean", "rms", "total")))
    out.print(res)
    if r.get("n_failed"):
        out.print(f"[red]{r['n_failed']} points could not be corrected (inverse did not converge)[/red]")
