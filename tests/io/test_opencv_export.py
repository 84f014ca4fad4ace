import json

import cv2
import numpy as np
import pytest

from imaging_helpers import known_calibration, reference_maps, write_calibration
from oapcal.imaging.remap import output_geometry
from oapcal.io.opencv_export import opencv_parameters
from oapcal.model import PARAM_NAMES, params_from_dict

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


# ------------------------------------------------------------- the other model families


def test_eq1_json_export_keeps_the_version_1_keys(run_cli, tmp_path):
    calib = write_calibration(tmp_path / "calib.json")
    code, stdout, err = run_cli("export-opencv", calib, "--out", tmp_path / "cv.json")
    assert code == 0, err
    data = json.loads((tmp_path / "cv.json").read_text())
    assert list(data) == ["format", "version", "calibration", "camera_matrix", "dist_coeffs",
                          "new_camera_matrix", "image_size", "new_image_size", "um_per_px"]  # fmt: skip
    assert data["version"] == 1
    assert stdout == "wrote {}: pass new_image_size 640x480 to cv2.initUndistortRectifyMap\n".format(
        tmp_path / "cv.json"
    )
    assert sorted(p.name for p in tmp_path.iterdir()) == ["calib.json", "cv.json"]


@pytest.mark.parametrize("geometry", [{}, {"extent": "full"}, {"out_size": (300, 200)}])
def test_rotation_family_is_exact_with_opencvs_rectification_rotation(geometry):
    cal = known_calibration(params=np.append(FULL, 4.0), free=known_calibration().free + ("rotation",))
    g = output_geometry(cal, (480, 640), **geometry)
    export = opencv_parameters(cal.params, (640, 480), g)
    assert export["exact"] is True and export["model_family"] == "brown-conrady+rotation"
    ref_x, ref_y = reference_maps(cal.params, g.shape, g.x0, g.y0, g.scale)
    mx, my = cv2.initUndistortRectifyMap(
        np.array(export["camera_matrix"]), np.array(export["dist_coeffs"]), np.array(export["R"]),
        np.array(export["new_camera_matrix"]), tuple(export["new_image_size"]), cv2.CV_32FC1,
    )  # fmt: skip
    assert np.abs(mx - ref_x).max() < 1e-3 and np.abs(my - ref_y).max() < 1e-3
    # without R the 4 degrees show: R is needed
    assert np.abs(_opencv_maps(export)[0] - ref_x).max() > 5


def test_cli_rotation_family_writes_R(run_cli, tmp_path):
    cal = known_calibration(params=np.append(FULL, -2.0), free=PARAM_NAMES + ("rotation",),
                            stderr=np.full(14, np.nan), covariance=np.zeros((14, 14)))  # fmt: skip
    from oapcal.io.calibration import save_calibration

    save_calibration(cal, tmp_path / "rot.json")
    code, stdout, err = run_cli("export-opencv", tmp_path / "rot.json", "--out", tmp_path / "cv.yml")
    assert code == 0, err
    assert "exact for the brown-conrady+rotation model): pass R and new_image_size 640x480" in stdout
    fs = cv2.FileStorage(str(tmp_path / "cv.yml"), cv2.FILE_STORAGE_READ)
    K, D, R, K_new = (fs.getNode(k).mat() for k in ("camera_matrix", "dist_coeffs", "R", "new_camera_matrix"))
    assert fs.getNode("model_family").string() == "brown-conrady+rotation" and fs.getNode("exact").real() == 1
    fs.release()
    mx, my = cv2.initUndistortRectifyMap(K, D, R, K_new, (640, 480), cv2.CV_32FC1)
    ref_x, ref_y = reference_maps(cal.params, (480, 640))
    assert np.abs(mx - ref_x).max() < 1e-3 and np.abs(my - ref_y).max() < 1e-3


def test_relay_has_no_opencv_parameters():
    from oapcal.errors import DataError
    from relay_helpers import relay_calibration

    with pytest.raises(DataError, match="no OpenCV camera parameters reproduce the relay model"):
        opencv_parameters(relay_calibration().params, (640, 480))


@pytest.fixture(scope="module")
def relay_export(tmp_path_factory):
    """A relay calibration exported by the command line as JSON (+ maps) and as YAML."""
    from oapcal.cli import main
    from relay_helpers import write_relay_calibration

    d = tmp_path_factory.mktemp("relay_export")
    calib = write_relay_calibration(d / "relay.json")
    for out in ("cv.json", "cv.yml"):
        assert main(["export-opencv", str(calib), "--out", str(d / out)]) == 0
    return d


