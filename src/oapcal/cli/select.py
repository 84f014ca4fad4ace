"""``oapcal select`` (AICc over all 4,096 models) and ``oapcal robustness`` (subsampling)."""

from __future__ import annotations

import click

from oapcal.cli._common import (
    check_output,
    check_work,
    console,
    count_option,
    file_option,
    load_pairs,
    points_options,
    progress_bar,
    range_option,
)
from oapcal.cli._priors import load_priors, priors_option
from oapcal.cli._relay import refuse_normalize, relay_design_options

#: Most robustness trials (and the memory per trial, per point and per model: measured about
#: 10 B per point for 252 points, so these are generous).
MAX_TRIALS = 10_000_000
BYTES_PER_TRIAL_POINT = 16
BYTES_PER_TRIAL_MODEL = 512

SELECT_INIT_HELP = (
    "Starting values of every fit: 'auto' (the data's own centre, scale and turn: the start "
    "'oapcal fit' uses too), 'zero' (all 0, m = 1; the paper's choice for normalized data), "
    "'pixel' (the paper's pixel-scale guesses) or name=value pairs such as 'k1=1e-6,m=1'."
)
NORMALIZE_HELP = (
    "'grid': centre each point set on the middle of its x and y ranges and scale it to span "
    "-0.5..0.5 in y (the paper's simulated grids); 'experiment': scale and align the reference "
    "points onto the distorted ones; 'none': use the points as given."
)

#: The options ``select`` and ``robustness`` share.
normalize_option = click.option(
    "--normalize",
    "normalization",
    type=click.Choice(["none", "grid", "experiment"]),
    default="none",
    show_default=True,
    help=NORMALIZE_HELP,
)
init_option = click.option("--init", "init", default="auto", show_default=True, help=SELECT_INIT_HELP)


def _wide_console():
    """The shared console, at least 150 columns wide when stdout is not a terminal."""
    out = console()
    if not out.is_terminal:
        out.width = max(out.width, 150)
    return out


def _fmt(value, spec: str) -> str:
    import math

    if value is None or not math.isfinite(value):
        return "-"
    return format(value, spec)


@click.command("select")
@points_options
@normalize_option
@init_option
@count_option("--top", least=1, default=10, help="Rows in the table.")
@click.option(
    "--cv",
    "cv",
    type=click.IntRange(min=2),
    default=None,
    help="Add the K-fold cross-validated mean corrected error of the top models.",
)
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of the cross-validation folds.")
@file_option(
    "--json",
    "json_out",
    help="Write all 4,096 models, best first, to this JSON file ('-': stdout, no table).",
    dash=True,
)
@click.option(
    "--families",
    default=None,
    help="Rank model families together: a comma list of bc (Eq. 1), bc+rotation (Eq. 1 with the "
    "target's rotation), bc+tilt and bc+rotation+tilt (Eq. 1 with the perspective terms tilt_x, "
    "tilt_y) and relay (the physical relay, from the design options), by AICc and "
    "--cv-fold held-out error (default 5 folds); recommends by the held-out error.",
)
@click.option(
    "--model",
    "model",
    default=None,
    help="'relay': rank the relay's subsets alone (the same as --families relay).",
)
@click.option(
    "--image-size",
    default=None,
    help="With --families: camera image size WxH in px (the relay's centre, and the region every "
    "recommended model must correct without folding over, as fit checks it).",
)
@click.option(
    "--region",
    default="auto",
    show_default=True,
    metavar="auto|hull|X0,Y0,X1,Y1",
    help="With --families: the region the correction will cover, over which each model's "
    "predicted error (held-out error and the propagated parameter uncertainty) decides the "
    "recommendation: 'auto' the image frame with --image-size, else the landmarks' hull; "
    "'hull'; or a box in px of the reference points.",
)
@relay_design_options
@priors_option
# one parameter per command-line option (Click passes them so)
def select_command(points, normalization, init, top, cv, seed, json_out, families=None, image_size=None,
                   relay_design=None, model=None, region="auto", priors="auto"):  # fmt: skip
    """Rank all 4,096 models of Eq. 1 by AICc of the corrected points (with --families: Eq. 1,
    its rotation variant and the physical relay together)."""
    check_output(json_out, points)
    if model is not None:
        if model.strip() != "relay" or families is not None:
            raise click.BadParameter(
                "select takes --model relay only (Eq. 1 is ranked over all its subsets without it); "
                "for several families give --families",
                param_hint="--model",
            )
        families = "relay"
    relay_priors = load_priors(priors, relay=families is not None)
    if families is None and (relay_priors is not None or region != "auto"):
        flag = "--priors" if relay_priors is not None else "--region"
        raise click.UsageError(
            f"{flag} applies to choosing across families: give --families (or --model relay)"
        )
    if families is not None:
        return _select_families(points, families, normalization, init, top, cv, seed, json_out, image_size,
                                relay_design, _parse_region(region), relay_priors)  # fmt: skip
    pairs = load_pairs(points)
    from oapcal.fitting import initial_params
    from oapcal.select import select_models

    initial_params(init, pairs.xy_u[:1], pairs.xy_d[:1], [True] * 13)  # a bad --init fails here
    bar, update = progress_bar("fitting 4,096 models")
    with bar:
        sel = select_models(  # without a bar drawn, no progress: the models are fitted in one batch
            pairs.xy_u, pairs.xy_d, normalization=normalization, init=init, cv=cv, cv_top=top,
            seed=seed, progress=None if bar.disable else update,
        )  # fmt: skip
    if json_out is not None:
        from oapcal.io.results import save_selection

        save_selection(sel, json_out)
    if json_out != "-":
        print_selection(sel, top, source=pairs.source)
    if sel.n_valid == 0:
        click.echo("oapcal: warning: no model could be scored; see the reasons in the table", err=True)
        return 3
    return 0


