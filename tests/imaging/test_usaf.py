"""USAF-1951 geometry and rendering against the standard's numbers."""

import numpy as np
import pytest

from oapcal.errors import DataError
from oapcal.imaging.usaf import (
    LAYOUTS,
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


# The whole published lookup table (lp/mm, rows: element 1-6, columns: group -2 to 9), as
# printed, e.g. in the "1951 USAF resolution test chart" article's table.
PUBLISHED = """
0.250 0.500 1.00 2.00 4.00 8.00 16.00 32.0 64.0 128.0 256.0 512.0
0.281 0.561 1.12 2.24 4.49 8.98 17.96 35.9 71.8 143.7 287.4 574.7
0.315 0.630 1.26 2.52 5.04 10.08 20.16 40.3 80.6 161.3 322.5 645.1
0.354 0.707 1.41 2.83 5.66 11.31 22.63 45.3 90.5 181.0 362.0 724.1
0.397 0.794 1.59 3.17 6.35 12.70 25.40 50.8 101.6 203.2 406.4 812.7
0.445 0.891 1.78 3.56 7.13 14.25 28.51 57.0 114.0 228.1 456.1 912.3
"""


def test_every_entry_of_the_published_table():
    rows = [line.split() for line in PUBLISHED.strip().splitlines()]
    assert len(rows) == 6 and all(len(r) == 12 for r in rows)
    for e, row in enumerate(rows, start=1):
        for g, text in zip(range(-2, 10), row):
            decimals = len(text.split(".")[1])
            # equal to the printed value to half a unit of its last digit
            assert abs(line_pairs_per_mm(g, e) - float(text)) <= 0.5 * 10.0**-decimals + 1e-12, (g, e)


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


def _triplet(t, g, e, o):
    """x0, y0, x1, y1 (um) of a triplet."""
    sel = (t.bar_group == g) & (t.bar_element == e) & (t.bar_orientation == o)
    b = t.bars[sel]
    return np.array([*b[:, :2].min(axis=0), *b[:, 2:].max(axis=0)])


def test_standard_arrangement_of_a_layer():
    t = usaf_target((4, 5))
    w = {(g, e): bar_width_um(g, e) for g in (4, 5) for e in range(1, 7)}
    # Left column, even group 4, elements 2-6: horizontal bars, then vertical bars, 2 w apart,
    # left-aligned; each element 2 w (of the one above) below the one above: tops 7 w apart.
    for e in range(2, 7):
        h, v = _triplet(t, 4, e, "H"), _triplet(t, 4, e, "V")
        assert v[0] - h[2] == pytest.approx(2 * w[4, e])
        assert h[1] == pytest.approx(v[1]) and h[0] == pytest.approx(_triplet(t, 4, 2, "H")[0])
        if e < 6:
            assert _triplet(t, 4, e + 1, "H")[1] - h[1] == pytest.approx(7 * w[4, e])
    # Right column, odd group 5, elements 1-6, and the even group's element 1: vertical bars,
    # then horizontal bars, 2 w apart, right-aligned.
    right = _triplet(t, 5, 1, "H")[2]
    for g, e in [(5, 1), (5, 2), (5, 3), (5, 4), (5, 5), (5, 6), (4, 1)]:
        h, v = _triplet(t, g, e, "H"), _triplet(t, g, e, "V")
        assert h[0] - v[2] == pytest.approx(2 * w[g, e]) and h[2] == pytest.approx(right)
        if g == 5 and e < 6:
            assert _triplet(t, 5, e + 1, "V")[1] - v[1] == pytest.approx(7 * w[5, e])
    # Both columns start at the top; element 1 of group 4 is at the bottom right, level with
    # the bottom of the left column; the layer is a square of side 23.96 w1.
    top, bottom = _triplet(t, 4, 2, "H")[1], _triplet(t, 4, 6, "H")[3]
    assert _triplet(t, 5, 1, "V")[1] == pytest.approx(top)
    assert _triplet(t, 4, 1, "H")[3] == pytest.approx(bottom)
    assert (bottom - top) / w[4, 1] == pytest.approx(23.96, abs=0.005)
    assert (right - _triplet(t, 4, 2, "H")[0]) / w[4, 1] == pytest.approx(23.96, abs=0.005)
    # The reference square: top-aligned, 2 w2 right of element 2, 2 w of G5E1 left of G5E1.
    (sq,) = t.squares
    assert sq[1] == pytest.approx(top)
    assert sq[0] - _triplet(t, 4, 2, "V")[2] == pytest.approx(2 * w[4, 2])
    assert _triplet(t, 5, 1, "V")[0] - sq[2] == pytest.approx(2 * w[5, 1])
    assert sq[3] - sq[1] == pytest.approx(sq[2] - sq[0])
    # Element numbers beside the elements: left of the left column, right of the right one.
    for text, kind, g, e, box in zip(t.label_text, t.label_kind, t.label_group, t.label_element, t.labels):
        if kind != "element":
            continue
        assert text == str(e)
        h = _triplet(t, g, e, "H")
        if g == 4 and e > 1:
            assert box[2] < h[0]
        else:
            assert box[0] > h[2]
        assert box[1] < (h[1] + h[3]) / 2 < box[3]
    assert sorted(t.label_text[i] for i, k in enumerate(t.label_kind) if k == "group") == ["4", "4", "5"]
    assert len(t.bars) == 72 and len(set(t.corner_ids)) == 288


@pytest.mark.parametrize("name", list(LAYOUTS))
def test_every_layout_keeps_bars_squares_and_layers_apart(name):
    t = usaf_target(tuple(range(-2, 10)), name)
    b = np.concatenate([t.bars, t.squares])
    ov_x = np.minimum(b[:, None, 2], b[None, :, 2]) - np.maximum(b[:, None, 0], b[None, :, 0])
    ov_y = np.minimum(b[:, None, 3], b[None, :, 3]) - np.maximum(b[:, None, 1], b[None, :, 1])
    overlap = (ov_x > 0) & (ov_y > 0)
    np.fill_diagonal(overlap, False)
    assert not overlap.any()
    # each layer nests inside the one before: its bars and squares inside the other's bounding box
    for g in range(0, 10, 2):
        outer = usaf_target((g - 2, g - 1), name).full_bbox_um
        inner = usaf_target((g, g + 1), name)
        ib = np.array([*np.concatenate([inner.bars, inner.squares])[:, :2].min(0),
                       *np.concatenate([inner.bars, inner.squares])[:, 2:].max(0)])  # fmt: skip
        assert outer[0] < ib[0] and ib[2] < outer[2] and outer[1] < ib[1] and ib[3] < outer[3]


def test_mirrored_layer_of_the_whole_target_print():
    t = usaf_target((0, 1), "whole-target")
    # layer 0-1 is drawn mirrored: the odd group's column on the left, drawn digit, H, V;
    # the even group's elements 2-6 on the right drawn V, H, digit; its element 1 bottom left.
    assert _triplet(t, 1, 1, "H")[2] < _triplet(t, 1, 1, "V")[0]
    assert _triplet(t, 0, 2, "V")[2] < _triplet(t, 0, 2, "H")[0]
    assert _triplet(t, 1, 1, "H")[0] < _triplet(t, 0, 2, "V")[0]
    assert _triplet(t, 0, 1, "H")[0] == pytest.approx(_triplet(t, 1, 1, "H")[0])
    assert _triplet(t, 0, 1, "H")[2] < _triplet(t, 0, 1, "V")[0]
    # bar 0 is still the top (left) bar of a triplet
    for g, e, o in [(1, 1, "V"), (0, 2, "H")]:
        sel = (t.bar_group == g) & (t.bar_element == e) & (t.bar_orientation == o)
        first = t.bars[sel & (t.bar_index == 0)][0]
        assert first[0 if o == "V" else 1] == pytest.approx(_triplet(t, g, e, o)[0 if o == "V" else 1])
    outer = usaf_target((-2, -1), "whole-target")
    assert _triplet(outer, -2, 2, "H")[2] < _triplet(outer, -2, 2, "V")[0]  # not mirrored


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
