"""The trust region on the command line: `correct` writes only where the predicted error
is at most --max-error-px by default, `--extent input` the whole frame with a warning, and
`correct`, `export-opencv` and `correct-points` say how far beyond the landmarks' hull they
correct and with what predicted error."""

import json

import cv2
import numpy as np
import pytest

from oapcal.calibration import calibrate
from oapcal.imaging.remap import correct_image, correction_map
from oapcal.io.calibration import calibration_to_dict, save_calibration
from oapcal.model import distort
from oapcal.synthetic import EXAMPLE_TRUTH


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("trust")
    rng = np.random.default_rng(4)
    xy_u = rng.uniform((200, 150), (440, 330), (120, 2))  # the central 14 % of the frame
    xy_d = distort(xy_u, EXAMPLE_TRUTH) + rng.normal(0, 0.3, xy_u.shape)
    cal = calibrate(xy_u, xy_d, "paper", image_size=(640, 480), rotation="none")
    save_calibration(cal, d / "calib.json")
    old = calibration_to_dict(cal)
    del old["error_model"]  # as written before the error model existed
    (d / "old.json").write_text(json.dumps(old))
    image = rng.integers(10, 250, (480, 640)).astype(np.uint8)
    cv2.imwrite(str(d / "img.png"), image)
    with open(d / "points.csv", "w") as f:
        f.write("x_u,y_u,x_d,y_d\n")
        middle = np.argsort(np.hypot(*(xy_u - xy_u.mean(axis=0)).T))[:5]  # well inside the hull
        for (a, b), (c, e) in zip(xy_u[middle], xy_d[middle]):
            f.write(f"{a},{b},{c},{e}\n")
        far = distort(np.array([[20.0, 20.0]]), EXAMPLE_TRUTH)[0]
        f.write(f"20,20,{far[0]},{far[1]}\n")
    return d, cal, image


def test_correct_writes_only_the_trust_region_by_default(run_cli, files):
    d, cal, image = files
    code, out, err = run_cli(
        "correct", d / "calib.json", d / "img.png", "--out-dir", d / "a", "--border", "3"
    )
    assert code == 0, err
    assert "trust region:" in err and "beyond the landmarks' hull" in err and "border value 3" in err
    cmap = correction_map(cal, (480, 640), max_error_px=1.0)
    expected = correct_image(image, cmap, "linear", border=3)
    got = cv2.imread(str(d / "a" / "img.png"), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(got, expected)
    assert (got[~cmap.trusted] == 3).all() and 0.05 < cmap.trusted.mean() < 0.95


def test_extent_input_writes_the_whole_frame_with_a_warning(run_cli, files):
    d, cal, image = files
    code, out, err = run_cli(
        "correct", d / "calib.json", d / "img.png", "--out-dir", d / "b", "--extent", "input"
    )
    assert code == 0, err
    assert err.startswith("oapcal: warning: the whole output is corrected") and "predicted above 1 px" in err
    got = cv2.imread(str(d / "b" / "img.png"), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(got, correct_image(image, correction_map(cal, (480, 640)), "linear"))


def test_max_error_px_sets_the_threshold_and_json_reports_it(run_cli, files):
    d, cal, image = files
    code, out, err = run_cli("correct", d / "calib.json", d / "img.png", "--out-dir", d / "c",
                             "--max-error-px", "3", "--json")  # fmt: skip
    assert code == 0, err
    trust = json.loads(out)["trust"]
    cmap = correction_map(cal, (480, 640), max_error_px=3.0)
    assert trust["masked"] and trust["max_error_px"] == 3.0
    assert trust["trusted_fraction"] == pytest.approx(cmap.trusted.mean())
    got = cv2.imread(str(d / "c" / "img.png"), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(got, correct_image(image, cmap, "linear"))
    # --map fixes the output: a threshold with it is a usage error
    code, _, err = run_cli("correct", d / "calib.json", d / "img.png", "--out-dir", d / "c2", "--map",
                           d / "m.npz", "--max-error-px", "2")  # fmt: skip
    assert code == 2 and "--max-error-px" in err
    # the saved map holds the trust region
    code, _, err = run_cli("correct", d / "calib.json", "--save-map", d / "m.npz")
    assert code == 0, err
    data = np.load(d / "m.npz")
    np.testing.assert_array_equal(data["map_x"], correction_map(cal, (480, 640), max_error_px=1.0).map_x)


def test_old_calibration_says_it_has_no_error_model(run_cli, files):
    d, _, _ = files
    code, _, err = run_cli("correct", d / "old.json", d / "img.png", "--out-dir", d / "e")
    assert code == 0, err
    assert "no error model" in err


def test_export_opencv_and_correct_points_say_how_far_they_extrapolate(run_cli, files):
    d, _, _ = files
    code, out, err = run_cli("export-opencv", d / "calib.json", "--out", d / "cam.yml")
    assert code == 0, err
    assert "beyond the landmarks' hull" in err and "OpenCV corrects the whole frame" in err
    code, out, err = run_cli("correct-points", d / "calib.json", d / "points.csv", "--out", d / "c.csv")
    assert code == 0, err
    assert "1 of 6 corrected points lie beyond the landmarks' hull" in err
