"""The options that describe the nominal relay a ``--model relay`` fit starts from (shared
by ``fit``, ``select`` and ``robustness``), and reading them into a design.

Imports nothing heavy at module level (see :mod:`oapcal.cli`).
"""

from __future__ import annotations

import functools
import math

import click

from oapcal.cli._common import Finite
from oapcal.cli._design_flags import OPTION_STYLES
from oapcal.optics.design import FIELDS, MICROSCOPE_MAGNIFICATION_RANGE

#: |M| of --microscope-magnification at least, and at most (the design table's range).
MIN_MICROSCOPE_MAGNIFICATION, MAX_MICROSCOPE_MAGNIFICATION = MICROSCOPE_MAGNIFICATION_RANGE
#: Defaults of the design options (the paper's OAPs and camera, as ``simulate relay``).
DEFAULT_FOCAL_LENGTH_MM = FIELDS["focal_length_mm"].default
DEFAULT_PIXEL_SIZE_UM = FIELDS["pixel_size_um"].default


def design_option(style: str, name: str, **changes):
    """The click option of design field ``name`` as commands of ``style`` spell it
    (:data:`OPTION_STYLES`, with the style's changes); ``changes`` replace the table's
    ``default``, ``low``, ``low_open``, ``high`` for this command."""
    field = FIELDS[name]
    flag, dest, text, *styled = OPTION_STYLES[style][name]
    spec = {"default": field.default, "low": field.low, "high": field.high, "low_open": field.low_open,
            **(styled[0] if styled else {}), **changes}  # fmt: skip
    default = spec["default"]
    extra = {}
    if field.choices:
        kind = click.Choice([str(c) for c in field.choices], case_sensitive=name != "orientation")
        default = None if default is None else str(default)
    elif field.abs_range is not None:
        kind = Finite(min=-field.abs_range[1], max=field.abs_range[1])
        extra["metavar"] = "M"
    elif field.numeric:
        kind = Finite(
            min=spec["low"], max=spec["high"], min_open=spec["low_open"] and spec["low"] is not None
        )
    else:  # the centre: a point, parsed by the command
        kind, extra["metavar"] = None, "X,Y"
    if default is not None:
        extra["show_default"] = True
    return click.option(flag, dest, type=kind, default=default, help=text, **extra)


def design_options(style: str, *names: str):
    """Add the options of the design fields ``names`` (all of ``style``'s when none are
    given) to a command, in that order, each as :func:`design_option`; the command receives
    them under their Python names."""
    names = names or tuple(OPTION_STYLES[style])

    def decorate(func):
        for name in reversed(names):  # click lists the options last applied first
            func = design_option(style, name)(func)
        return func

    return decorate


RELAY_MODEL_HELP = (
    " Or 'relay' (the physical relay: its misalignment and the target's pose, from the "
    "design given by --relay-setup/--d1, --focal-length, --orientation, --pixel-size), or "
    "'relay:NAMES' for a subset such as relay:d1,tilt2x,tilt2y,camera (docs/models.md)."
)


def model_option(rotation: str, after: str = ""):
    """``--model`` of ``fit`` and ``selfcal``: an Eq. (1) preset or names, ``+rotation``
    (``rotation``: what it does there) or a relay spec (:data:`RELAY_MODEL_HELP`), then the
    command's own ``after``."""
    return click.option("--model", "model", default="paper", show_default=True,
                        help="Free parameters: a preset (full, paper, radial) or a comma list of names; add "
                        + rotation + RELAY_MODEL_HELP + after)  # fmt: skip


def is_relay(model: str | None) -> bool:
    """Whether a ``--model`` value names the relay family (:func:`oapcal.entry.is_relay_spec`,
    imported when asked so that loading the CLI loads no fitting code)."""
    from oapcal.entry import is_relay_spec

    return is_relay_spec(model)


def field_option(text: str):
    """``--field``: the full width (mm) of the square object field a relay is traced over
    (``simulate relay``, ``tolerance``), with the command's help ``text``."""
    return click.option("--field", "field_mm", type=Finite(min=0, max=1000, min_open=True), default=1.0,
                        show_default=True, help=text)  # fmt: skip


def relay_design_options(func):
    """Add the design options of a relay model to a command (passed as ``relay_design``, a
    dict of their values, to keep the command's signature short)."""
    keys = tuple(dest for _, dest, *_ in OPTION_STYLES["relay"].values())

    @functools.wraps(func)
    def wrapper(*args, **kwargs):
        kwargs["relay_design"] = {k: kwargs.pop(k) for k in keys}
        return func(*args, **kwargs)

    return design_options("relay")(wrapper)


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
    return check_microscope(
        value, "-5 for a 5x objective that inverts the image", " when there is no microscope"
    )


def check_microscope(value, example: str = "-5", when: str = ""):
    """``value`` of --microscope-magnification, refused (a usage error) below the design
    table's smallest |M|."""
    if value is not None and abs(value) < MIN_MICROSCOPE_MAGNIFICATION:
        raise click.BadParameter(
            f"{value:g} is not a magnification: give |M| >= {MIN_MICROSCOPE_MAGNIFICATION:g} "
            f"(e.g. {example}), or leave the option out{when}",
            param_hint="--microscope-magnification",
        )
    return value


#: The design fields that are arguments of :func:`oapcal.optics.relay.oap_relay` too.
RELAY_FIELDS = ("d1_mm", "orientation", "stop_distance_mm", "focal_length_mm", "focal_length_2_mm")


def traced_relay(values: dict, misalignment=None):
    """The relay (:func:`oapcal.optics.relay.oap_relay`) of a traced command's design
    options, ``values`` keyed by field name (``setup``, ``d1_mm`` ...): its errors name the
    geometry (``d1 (the collimated path length) must be a positive number of mm``)."""
    from oapcal.optics.relay import oap_relay

    fields = {k: values[k] for k in RELAY_FIELDS if k in values}
    return oap_relay(int(values["setup"]), misalignment=misalignment, **fields)


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
