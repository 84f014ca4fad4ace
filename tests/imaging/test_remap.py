import numpy as np

from oapcal.imaging.remap import correct_image, correction_map
from oapcal.model import distort
from oapcal.synthetic import EXAMPLE_TRUTH


def test_map_is_the_forward_model_at_output_pixels():
    mx, my = correction_map(EXAMPLE_TRUTH, (48, 64))
    r, c = 17, 40
    expected = distort(np.array([[c, r]], float), EXAMPLE_TRUTH)[0]
    np.testing.assert_allclose([mx[r, c], my[r, c]], expected, rtol=1e-6)


def test_correcting_a_distorted_image_restores_it():
    # Render a smooth pattern in undistorted coordinates, distort it by sampling the
    # pattern at the inverse... here: build the distorted image analytically by remapping
    # with the inverse map, then correct and compare away from the borders.
    rows, cols = 240, 320
    yy, xx = np.mgrid[0:rows, 0:cols].astype(float)
    pattern = lambda x, y: 127 + 100 * np.sin(x / 9.0) * np.cos(y / 13.0)  # noqa: E731
    from oapcal.model import undistort

    p = EXAMPLE_TRUTH.copy() * 1.0
    p[[8, 9]] = [-160, -120]
    p[[10, 11]] = [160, 120]
    inv = undistort(np.stack([xx, yy], -1).reshape(-1, 2), p)
    distorted = pattern(*inv.xy.T).reshape(rows, cols).astype(np.float32)
    corrected = correct_image(distorted, correction_map(p, (rows, cols)), "cubic")
    truth = pattern(xx, yy)
    inner = (slice(40, -40), slice(40, -40))
    assert np.nanmax(np.abs(corrected[inner] - truth[inner])) < 1.0
    assert corrected.dtype == np.float32
