"""The ``oapcal`` command line: thin commands over library calls.

Each subcommand lives in a module of this package and is imported only when it runs
(or when ``--help`` lists it), and every module imports only Click at import time, so
``oapcal --help`` stays fast.  :func:`main` turns errors into exit codes:

* 0 success;
* 2 a user error: a Click usage error, or any :class:`oapcal.errors.OapcalError`,
  printed as one line on stderr (no traceback);
* 1 an internal error (set ``OAPCAL_DEBUG=1`` to see the traceback);
* 3 the command ran but a numerical result failed (a fit that did not converge);
* 4 a batch (``correct``) finished but some inputs failed (each reported on stderr).
"""

from __future__ import annotations

import importlib
import os
import sys

import click

from oapcal import __version__

#: name -> "module:attribute" of every subcommand.
COMMANDS: dict[str, str] = {
    "fit": "oapcal.cli.fit:fit_command",
    "correct-points": "oapcal.cli.fit:correct_points_command",
    "demo": "oapcal.cli.demo:demo_command",
    "simulate": "oapcal.cli.simulate:simulate_group",
    "correct": "oapcal.cli.correct:correct_command",
    "export-opencv": "oapcal.cli.export:export_opencv_command",
    "esf": "oapcal.cli.esf:esf_command",
    "report": "oapcal.cli.report:report_command",
    "landmarks": "oapcal.cli.landmarks:landmarks_group",
    "detect": "oapcal.cli.detect:detect_command",
    "select": "oapcal.cli.select:select_command",
    "robustness": "oapcal.cli.select:robustness_command",
}


class LazyGroup(click.Group):
    """A group that imports each subcommand's module only when it is needed."""

    def list_commands(self, ctx):
        return sorted(set(super().list_commands(ctx)) | set(COMMANDS))

    def get_command(self, ctx, name):
        if name in COMMANDS:
            module, attr = COMMANDS[name].split(":")
            return getattr(importlib.import_module(module), attr)
        return super().get_command(ctx, name)


@click.group(cls=LazyGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="oapcal")
def cli():
    """Calibrate and remove the distortion of off-axis parabolic mirror relays.

    Typical use: fit a model to labelled point pairs, then correct images with it.

    \b
      oapcal fit points.csv --model paper --out calib.json
      oapcal correct-points calib.json points.csv --out corrected.csv
    """


def main(argv: list[str] | None = None) -> int:
    """Run the command line with ``argv`` (default ``sys.argv[1:]``); return the exit code."""
    from oapcal.errors import OapcalError

    args = sys.argv[1:] if argv is None else list(argv)
    try:
        result = cli.main(args=args, prog_name="oapcal", standalone_mode=False)
    except click.exceptions.Exit as exc:
        return exc.exit_code
    except click.ClickException as exc:
        exc.show()
        return exc.exit_code
    except click.exceptions.Abort:
        click.echo("oapcal: aborted", err=True)
        return 130
    except OapcalError as exc:
        click.echo(f"oapcal: error: {exc}", err=True)
        return 2
    except KeyboardInterrupt:
        click.echo("oapcal: interrupted", err=True)
        return 130
    except Exception as exc:  # an internal error, not the user's
        if os.environ.get("OAPCAL_DEBUG"):
            raise
        click.echo(
            f"oapcal: internal error: {type(exc).__name__}: {exc} "
            "(set OAPCAL_DEBUG=1 for the traceback and please report it)",
            err=True,
        )
        return 1
    return result if isinstance(result, int) else 0
