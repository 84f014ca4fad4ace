"""The report of a calibration whose model folds over beyond its landmarks (written by fit
with a note) says so, and names how its error model combined the refits of its sides."""

import html

import numpy as np

from oapcal.calibration import calibrate
from oapcal.io.calibration import save_calibration
from oapcal.model import distort, params_from_dict


def _report(run_cli, tmp_path, cal):
    save_calibration(cal, tmp_path / "c.json")
    code, _, err = run_cli("report", tmp_path / "c.json", "--out", tmp_path / "r.html")
    assert code == 0, err
    return html.unescape((tmp_path / "r.html").read_text())


def _pairs(k1):
    gx, gy = np.meshgrid(np.linspace(0, 639, 12), np.linspace(0, 479, 9))
    xy_u = np.stack([gx.ravel(), gy.ravel()], -1)
    truth = params_from_dict({"k1": k1, "x_off": -320, "y_off": -240, "c_x": 320, "c_y": 240, "m": 1})
    rng = np.random.default_rng(1)
    return xy_u, distort(xy_u, truth) + rng.normal(0, 0.05, xy_u.shape)


def test_a_fold_beyond_the_landmarks_is_noted_in_the_report(run_cli, tmp_path):
    # barrel distortion that turns back ~580 px from the centre: inside a 1600 x 1200 frame
    cal = calibrate(*_pairs(-1e-6), "paper", image_size=(1600, 1200))
    text = _report(run_cli, tmp_path, cal)
    assert "Note: the model folds over beyond the reference points' bounds" in text
    assert "1600x1200 px image" in text
    assert "the worst of 8 refits" in text  # Eq. (1): the worst side


def test_no_fold_no_note(run_cli, tmp_path):
    cal = calibrate(*_pairs(-2e-7), "paper", image_size=(640, 480))
    assert "folds over" not in _report(run_cli, tmp_path, cal)
