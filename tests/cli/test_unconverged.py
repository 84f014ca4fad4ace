"""A fit that does not converge writes nothing unless asked (--keep-unconverged), and no
command uses an unconverged calibration unless asked (--allow-unconverged); a turned
target gets its rotation fitted, and the command says so."""

import json

import numpy as np
import pytest

from oapcal.io.points import write_point_pairs
from oapcal.model import params_from_dict
from oapcal.synthetic import synthetic_pairs

WEAK = params_from_dict({"k1": 2e-10, "s3": 1e-7, "x_off": -320.0, "y_off": -240.0, "c_x": 320.0,
                         "c_y": 240.0, "m": 1.0})  # fmt: skip


@pytest.fixture
def turned_points(tmp_path):
    """Point pairs of a barely distorting microscope with the target turned by 0.46 deg."""
    data = synthetic_pairs(WEAK, noise_px=0.2, seed=7)
    t = np.radians(0.46)
    rot = np.array([[np.cos(t), -np.sin(t)], [np.sin(t), np.cos(t)]])
    xy_u = (data.xy_u - [320, 240]) @ rot.T + [320, 240]
    path = tmp_path / "turned.csv"
    write_point_pairs(path, xy_u, data.xy_d)
    return path


def test_default_fit_adds_the_rotation_and_says_so(run_cli, turned_points, tmp_path):
    out = tmp_path / "c.json"
    code, _, err = run_cli("fit", turned_points, "--image-size", "640x480", "--out", out)
    assert code == 0
    assert "note: the target is turned by" in err and "fitted paper+rotation" in err
    assert "--rotation none" in err
    stored = json.loads(out.read_text())
    assert stored["model_family"] == "brown-conrady+rotation" and stored["fit"]["converged"] is True


def test_unconverged_fit_writes_nothing_and_names_the_cause(run_cli, turned_points, tmp_path):
    out = tmp_path / "c.json"
    code, _, err = run_cli("fit", turned_points, "--rotation", "none", "--out", out)
    assert code == 3
    assert not out.exists()
    (line,) = [ln for ln in err.splitlines() if ln.startswith("oapcal: error:")]
    assert str(turned_points) in line and "did not converge" in line and "nothing written" in line
    assert "distortion centre runs away" in line and "--keep-unconverged" in line


def test_unconverged_calibration_is_kept_only_when_asked_and_refused_by_users(
    run_cli, turned_points, tmp_path
):
    calib = tmp_path / "c.json"
    code, _, err = run_cli("fit", turned_points, "--rotation", "none", "--keep-unconverged",
                           "--image-size", "640x480", "--out", calib)  # fmt: skip
    assert code == 3 and calib.exists() and "written anyway" in err
    assert json.loads(calib.read_text())["fit"]["converged"] is False

    import cv2

    image = tmp_path / "img.png"
    cv2.imwrite(str(image), np.full((480, 640), 128, np.uint8))
    refusals = {
        "correct": ("correct", calib, image, "--out-dir", tmp_path / "out"),
        "correct-points": ("correct-points", calib, turned_points, "--out", tmp_path / "cp.csv"),
        "export-opencv": ("export-opencv", calib, "--out", tmp_path / "cam.yml"),
    }
    for name, args in refusals.items():
        code, out, err = run_cli(*args)
        assert code == 2, name
        lines = err.strip().splitlines()
        assert len(lines) == 1 and str(calib) in lines[0] and "did not converge" in lines[0], name
        assert "--allow-unconverged" in lines[0] and "Traceback" not in err, name
    assert not (tmp_path / "out").exists() and not (tmp_path / "cp.csv").exists()
    assert not (tmp_path / "cam.yml").exists()
    for name, args in refusals.items():
        code, _, err = run_cli(*args, "--allow-unconverged")
        assert code == 0, (name, err)
    assert (tmp_path / "out" / "img.png").exists() and (tmp_path / "cp.csv").exists()


def test_rotation_option_conflicts_with_a_rotation_model(run_cli, turned_points):
    code, _, err = run_cli("fit", turned_points, "--model", "paper+rotation", "--rotation", "none")
    assert code == 2 and "fits the rotation already" in err


def test_a_fit_with_negative_m_is_refused_and_the_default_fits_the_turn(run_cli, tmp_path):
    data = synthetic_pairs(seed=3)
    points = tmp_path / "upside_down.csv"
    write_point_pairs(points, -(data.xy_u - [320, 240]) + [320, 240], data.xy_d)
    out = tmp_path / "c.json"
    code, _, err = run_cli("fit", points, "--rotation", "none", "--out", out)
    assert code == 3 and not out.exists()
    assert "m = -1.01 <= 0" in err and "turned by about 180 deg" in err and "Traceback" not in err
    code, _, err = run_cli("fit", points, "--out", out)
    assert code == 0 and "turned by -180 deg" in err
    assert json.loads(out.read_text())["params"]["m"] > 0
    code, _, err = run_cli("correct-points", out, points, "--out", tmp_path / "cp.csv")
    assert code == 0, err
