"""Self-calibration refuses frames it cannot use: no texture, too little overlap, a moving
sample, too few frames for the model; and known steps of the wrong sign."""

import numpy as np
import pytest
from selfcal_scenes import PIXEL_UM, grid_moves, render_moves, texture, truth_params

from oapcal.selfcal import SelfcalRefused, find_matches, self_calibrate


@pytest.fixture(scope="module")
def tex():
    return texture(1)


def test_no_texture():
    rng = np.random.default_rng(0)
    frames = [np.clip(100 + rng.normal(0, 2, (150, 200)), 0, 255).astype(np.uint8) for _ in range(5)]
    with pytest.raises(SelfcalRefused, match="frame 0 has no texture") as info:
        find_matches(frames)
    assert info.value.reason == "texture"
    with pytest.raises(SelfcalRefused, match="no texture"):
        find_matches([np.full((150, 200), 7, np.uint8)] * 3)


def test_too_little_overlap(tex):
    moves = np.array([(0.0, 0.0), (30.0, 0.0), (0.0, 30.0), (30.0, 30.0), (185.0, 140.0)])
    frames = render_moves(truth_params(), moves, tex)
    with pytest.raises(SelfcalRefused, match="frame 4 overlaps too little") as info:
        find_matches(frames)
    assert info.value.reason == "overlap"


def test_too_few_frames(tex):
    frames = render_moves(truth_params(), [(0.0, 0.0), (40.0, 20.0)], tex)
    with pytest.raises(SelfcalRefused, match="2 frames are too few") as info:
        self_calibrate(find_matches(frames), "radial")
    assert info.value.reason == "frames"


def test_moves_along_one_line(tex):
    frames = render_moves(truth_params(), [(0.0, 0.0), (30.0, 0.0), (60.0, 0.0), (-30.0, 0.0)], tex)
    with pytest.raises(SelfcalRefused, match="along one line") as info:
        self_calibrate(find_matches(frames), "radial")
    assert info.value.reason == "frames"


def test_too_few_matches_for_the_model(tex):
    frames = render_moves(truth_params(), [(0.0, 0.0), (40.0, 0.0), (0.0, 30.0)], tex)
    matches = find_matches(frames, max_per_pair=20)
    with pytest.raises(SelfcalRefused, match="too few for") as info:
        self_calibrate(matches, "full")
    assert info.value.reason == "frames"


def test_moving_sample(tex):
    """Half the scene shifts by 3 px in every other frame: not one rigid scene."""
    moves = grid_moves()
    frames = []
    moved = tex.copy()
    moved[:, tex.shape[1] // 2 :] = np.roll(tex, 3, axis=1)[:, tex.shape[1] // 2 :]
    for i, move in enumerate(moves):
        frames += render_moves(truth_params(), [move], moved if i % 2 else tex, seed=i)
    with pytest.raises(SelfcalRefused, match="not views of one rigid, static scene") as info:
        self_calibrate(find_matches(frames), "radial")
    assert info.value.reason == "moving"


def test_steps_of_the_wrong_sign_are_refused(tex):
    """The sign convention: steps are where the sample's image moves; their negatives do not fit."""
    matches = find_matches(render_moves(truth_params(), grid_moves(), tex))
    right = self_calibrate(matches, "radial", steps_um=grid_moves() * PIXEL_UM, um_per_px=PIXEL_UM)
    assert right.calibration.residuals.rms_px < 0.1
    with pytest.raises(SelfcalRefused) as info:
        self_calibrate(
            matches, "radial", steps_um=-grid_moves() * PIXEL_UM, um_per_px=PIXEL_UM, stage_rotation=False
        )
    assert info.value.reason == "moving"
