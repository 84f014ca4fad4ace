"""Self-calibration recovers known truth on seeded renders; its gauge statements hold."""

import numpy as np
import pytest
from selfcal_scenes import PIXEL_UM, affine_error, frame_points, grid_moves, truth_params

from oapcal.model import undistort
from oapcal.selfcal import SelfcalRefused, self_calibrate
from oapcal.selfcal.solve import initial_translations


def _moves(result):
    return result.translations - result.translations[0]


def test_pure_translation_gives_the_identity(flat):
    d = frame_points()
    true_moves = grid_moves() - grid_moves()[0]
    # known steps (paper): the steps fix scale and aspect, so the identity itself
    result = self_calibrate(flat, "paper", steps_um=grid_moves() * PIXEL_UM, um_per_px=PIXEL_UM)
    u = undistort(d, result.calibration.params).xy
    assert np.abs(u - d).max() < 0.03
    assert np.abs(_moves(result) - true_moves).max() < 0.05
    assert result.calibration.residuals.rms_px < 0.05
    # unknown moves (radial): the identity up to the affine gauge. Without distortion the data
    # leave radial's centre free; it runs away with k1 -> 0, which acts as a scale and a
    # small aspect (0.2 % at 15,000 px), and the gauge report says so
    result = self_calibrate(flat, "radial")
    u = undistort(d, result.calibration.params).xy
    assert affine_error(u, d).max() < 0.03
    moves = _moves(result)
    a = np.linalg.lstsq(true_moves, moves, rcond=None)[0]  # the moves' linear gauge
    assert np.abs(true_moves @ a - moves).max() < 0.05
    assert np.abs(a - np.eye(2)).max() < 0.01
    assert result.calibration.residuals.rms_px < 0.05
    aspect = next(line for line in result.gauge if line.startswith("aspect"))
    assert result.gauge_left["aspect"] > 0.5 or "weakly determined" in aspect


@pytest.mark.slow  # the centre runs away: ~200 iterations (4-9 s)
def test_pure_translation_unknown_moves_paper_is_the_identity_up_to_an_affine(flat):
    # paper can absorb most of an aspect change (its centre running away): the frames leave
    # it nearly free, and the gauge report says so
    result = self_calibrate(flat, "paper")
    d = frame_points()
    u = undistort(d, result.calibration.params).xy
    assert affine_error(u, d).max() < 0.03
    assert result.gauge_left["aspect"] < 0.1
    assert any(
        line.startswith("aspect: weakly determined") or "not determined" in line
        for line in result.gauge
        if line.startswith("aspect")
    )


@pytest.mark.parametrize("model", ["radial", "paper"])
def test_known_truth_recovered_unknown_moves(distorted, model):
    truth = truth_params()
    d = frame_points()
    v = undistort(d, truth).xy
    # the truth bends the frame by ~1.8 px beyond an affine map: the test can fail
    assert affine_error(d, v).max() > 1.5
    result = self_calibrate(distorted, model)
    u = undistort(d, result.calibration.params).xy
    err = affine_error(u, v)
    assert err.mean() < 0.02 and err.max() < 0.08
    # the moves (1/4 field apart) are recovered, in the truth's scale (m pinned at 1 = the truth's)
    assert np.abs(_moves(result) - (grid_moves() - grid_moves()[0])).max() < 0.1
    assert result.calibration.fit.converged


def test_known_steps_fix_scale_and_aspect(distorted):
    truth = truth_params()
    steps = grid_moves() * PIXEL_UM
    result = self_calibrate(distorted, "radial", steps_um=steps, um_per_px=PIXEL_UM)
    names = result.calibration.family.param_names
    m = result.calibration.params[names.index("m")]
    assert m == pytest.approx(1.0, rel=1e-3)  # the truth's m
    ux, uy = result.um_per_px_centre
    # the truth's own um per px at the centre, from its inverse's Jacobian (finite differences)
    c = np.array([[99.5, 74.5]])
    h = 1e-3
    jx = (undistort(c + [h, 0], truth).xy - undistort(c - [h, 0], truth).xy)[0] / (2 * h)
    jy = (undistort(c + [0, h], truth).xy - undistort(c - [0, h], truth).xy)[0] / (2 * h)
    assert ux == pytest.approx(PIXEL_UM * np.linalg.norm(jx), rel=1e-3)
    assert uy == pytest.approx(PIXEL_UM * np.linalg.norm(jy), rel=1e-3)
    assert abs(result.stage_rotation_deg) < 0.05
    d = frame_points()
    u = undistort(d, result.calibration.params).xy
    v = undistort(d, truth).xy
    assert np.linalg.norm(u - v - (u - v).mean(0), axis=1).max() < 0.1


def test_scale_is_a_gauge_without_steps(distorted):
    """With unknown moves a scaled correction and scaled moves fit the matches exactly as
    well, relative to the scale (every residual scales by s): the frames cannot fix it."""
    result = self_calibrate(distorted, "radial")
    p = np.array(result.calibration.params)
    names = list(result.calibration.family.param_names)
    m, t = distorted, result.translations

    def residuals(params, moves):
        ua = undistort(m.xy_a, params).xy
        ub = undistort(m.xy_b, params).xy
        return ua - moves[m.frame_a] - ub + moves[m.frame_b]

    s = 1.37
    q = p.copy()
    q[names.index("m")] /= s  # D(r / s): m(r/s + off) = (m/s)(r + s off)
    q[names.index("x_off")] *= s
    q[names.index("y_off")] *= s
    np.testing.assert_allclose(residuals(q, s * t), s * residuals(p, t), atol=1e-7)
    # the measured gauge: the model absorbs a scale exactly, not an aspect change or a shear
    assert result.gauge_left["scale"] < 1e-6
    assert result.gauge_left["aspect"] > 0.5 and result.gauge_left["shear"] > 0.5
    assert any(line.startswith("scale:") and "not determined" in line for line in result.gauge)


def test_rotation_is_a_gauge_without_steps(distorted):
    result = self_calibrate(distorted, "radial+rotation")
    assert result.gauge_left["rotation"] < 1e-6 and result.gauge_left["scale"] < 1e-6
    names = result.calibration.family.param_names
    assert result.calibration.params[names.index("rotation")] == 0.0  # pinned
    plain = self_calibrate(distorted, "radial")
    assert plain.gauge_left["rotation"] > 0.5  # Eq. (1) alone cannot turn: fixed by its form


def test_initial_translations_from_matches(distorted):
    t = initial_translations(distorted)
    # within the distortion (a few px) of the true moves
    assert np.abs(t - (grid_moves() - grid_moves()[0])).max() < 3.0


def test_steps_of_the_wrong_sign_are_refused(distorted):
    """The sign convention: steps are where the sample's image moves; their negatives do not fit."""
    right = self_calibrate(distorted, "radial", steps_um=grid_moves() * PIXEL_UM, um_per_px=PIXEL_UM)
    assert right.calibration.residuals.rms_px < 0.1
    with pytest.raises(SelfcalRefused) as info:
        self_calibrate(
            distorted, "radial", steps_um=-grid_moves() * PIXEL_UM, um_per_px=PIXEL_UM, stage_rotation=False
        )
    assert info.value.reason == "moving"
