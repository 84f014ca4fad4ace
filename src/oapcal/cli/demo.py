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
def demo_command(out_dir, seed):
    """Run the whole pipeline on built-in data and write the results into a directory."""
    from oapcal.cli.fit import print_fit
    from oapcal.demo import run_demo

    result = run_demo(out_dir, seed=seed)
    print_fit(result.calibration)
    click.echo(
        f"Largest deviation of a fitted parameter from the known truth: "
        f"{result.max_abs_z:.2f} standard errors"
    )
    for label, path in result.files.items():
        click.echo(f"wrote {label}: {path}")
    return 0
