"""`correct --format` writes each input as TIFF, OME-TIFF or OME-Zarr (the streaming path),
`--dask-format ome-zarr` with Dask, and `--dask` on one machine says when it streams."""

import json

import cv2
import numpy as np
import pytest
import tifffile

from oapcal.calibration import calibrate
from oapcal.imaging.remap import correct_image, correction_map
from oapcal.io.calibration import save_calibration
from oapcal.model import distort
from oapcal.synthetic import EXAMPLE_TRUTH


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("formats")
    rng = np.random.default_rng(7)
    xy_u = rng.uniform((20, 20), (620, 460), (150, 2))  # over the whole frame: all of it trusted
    xy_d = distort(xy_u, EXAMPLE_TRUTH) + rng.normal(0, 0.05, xy_u.shape)
    cal = calibrate(xy_u, xy_d, "paper", image_size=(640, 480), rotation="none", um_per_px=4.8)
    save_calibration(cal, d / "calib.json")
    image = rng.integers(10, 250, (480, 640)).astype(np.uint8)
    cv2.imwrite(str(d / "img.png"), image)
    tifffile.imwrite(d / "stack.tif", np.stack([image, image[::-1]]))
    return d, cal, image


@pytest.mark.parametrize("fmt, name", [("tiff", "img.tif"), ("ome-tiff", "img.ome.tif")])
def test_format_writes_the_corrected_image_as_tiff(run_cli, files, fmt, name):
    d, cal, image = files
    out = d / f"out-{fmt}"
    code, _, err = run_cli("correct", d / "calib.json", d / "img.png", "--out-dir", out, "--format", fmt)
    assert code == 0, err
    expected = correct_image(image, correction_map(cal, (480, 640), max_error_px=1.0), "linear")
    with tifffile.TiffFile(out / name) as tif:
        np.testing.assert_array_equal(tif.asarray(), expected)
        assert tif.is_ome == (fmt == "ome-tiff")
        if tif.is_ome:
            assert 'PhysicalSizeX="' in tif.ome_metadata


def test_format_ome_zarr_writes_an_ngff_group(run_cli, files):
    import zarr

    d, cal, image = files
    out = d / "out-zarr"
    code, _, err = run_cli(
        "correct", d / "calib.json", d / "stack.tif", "--out-dir", out, "--format", "ome-zarr"
    )
    assert code == 0, err
    group = zarr.open_group(str(out / "stack.ome.zarr"), mode="r")
    assert "multiscales" in group.attrs.asdict() or "ome" in group.attrs.asdict()
    cmap = correction_map(cal, (480, 640), max_error_px=1.0)
    data = np.asarray(group["0"]).reshape(2, 480, 640)
    np.testing.assert_array_equal(data[1], correct_image(image[::-1], cmap, "linear"))


def test_format_with_dask_is_refused_in_one_line(run_cli, files):
    d, _, _ = files
    code, _, err = run_cli("correct", d / "calib.json", d / "stack.tif", "--out-dir", d / "x", "--dask",
                           "--format", "tiff")  # fmt: skip
    assert code == 2 and err.count("\n") == 1 and "--dask-format" in err, err
    assert not (d / "x").exists()


def test_dask_on_one_worker_streams_and_says_so(run_cli, files):
    pytest.importorskip("dask", reason="the dask extra is not installed")
    d, _, _ = files
    code, out, err = run_cli("correct", d / "calib.json", d / "stack.tif", "--out-dir", d / "dz", "--dask",
                             "--dask-format", "ome-zarr", "--quiet")  # fmt: skip
    assert code == 0, err
    assert "oapcal: note:" in err and err.count("oapcal: note:") == 1, err
    assert (d / "dz" / "stack.ome.zarr").is_dir()
    code, out, err = run_cli("correct", d / "calib.json", d / "stack.tif", "--out-dir", d / "dj", "--dask",
                             "--json")  # fmt: skip
    assert code == 0 and "note:" not in err
    json.loads(out)
