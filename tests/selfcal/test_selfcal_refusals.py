"""Self-calibration refuses frames it cannot use: no texture, too little overlap, a moving
sample, too few frames for the model; and known steps of the wrong sign."""

import numpy as np
import pytest
from selfcal_scenes import grid_moves, render_moves, texture, truth_params

from oapcal.selfcal import SelfcalRefused, find_matches, self_calibrate


def test_no_texture():
    rng = np.random.default_rng(0)
    frames = [np.clip(100 + rng.normal(0, 2, (150, 200)), 0, 255).astype(np.uint8) for _ in range(5)]
    with pytest.raises(SelfcalRefused, match="frame 0 has no texture") as info:
        find_matches(frames)
    assert info.value.reason == "texture"
    with pytest.raises(SelfcalRefused, match="no texture"):
        find_matches([np.full((150, 200), 7, np.uint8)] * 3)


def test_too_little_overlap(scene_frames):
    frames = [scene_frames[i] for i in (4, 5, 7, 8, 9)]  # the last far from the others
    with pytest.raises(SelfcalRefused, match="frame 4 overlaps too little") as info:
        find_matches(frames)
    assert info.value.reason == "overlap"


def test_too_few_frames(scene_frames):
    frames = scene_frames[3:5]
    with pytest.raises(SelfcalRefused, match="2 frames are too few") as info:
        self_calibrate(find_matches(frames), "radial")
    assert info.value.reason == "frames"


def test_moves_along_one_line(scene_frames):
    frames = scene_frames[3:6]
    with pytest.raises(SelfcalRefused, match="along one line") as info:
        self_calibrate(find_matches(frames), "radial")
    assert info.value.reason == "frames"


def test_too_few_matches_for_the_model(scene_frames):
    frames = [scene_frames[i] for i in (4, 5, 7)]
    matches = find_matches(frames, max_per_pair=20)
    with pytest.raises(SelfcalRefused, match="too few for") as info:
        self_calibrate(matches, "full")
    assert info.value.reason == "frames"


def test_moving_sample():
    """Half the scene shifts by 3 px in every other frame: not one rigid scene."""
    moves = grid_moves()[[1, 3, 4, 5, 7]]
    tex = texture(1)
    frames = []
    moved = tex.copy()
    moved[:, tex.shape[1] // 2 :] = np.roll(tex, 3, axis=1)[:, tex.shape[1] // 2 :]
    for i, move in enumerate(moves):
        frames += render_moves(truth_params(), [move], moved if i % 2 else tex, seed=i)
    with pytest.raises(SelfcalRefused, match="not views of one rigid, static scene") as info:
        self_calibrate(find_matches(frames), "radial")
    assert info.value.reason == "moving"
