"""Helpers shared by the commands: point-file input, output checks, printing.

Imports nothing heavy at module level (see :mod:`oapcal.cli`).
"""

from __future__ import annotations

import json
import sys

import click

INIT_HELP = (
    "Starting values: 'auto' (default: both of the next two, the better fit is kept), "
    "'zero' (all 0, m = 1; the paper's choice for normalized data), 'pixel' (the paper's "
    "pixel-scale guesses), or name=value pairs such as 'k1=1e-6,m=1'."
)


def points_options(func):
    """The ``POINTS`` argument shared by commands that read point pairs."""
    return click.argument("points", type=click.Path(dir_okay=False, allow_dash=True))(func)


def load_pairs(points: str, require=("x_u", "y_u", "x_d", "y_d")):
    """Read point pairs given on the command line (see :func:`oapcal.io.points.read_points`)."""
    from oapcal.io.points import read_points

    return read_points(points, require=require)


def check_output(out: str | None, *inputs) -> None:
    """Refuse an output path that would overwrite one of the inputs."""
    if out is None or out == "-":
        return
    from oapcal.io.atomic import ensure_not_input

    ensure_not_input(out, inputs)


def print_json(obj) -> None:
    """Print one JSON object on stdout."""
    sys.stdout.write(json.dumps(obj, indent=2, allow_nan=False, default=_json_default) + "\n")


def _json_default(value):
    import numpy as np

    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    raise TypeError(f"not JSON serializable: {type(value).__name__}")


def console():
    """A Rich console on stdout."""
    from rich.console import Console

    return Console(file=sys.stdout, highlight=False)


def parse_size(text: str | None, option: str = "--image-size"):
    """``"640x480"`` -> ``(640, 480)``; raises a usage error naming ``option``."""
    if text is None:
        return None
    try:
        w, h = (int(v) for v in text.lower().split("x"))
        if w <= 0 or h <= 0:
            raise ValueError
    except ValueError:
        raise click.BadParameter(f"{text!r} is not a size like 640x480", param_hint=option) from None
    return (w, h)
