"""Rendered scenes shared by the self-calibration tests (rendered once per session)."""

import numpy as np
import pytest
from selfcal_scenes import grid_moves, render_moves, texture, truth_params

from oapcal.model import identity_params

#: A tenth frame far from the others (it shares 7.5 % x 6.7 % of the frame with frame 8).
FAR_MOVE = (185.0, 140.0)


@pytest.fixture(scope="session")
def scene_frames():
    """Frames 0-8: the 3 x 3 grid of moves through the Eq. (1) truth; frame 9: far away."""
    moves = np.vstack([grid_moves(), [FAR_MOVE]])
    return render_moves(truth_params(), moves, texture(0))


@pytest.fixture(scope="session")
def distorted(scene_frames):
    """Matches of the 9 grid frames."""
    from oapcal.selfcal import find_matches

    return find_matches(scene_frames[:9])


@pytest.fixture(scope="session")
def flat():
    """Matches of 9 frames without distortion: the frames differ by pure translations."""
    from oapcal.selfcal import find_matches

    return find_matches(render_moves(identity_params(), grid_moves(), texture(0)))
