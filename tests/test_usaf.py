"""USAF-1951 geometry and rendering against the standard's numbers."""

import numpy as np
import pytest

from oapcal.errors import DataError
from oapcal.imaging.usaf import (
    bar_width_um,
    line_pairs_per_mm,
    parse_groups,
    render_rectangles,
    render_usaf,
    usaf_target,
)

# Published lookup table of the standard (lp/mm, two decimals): (group, element) -> lp/mm.
TABLE = {(4, 1): 16.00, (4, 3): 20.16, (4, 6): 28.51, (5, 1): 32.00, (5, 4): 45.25, (5, 6): 57.02,
         (0, 1): 1.00, (2, 2): 4.49, (7, 6): 228.07}  # fmt: skip


@pytest.mark.parametrize("ge,lp", TABLE.items())
def test_resolution_matches_the_published_table(ge, lp):
    assert line_pairs_per_mm(*ge) == pytest.approx(lp, abs=0.006)
    assert bar_width_um(*ge) == pytest.approx(1000 / (2 * lp), rel=2e-4)


def test_bars_are_5w_by_w_with_gaps_w():
    t = usaf_target((4, 5))
    width = t.bars[:, 2] - t.bars[:, 0]
    height = t.bars[:, 3] - t.bars[:, 1]
    short = np.minimum(width, height)
    long = np.maximum(width, height)
    np.testing.assert_allclose(short, t.bar_width)
    np.testing.assert_allclose(long, 5 * t.bar_width)
    # G4E1 horizontal triplet: bars 31.25 um thick, gaps 31.25 um, stacked in y.
    sel = (t.bar_group == 4) & (t.bar_element == 1) & (t.bar_orientation == "H")
    tops = np.sort(t.bars[sel, 1])
    np.testing.assert_allclose(np.diff(tops), [62.5, 62.5])
    assert np.all((t.bar_orientation == "H") == (width > height))


def test_standard_arrangement_of_a_layer():
    t = usaf_target((4, 5))

    def centre(g, e):
        sel = (t.bar_group == g) & (t.bar_element == e)
        return t.bars[sel].reshape(-1, 2, 2).mean(axis=(0, 1))

    # Odd group 5: elements 1-6 top to bottom on the right; even group 4: element 1 at the
    # lower right, elements 2-6 top to bottom on the left.
    ys5 = [centre(5, e)[1] for e in range(1, 7)]
    ys4 = [centre(4, e)[1] for e in range(2, 7)]
    assert np.all(np.diff(ys5) > 0) and np.all(np.diff(ys4) > 0)
    assert min(centre(5, e)[0] for e in range(1, 7)) > max(centre(4, e)[0] for e in range(2, 7))
    assert centre(4, 1)[1] > max(ys5) and centre(4, 1)[0] > centre(4, 2)[0]
    assert len(t.bars) == 72 and len(set(t.corner_ids)) == 288


def test_no_bars_overlap_and_next_layer_nests_inside():
    t = usaf_target((4, 5, 6, 7))
    b = t.bars
    ov_x = np.minimum(b[:, None, 2], b[None, :, 2]) - np.maximum(b[:, None, 0], b[None, :, 0])
    ov_y = np.minimum(b[:, None, 3], b[None, :, 3]) - np.maximum(b[:, None, 1], b[None, :, 1])
    overlap = (ov_x > 0) & (ov_y > 0)
    np.fill_diagonal(overlap, False)
    assert not overlap.any()
    outer = usaf_target((4, 5)).bbox_um
    inner = usaf_target((6, 7)).bbox_um
    assert outer[0] < inner[0] and inner[2] < outer[2] and outer[1] < inner[1] and inner[3] < outer[3]
    # one layer is the next larger one scaled by 1/4
    np.testing.assert_allclose(np.ptp(usaf_target((2, 3)).bars, axis=0)[[0, 1]] / 4,
                               np.ptp(usaf_target((4, 5)).bars, axis=0)[[0, 1]])  # fmt: skip


def test_rendered_bar_widths_and_positions_within_a_tenth_of_a_pixel():
    s = 4.8
    r = render_usaf((4, 5), um_per_px=s)
    t = usaf_target((4, 5))
    bars_px = t.rectangles_px(s, (640, 480))
    yy, xx = np.mgrid[0:480, 0:640]
    for g, e in [(4, 1), (4, 4), (5, 1), (5, 6)]:
        for orient in "HV":
            i = np.flatnonzero((t.bar_group == g) & (t.bar_element == e) & (t.bar_orientation == orient))[1]
            x0, y0, x1, y1 = bars_px[i]
            # Integrate the rendered intensity in a box around the bar (gaps of w on both sides).
            w_px = bar_width_um(g, e) / s
            box = (
                (xx > x0 - 0.9 * w_px)
                & (xx < x1 + 0.9 * w_px)
                & (yy > y0 - 0.9 * w_px)
                & (yy < y1 + 0.9 * w_px)
            )
            box &= (np.abs(xx - (x0 + x1) / 2) <= (x1 - x0) / 2 + w_px - 0.5) | (orient == "H")
            box &= (np.abs(yy - (y0 + y1) / 2) <= (y1 - y0) / 2 + w_px - 0.5) | (orient == "V")
            cover = (r.image - 0.05) / 0.95 * box
            area = cover.sum()
            long_px = 5 * w_px
            assert area / long_px == pytest.approx(w_px, abs=0.1)  # bar width in px
            cx = (cover * xx).sum() / area
            cy = (cover * yy).sum() / area
            assert abs(cx - (x0 + x1) / 2) < 0.1 and abs(cy - (y0 + y1) / 2) < 0.1


def test_area_sampling_matches_fine_point_sampling():
    rects = np.array([[1.3, 2.7, 9.55, 6.12]])  # x0, y0, x1, y1 (px)
    exact = render_rectangles(rects, (14, 14))
    n = 400  # point samples per pixel side
    sub = (np.arange(14 * n) + 0.5) / n - 0.5
    inx = (sub >= rects[0, 0]) & (sub <= rects[0, 2])
    iny = (sub >= rects[0, 1]) & (sub <= rects[0, 3])
    points = np.outer(iny, inx).reshape(14, n, 14, n).mean(axis=(1, 3))
    np.testing.assert_allclose(exact, points, atol=2.0 / n)


def test_dark_polarity_and_group_parsing():
    bright = render_usaf((5,), image_size=(200, 160))
    dark = render_usaf((5,), image_size=(200, 160), polarity="dark")
    np.testing.assert_allclose(bright.image + dark.image, 1.05)
    assert (
        parse_groups("4-5") == (4, 5)
        and parse_groups("-2--1") == (-2, -1)
        and parse_groups("2,4-5") == (2, 4, 5)
    )
    for bad in ("four", "", "4,4", "8-10"):
        with pytest.raises(DataError):
            parse_groups(bad)
