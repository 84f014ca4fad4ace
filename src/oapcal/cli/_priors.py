"""The ``--priors`` option of ``fit`` and ``select`` (relay models), and reading its value.

Imports nothing heavy at module level (see :mod:`oapcal.cli`).
"""

from __future__ import annotations

import click

PRIORS_HELP = (
    "With a relay model: Gaussian priors on the misalignment from the mounts' tolerances "
    "(a maximum a posteriori fit, docs/models.md): 'auto' (the default: 'default' for a relay "
    "model, none for Eq. 1), 'off' (no priors: the least-squares fit), "
    "'default' (scale 1 %, tilt 0.05 deg, decentre 0.2 mm, clock 0.05 deg, focal_length 0.2 mm, d1 5 %, "
    "stop_decentre 0.2 mm, camera_tilt 1 deg, defocus 0.2 mm, object_tilt 1 deg; 1 sigma), "
    "key=value pairs over the defaults (tilt=0.1,d1=2,noise_px=0.3,noise_floor_px=0.05; inf: no prior, "
    "0: fixed) or a JSON file of them."
)

#: ``--priors``' default: the default priors for a relay model, none for Eq. (1).
AUTO = "auto"

priors_option = click.option("--priors", "priors", default=AUTO, show_default=True, metavar="SPEC",
                             help=PRIORS_HELP)  # fmt: skip


def load_priors(value: str | None, relay: bool = True):
    """``--priors`` as :class:`~oapcal.optics.relay_model.RelayPriors` (None for ``off``):
    ``auto`` is ``default`` when ``relay`` (a relay model is fitted) and None otherwise; a
    value ending in ``.json`` is a file of widths (read through :mod:`oapcal.io.userfile`)."""
    from oapcal.errors import OapcalError
    from oapcal.optics.relay_model import parse_priors, priors_from_dict

    if value is None:
        return None
    text = value.strip()
    if text.lower() == AUTO:
        return parse_priors("default") if relay else None
    if text.lower().endswith(".json"):
        from oapcal.io.userfile import read_json

        data = read_json(text, "priors file")
        try:
            return priors_from_dict(data, spec=text)
        except OapcalError as exc:  # name the file
            raise type(exc)(f"{text}: {exc}", param="priors") from None
    return parse_priors(text)
