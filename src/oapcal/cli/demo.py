"""``oapcal demo``: the whole pipeline on built-in data."""

from __future__ import annotations

import click


@click.command("demo")
@click.option(
    "--out-dir",
    type=click.Path(file_okay=False),
    default="oapcal-demo",
    show_default=True,
    help="Directory for the demo's outputs.",
)
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of the built-in data.")
@click.option("--no-report", is_flag=True, help="Skip the target image and the HTML report (faster).")
def demo_command(out_dir, seed, no_report):
    """Run the whole pipeline on built-in data and write the results into a directory."""
    import sys

    from oapcal.cli.fit import print_fit
    from oapcal.demo import run_demo

    result = run_demo(out_dir, seed=seed)
    print_fit(result.calibration)
    if not no_report:
        from oapcal.io.points import read_points
        from oapcal.report import demo_report
        from oapcal.synthetic import EXAMPLE_TRUTH

        pairs = read_points(result.files["points"])
        result.files.update(
            demo_report(out_dir, result.calibration, EXAMPLE_TRUTH, (pairs.xy_u, pairs.xy_d), seed=seed,
                        show_progress=sys.stderr.isatty())
        )  # fmt: skip
    click.echo(
        f"Largest deviation of a fitted parameter from the known truth: "
        f"{result.max_abs_z:.2f} standard errors"
    )
    for label, path in result.files.items():
        click.echo(f"wrote {label}: {path}")
    return 0
