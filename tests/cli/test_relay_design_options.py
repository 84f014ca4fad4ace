"""The commands' relay-design options accept what RelayDesign accepts (one table)."""

import click
import pytest

from oapcal.cli.fit import fit_command
from oapcal.errors import DataError
from oapcal.optics.relay_model import RelayDesign

CASES = [  # (flag of fit, RelayDesign field, values at and beyond the ends of the range)
    ("--pixel-size", "pixel_size_um", [0.0, 1e-9, 1000.0, 1000.001]),
    ("--d1", "d1_mm", [0.0, 0.5, 100_000.0, 100_000.5]),
    ("--focal-length", "focal_length_mm", [0.0, 1.0, 10_000.0, 10_001.0]),
    ("--focal-length-2", "focal_length_2_mm", [0.0, 1.0, 10_000.0, 10_001.0]),
    ("--stop-distance", "stop_distance_mm", [-0.001, 0.0, 100_000.0, 100_000.1]),
]


def _option(command, flag):
    return next(p for p in command.params if isinstance(p, click.Option) and flag in p.opts)


@pytest.mark.parametrize("flag,field,values", CASES)
def test_fit_options_and_relay_design_agree_on_every_range_end(flag, field, values):
    option = _option(fit_command, flag)
    for value in values:
        try:
            option.type.convert(value, option, None)
            cli_ok = True
        except click.BadParameter:
            cli_ok = False
        try:
            RelayDesign(**{field: value})
            library_ok = True
        except DataError:
            library_ok = False
        assert cli_ok == library_ok, (flag, value)


def test_fit_setup_and_orientation_choices_are_the_designs():
    assert list(_option(fit_command, "--relay-setup").type.choices) == ["1", "2"]
    assert list(_option(fit_command, "--orientation").type.choices) == ["U", "Z"]
    assert _option(fit_command, "--pixel-size").default == RelayDesign().pixel_size_um
    assert _option(fit_command, "--focal-length").default == RelayDesign().focal_length_mm
