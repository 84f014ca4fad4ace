"""``DESIGN_OPTIONS`` (the options an error about a relay design names) is derived from the
design table and the commands' spellings; every command's hint is the one the hand-written
list of earlier releases gave."""

import click
import pytest

from fresh_python import run_fresh
from oapcal.cli import _common, cli
from oapcal.cli._design_flags import DESIGN_OPTIONS, OPTION_STYLES

#: The hand-written list of ``cli/_common.py`` before it was derived (kept here as the reference).
HAND_WRITTEN = (
    "relay_setup", "relay_d1", "relay_focal_length", "relay_focal_length_2", "relay_stop", "relay_pixel_size",
    "relay_centre", "microscope_magnification", "setup", "d1", "d1_mm", "focal_length", "focal_length_2",
    "stop_distance", "pixel_size",
)  # fmt: skip


def _commands(group=cli, path=()):
    ctx = click.Context(group)
    for name in sorted(group.list_commands(ctx)):
        cmd = group.get_command(ctx, name)
        if isinstance(cmd, click.Group):
            yield from _commands(cmd, (*path, name))
        else:
            yield " ".join((*path, name)), cmd


def test_derived_names_are_the_hand_written_ones():
    assert set(DESIGN_OPTIONS) == set(HAND_WRITTEN)
    assert len(DESIGN_OPTIONS) == len(set(DESIGN_OPTIONS))
    assert _common.DESIGN_OPTIONS is DESIGN_OPTIONS


@pytest.mark.parametrize("param", ["design", ("design", "um_per_px"), ("um_per_px", "design")])
def test_every_command_hints_the_same_flags(monkeypatch, param):
    derived = {name: _common.flag_hint(cmd, param) for name, cmd in _commands()}
    monkeypatch.setattr(_common, "DESIGN_OPTIONS", HAND_WRITTEN)
    before = {name: _common.flag_hint(cmd, param) for name, cmd in _commands()}
    assert derived == before
    assert "--relay-setup, --d1, --focal-length" in derived["fit"]
    assert derived["tolerance"].startswith(" (set by --setup, --d1, --focal-length")


def test_orientation_is_never_hinted():
    styles = [style["orientation"][1] for style in OPTION_STYLES.values() if "orientation" in style]
    assert styles == ["relay_orientation", "orientation"]
    assert not set(styles) & set(DESIGN_OPTIONS)


def test_the_table_module_imports_no_cli_module():
    _, loaded = run_fresh("import oapcal.cli._design_flags")
    assert sorted(m for m in loaded if m.startswith("oapcal.cli.")) == ["oapcal.cli._design_flags"]
