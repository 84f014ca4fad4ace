"""The model as a value (:class:`oapcal.model.Model`): it is the functions it wraps,
carries its family by name, and refuses what is not a model of that family."""

import numpy as np
import pytest

from oapcal.errors import ModelSpecError
from oapcal.model import (
    BROWN_CONRADY_POSE,
    Model,
    distort,
    family_named,
    jacobian_point,
    params_from_dict,
    undistort,
)

P = params_from_dict(
    {"k1": 2e-7, "p1": 1e-6, "s3": -3e-6, "x_off": -4.0, "c_x": 320.0, "c_y": 240.0, "m": 1.01}
)
FREE = ("k1", "p1", "s3", "x_off", "c_x", "c_y", "m")
XY = np.random.default_rng(1).uniform([-300, -220], [300, 220], (50, 2))


def test_model_is_the_functions_it_wraps():
    m = Model("brown-conrady", P, FREE)
    np.testing.assert_array_equal(m(XY), distort(XY, P))
    np.testing.assert_array_equal(m.jacobian(XY), jacobian_point(XY, P))
    np.testing.assert_array_equal(m.inverse(m(XY)).xy, undistort(distort(XY, P), P).xy)
    assert np.allclose(m.inverse(m(XY)).xy, XY, atol=1e-8)


def test_family_by_name_and_vector_checked():
    assert family_named("brown-conrady+rotation") is BROWN_CONRADY_POSE
    with pytest.raises(ModelSpecError, match="unknown model family"):
        family_named("zernike")
    with pytest.raises(ModelSpecError, match="has 14 parameters"):
        Model("brown-conrady+rotation", P, FREE)  # a 13-vector is not guessed to be Eq. (1)
    with pytest.raises(ModelSpecError, match="unknown parameter"):
        Model("brown-conrady", P, ("k1", "rotation"))


def test_model_is_frozen_and_orders_free_names():
    m = Model("brown-conrady", P, ("m", "k1"))
    assert m.free == ("k1", "m")
    assert m.mask.sum() == 2 and m.mask[0] and m.mask[12]
    with pytest.raises(ValueError):
        m.params[0] = 1.0  # read-only
    assert m.with_params(P * 0 + P).value("x_off") == -4.0


def test_pose_composition_rotates_the_reference_points():
    m = Model("brown-conrady", P, FREE)
    # a rotation by theta of the reference points, by hand (counter-clockwise, docs/models.md)
    t = np.deg2rad(7.0)
    rot = XY @ np.array([[np.cos(t), np.sin(t)], [-np.sin(t), np.cos(t)]])
    posed = m.with_pose(7.0)
    assert posed.family is BROWN_CONRADY_POSE and "rotation" in posed.free
    np.testing.assert_allclose(posed(XY), m(rot), atol=1e-9)
    np.testing.assert_allclose(posed.with_pose(-7.0)(XY), m(XY), atol=1e-9)
    assert Model.identity()(XY) is not None and np.allclose(Model.identity()(XY), XY)
