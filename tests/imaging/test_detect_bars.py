"""The bottom-up bar finder (``detect.bars``) at any in-plane angle: the spacing test's lower
limit takes a bar's width from its blob's second moments (the rectangle round a turned bar's
staircase edges is up to 1.1 px wider, which failed the test: the real LAB-UMK micrograph
turned by 15, 30 or 60 degrees was refused)."""

import cv2
import numpy as np
import pytest

from oapcal.imaging.detect.bars import find_bars, find_triplets

WIDTH = 5.6  # px: a bar of the triplet, the LAB-UMK micrograph's G4E4 (measured period 11.2 px)
LENGTH = 5 * WIDTH
SIZE = 160


def _triplet_image(angle_deg: float, blur: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Three bright bars (``WIDTH`` x ``LENGTH`` px, period ``2 WIDTH``) on a dark ground,
    their long axis at ``angle_deg`` from x, drawn exactly (8x supersampled, area-averaged)
    and blurred by ``blur`` px; returns the image and the bars' centres."""
    ss = 8
    phi = np.deg2rad(angle_deg)
    along = np.array([np.cos(phi), np.sin(phi)])
    normal = np.array([-np.sin(phi), np.cos(phi)])
    c = np.array([(SIZE - 1) / 2, (SIZE - 1) / 2])
    centres = np.array([c + k * 2 * WIDTH * normal for k in (-1, 0, 1)])
    big = np.zeros((SIZE * ss, SIZE * ss), np.float32)
    for m in centres:
        signs = ((-1, -1), (1, -1), (1, 1), (-1, 1))
        quad = [m + sa * LENGTH / 2 * along + sn * WIDTH / 2 * normal for sa, sn in signs]
        pts = np.round(((np.array(quad) + 0.5) * ss - 0.5) * 16).astype(np.int32)  # 4 fractional bits
        cv2.fillPoly(big, [pts], 1.0, lineType=cv2.LINE_8, shift=4)
    img = cv2.resize(big, (SIZE, SIZE), interpolation=cv2.INTER_AREA)
    img = cv2.GaussianBlur(img, (0, 0), blur)
    return 0.1 + 0.8 * img, centres


@pytest.mark.parametrize("angle", np.arange(0.0, 180.0, 7.5))
def test_a_triplet_is_found_at_any_angle_with_its_width(angle):
    img, centres = _triplet_image(angle)
    t = find_triplets(img)
    # (the dark mask's hole round a bright bar comes back as a dark bar at the same place, so
    # the same triplet may be found twice, or only with the dark polarity; the pose search
    # matches either)
    near = np.flatnonzero(np.hypot(*(t.centre - centres[1]).T) < 1.0)
    assert len(near) >= 1, "no triplet at the middle bar"
    for k in near:
        assert t.width[k] == pytest.approx(WIDTH, rel=0.03)
        assert abs((np.rad2deg(t.angle[k]) - angle + 90) % 180 - 90) < 1.5


def test_a_turned_bar_measures_no_wider_than_an_unturned_one():
    """Each bar's width from its moments, turned by 7.5-172.5 degrees, is at most 0.3 px
    over its width unturned (the rectangle round the blob is up to 1.1 px over it)."""

    def widths(angle):
        img, centres = _triplet_image(angle)
        bars, pol = find_bars(img)
        bright = bars[pol > 0]
        out = []
        for m in centres:
            d = np.hypot(*(bright[:, :2] - m).T)
            assert d.min() < 1.0
            out.append(bright[np.argmin(d), 5])
        return np.array(out)

    unturned = widths(0.0).max()
    turned = np.concatenate([widths(a) for a in np.arange(7.5, 180.0, 7.5)])
    assert turned.max() < unturned + 0.3
    assert turned.min() > unturned - 1.0
