"""``oapcal simulate``: a group of simulations (``relay``, ``image``)."""

from __future__ import annotations

import importlib

import click

#: name -> "module:attribute" of every ``simulate`` subcommand.
SUBCOMMANDS: dict[str, str] = {
    "relay": "oapcal.cli.simulate_relay:relay_command",
    "image": "oapcal.cli.simulate_image:simulate_image_command",
}


class _LazySimulate(click.Group):
    def list_commands(self, ctx):
        return sorted(SUBCOMMANDS)

    def get_command(self, ctx, name):
        if name not in SUBCOMMANDS:
            return None
        from oapcal.cli._common import harden

        module, attr = SUBCOMMANDS[name].split(":")
        return harden(getattr(importlib.import_module(module), attr))


@click.group("simulate", cls=_LazySimulate)
def simulate_group():
    """Simulate the optics: ray-traced relay distortion, synthetic camera images."""
