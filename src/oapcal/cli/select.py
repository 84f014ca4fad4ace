"""``oapcal select`` (AICc over all 4,096 models) and ``oapcal robustness`` (subsampling)."""

from __future__ import annotations

import click

from oapcal.cli._common import check_output, check_work, console, load_pairs, points_options, progress_bar

#: Most robustness trials (and the memory per trial, per point and per model: measured about
#: 10 B per point for 252 points, so these are generous).
MAX_TRIALS = 10_000_000
BYTES_PER_TRIAL_POINT = 16
BYTES_PER_TRIAL_MODEL = 512

SELECT_INIT_HELP = (
    "Starting values of every fit: 'zero' (all 0, m = 1; the paper's choice for normalized "
    "data), 'pixel' (the paper's pixel-scale guesses) or name=value pairs such as 'k1=1e-6,m=1'."
)
NORMALIZE_HELP = (
    "'grid': centre each point set on the middle of its x and y ranges and scale it to span "
    "-0.5..0.5 in y (the paper's simulated grids); 'experiment': scale and align the reference "
    "points onto the distorted ones; 'none': use the points as given."
)


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
@click.option(
    "--normalize",
    "normalization",
    type=click.Choice(["none", "grid", "experiment"]),
    default="none",
    show_default=True,
    help=NORMALIZE_HELP,
)
@click.option("--init", "init", default="zero", show_default=True, help=SELECT_INIT_HELP)
@click.option("--top", type=click.IntRange(min=1), default=10, show_default=True, help="Rows in the table.")
@click.option(
    "--cv",
    "cv",
    type=click.IntRange(min=2),
    default=None,
    help="Add the K-fold cross-validated mean corrected error of the top models.",
)
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of the cross-validation folds.")
@click.option(
    "--json",
    "json_out",
    type=click.Path(dir_okay=False, allow_dash=True),
    default=None,
    help="Write all 4,096 models, best first, to this JSON file ('-': stdout, no table).",
)
def select_command(points, normalization, init, top, cv, seed, json_out):
    """Rank all 4,096 models of Eq. 1 by AICc of the corrected points."""
    check_output(json_out, points)
    pairs = load_pairs(points)
    from oapcal.fitting import initial_params
    from oapcal.select import select_models

    initial_params(init, pairs.xy_u[:1], pairs.xy_d[:1], [True] * 13)  # a bad --init fails here
    bar, update = progress_bar("fitting 4,096 models")
    with bar:
        sel = select_models(
            pairs.xy_u, pairs.xy_d, normalization=normalization, init=init, cv=cv, cv_top=top,
            seed=seed, progress=update,
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
    for col in ("#", "free parameters", "K", "AICc", "dAICc", "weight", "RSS", "mean err"):
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
        ]
        if sel.cv_folds:
            row.append(_fmt(m.cv_mean_error, ".4g") + (f" ({m.cv_failed} failed)" if m.cv_failed else ""))
        table.add_row(*row)
    out.print(table)
    where = "the normalized coordinates of the fit" if sel.normalization != "none" else "the points' units"
    out.print(
        f"K = free parameters + 1 (the error variance); n = {2 * sel.n_points} residuals; RSS in {where}; "
        "errors in the units of the reference points as given."
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
@click.option(
    "--fraction",
    type=click.FloatRange(0, 1, min_open=True, max_open=True),
    default=0.9,
    show_default=True,
    help="Fraction of the points kept in each trial (the rest are held out).",
)
@click.option("--seed", type=int, default=0, show_default=True)
@click.option("--init", "init", default="zero", show_default=True, help=SELECT_INIT_HELP)
@click.option(
    "--normalize",
    "normalization",
    type=click.Choice(["none", "grid", "experiment"]),
    default="none",
    show_default=True,
    help=NORMALIZE_HELP,
)
@click.option(
    "--wrong-minimum-ratio",
    type=click.FloatRange(min=1, min_open=True),
    default=1.5,
    show_default=True,
    help="A converged fit whose RMS on the kept points exceeds this times the model's "
    "all-points RMS counts as a wrong local minimum.",
)
@click.option(
    "--json",
    "json_out",
    type=click.Path(dir_okay=False, allow_dash=True),
    default=None,
    help="Write the results to this JSON file ('-': stdout, no table).",
)
def robustness_command(
    points, models, trials, fraction, seed, init, normalization, wrong_minimum_ratio, json_out
):
    """Subsampling test: refit each model on random subsets, count non-convergence."""
    check_output(json_out, points)
    from oapcal.model import parse_model

    specs = [s.strip().replace("+", ",") for s in models.split(",") if s.strip()]
    for spec in specs:
        parse_model(spec)  # a bad spec fails before the file is read
    pairs = load_pairs(points)
    from oapcal.fitting import initial_params
    from oapcal.select import robustness

    initial_params(init, pairs.xy_u[:1], pairs.xy_d[:1], [True] * 13)
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
    return 0


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
    names = [n for n in _param_names() if any(n in m.free for m in result.models)]
    for name in names:
        cells = (_fmt(m.param_std.get(name), ".3g") if name in m.free else "" for m in result.models)
        spread.add_row(name, *cells)
    out.print(spread)


def _param_names():
    from oapcal.model import PARAM_NAMES

    return PARAM_NAMES