def _parse_region(text: str):
    """``--region``: ``auto``, ``hull`` or ``X0,Y0,X1,Y1`` (px, x1 > x0, y1 > y0)."""
    import math

    text = (text or "auto").strip()
    if text in ("auto", "hull"):
        return text
    try:
        box = tuple(float(v) for v in text.split(","))
    except ValueError:
        box = ()
    if len(box) != 4 or not all(math.isfinite(v) for v in box) or box[2] <= box[0] or box[3] <= box[1]:
        raise click.BadParameter(
            f"{text!r} is not auto, hull or a box X0,Y0,X1,Y1 with X1 > X0 and Y1 > Y0 (px), "
            "e.g. 0,0,639,479",
            param_hint="--region",
        )
    return box


def _select_families(
    points,
    families,
    normalization,
    init,
    top,
    cv,
    seed,
    json_out,
    image_size,
    relay_design,
    region="auto",
    priors=None,
):
    """``oapcal select --families``."""
    from oapcal.cli._common import parse_size
    from oapcal.cli._relay import design_from_options
    from oapcal.families import parse_families, select_families

    keys = parse_families(families)
    refuse_normalize(normalization, "models of different families are compared on the points as given")
    size = parse_size(image_size)
    design = design_from_options(relay_design)
    pairs = load_pairs(points)
    bar, update = progress_bar("fitting the models of " + ", ".join(keys))
    with bar:
        sel = select_families(pairs.xy_u, pairs.xy_d, design, keys, cv=cv or 5, cv_top=min(top, 10),
                              init=init, seed=seed, progress=update, image_size=size, priors=priors,
                              region=region)  # fmt: skip
    if json_out is not None:
        from oapcal.io.results import save_family_selection

        save_family_selection(sel, json_out)
    if json_out != "-":
        print_family_selection(sel, top, source=pairs.source)
    return 0 if sel.recommended is not None else 3


