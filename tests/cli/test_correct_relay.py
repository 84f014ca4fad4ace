"""``oapcal correct`` (images, stacks, --dask) and ``correct-points`` with a relay
calibration, against the library's map and inverse called directly."""

import cv2
import numpy as np
import pytest
import tifffile

from oapcal.imaging.remap import correct_image, correction_map
from oapcal.io.maps import load_map
from oapcal.model import RELAY, distort, undistort
from relay_helpers import relay_calibration, write_relay_calibration


@pytest.fixture(scope="module")
def relay_files(tmp_path_factory):
    """A relay calibration file, a grey 16-bit image, a colour PNG and a 3-frame stack."""
    d = tmp_path_factory.mktemp("relay_correct")
    calib = write_relay_calibration(d / "relay.json")
    rng = np.random.default_rng(8)
    grey = cv2.GaussianBlur(rng.integers(0, 65535, (480, 640), dtype=np.uint16), (0, 0), 1.5)
    colour = cv2.GaussianBlur(rng.integers(0, 255, (480, 640, 3), dtype=np.uint8), (0, 0), 1.5)
    stack = cv2.GaussianBlur(rng.random((480, 640, 3), dtype=np.float32), (0, 0), 1.5).transpose(2, 0, 1)
    tifffile.imwrite(d / "grey.tif", grey)
    cv2.imwrite(str(d / "colour.png"), colour)
    tifffile.imwrite(d / "stack.tif", np.ascontiguousarray(stack), photometric="minisblack")
    return d, calib, grey, colour, stack


def test_the_relay_map_is_the_relay(relay_files):
    """The map correct uses samples the distorted image where the relay puts each output
    pixel (distort() of the family, the definition), and is not Eq. (1)'s identity."""
    cal = relay_calibration()
    assert cal.family is RELAY
    cmap = correction_map(cal, (480, 640))
    ys, xs = np.array([0, 100, 240, 479]), np.array([0, 500, 320, 639])
    want = distort(np.stack([xs, ys], -1).astype(float), cal.params)
    np.testing.assert_allclose(np.stack([cmap.map_x[ys, xs], cmap.map_y[ys, xs]], -1), want, atol=1e-3)
    assert np.abs(cmap.map_y - np.arange(480)[:, None]).max() > 10


@pytest.mark.parametrize("geometry", [(), ("--extent", "full", "--out-size", "400x300")])
def test_correct_images_and_stack_equal_the_library(run_cli, relay_files, tmp_path, geometry):
    d, calib, grey, colour, stack = relay_files
    out = tmp_path / "out"
    code, stdout, err = run_cli("correct", calib, d / "grey.tif", d / "colour.png", d / "stack.tif",
                                "--out-dir", out, "--save-map", tmp_path / "map.npz", *geometry)  # fmt: skip
    assert code == 0, err
    assert "3 corrected (5 frames)" in stdout
    kwargs = {"extent": "full", "out_size": (400, 300)} if geometry else {}
    cmap = correction_map(relay_calibration(), (480, 640), **kwargs)
    saved = load_map(tmp_path / "map.npz")
    np.testing.assert_array_equal(saved.map_x, cmap.map_x)
    np.testing.assert_array_equal(saved.map_y, cmap.map_y)
    np.testing.assert_array_equal(tifffile.imread(out / "grey.tif"), correct_image(grey, cmap))
    np.testing.assert_array_equal(cv2.imread(str(out / "colour.png")), correct_image(colour, cmap))
    got = tifffile.imread(out / "stack.tif")
    assert got.shape == (3,) + cmap.shape
    for frame, corrected in zip(stack, got, strict=True):
        np.testing.assert_array_equal(corrected, correct_image(frame, cmap))


@pytest.mark.parametrize("fmt", ["zarr", "tiff"])
def test_correct_dask_equals_the_library(run_cli, relay_files, tmp_path, fmt):
    d, calib, _, _, stack = relay_files
    out = tmp_path / "out"
    code, _, err = run_cli("correct", calib, d / "stack.tif", "--out-dir", out, "--dask", "--scheduler",
                           "synchronous", "--chunk-frames", "2", "--dask-format", fmt,
                           "--interp", "cubic")  # fmt: skip
    assert code == 0, err
    if fmt == "zarr":
        import zarr

        got = zarr.open_array(str(out / "stack.zarr"), mode="r")[:]
    else:
        got = tifffile.imread(out / "stack.tif")
    cmap = correction_map(relay_calibration(), (480, 640))
    for frame, corrected in zip(stack, got, strict=True):
        np.testing.assert_array_equal(corrected, correct_image(frame, cmap, "cubic"))


def test_correct_points_equals_undistort(run_cli, tmp_path):
    import csv

    from oapcal.io.points import write_point_pairs

    cal = relay_calibration()
    calib = write_relay_calibration(tmp_path / "relay.json")
    rng = np.random.default_rng(4)
    xy_u = np.column_stack([rng.uniform(0, 639, 50), rng.uniform(0, 479, 50)])
    xy_d = distort(xy_u, cal.params)
    write_point_pairs(tmp_path / "pts.csv", xy_u, xy_d)
    code, _, err = run_cli("correct-points", calib, tmp_path / "pts.csv", "--out", tmp_path / "c.csv")
    assert code == 0, err
    with open(tmp_path / "c.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    got = np.array([[float(r["x_c"]), float(r["y_c"])] for r in rows])
    assert [r["converged"] for r in rows] == ["1"] * 50
    inv = undistort(xy_d, cal.params)
    assert inv.converged.all()
    np.testing.assert_allclose(got, inv.xy, rtol=0, atol=1e-9)
    # and the inverse is the relay's: back on the reference points it was traced from
    np.testing.assert_allclose(got, xy_u, atol=1e-6)
