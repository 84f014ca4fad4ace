"""Everything that evaluates a model takes a :class:`oapcal.model.Model` (or a calibration,
or, as before, a bare vector of a built-in family), and gives the same numbers each way;
a vector of no family is refused by name instead of being taken for Eq. (1)."""

import numpy as np
import pytest

from oapcal.errors import DataError, ModelSpecError
from oapcal.imaging.field import DistortionField, ModelDistortionField, PixelField, setup1_like_field
from oapcal.imaging.remap import correction_map, output_geometry
from oapcal.imaging.render import Camera, Placement, Scene
from oapcal.model import (
    BROWN_CONRADY,
    BROWN_CONRADY_POSE,
    Model,
    as_model,
    distort,
    family_of,
    family_of_spec,
    params_from_dict,
)
from oapcal.uncertainty import position_covariance

P = params_from_dict({"k1": 2e-7, "p1": 1e-6, "s3": -3e-6, "x_off": -4.0, "c_x": 2.0, "c_y": -1.0, "m": 1.01})
FREE = ("k1", "p1", "s3", "x_off", "c_x", "c_y", "m")
XY = np.random.default_rng(3).uniform([0, 0], [639, 479], (40, 2))


def test_family_of_refuses_a_vector_of_no_family():
    assert family_of(np.zeros(13)) is BROWN_CONRADY and family_of(np.zeros((5, 14))) is BROWN_CONRADY_POSE
    for n in (0, 3, 12, 15, 37):
        with pytest.raises(ModelSpecError, match=r"13\) brown-conrady, \(\.\.\., 14\)"):
            family_of(np.zeros(n))
    with pytest.raises(ModelSpecError):
        distort(XY, np.zeros(12))  # was: taken for Eq. (1), then a shape error


def test_as_model_adapts_models_records_and_legacy_vectors():
    m = Model("brown-conrady", P, FREE)
    assert as_model(m) is m
    legacy = as_model(P)
    assert legacy.family is BROWN_CONRADY and legacy.free == ()
    np.testing.assert_array_equal(legacy.params, P)

    class Record:  # a fitted record written before Model (params, free)
        params, free = P, FREE

    assert as_model(Record()).free == FREE
    with pytest.raises(ModelSpecError, match="brown-conrady model was given where"):
        as_model(m, "relay")
    assert family_of_spec("paper+rotation") is BROWN_CONRADY_POSE and family_of_spec("paper") is BROWN_CONRADY


def test_distortion_field_takes_any_model_and_keeps_the_vector_form():
    posed = Model("brown-conrady", P, FREE).with_pose(3.0)
    field = ModelDistortionField(posed, 4.8, (640, 480))
    assert field.model is posed and field.params.shape == (14,)
    np.testing.assert_array_equal(field.forward(XY), posed(XY))
    np.testing.assert_allclose(field.inverse(field.forward(XY)), XY, atol=1e-8)
    np.testing.assert_array_equal(ModelDistortionField(P).forward(XY), distort(XY, P))
    assert isinstance(setup1_like_field(), PixelField) and DistortionField is PixelField
    with pytest.raises(DataError, match="13, 14, 36 or 39 values"):
        ModelDistortionField(np.zeros(12))


def test_correction_map_and_geometry_same_from_a_model_or_a_vector():
    m = Model("brown-conrady", P, FREE)
    a = correction_map(m, (48, 64), extent="full")
    b = correction_map(P, (48, 64), extent="full")
    assert a.geometry == b.geometry == output_geometry(P, (48, 64), extent="full")
    np.testing.assert_array_equal(a.map_x, b.map_x)
    np.testing.assert_array_equal(a.map_y, b.map_y)
    posed = m.with_pose(2.0)
    mx, my = correction_map(posed, (48, 64))
    gx, gy = np.meshgrid(np.arange(64.0), np.arange(48.0))
    want = posed(np.stack([gx, gy], -1))
    np.testing.assert_allclose(mx, want[..., 0], atol=1e-3)
    np.testing.assert_allclose(my, want[..., 1], atol=1e-3)


def test_uncertainty_and_rendering_take_a_model():
    m = Model("brown-conrady", P, ("k1", "c_x", "m"))
    cov = np.diag([1e-16, 0.01, 1e-6])
    np.testing.assert_array_equal(
        position_covariance(XY, m, cov), position_covariance(XY, P, cov, ("k1", "c_x", "m"))
    )
    scene = Scene(m, Placement(4.8, (31.5, 23.5)), Camera(size=(64, 48), snr=None, sigma_px=0))
    assert scene.model is m
    np.testing.assert_array_equal(scene.camera_from_reference(XY), distort(XY, P))
