"""``--model relay`` and ``+rotation`` through the command line, on fields traced by the
NumPy tracer (``oapcal simulate relay --reference design``), which is independent of the
compiled relay model."""

import json

import numpy as np
import pytest

from oapcal.io.calibration import load_calibration
from oapcal.io.points import read_points
from oapcal.model import RELAY, undistort


@pytest.fixture(scope="module")
def traced(tmp_path_factory):
    """A misaligned relay's field (tilted second mirror and camera), 13 x 13 points in camera px."""
    from click.testing import CliRunner

    from oapcal.cli import cli

    path = tmp_path_factory.mktemp("relay") / "grid.csv"
    args = ["simulate", "relay", "--units", "px", "--image-size", "640x480", "--grid", "13",
            "--m2-tilt-x", "0.03", "--camera-tilt-y", "0.5", "--reference", "design",
            "--out", str(path)]  # fmt: skip
    result = CliRunner().invoke(cli, args)
    assert result.exit_code == 0, result.output
    return path


def test_fit_relay_recovers_the_misalignment_exactly(run_cli, traced, tmp_path):
    out = tmp_path / "cal.json"
    model = "relay:tilt2,d1,defocus,camera"
    # the least-squares fit (--priors off): noise-free points give the misalignment exactly
    code, stdout, err = run_cli("fit", traced, "--model", model, "--relay-setup", "1", "--priors", "off",
                                "--pixel-size", "4.8", "--image-size", "640x480", "--out", out)  # fmt: skip
    assert code == 0, err
    cal = load_calibration(out)
    assert cal.family is RELAY and cal.relay_design["centre"] == [319.5, 239.5]
    values = cal.params_dict
    assert values["m2_tilt_x"] == pytest.approx(0.03, abs=1e-9)
    assert values["camera_tilt_y"] == pytest.approx(0.5, abs=1e-8)
    assert abs(values["camera_tilt_x"]) < 1e-8 and abs(values["d1"]) < 1e-6
    assert abs(values["camera_defocus"]) < 1e-8
    assert cal.residuals.max_px < 1e-6
    assert "The relay as fitted" in stdout and "m2_tilt_x: second mirror: tip" in stdout
    # correct-points uses the relay calibration: the corrected points are the reference points
    corrected = tmp_path / "corrected.csv"
    code, _, err = run_cli("correct-points", out, traced, "--out", corrected)
    assert code == 0, err
    pairs = read_points(traced)
    rows = corrected.read_text().splitlines()[1:]
    xy_c = np.array([[float(v) for v in r.split(",")[7:9]] for r in rows])
    np.testing.assert_allclose(xy_c, pairs.xy_u, atol=1e-6)
    np.testing.assert_allclose(xy_c, undistort(pairs.xy_d, cal.params).xy, atol=1e-9)


def test_fit_relay_refuses_an_unidentifiable_subset(run_cli, traced, tmp_path):
    # without priors (with the default priors every value is determined: relay:all fits)
    code, _, err = run_cli("fit", traced, "--model", "relay:all", "--image-size", "640x480", "--out",
                           tmp_path / "x.json", "--priors", "off")  # fmt: skip
    assert code == 2
    assert "cannot tell these relay parameters apart" in err and "m2_tilt_y ~ m2_decentre_x" in err
    assert not (tmp_path / "x.json").exists()
    code, _, err = run_cli("fit", traced, "--model", "relay:d1,tilt9", "--out", tmp_path / "y.json")
    assert code == 2 and "unknown relay parameter 'tilt9'" in err
    code, _, err = run_cli("fit", traced, "--model", "relay", "--normalize", "experiment")
    assert code == 2 and "--normalize" in err


def test_rotation_is_fitted_with_eq1(run_cli, traced, tmp_path):
    out = tmp_path / "rot.json"
    code, stdout, err = run_cli("fit", traced, "--model", "paper+rotation", "--out", out, "--json")
    assert code == 0, err
    data = json.loads(out.read_text())
    assert data["model_family"] == "brown-conrady+rotation" and "rotation" in data["free"]
    assert json.loads(stdout)["free"][-1] == "rotation"


def test_robustness_with_a_relay_model(run_cli, traced, tmp_path):
    out = tmp_path / "rob.json"
    code, stdout, err = run_cli("robustness", traced, "--models", "paper,relay:tilt2+camera",
                                "--trials", "20", "--init", "pixel", "--image-size", "640x480",
                                "--json", out, "--priors", "off")  # fmt: skip
    assert code == 0, err
    data = json.loads(out.read_text())
    relay = data["models"]["relay:tilt2,camera"]
    assert relay["not_converged"] == 0 and relay["heldout_mean_error_px"] < 1e-6
    assert data["models"]["paper"]["heldout_mean_error_px"] > 0.01  # Eq. (1)'s floor on this field


def test_report_reads_a_family_selection_file(run_cli, traced, tmp_path):
    cal = tmp_path / "cal.json"
    code, _, err = run_cli("fit", traced, "--model", "relay", "--image-size", "640x480", "--out", cal)
    assert code == 0, err
    from oapcal.families import Candidate, FamilySelection
    from oapcal.io.results import save_family_selection

    loaded = load_calibration(cal)
    mine = Candidate("relay", "relay", loaded.free, len(loaded.free), -10.0, 0.0, 1e-3, True, "", 1e-3, 0)
    other = Candidate("brown-conrady", "paper", ("k1", "m"), 2, 50.0, 60.0, 0.2, True, "", 0.21, 0)
    save_family_selection(FamilySelection(169, 5, (mine, other), mine), tmp_path / "fam.json")
    code, _, err = run_cli("report", cal, "--selection", tmp_path / "fam.json", "--out", tmp_path / "r.html")
    assert code == 0, err
    page = (tmp_path / "r.html").read_text()
    assert "Recommended in the selection file: relay (relay, held-out error 0.001 px)." in page
    assert "by the held-out error" not in page


@pytest.mark.slow
def test_select_model_relay_ranks_the_relay_subsets(run_cli, traced, tmp_path):
    out = tmp_path / "fam.json"
    code, stdout, err = run_cli("select", traced, "--model", "relay", "--image-size", "640x480", "--cv", "2",
                                "--top", "2", "--json", out)  # fmt: skip
    assert code == 0, err
    data = json.loads(out.read_text())
    assert {c["family"] for c in data["candidates"]} == {"relay"}
    assert data["recommended"].startswith("relay:")
    code, _, err = run_cli("select", traced, "--model", "paper")
    assert code == 2 and "--model" in err
