"""The propagated positional uncertainty against a Monte Carlo over noisy data sets."""

import numpy as np
import pytest

from oapcal.calibration import calibrate
from oapcal.fitting import fit_batch, initial_params
from oapcal.model import distort, parse_model, undistort
from oapcal.synthetic import EXAMPLE_TRUTH, synthetic_pairs
from oapcal.uncertainty import inside_hull, position_covariance, uncertainty_map


def test_propagated_sigma_matches_scatter_of_refits():
    """Refit 150 independent noise realisations; at a few output pixels, the true position
    of what each corrected image shows there, undistort(distort(u; p_b); p_true), scatters
    as the linear propagation of one fit's covariance predicts."""
    rng = np.random.default_rng(7)
    data = synthetic_pairs(seed=1, noise_px=0.5)
    n_trials = 150
    xy_d = data.xy_d_true + rng.normal(0.0, 0.5, (n_trials,) + data.xy_d_true.shape)
    mask = parse_model("paper")
    p0 = np.stack([initial_params("pixel", data.xy_u, xy_d[b], mask) for b in range(n_trials)])
    batch = fit_batch(data.xy_u, xy_d, np.repeat(mask[None], n_trials, 0), p0)
    assert batch.converged.all()
    u = np.array([[320.0, 240.0], [60.0, 60.0], [600.0, 440.0], [5.0, 470.0]])  # last: outside
    true_pos = np.stack([undistort(distort(u, p), EXAMPLE_TRUTH).xy for p in batch.params])
    empirical = np.sqrt(true_pos.var(axis=0).sum(axis=-1))
    cal = calibrate(data.xy_u, xy_d[0], "paper")
    cov = position_covariance(u, cal.params, cal.covariance, cal.free)
    predicted = np.sqrt(cov[:, 0, 0] + cov[:, 1, 1])
    # 150 samples estimate a standard deviation to about 6%; one fit's covariance adds a bit.
    np.testing.assert_allclose(predicted, empirical, rtol=0.2)


def test_map_shape_units_and_hull_flags():
    data = synthetic_pairs(seed=3)
    cal = calibrate(data.xy_u, data.xy_d, "paper", image_size=(640, 480), um_per_px=4.8)
    umap = uncertainty_map(cal, step=16)
    assert umap.sigma_px.shape == (30, 40)
    np.testing.assert_allclose(umap.sigma_um, 4.8 * umap.sigma_px)
    np.testing.assert_allclose(umap.sigma_px**2, umap.sigma_x_px**2 + umap.sigma_y_px**2)
    assert (umap.sigma_major_px <= umap.sigma_px + 1e-12).all()
    assert (umap.sigma_major_px >= umap.sigma_px / np.sqrt(2) - 1e-12).all()
    # Reference points span about 37..603 x 37..443 px: corners outside, centre inside.
    assert umap.outside_hull[0, 0] and umap.outside_hull[-1, -1] and not umap.outside_hull[15, 20]
    s = umap.summary()
    assert s["outside_max_px"] > s["inside_median_px"]


def test_inside_hull_hand_cases():
    tri = np.array([[0.0, 0.0], [4.0, 0.0], [0.0, 4.0]])
    pts = np.array([[1.0, 1.0], [2.0, 2.0], [2.1, 2.1], [-0.1, 1.0]])
    assert inside_hull(pts, tri).tolist() == [True, True, False, False]


def test_zero_covariance_gives_zero_sigma():
    cov = position_covariance(np.array([[10.0, 20.0]]), EXAMPLE_TRUTH, np.zeros((8, 8)),
                              ("k1", "p1", "s3", "x_off", "y_off", "c_x", "c_y", "m"))  # fmt: skip
    assert cov.shape == (1, 2, 2) and np.all(cov == 0)
    with pytest.raises(ValueError, match="covariance must be 8 x 8"):
        position_covariance(
            np.zeros((1, 2)), EXAMPLE_TRUTH, np.zeros((3, 3)), tuple("k1 p1 s3 x_off y_off c_x c_y m".split())
        )
