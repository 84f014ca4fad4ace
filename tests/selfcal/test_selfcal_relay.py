"""Self-calibration with the relay model on frames rendered through a misaligned relay
(small frames of large pixels, so that the frame still spans the relay's 3 x 2.3 mm field)."""

import numpy as np
import pytest
from selfcal_scenes import TEXTURE_UM, affine_error, texture

from oapcal.imaging.render import Camera, Placement, Scene, render_scene
from oapcal.model import undistort
from oapcal.optics.relay_model import RelayDesign, relay_params
from oapcal.selfcal import find_matches, self_calibrate

SIZE = (160, 120)
DESIGN = RelayDesign(setup=1, pixel_size_um=19.2, centre=(79.5, 59.5))
TRUTH_MIS = {"m2_decentre_y": 0.12, "d1": 20.0, "camera_tilt_x": -0.5, "camera_tilt_y": 0.8,
             "camera_defocus": 0.15, "m1_tilt_x": 0.02}  # fmt: skip


def _frames(truth, moves_px, tex):
    rows, cols = tex.shape
    centre = np.array([(cols - 1) / 2.0, (rows - 1) / 2.0])
    scene0 = Scene(
        truth, Placement(TEXTURE_UM * 4, tuple(centre)), Camera(size=SIZE, snr=200.0, sigma_px=0.7)
    )
    mat, _ = scene0.paraxial()
    out = []
    for i, move in enumerate(moves_px):
        src = centre - mat @ np.asarray(move, float) / (TEXTURE_UM * 4)
        scene = Scene(truth, Placement(TEXTURE_UM * 4, tuple(src)), scene0.camera)
        out.append(render_scene(tex, scene, seed=i).image)
    return out


@pytest.mark.slow
def test_relay_truth_recovered_and_its_gauge():
    truth = relay_params(DESIGN, TRUTH_MIS)
    moves = np.array([(i * 40.0, j * 30.0) for j in (-1, 0, 1) for i in (-1, 0, 1)])
    matches = find_matches(_frames(truth, moves, texture(3)), prior=relay_params(DESIGN))
    gx, gy = np.meshgrid(np.arange(0, SIZE[0], 4.0), np.arange(0, SIZE[1], 4.0))
    d = np.stack([gx.ravel(), gy.ravel()], -1)
    v = undistort(d, truth).xy
    design_err = affine_error(undistort(d, relay_params(DESIGN)).xy, v)
    result = self_calibrate(matches, "relay", design=DESIGN)
    err = affine_error(undistort(d, result.calibration.params).xy, v)
    assert design_err.max() > 1.0  # the misalignment matters: the test can fail
    assert err.mean() < 0.05 and err.max() < 0.25
    assert result.gauge_left["scale"] < 1e-6 and result.gauge_left["rotation"] < 1e-6
    names = result.calibration.family.param_names
    assert result.calibration.params[names.index("scale")] == 1.0
    steps = self_calibrate(matches, "relay", design=DESIGN, steps_um=moves * DESIGN.object_um_per_px)
    # the known steps give the truth's object um per px at the centre (its inverse's Jacobian)
    c, h = np.array([[79.5, 59.5]]), 1e-3
    jx = (undistort(c + [h, 0], truth).xy - undistort(c - [h, 0], truth).xy)[0] / (2 * h)
    jy = (undistort(c + [0, h], truth).xy - undistort(c - [0, h], truth).xy)[0] / (2 * h)
    ux, uy = steps.um_per_px_centre
    assert ux == pytest.approx(DESIGN.object_um_per_px * np.linalg.norm(jx), rel=2e-3)
    assert uy == pytest.approx(DESIGN.object_um_per_px * np.linalg.norm(jy), rel=2e-3)
