"""Labelling by hand: the target registered from a few clicked corners (no viewer needed)."""

import numpy as np
import pytest

import oapcal
from oapcal.errors import DataError
from oapcal.napari_plugin._labelling import propose_corners

#: Four corners spread over groups 4 and 5, both triplet directions.
CLICKED = ("G4E2H0C0", "G4E6V2C2", "G5E1V0C0", "G5E6H2C2")


def _truth(demo):
    return dict(zip(demo["ids"], demo["xy_d"]))


def test_four_clicks_propose_every_visible_corner_near_the_truth(demo):
    truth = _truth(demo)
    clicks = {i: tuple(truth[i]) for i in CLICKED}
    prop = propose_corners(clicks, (640, 480), "4-5")
    assert set(prop.ids) >= set(demo["ids"]) - {i for i in demo["ids"] if truth[i].min() < 3}
    index = {i: k for k, i in enumerate(prop.ids)}
    for i in CLICKED:  # clicked corners stay where they were clicked
        np.testing.assert_array_equal(prop.xy_d[index[i]], truth[i])
        assert prop.clicked[index[i]]
    assert prop.clicked.sum() == len(CLICKED) and prop.map_kind == "affine"
    err = np.array([np.hypot(*(prop.xy_d[index[i]] - truth[i])) for i in demo["ids"] if i in index])
    # an affine map through 4 corners cannot follow the relay's ~40 px distortion exactly,
    # but puts every corner within a bar width or so (G5 bars are 3.3-6.5 px wide)
    assert np.median(err) < 8 and err.max() < 20
    assert prop.orientation == "rot180" and not prop.mirrored
    assert prop.um_per_px == pytest.approx(demo["um_per_px"], rel=0.05)


def test_many_clicks_use_a_quadratic_map_that_follows_the_distortion(demo):
    truth = _truth(demo)
    picks = demo["ids"][:: max(1, len(demo["ids"]) // 12)][:12]
    prop = propose_corners({i: tuple(truth[i]) for i in picks}, (640, 480), (4, 5))
    assert prop.map_kind == "quadratic"
    index = {i: k for k, i in enumerate(prop.ids)}
    err = np.array([np.hypot(*(prop.xy_d[index[i]] - truth[i])) for i in demo["ids"] if i in index])
    assert np.median(err) < 2.0


def test_the_reference_points_follow_detections_convention(demo):
    truth = _truth(demo)
    prop = propose_corners({i: tuple(truth[i]) for i in CLICKED}, (640, 480), (4, 5), um_per_px=4.8)
    expected = oapcal.usaf_target((4, 5)).reference_px(4.8, (640, 480), "rot180")
    ids = oapcal.usaf_target((4, 5)).corner_ids
    index = {i: k for k, i in enumerate(ids)}
    np.testing.assert_allclose(prop.xy_u, expected[[index[i] for i in prop.ids]])


@pytest.mark.parametrize(
    "clicks,match",
    [
        ({"G4E2H0C0": (1, 2), "G9E9H9C9": (3, 4), "G4E3H0C0": (5, 6)}, "unknown corner id 'G9E9H9C9'"),
        ({"G4E2H0C0": (1, 2), "G4E3H0C0": (5, 6)}, "at least 3 corners"),
        ({"G4E2H0C0": (1, 2), "G4E2H1C0": (5, 2), "G4E2H2C0": (9, 2)}, "one line"),
    ],
)
def test_bad_clicks_are_named(clicks, match):
    with pytest.raises(DataError, match=match):
        propose_corners(clicks, (640, 480), (4, 5))