def print_family_selection(sel, top: int, source: str = "") -> None:
    """The best ``top`` models of each family by AICc, and the recommendation."""
    from rich.table import Table

    from oapcal.families import FOLDS_PREFIX, REFUSED_PREFIX

    out = _wide_console()
    table = Table(
        title=f"Best models of each family by AICc ({source}, {sel.n_points} points)", title_justify="left"
    )
    for col in ("family", "model (--model)", "K", "AICc corrected", "dAICc", "mean err",
                f"{sel.cv_folds}-fold CV err", "sigma over region", "predicted err"):  # fmt: skip
        table.add_column(col, justify="left" if col in ("family", "model (--model)") else "right")
    families = list(dict.fromkeys(c.family for c in sel.candidates))
    for family in families:
        shown = [c for c in sel.candidates if c.family == family and c.valid][:top]
        if sel.recommended is not None and sel.recommended.family == family and sel.recommended not in shown:
            shown.append(sel.recommended)  # the recommendation is always in the table
        for c in shown:
            mark = " [bold green]<- recommended[/bold green]" if c is sel.recommended else ""
            k = str(c.k + 1) if c.k_eff is None else f"{c.k_eff + 1:.3g}"
            table.add_row(c.family, c.spec + mark, k, _fmt(c.aicc, ".2f"),
                          _fmt(c.delta_aicc, ".2f"), _fmt(c.mean_error, ".4g"),
                          _fmt(c.cv_mean_error, ".4g"), _fmt(c.region_sigma, ".4g"),
                          _fmt(c.predicted_error, ".4g"))  # fmt: skip
    out.print(table)
    n_bad = sum(not c.valid for c in sel.candidates)
    n_region = sum(c.reason.startswith(REFUSED_PREFIX) for c in sel.candidates)
    n_folds = sum(c.reason.startswith(FOLDS_PREFIX) for c in sel.candidates)
    if n_bad:
        out.print(f"{n_bad} models could not be scored (not identifiable, or the fit or its inverse failed).")
    if n_region:
        out.print(
            f"{n_region} of them fold over or are not finite on the points' bounds or the image "
            "(fit would refuse to write them)."
        )
    if n_folds:
        out.print(
            f"{n_folds} of them fold over in the image beyond the points: not recommended (fit writes them "
            "with a note, and correct writes only their trust region, not the whole image)."
        )
    h = getattr(sel, "heldout_best", None) or sel.recommended
    if h is not None:
        out.print(f"Recommended by held-out error: --model {h.spec} ({h.family}, {h.cv_mean_error:.4g} px).")
    for note in getattr(sel, "notes", ()):
        out.print(f"Note: {note}.")
    r = sel.recommended
    if r is not None and r.predicted_error is not None:
        where = (
            "the landmarks' hull"
            if sel.region is None
            else "the region " + ",".join(f"{v:g}" for v in sel.region)
        )
        priors = (
            " --priors " + str(sel.priors.get("spec")) if sel.priors and r.family.startswith("relay") else ""
        )
        out.print(
            f"[bold]Recommended for correcting {where}[/bold] (held-out error and the propagated "
            f"uncertainty there): --model {r.spec}{priors} ({r.family}, predicted "
            f"{r.predicted_error:.4g} px)."
        )


def print_selection(sel, top: int, source: str = "") -> None:
    """The top-N table and a summary of the models that could not be scored."""
    from collections import Counter

    from rich.table import Table

    out = _wide_console()
    title = (
        f"Top {min(top, len(sel.models))} of {len(sel.models)} models by AICc ({source}, "
        f"{sel.n_points} points, --normalize {sel.normalization}, --init {sel.init})"
    )
    table = Table(title=title, title_justify="left")
    for col in ("#", "free parameters", "K", "AICc corrected", "dAICc", "weight", "RSS", "mean err",
                "AICc forward"):  # fmt: skip
        table.add_column(col, justify="left" if col == "free parameters" else "right")
    if sel.cv_folds:
        table.add_column(f"{sel.cv_folds}-fold CV err", justify="right")
    for rank, m in enumerate(sel.models[:top], 1):
        row = [
            str(rank),
            ",".join(m.free) if m.valid else f"{','.join(m.free)} [red]({m.reason})[/red]",
            str(m.k + 1),
            _fmt(m.aicc, ".2f"),
            _fmt(m.delta_aicc, ".2f"),
            _fmt(m.weight, ".3f"),
            _fmt(m.rss, ".4g"),
            _fmt(m.mean_error, ".4g"),
            _fmt(m.aicc_forward, ".2f"),
        ]
        if sel.cv_folds:
            row.append(_fmt(m.cv_mean_error, ".4g") + (f" ({m.cv_failed} failed)" if m.cv_failed else ""))
        table.add_row(*row)
    out.print(table)
    where = "the normalized coordinates of the fit" if sel.normalization != "none" else "the points' units"
    out.print(
        f"K = free parameters + 1 (the error variance); n = {2 * sel.n_points} residuals; RSS in {where}; "
        "errors in the units of the reference points as given. AICc corrected: of the residuals "
        "after correction (the ranking); AICc forward: of the forward residuals the fit minimises "
        "(what 'oapcal fit' reports as AICc)."
    )
    bad = [m for m in sel.models if not m.valid]
    if bad:
        kinds = Counter(m.reason_code for m in bad)
        summary = "; ".join(f"{n} {_INVALID_TEXT.get(code, code)}" for code, n in kinds.most_common())
        out.print(f"{len(bad)} models could not be scored and are ranked last: {summary}.")


