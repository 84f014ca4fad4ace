"""The options that describe the nominal relay a ``--model relay`` fit starts from (shared
by ``fit``, ``select`` and ``robustness``), and reading them into a design.

Imports nothing heavy at module level (see :mod:`oapcal.cli`).
"""

from __future__ import annotations

import functools
import math

import click

from oapcal.cli._common import Finite

#: Defaults of the design options (the paper's OAPs and camera, as ``simulate relay``).
DEFAULT_FOCAL_LENGTH_MM = 50.8
DEFAULT_PIXEL_SIZE_UM = 4.8
#: |M| of --microscope-magnification at most, and at least (a copy of
#: ``relay_model.MICROSCOPE_MAGNIFICATION_RANGE``: importing it would load NumPy for --help).
MAX_MICROSCOPE_MAGNIFICATION = 1000.0
MIN_MICROSCOPE_MAGNIFICATION = 0.01

RELAY_MODEL_HELP = (
    " Or 'relay' (the physical relay: its misalignment and the target's pose, from the "
    "design given by --relay-setup/--d1, --focal-length, --orientation, --pixel-size), or "
    "'relay:NAMES' for a subset such as relay:d1,tilt2x,tilt2y,camera (docs/models.md)."
)


def is_relay(model: str | None) -> bool:
    """Whether a ``--model`` value names the relay family."""
    return isinstance(model, str) and (model.strip() == "relay" or model.strip().startswith("relay:"))


def relay_design_options(func):
    """Add the design options of a relay model to a command (passed as ``relay_design``, a
    dict of their values, to keep the command's signature short)."""
    length = Finite(min=0, max=10_000, min_open=True)
    w = "With --model relay: "
    options = [
        click.option("--relay-setup", type=click.Choice(["1", "2"]), default="1", show_default=True,
                     help=w + "the paper's setup 1 (d1 = 860 mm) or 2 (660 mm)."),
        click.option("--d1", "relay_d1", type=Finite(min=0, max=100_000, min_open=True), default=None,
                     help=w + "collimated path length, mm (overrides --relay-setup)."),
        click.option("--focal-length", "relay_focal_length", type=length, default=DEFAULT_FOCAL_LENGTH_MM,
                     show_default=True, help=w + "reflected focal length of the mirrors, mm."),
        click.option("--focal-length-2", "relay_focal_length_2", type=length, default=None,
                     help=w + "the second mirror's, mm (default: --focal-length)."),
        click.option("--orientation", "relay_orientation", default="U", show_default=True,
                     type=click.Choice(["U", "Z"], case_sensitive=False), help=w + "U or Z."),
        click.option("--stop-distance", "relay_stop", type=Finite(min=0, max=100_000), default=0.0,
                     show_default=True, help=w + "aperture stop, mm after the first mirror."),
        click.option("--pixel-size", "relay_pixel_size", type=Finite(min=0, max=1000, min_open=True),
                     default=DEFAULT_PIXEL_SIZE_UM, show_default=True, help=w + "camera pixel size, um."),
        click.option("--relay-centre", "relay_centre", default=None, metavar="X,Y",
                     help=w + "the point (px) on the relay's axis (default: the image centre with "
                     "--image-size, else the middle of the reference points)."),
        click.option("--microscope-magnification", "microscope_magnification", default=None, metavar="M",
                     type=Finite(min=-MAX_MICROSCOPE_MAGNIFICATION, max=MAX_MICROSCOPE_MAGNIFICATION),
                     help=w + "a finite-conjugate microscope between the relay and the camera, its "
                     "magnification; negative when it inverts the image (-5: a 5x objective forming a "
                     "real image). The model is then relay+microscope (docs/models.md)."),
    ]  # fmt: skip

    @functools.wraps(func)
    def wrapper(*args, **kwargs):
        keys = ("relay_setup", "relay_d1", "relay_focal_length", "relay_focal_length_2", "relay_orientation",
                "relay_stop", "relay_pixel_size", "relay_centre", "microscope_magnification")  # fmt: skip
        kwargs["relay_design"] = {k: kwargs.pop(k) for k in keys}
        return func(*args, **kwargs)

    for option in reversed(options):
        wrapper = option(wrapper)
    return wrapper


def parse_xy(text: str, option: str, example: str) -> tuple[float, float]:
    """``"0.5,-0.25"`` -> ``(0.5, -0.25)``; a usage error naming ``option`` (with an
    ``example`` of a good value) for anything else."""
    try:
        x, y = (float(v) for v in text.split(","))
        if not (math.isfinite(x) and math.isfinite(y)):
            raise ValueError
    except ValueError:
        raise click.BadParameter(f"{text!r} is not a point like {example}", param_hint=option) from None
    return (x, y)


def _parse_centre(text: str | None):
    return None if text is None else parse_xy(text, "--relay-centre", "320,240 (px)")


def design_from_options(values: dict):
    """The :class:`~oapcal.optics.relay_model.RelayDesign` of the options' values."""
    from oapcal.optics.relay_model import RelayDesign

    return RelayDesign(
        setup=int(values["relay_setup"]), d1_mm=values["relay_d1"],
        focal_length_mm=values["relay_focal_length"], focal_length_2_mm=values["relay_focal_length_2"],
        orientation=values["relay_orientation"].upper(),
        stop_distance_mm=values["relay_stop"], pixel_size_um=values["relay_pixel_size"],
        centre=_parse_centre(values["relay_centre"]),
        microscope_magnification=_microscope(values.get("microscope_magnification")),
    )  # fmt: skip


def _microscope(value):
    if value is not None and abs(value) < MIN_MICROSCOPE_MAGNIFICATION:
        raise click.BadParameter(
            f"{value:g} is not a magnification: give |M| >= {MIN_MICROSCOPE_MAGNIFICATION:g} (e.g. -5 for "
            "a 5x objective that inverts the image), or leave the option out when there is no microscope",
            param_hint="--microscope-magnification",
        )
    return value


def refuse_normalize(normalization: str | None, why: str) -> None:
    """A usage error for ``--normalize`` with a model that fits the points as given (``why``
    says which and why)."""
    if normalization not in (None, "none"):
        raise click.BadParameter(f"{why}: drop --normalize", param_hint="--normalize")


def check_relay_spec(model: str) -> None:
    """Parse a ``relay`` / ``relay:NAMES`` spec early (a bad name fails before files are read;
    the microscope's names are checked against the design by the fit)."""
    from oapcal.model import RELAY_MICROSCOPE
    from oapcal.optics.relay_model import relay_mask

    relay_mask(model, RELAY_MICROSCOPE)
