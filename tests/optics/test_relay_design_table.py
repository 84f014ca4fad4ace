"""The design's one table of fields, and simulate_relay's design + options form."""

import re

import pytest

from oapcal.errors import DataError
from oapcal.optics.design import FIELDS
from oapcal.optics.relay_model import RelayDesign
from oapcal.optics.summary import SimulationOptions, simulate_relay


@pytest.mark.parametrize(
    "field,value,words",
    [("pixel_size_um", -4.8, "(0, 1000]"), ("d1_mm", 0.0, "(0, 100000]"),
     ("stop_distance_mm", -1.0, "[0, 100000]"), ("focal_length_mm", float("nan"), "(0, 10000]")],
)  # fmt: skip
def test_relay_design_refuses_values_outside_the_table(field, value, words):
    with pytest.raises(
        DataError, match=rf"relay design {field} is .*; it must be a number in {re.escape(words)}"
    ):
        RelayDesign(**{field: value})


def test_relay_design_defaults_are_the_papers():
    design = RelayDesign()
    assert (design.setup, design.focal_length_mm, design.pixel_size_um, design.stop_distance_mm) == (
        1,
        50.8,
        4.8,
        0.0,
    )
    assert FIELDS["pixel_size_um"].unit == "um" and FIELDS["d1_mm"].nullable


def test_simulate_relay_takes_a_design_and_options_as_the_old_keywords():
    mis = {"m2_tilt_x": 0.02}
    old = simulate_relay(2, n=5, rings=2, pixel_size_um=5.0, orientation="Z", misalignment=mis).summary
    design = RelayDesign(setup=2, orientation="Z", pixel_size_um=5.0)
    new = simulate_relay(design, SimulationOptions(n=5, rings=2), misalignment=mis).summary
    assert new == old
    assert new["relay"]["orientation"] == "Z" and new["grid"]["pixel_size_um"] == 5.0


def test_simulate_relay_refuses_an_unknown_option():
    with pytest.raises(TypeError):
        simulate_relay(1, n=5, ringz=2)


def test_relay_distortion_takes_a_design_as_the_old_keywords():
    import numpy as np

    from oapcal.optics.field import relay_distortion

    mis = {"m1_tilt_y": 0.01}
    old = relay_distortion(None, d1_mm=700.0, pixel_size_um=5.0, grid=16, misalignment=mis)
    new = relay_distortion(RelayDesign(setup=None, d1_mm=700.0, pixel_size_um=5.0), grid=16, misalignment=mis)
    xy = np.array([[10.0, 20.0], [320.0, 240.0], [600.0, 400.0]])
    assert new.pixel_size_um == 5.0 and np.array_equal(new.forward(xy), old.forward(xy))
    with pytest.raises(TypeError, match="focal_lenght_mm"):
        relay_distortion(1, focal_lenght_mm=50.8)
