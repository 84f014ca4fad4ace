"""Eq. (1) with the target's in-plane rotation (``model.BROWN_CONRADY_POSE``) against the
NumPy reference of Eq. (1) applied to rotated points."""

import numpy as np

import reference_model as ref
from oapcal.fitting import fit_batch
from oapcal.model import BROWN_CONRADY_POSE, distort, jacobian_params, jacobian_point, parse_model, undistort


def _rotated(xy, deg):
    t = np.radians(deg)
    return xy @ np.array([[np.cos(t), -np.sin(t)], [np.sin(t), np.cos(t)]]).T


def _params(rng):
    p = np.zeros(14)
    size = [0.05, 0.01, 0.01, 0.01, 0.01, 0.005, 0.01, 0.005, 0.02, 0.02, 0.02, 0.02, 0.05]
    p[:13] = rng.normal(0, 1, 13) * size
    p[12] += 1.0
    p[13] = rng.uniform(-3, 3)
    return p


def test_forward_jacobians_and_inverse_match_the_reference():
    rng = np.random.default_rng(0)
    xy = rng.uniform(-0.5, 0.5, (50, 2))
    for _ in range(5):
        p = _params(rng)
        rot = _rotated(xy, p[13])
        got = distort(xy, p, family=BROWN_CONRADY_POSE)
        np.testing.assert_allclose(got, ref.distort(rot, p[:13]), atol=1e-13)
        t = np.radians(p[13])
        r = np.array([[np.cos(t), -np.sin(t)], [np.sin(t), np.cos(t)]])
        want = ref.jacobian_point(rot, p[:13]) @ r
        np.testing.assert_allclose(jacobian_point(xy, p, family=BROWN_CONRADY_POSE), want, atol=1e-12)
        cols = jacobian_params(xy, p, family=BROWN_CONRADY_POSE)
        np.testing.assert_allclose(cols[..., :13], ref.jacobian_params(rot, p[:13]), atol=1e-12)
        h = 1e-6
        up, down = ref.distort(_rotated(xy, p[13] + h), p[:13]), ref.distort(_rotated(xy, p[13] - h), p[:13])
        fd = (up - down) / (2 * h)
        np.testing.assert_allclose(cols[..., 13], fd, atol=1e-8)
        back = undistort(distort(xy, p, family=BROWN_CONRADY_POSE), p, family=BROWN_CONRADY_POSE)
        assert back.converged.all()
        np.testing.assert_allclose(back.xy, xy, atol=1e-9)


def test_a_turned_target_is_fitted_exactly():
    rng = np.random.default_rng(1)
    xy = rng.uniform(-0.5, 0.5, (200, 2))
    p = np.zeros(14)
    p[[0, 12, 13]] = [0.08, 1.01, 0.6]
    xd = distort(xy, p, family=BROWN_CONRADY_POSE)
    mask = np.append(parse_model("paper"), True)
    p0 = np.zeros(14)
    p0[12] = 1.0
    fit = fit_batch(xy, xd, mask[None], p0[None], family=BROWN_CONRADY_POSE).item(0)
    assert fit.converged
    assert abs(fit.params[13] - 0.6) < 1e-8
    # Eq. (1) alone has no rotation: it cannot fit the same points
    plain = fit_batch(xy, xd, parse_model("paper")[None], p0[None, :13]).item(0)
    assert plain.rss > 1e6 * fit.rss
