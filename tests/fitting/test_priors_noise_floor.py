"""The noise floor of the priors' weighting (relay_model.NOISE_FLOOR_PX): a MAP relay fit
to landmarks without noise converges, and a floor set by the user is used and recorded."""

import numpy as np
import pytest

from oapcal.errors import ModelSpecError
from oapcal.model import distort
from oapcal.optics.relay_model import NOISE_FLOOR_PX, RelayDesign, calibrate_relay, parse_priors, relay_params

DESIGN = RelayDesign(setup=1, centre=(319.5, 239.5))
MISALIGNMENT = {"m2_tilt_x": 0.03, "m1_tilt_y": -0.04, "m2_decentre_y": 0.15, "d1": 20.0,
                "camera_tilt_x": 0.6, "camera_defocus": 0.12, "m1_decentre_x": -0.1}  # fmt: skip


def _noise_free_grid(n=11):
    """An n x n grid over the 1 mm field traced through a misaligned relay, no noise."""
    truth = relay_params(DESIGN, MISALIGNMENT, {"rotation": 0.4})
    g = np.stack(np.meshgrid(np.linspace(215.0, 424.0, n), np.linspace(135.0, 344.0, n)), -1).reshape(-1, 2)
    return g, distort(g, truth)


def test_relay_all_with_default_priors_converges_on_a_noise_free_grid():
    """Without the floor the estimated noise fell to 2e-5 px, the priors became rigid and this
    fit ended at the iteration cap (1,000 Jacobians) unconverged."""
    xy_u, xy_d = _noise_free_grid()
    cal = calibrate_relay(xy_u, xy_d, DESIGN, "all", priors="default")
    assert cal.fit.converged, cal.fit.message
    assert cal.fit.n_iter < 200
    # the noise that weighed the rows is the floor: the residuals' own estimate is far below it
    assert cal.priors["noise_used_px"] == NOISE_FLOOR_PX == 0.05
    assert cal.priors["noise_floor_px"] == NOISE_FLOOR_PX
    assert np.sqrt(cal.fit.rss / cal.fit.n_residuals) < 0.05 * NOISE_FLOOR_PX
    # and the grid is reproduced (the priors at the floor's weight barely pull)
    assert np.abs(distort(xy_u, cal.params) - xy_d).max() < 0.01


def test_the_floor_is_a_priors_word_and_a_given_noise_is_used_as_given():
    xy_u, xy_d = _noise_free_grid(n=9)
    cal = calibrate_relay(xy_u, xy_d, DESIGN, "default", priors="noise_floor_px=0.2")
    assert cal.fit.converged and cal.priors["noise_used_px"] == 0.2
    given = calibrate_relay(xy_u, xy_d, DESIGN, "default", priors="noise_px=0.01")
    assert given.priors["noise_used_px"] == 0.01
    assert parse_priors("default").noise_floor_px == NOISE_FLOOR_PX
    assert parse_priors({"noise_floor_px": 0}).noise_floor_px == 0.0
    for bad, match in (("noise_floor_px=-1", ">= 0"), ("noise_floor_px=inf", "number of px")):
        with pytest.raises(ModelSpecError, match=match):
            parse_priors(bad)


def test_an_estimate_above_the_floor_is_not_changed():
    """0.3 px noise: the floor does not enter (the noise used is the estimate)."""
    xy_u, xy_d = _noise_free_grid(n=9)
    rng = np.random.default_rng(4)
    noisy = xy_d + rng.normal(0, 0.3, xy_d.shape)
    cal = calibrate_relay(xy_u, noisy, DESIGN, "default", priors="default")
    assert 0.2 < cal.priors["noise_used_px"] < 0.4