def test_relay_export_maps_reproduce_correct_image(relay_export):
    from oapcal.imaging.remap import correct_image, correction_map
    from relay_helpers import relay_calibration

    d = relay_export
    data = json.loads((d / "cv.json").read_text())
    assert data["version"] == 2 and data["model_family"] == "relay" and data["exact"] is False
    assert data["maps"]["file"] == "cv.maps.npz"
    with np.load(d / data["maps"]["file"]) as z:
        jx, jy = z[data["maps"]["map_x"]], z[data["maps"]["map_y"]]
    fs = cv2.FileStorage(str(d / "cv.yml"), cv2.FILE_STORAGE_READ)
    yx, yy = fs.getNode("map_x").mat(), fs.getNode("map_y").mat()
    assert fs.getNode("exact").real() == 0 and fs.getNode("model_family").string() == "relay"
    fs.release()
    assert jx.dtype == np.float32 and jx.shape == (480, 640)
    rng = np.random.default_rng(3)
    image = cv2.GaussianBlur(rng.integers(0, 65535, (480, 640), dtype=np.uint16), (0, 0), 2)
    want = correct_image(image, correction_map(relay_calibration(), (480, 640)))
    for mx, my in ((jx, jy), (yx, yy)):
        got = cv2.remap(image, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        np.testing.assert_array_equal(got, want)
    # the maps are the relay's: distort() at a few output pixels (the definition)
    from oapcal.model import distort

    ys, xs = np.array([5, 240, 400]), np.array([20, 320, 600])
    np.testing.assert_allclose(
        np.stack([jx[ys, xs], jy[ys, xs]], -1),
        distort(np.stack([xs, ys], -1).astype(float), relay_calibration().params), atol=1e-3,
    )  # fmt: skip


def test_relay_export_reports_the_approximation_error_opencv_gives(relay_export):
    d = relay_export
    data = json.loads((d / "cv.json").read_text())
    approx = data["approximation"]
    with np.load(d / "cv.maps.npz") as z:
        ex, ey = z["map_x"].astype(float), z["map_y"].astype(float)
    # OpenCV's own map from the approximation's coefficients, against the exact maps, over
    # the output pixels whose exact source lies in the 640x480 input
    ax, ay = _opencv_maps(data)
    inside = (ex >= 0) & (ex <= 639) & (ey >= 0) & (ey <= 479)
    err = np.hypot(ax - ex, ay - ey)[inside]
    assert approx["n_pixels"] == inside.sum()
    assert approx["mean_px"] == pytest.approx(err.mean(), abs=1e-3)
    assert approx["max_px"] == pytest.approx(err.max(), abs=1e-3)
    assert approx["mean_px"] > 0.05  # the relay is not Eq. (1): the approximation is visibly off
    # the calibrated region: the reference points' box (output pixel = undistorted point here)
    from relay_helpers import relay_calibration

    x0, y0, x1, y1 = relay_calibration().bounds
    cols, rows = np.meshgrid(np.arange(640), np.arange(480))
    box = inside & (cols >= x0) & (cols <= x1) & (rows >= y0) & (rows <= y1)
    err_box = np.hypot(ax - ex, ay - ey)[box]
    assert approx["calibrated_mean_px"] == pytest.approx(err_box.mean(), abs=1e-3)
    assert approx["calibrated_max_px"] == pytest.approx(err_box.max(), abs=1e-3)
    fs = cv2.FileStorage(str(d / "cv.yml"), cv2.FILE_STORAGE_READ)
    assert fs.getNode("approximation_mean_px").real() == pytest.approx(approx["mean_px"])
    np.testing.assert_array_equal(fs.getNode("dist_coeffs").mat().ravel(), data["dist_coeffs"])
    assert "no OpenCV coefficient set reproduces the relay model" in fs.getNode("note").string()
    fs.release()


def test_relay_approximation_is_the_least_squares_eq1_fit():
    """Independently of oapcal's solver: SciPy's least_squares from the returned
    approximation finds no better Eq. (1) fit to the same samples."""
    from scipy.optimize import least_squares

    from oapcal.io.opencv_export import brown_conrady_approximation
    from oapcal.model import distort, scale_params
    from relay_helpers import relay_calibration

    cal = relay_calibration()
    g = output_geometry(cal, (480, 640))
    approx = brown_conrady_approximation(cal, (640, 480), g)
    gx, gy = np.meshgrid(np.linspace(0, 639, 64), np.linspace(0, 479, 48))
    u = np.stack([gx.ravel(), gy.ravel()], -1)
    dd = distort(u, cal.params)
    keep = (dd[:, 0] >= 0) & (dd[:, 0] <= 639) & (dd[:, 1] >= 0) & (dd[:, 1] <= 479)
    u, dd = u[keep] / 640, dd[keep] / 640

    def residuals(q):
        return (distort(u, q) - dd).ravel()

    q0 = scale_params(approx.params, 640)
    better = least_squares(residuals, q0, method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15)
    rss0 = float(np.sum(residuals(q0) ** 2))
    assert better.cost * 2 >= rss0 * (1 - 1e-3)


def test_relay_json_export_is_all_or_nothing(run_cli, tmp_path, monkeypatch):
    import oapcal.io.maps
    from relay_helpers import write_relay_calibration

    calib = write_relay_calibration(tmp_path / "relay.json")

    def broken(cmap, path):
        raise OSError("disk full")

    monkeypatch.setattr(oapcal.io.maps, "save_map", broken)
    code, _, err = run_cli("export-opencv", calib, "--out", tmp_path / "cv.json")
    assert code != 0 and "disk full" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["relay.json"]
