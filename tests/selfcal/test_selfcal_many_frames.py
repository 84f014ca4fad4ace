"""Many frames: the phase correlation of every pair must not depend on how many pairs came
before it (``cv2.phaseCorrelate`` given a window multiplies its inputs by it in place, so
50 frames of 2048 x 2048 were refused as "too little overlap": the later pairs correlated
frames windowed dozens of times)."""

import cv2
import numpy as np
import pytest
from selfcal_scenes import texture

from oapcal.selfcal import SelfcalRefused, find_matches
from oapcal.selfcal.matches import pair_shifts


def cut_grid(k: int, side: int, seed: int = 3):
    """``k x k`` frames of ``side`` px cut from one random texture at steps of a quarter of
    the frame (pure translations, integer px), and their true shifts: frame ``f``'s content
    lies ``moves[f]`` px further right and down than in frame 0."""
    step = side // 4
    span = (k - 1) * step
    tex = (texture(seed, (side + span + 8,) * 2) * 255).astype(np.uint8)
    moves = np.array([(i * step, j * step) for j in range(k) for i in range(k)], float)
    o = 4 + span
    frames = [tex[o - y : o - y + side, o - x : o - x + side].copy() for x, y in moves.astype(int)]
    return frames, moves


def reduced_frames(frames):
    return [f.astype(np.float32) - np.float32(f.mean()) for f in frames]


def test_pair_shifts_leave_the_frames_unchanged():
    frames, _ = cut_grid(2, 64)
    small = reduced_frames(frames)
    before = [f.copy() for f in small]
    window = cv2.createHanningWindow((64, 64), cv2.CV_32F)
    pair_shifts(small, 1.0, window)
    for f, g in zip(small, before, strict=True):
        np.testing.assert_array_equal(f, g)


def test_every_pair_as_if_alone():
    """Each pair's shift and response from the whole set equal those of the pair alone,
    and the neighbours' shifts are the true moves."""
    frames, moves = cut_grid(4, 96)
    small = reduced_frames(frames)
    window = cv2.createHanningWindow((96, 96), cv2.CV_32F)
    shifts, response = pair_shifts(small, 1.0, window)
    for a, b in [(0, 1), (5, 6), (10, 11), (14, 15), (11, 15)]:
        alone, r_alone = pair_shifts([small[a], small[b]], 1.0, window)
        np.testing.assert_allclose(shifts[a, b], alone[0, 1], atol=1e-9)
        assert response[a, b] == pytest.approx(r_alone[0, 1], abs=1e-9)
        np.testing.assert_allclose(shifts[a, b], moves[b] - moves[a], atol=0.3)


def test_sixteen_frames_all_connected():
    """A 4 x 4 grid was refused ("frame 15 overlaps too little") before the fix; now every
    frame joins and every kept pair's shift is the true move."""
    frames, moves = cut_grid(4, 128)
    matches = find_matches(frames)
    assert {p.a for p in matches.pairs} | {p.b for p in matches.pairs} == set(range(16))
    for p in matches.pairs:
        np.testing.assert_allclose(p.shift, moves[p.b] - moves[p.a], atol=0.5)
    d = matches.xy_b - matches.xy_a
    np.testing.assert_allclose(d, moves[matches.frame_b] - moves[matches.frame_a], atol=0.05)


@pytest.mark.slow
def test_fifty_frames_all_connected():
    """50 frames (a 7 x 7 grid plus one), the count of the issue's goal, at 256 px."""
    frames, moves = cut_grid(7, 256)
    frames.append(frames[24][8:, 8:].copy())
    frames[-1] = np.pad(frames[-1], ((0, 8), (0, 8)), mode="edge")
    moves = np.vstack([moves, moves[24] - 8])
    matches = find_matches(frames)
    seen = {p.a for p in matches.pairs} | {p.b for p in matches.pairs}
    assert seen == set(range(50))
    wrong = [p for p in matches.pairs if np.abs(np.subtract(p.shift, moves[p.b] - moves[p.a])).max() > 0.5]
    assert not wrong


def test_far_frame_still_refused():
    """The fix does not make the overlap test lenient: a frame far from the rest is refused."""
    frames, _ = cut_grid(2, 96)
    rng = np.random.default_rng(9)
    other = (texture(11, (96, 96)) * 255).astype(np.uint8)
    with pytest.raises(SelfcalRefused, match="overlap") as info:
        find_matches([*frames, np.clip(other + rng.normal(0, 1, other.shape), 0, 255).astype(np.uint8)])
    assert info.value.reason == "overlap"