#: How the selection table names each kind of invalid model (select.INVALID_REASONS).
_INVALID_TEXT = {
    "not_converged": "fit did not converge",
    "too_few_residuals": "too few residuals for AICc",
    "inverse_failed": "inverse failed",
    "aicc_not_finite": "AICc is not finite",
}


@click.command("robustness")
@points_options
@click.option(
    "--models",
    "models",
    default="paper,full",
    show_default=True,
    help="Models to test, comma-separated: presets (paper, full, radial) or '+'-joined "
    "parameter lists such as k1+s3+c_x+c_y.",
)
@click.option("--trials", type=click.IntRange(1, MAX_TRIALS), default=10000, show_default=True)
@range_option(
    "--fraction",
    type=click.FloatRange(0, 1, min_open=True, max_open=True),
    default=0.9,
    help="Fraction of the points kept in each trial (the rest are held out).",
)
@click.option("--seed", type=int, default=0, show_default=True)
@init_option
@normalize_option
@range_option(
    "--wrong-minimum-ratio",
    type=click.FloatRange(min=1, min_open=True),
    default=1.5,
    help="A converged fit whose RMS on the kept points exceeds this times the model's "
    "all-points RMS counts as a wrong local minimum.",
)
@file_option(
    "--json", "json_out", help="Write the results to this JSON file ('-': stdout, no table).", dash=True
)
@click.option("--image-size", default=None, help="With a relay model: camera image size WxH in px.")
@relay_design_options
@priors_option
# one parameter per command-line option (Click passes them so)
def robustness_command(
    points, models, trials, fraction, seed, init, normalization, wrong_minimum_ratio, json_out,
    image_size=None, relay_design=None, priors="auto",
):  # fmt: skip
    """Subsampling test: refit each model on random subsets, count non-convergence."""
    check_output(json_out, points)
    from oapcal.cli._relay import is_relay

    specs = [_robustness_spec(s) for s in models.split(",") if s.strip()]
    relay = any(is_relay(s) for s in specs)
    if relay:
        refuse_normalize(normalization, "a relay model fits the points as given")
    relay_priors = load_priors(priors, relay=relay)
    if relay_priors is not None and not relay:
        raise click.UsageError(f"--priors {priors} applies to a relay model (--models relay...); drop it")
    pairs = load_pairs(points)
    from oapcal.fitting import initial_params
    from oapcal.select import robustness

    initial_params(init, pairs.xy_u[:1], pairs.xy_d[:1], [True] * 13)
    specs = [_started_relay(s, pairs, image_size, relay_design, relay_priors) if is_relay(s) else s
             for s in specs]  # fmt: skip
    check_work(
        trials * (BYTES_PER_TRIAL_POINT * len(pairs) + BYTES_PER_TRIAL_MODEL * len(specs)),
        f"{trials} trials of {len(pairs)} points x {len(specs)} models", "give fewer --trials",
    )  # fmt: skip
    bar, update = progress_bar(f"{trials} trials x {len(specs)} models")
    with bar:
        result = robustness(
            pairs.xy_u, pairs.xy_d, specs, trials=trials, fraction=fraction, seed=seed, init=init,
            normalization=normalization, wrong_minimum_ratio=wrong_minimum_ratio, progress=update,
        )  # fmt: skip
    if json_out is not None:
        from oapcal.io.results import save_robustness

        save_robustness(result, json_out)
    if json_out != "-":
        print_robustness(result, source=pairs.source)
        if relay_priors is not None:
            click.echo(f"relay models: maximum a posteriori fits, priors {relay_priors.spec} "
                       "(docs/models.md; --priors off: least squares)")  # fmt: skip
    return 0


