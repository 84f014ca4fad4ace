"""``oapcal demo``: the whole pipeline on built-in data."""

from __future__ import annotations

import click

from oapcal.cli._common import count_option, flag_option


@click.command("demo")
@click.option(
    "--out-dir",
    type=click.Path(file_okay=False),
    default="oapcal-demo",
    show_default=True,
    help="Directory for the demo's outputs (created).",
)
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of the simulated image noise.")
@count_option("--trials", least=0, default=1000, help="Robustness trials (0 skips the robustness test).")
@flag_option("--no-report", help="Skip the HTML report (faster).")
def demo_command(out_dir, seed, trials, no_report):
    """Run the whole method on built-in data: trace the relay, select the model, simulate
    and detect a USAF target, fit, test robustness, correct the image, write a report."""
    from oapcal.cli._common import sanitize

    result = _run(out_dir, seed, trials, no_report)
    _print_steps(result, trials)
    _print_correction(result.extra.get("trust"))
    for label, path in result.files.items():
        click.echo(sanitize(f"wrote {label}: {path}"))
    return 0


def _run(out_dir, seed, trials, no_report):
    """:func:`oapcal.demo.run_demo` with a progress bar over its steps."""
    from oapcal.cli._common import progress_bar
    from oapcal.demo import STEPS, run_demo

    skipped = {"report"} if no_report else set()
    if trials == 0:
        skipped.add("robustness")
    steps = [s for s in STEPS if s not in skipped]
    bar, update = progress_bar("demo")
    with bar:

        def step(name):
            update(steps.index(name), len(steps), f"demo: {name}")

        result = run_demo(out_dir, seed=seed, trials=trials, report=not no_report, step=step)
        update(len(steps), len(steps))
    return result


def _print_steps(result, trials) -> None:
    """Steps 1-6 of the demo's summary."""
    from oapcal.cli._common import console
    from oapcal.cli.fit import print_fit

    out = console()
    d = result.relay["distortion"]
    paper = result.relay.get("paper") or {}
    out.print(
        f"[bold]1. Relay (setup 1), 17x17 grid over 1 mm:[/bold] distortion max {d['max_um']:.1f} um "
        f"(paper {paper.get('max_um', float('nan')):g}), mean {d['mean_um']:.1f} um "
        f"(paper {paper.get('mean_um', float('nan')):g})"
    )
    best = result.selection.models[:3]
    out.print(
        "[bold]2. Model selection by AICc (of the corrected residuals) over 4,096 subsets (grid):[/bold]"
    )
    for rank, m in enumerate(best, 1):
        out.print(f"   {rank}. {','.join(m.free)}  dAICc {m.delta_aicc:.2f}  weight {m.weight:.3f}")
    out.print(f"   fitted model: {','.join(result.extra['chosen'])}")
    det = result.detection
    out.print(
        f"[bold]3-4. Simulated USAF groups 4-5 through the relay; detection:[/bold] {det['found']} "
        f"of {det['visible']} fully visible corners found ({100 * det['coverage']:.1f} %), median "
        f"error vs truth {det['median_error_px']:.3f} px, mismatches {det['mismatches']}"
    )
    out.print("[bold]5. Fit of the selected model to the detected corners:[/bold]")
    print_fit(result.calibration)
    te = result.truth_error
    out.print(
        f"   fitted model vs ray-traced truth at {te['n']} corners: mean {te['mean_px']:.3f} px, "
        f"max {te['max_px']:.3f} px"
    )
    if result.robustness is not None:
        out.print(f"[bold]6. Robustness ({trials} trials of 90 % of the points):[/bold]")
        for m in result.robustness.models:
            out.print(
                f"   {m.name}: not converged {m.not_converged} of {m.trials}; held-out mean error "
                f"{m.heldout_mean_error:.3f} px"
            )


def _print_correction(trust) -> None:
    """Step 7 of the demo's summary: where the correction is trusted."""
    from oapcal.cli._common import console

    if trust:
        console().print(
            f"[bold]7. Correction:[/bold] trusted (predicted error <= {trust['max_error_px']:g} px) in "
            f"{100 * trust['trusted_fraction']:.0f} % of the frame; the landmarks cover "
            f"{100 * (1 - trust['outside_fraction']):.0f} %, and the frame reaches "
            f"{trust['max_distance_px']:.0f} px beyond their hull (predicted error up to "
            f"{trust['max_predicted_px']:.3g} px); the rest of corrected.png is black (the report shows "
            "the trust region)"
        )
