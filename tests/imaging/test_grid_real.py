"""Dot-grid and chessboard detection on the real images of ../shared/real/targets (SOURCES.md
there: real cameras, real lens distortion, no stated pitch).  Without a truth, a wrong index
shows as a jump of a whole pitch against a smooth map of the indices: every landmark must lie
within a tenth of a pitch of a quartic polynomial in its indices fitted to all of them."""

import numpy as np
import pytest

from oapcal.imaging.detect.grid import detect_grid
from paths import REAL as SHARED_REAL

REAL = SHARED_REAL / "targets"
needs_real = pytest.mark.skipif(
    not REAL.is_dir(),
    reason="../shared/real/targets (the real dot-grid and chessboard images) is not present",
)


def _read(name):
    from oapcal.io.imagefile import read_image_grey

    return read_image_grey(REAL / name)


def smooth_residuals(det, degree=4):
    rc = det.rc.astype(float)
    u = (rc - rc.mean(axis=0)) / max(np.ptp(rc, axis=0).max() / 2, 1)
    a = np.stack([u[:, 0] ** i * u[:, 1] ** j for i in range(degree + 1) for j in range(degree + 1 - i)], 1)
    coef, *_ = np.linalg.lstsq(a, det.xy_d, rcond=None)
    return np.hypot(*(det.xy_d - a @ coef).T)


@needs_real
def test_real_dot_grid_xray_05():
    """1280 x 800, ~85 x 53 dark dots, a dust speck, an object at the top-right corner."""
    det = detect_grid(_read("xray_dot_pattern_05.jpg"), "dots", pitch_um=100.0)
    assert det.ok, det.message
    assert det.polarity == "dark"
    assert len(det.ids) >= 4200  # measured 4335 (the dots cut by the frame are not expected)
    assert det.coverage >= 0.97
    res = smooth_residuals(det)
    assert res.max() < 0.1 * det.pitch_px, res.max()
    assert 14.0 < det.pitch_px < 16.0  # 85 dots across 1280 px
    assert det.counts["shared_with_second_seed"] > 0.9 * len(det.ids)


@pytest.mark.slow
@needs_real
def test_real_dot_grid_xray_01():
    """2560 x 2160, a vignetted, curved border, a text overlay: the field inside is indexed."""
    det = detect_grid(_read("xray_dot_pattern_01.jpg"), "dots", pitch_um=100.0)
    assert det.ok, det.message
    assert len(det.ids) >= 4000
    res = smooth_residuals(det, degree=5)
    assert res.max() < 0.15 * det.pitch_px, res.max()


@pytest.mark.slow
@needs_real
def test_real_chessboard_laptop():
    """3264 x 1836 colour, a printed chessboard under uneven light with a printing flaw."""
    det = detect_grid(_read("laptop_chessboard.jpg"), "chessboard", pitch_um=1000.0)
    assert det.ok, det.message
    rows, cols = det.summary()["grid_rows"], det.summary()["grid_cols"]
    assert (rows, cols) == (25, 36)  # inner corners of the 26 x 37 squares, counted on the image
    assert len(det.ids) >= 0.99 * rows * cols  # measured 900 of 900
    res = smooth_residuals(det)
    assert res.max() < 0.1 * det.pitch_px, res.max()