def _robustness_spec(text: str) -> str:
    """One --models entry: '+'-joined names become a comma list (``k1+s3`` -> ``k1,s3``),
    keeping ``+rotation`` and ``+tilt`` suffixes (``k1+s3+rotation``, ``paper+rotation+tilt``)
    and relay subsets (``relay:d1+tilt2x``); checked before any file is read."""
    from oapcal.cli._relay import check_relay_spec, is_relay
    from oapcal.model import ROTATION_SUFFIX, TILT_SUFFIX, parse_any_model

    text = text.strip()
    if is_relay(text):
        spec = text.replace("+", ",")
        check_relay_spec(spec)
        return spec
    suffix = ""
    for end in (TILT_SUFFIX, ROTATION_SUFFIX):
        if text.endswith(end):
            text, suffix = text[: -len(end)], end + suffix
    spec = text.replace("+", ",") + suffix
    parse_any_model(spec)
    return spec


def _started_relay(spec: str, pairs, image_size, relay_design, priors=None):
    """A relay --models entry as a model with its design's start; with ``priors``
    (:class:`~oapcal.optics.relay_model.RelayPriors`) its trials are maximum a posteriori
    fits, the rows weighed by the noise of the all-points fit (as select's folds)."""
    from oapcal.cli._common import parse_size
    from oapcal.cli._relay import design_from_options
    from oapcal.optics.relay_model import default_centre, map_fit, relay_mask, relay_params
    from oapcal.subsampling import StartedModel

    design = default_centre(design_from_options(relay_design), pairs.xy_u, parse_size(image_size))
    mask = relay_mask(spec, design.family)
    prior = None
    if priors is not None:
        _, noise = map_fit(pairs.xy_u, pairs.xy_d, design, mask[None], priors, covariance=False)
        prior = priors.arrays(design, float(noise[0]))
    return StartedModel(spec, mask, relay_params(design), family=design.family, prior=prior)


def print_robustness(result, source: str = "") -> None:
    """Counts by reason, held-out error and parameter spread of each model."""
    from rich.table import Table

    from oapcal.select import REASONS

    out = _wide_console()
    table = Table(
        title=(
            f"Robustness ({source}): {result.models[0].trials} trials keeping {result.n_keep} of "
            f"{result.n_points} points, --init {result.init}, seed {result.seed}"
        ),
        title_justify="left",
    )
    table.add_column("model")
    table.add_column("not converged", justify="right")
    for reason in REASONS:
        table.add_column(reason, justify="right")
    table.add_column("held-out mean err", justify="right")
    for m in result.models:
        table.add_row(
            m.name,
            str(m.not_converged),
            *(str(m.by_reason[r]) for r in REASONS),
            _fmt(m.heldout_mean_error, ".4g"),
        )
    out.print(table)
    out.print(
        f"wrong_minimum: converged, but RMS on the kept points > {result.wrong_minimum_ratio:g} x the "
        "model's best all-points RMS."
    )
    spread = Table(title="Spread (std) of each parameter over the converged trials", title_justify="left")
    spread.add_column("parameter")
    for m in result.models:
        spread.add_column(m.name, justify="right")
    from oapcal.model import BROWN_CONRADY_TILT, RELAY_MICROSCOPE

    order = list(dict.fromkeys(BROWN_CONRADY_TILT.param_names + RELAY_MICROSCOPE.param_names))
    names = [n for n in order if any(n in m.free for m in result.models)]
    for name in names:
        cells = (_fmt(m.param_std.get(name), ".3g") if name in m.free else "" for m in result.models)
        spread.add_row(name, *cells)
    out.print(spread)
