import numpy as np
import pytest

from imaging_helpers import known_calibration, reference_maps
from oapcal.errors import DataError
from oapcal.imaging.remap import correct_image, correction_map, output_geometry
from oapcal.model import params_from_dict, undistort

FULL = params_from_dict(
    {"k1": 3e-7, "k2": -2e-13, "p1": -2e-5, "p2": 3e-5, "s1": 1e-4, "s2": -1e-10, "s3": 2e-4,
     "s4": 1e-10, "x_off": -310, "y_off": -250, "c_x": 325, "c_y": 236, "m": 1.02}
)  # fmt: skip


def test_grid_map_equals_the_model_for_all_13_parameters():
    cmap = correction_map(FULL, (48, 64))
    mx, my = reference_maps(FULL, (48, 64))
    np.testing.assert_allclose(cmap.map_x, mx, atol=1e-4)
    np.testing.assert_allclose(cmap.map_y, my, atol=1e-4)


def test_default_geometry_is_the_input_frame():
    g = correction_map(known_calibration(), (480, 640)).geometry
    assert (g.shape, g.x0, g.y0, g.scale, g.um_per_px) == ((480, 640), 0.0, 0.0, 1.0, 4.8)


def test_output_pixel_size_sets_the_scale():
    # 9.6 um per output px with 4.8 um per calibration unit: 2 units per px, so the
    # 640x480 frame ([0, 639] x [0, 479]) needs floor(639/2)+1 = 320 by floor(479/2)+1 = 240 px.
    cal = known_calibration()
    cmap = correction_map(cal, (480, 640), um_per_px=9.6)
    assert cmap.shape == (240, 320) and cmap.geometry.scale == 2.0 and cmap.geometry.um_per_px == 9.6
    mx, my = reference_maps(cal.params, (240, 320), scale=2.0)
    np.testing.assert_allclose(cmap.map_x, mx, atol=1e-4)


def test_calibrated_extent_is_the_box_of_the_reference_points():
    cal = known_calibration(bounds=(40.0, 50.0, 600.0, 430.0))
    g = output_geometry(cal, (480, 640), extent="calibrated")
    assert (g.x0, g.y0, g.shape) == (40.0, 50.0, (381, 561))


def test_full_extent_keeps_every_corner_of_the_input():
    cal = known_calibration()
    rows, cols = 480, 640
    image = np.zeros((rows, cols), np.float32)
    corners = [(2, 2), (2, cols - 3), (rows - 3, 2), (rows - 3, cols - 3)]
    for r, c in corners:
        image[r - 2 : r + 3, c - 2 : c + 3] = 1.0
    default = correct_image(image, correction_map(cal, (rows, cols)))
    full = correction_map(cal, (rows, cols), extent="full")
    out = correct_image(image, full)
    g = full.geometry
    # Each corner blob appears where the inverse model puts that corner (independent Newton).
    xy_u = undistort(np.array([[c, r] for r, c in corners], float), cal.params).xy
    for x, y in xy_u:
        col, row = round((x - g.x0) / g.scale), round((y - g.y0) / g.scale)
        assert out[row - 1 : row + 2, col - 1 : col + 2].max() > 0.5
    # The default frame cuts at least one corner off; the full one keeps more of the image.
    assert out.sum() > default.sum()
    # The box is tight: the valid area touches every edge of the output.
    valid = correct_image(np.ones_like(image), full) > 0
    assert valid[0].any() and valid[-1].any() and valid[:, 0].any() and valid[:, -1].any()


def test_output_size_fits_the_region_and_keeps_the_aspect():
    g = output_geometry(known_calibration(), (480, 640), out_size=(321, 321))
    assert g.shape == (321, 321) and g.scale == pytest.approx(639 / 320)
    assert g.x0 == pytest.approx(0.0) and g.y0 + 160 * g.scale == pytest.approx(239.5)


def test_geometry_errors_are_named():
    with pytest.raises(DataError, match="needs a calibration with 'um_per_px'"):
        output_geometry(known_calibration(um_per_px=None), (480, 640), um_per_px=2.0)
    with pytest.raises(DataError, match="needs a calibration with 'bounds'"):
        output_geometry(known_calibration(bounds=None), (480, 640), extent="calibrated")
    with pytest.raises(DataError, match="more than 16 times"):
        output_geometry(known_calibration(), (480, 640), um_per_px=0.5)
