import json

import cv2
import numpy as np
import pytest

from imaging_helpers import known_calibration, reference_maps, write_calibration
from oapcal.imaging.remap import output_geometry
from oapcal.io.opencv_export import opencv_parameters
from oapcal.model import params_from_dict

FULL = params_from_dict(
    {"k1": 3e-7, "k2": -2e-13, "p1": -2e-5, "p2": 3e-5, "s1": 1e-4, "s2": -1e-10, "s3": 2e-4,
     "s4": 1e-10, "x_off": -310, "y_off": -250, "c_x": 325, "c_y": 236, "m": 1.02}
)  # fmt: skip


def _opencv_maps(export):
    return cv2.initUndistortRectifyMap(
        np.array(export["camera_matrix"]), np.array(export["dist_coeffs"]), None,
        np.array(export["new_camera_matrix"]), tuple(export["new_image_size"]), cv2.CV_32FC1,
    )  # fmt: skip


@pytest.mark.parametrize("geometry", [{}, {"extent": "full"}, {"out_size": (300, 200)}, {"um_per_px": 9.6}])
def test_opencv_reproduces_the_map_for_all_13_parameters(geometry):
    cal = known_calibration(
        params=FULL, free=tuple(known_calibration().free) + ("k2", "p2", "s1", "s2", "s4")
    )
    g = output_geometry(cal, (480, 640), **geometry)
    mx, my = _opencv_maps(opencv_parameters(cal.params, (640, 480), g))
    ref_x, ref_y = reference_maps(cal.params, g.shape, g.x0, g.y0, g.scale)
    assert mx.shape == g.shape
    assert np.abs(mx - ref_x).max() < 1e-3 and np.abs(my - ref_y).max() < 1e-3
    assert np.abs(ref_x - (g.x0 + g.scale * np.arange(g.shape[1]))).max() > 10  # real distortion


def test_cli_writes_json_and_opencv_yaml(run_cli, tmp_path):
    calib = write_calibration(tmp_path / "calib.json")
    code, stdout, err = run_cli("export-opencv", calib, "--out", tmp_path / "cv.yml")
    assert code == 0, err
    code, _, err = run_cli("export-opencv", calib, "--out", tmp_path / "cv.json")
    assert code == 0, err
    data = json.loads((tmp_path / "cv.json").read_text())
    fs = cv2.FileStorage(str(tmp_path / "cv.yml"), cv2.FILE_STORAGE_READ)
    for key in ("camera_matrix", "dist_coeffs", "new_camera_matrix"):
        np.testing.assert_allclose(fs.getNode(key).mat().ravel(), np.ravel(data[key]))
    fs.release()
    assert len(data["dist_coeffs"]) == 12
    # k1 F^2 with F = max(640, 480) and oapcal's k1 = 4e-7 (EXAMPLE_TRUTH), by hand: 0.16384.
    assert data["dist_coeffs"][0] == pytest.approx(0.16384)
    mx, my = _opencv_maps(data)
    ref_x, ref_y = reference_maps(known_calibration().params, (480, 640))
    assert np.abs(mx - ref_x).max() < 1e-3 and np.abs(my - ref_y).max() < 1e-3


def test_cli_export_errors(run_cli, tmp_path):
    calib = write_calibration(tmp_path / "calib.json", image_size=None)
    code, _, err = run_cli("export-opencv", calib, "--out", tmp_path / "cv.yml")
    assert code == 2 and "has no image_size; give --image-size WxH" in err
    code, _, err = run_cli("export-opencv", calib, "--out", tmp_path / "cv.txt", "--image-size", "640x480")
    assert code == 2 and "must end in .json, .yml, .yaml, .xml" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["calib.json"]
