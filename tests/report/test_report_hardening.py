"""Calibrations that load everywhere else also make a report (issue 24, item 15): a hull
without area (collinear or repeated vertices) and frames one or a few pixels wide."""

import dataclasses
import json

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import oapcal
from oapcal.report import build_report
from oapcal.synthetic import synthetic_pairs
from oapcal.uncertainty import inside_hull, uncertainty_map


@pytest.fixture(scope="module")
def calibration():
    data = synthetic_pairs(n_x=6, n_y=5, seed=3)
    return oapcal.calibrate(data.xy_u, data.xy_d, "paper", um_per_px=4.8, image_size=(640, 480))


FLAT_HULLS = {
    "collinear": [[0.0, 0.0], [100.0, 100.0], [200.0, 200.0]],
    "repeated": [[5.0, 5.0]] * 4,
    "horizontal": [[0.0, 10.0], [50.0, 10.0], [640.0, 10.0], [300.0, 10.0]],
}


@pytest.mark.parametrize("kind", sorted(FLAT_HULLS))
def test_a_hull_without_area_contains_nothing_and_the_report_says_so(calibration, kind, tmp_path):
    path = tmp_path / "c.json"
    oapcal.save_calibration(calibration, path)
    doc = json.loads(path.read_text())
    doc["hull"] = FLAT_HULLS[kind]
    path.write_text(json.dumps(doc))
    cal = oapcal.load_calibration(path)  # the loader accepts it, as every command does
    umap = uncertainty_map(cal, (48, 64), step=8)
    assert umap.outside_hull.all()  # no pixel is inside a region of no area
    if kind == "collinear":  # the whole report once (its figures take a few seconds)
        html, data = build_report(dataclasses.replace(cal, image_size=(64, 48)))
        assert html.startswith("<!DOCTYPE html>") and data.uncertainty


def test_inside_hull_agrees_on_a_thin_but_real_triangle():
    thin = np.array([[0.0, 0.0], [100.0, 0.0], [50.0, 1e-3]])
    assert inside_hull(np.array([[50.0, 1e-4], [50.0, 1e-2]]), thin).tolist() == [True, False]


@pytest.mark.parametrize("size", [(1, 1), (40, 1)])
def test_a_report_on_a_frame_one_pixel_high(calibration, size):
    html, data = build_report(dataclasses.replace(calibration, image_size=size))
    assert html.startswith("<!DOCTYPE html>") and data.uncertainty


@pytest.mark.slow
@settings(max_examples=6, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(width=st.integers(1, 40), height=st.integers(1, 3))
def test_a_report_on_any_frame_size_from_one_pixel(calibration, width, height):
    for size in ((width, height), (height, width)):  # thin both ways
        html, data = build_report(dataclasses.replace(calibration, image_size=size))
        assert html.startswith("<!DOCTYPE html>") and data.uncertainty
