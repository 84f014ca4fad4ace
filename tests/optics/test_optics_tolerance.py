"""Tolerancing: sensitivities against independent computations and optics, the Monte Carlo,
and ``oapcal tolerance``."""

import json

import numpy as np
import pytest
from scipy.linalg import orthogonal_procrustes

from fresh_python import run_fresh
from oapcal.errors import GeometrySpecError
from oapcal.model import undistort
from oapcal.optics.misalign import PARAMETERS
from oapcal.optics.relay import grid_distortion, oap_relay
from oapcal.optics.tolerance import GROUPS, RESOLUTION_PX, Tolerancing, expand_tolerances

PX = 1e3 / 4.8  # px per image mm
CENTRE = np.array([319.5, 239.5])


@pytest.fixture(scope="module")
def tol():
    return Tolerancing(oap_relay(1), n=9)


@pytest.fixture(scope="module")
def rows(tol):
    return {r["parameter"]: r for r in tol.sensitivity()}


def _rigid_residual(tol, misalignment):
    """Corrected points of a misaligned relay vs the ideal image, after the best rotation
    and shift (SciPy's orthogonal Procrustes, not the code under test)."""
    grid = grid_distortion(oap_relay(1, misalignment=misalignment), n=9)
    truth = grid_distortion(oap_relay(1), n=9).xy_u * PX + CENTRE
    corrected = undistort(grid.xy_d * PX + CENTRE, tol.calibration.params).xy
    a, b = corrected - corrected.mean(0), truth - truth.mean(0)
    rot, _ = orthogonal_procrustes(a, b)
    return a @ rot - b


def test_aligned_metrics_are_the_calibrations_own_floor(tol):
    grid = grid_distortion(oap_relay(1), n=9)
    assert tol.aligned["max_px"] == pytest.approx(grid.distortion.max() * PX)
    assert tol.aligned["mean_px"] == pytest.approx(grid.distortion.mean() * PX)
    direct = np.hypot(*_rigid_residual(tol, None).T)
    assert tol.aligned["corrected_mean_px"] == pytest.approx(direct.mean(), rel=1e-6)
    assert tol.aligned["corrected_max_px"] == pytest.approx(direct.max(), rel=1e-6)
    assert 0.05 < tol.aligned["corrected_mean_px"] < 0.5  # the paper model's floor, not 0
    assert tol.aligned["shift_px"] == 0.0 and tol.aligned["scale_error_ppm"] == 0.0


@pytest.mark.parametrize("name", ["m2_tilt_x", "m2_decentre_y", "camera_tilt_y", "m1_tilt_y"])
def test_corrected_error_rates_match_an_independent_difference(tol, rows, name):
    h = 1e-3
    rate = (_rigid_residual(tol, {name: h}) - _rigid_residual(tol, {name: -h})) / (2 * h)
    assert rows[name]["corrected_mean_px"] == pytest.approx(np.hypot(*rate.T).mean(), rel=1e-4)
    assert rows[name]["corrected_max_px"] == pytest.approx(np.hypot(*rate.T).max(), rel=1e-4)


def test_sensitivities_follow_the_optics(rows):
    # A mirror tipped by 1 deg turns the beam by 2 deg: the image moves 2 f tan(2 deg).
    for name in ("m1_tilt_x", "m2_tilt_x"):
        assert rows[name]["shift_px"] == pytest.approx(2 * 50.8 * np.radians(1.0) * PX, rel=1e-3)
    # The focusing mirror moved sideways carries the image along, 1 mm per mm.
    assert rows["m2_decentre_x"]["shift_px"] == pytest.approx(PX, rel=1e-6)
    # Defocus: the exit pupil (the stop at OAP 1 imaged by OAP 2) lies f^2 / (d1 - f)
    # beyond the focus, so moving the camera by 1 mm scales the image by -(d1 - f) / f^2.
    assert rows["camera_defocus"]["scale_ppm"] == pytest.approx(-(860 - 50.8) / 50.8**2 * 1e6, rel=1e-3)
    # With the stop at OAP 1, clocking it or changing its focal length leaves every
    # chief ray alone (they pass its centre, whose position and normal stay).
    for name in ("m1_clock", "m1_focal_length"):
        assert max(abs(v) for k, v in rows[name].items() if k.endswith("_px")) < RESOLUTION_PX
        assert abs(rows[name]["scale_ppm"]) < 1.0
    # Symmetric-breaking perturbations raise the max distortion either way (a kink).
    r = rows["m2_tilt_y"]
    assert r["max_plus_px"] == pytest.approx(r["max_minus_px"], rel=1e-3) and r["max_plus_px"] > 1.0
    assert set(rows) == set(PARAMETERS)


def test_monte_carlo_is_seeded_and_summarizes_its_samples(tol):
    tolerances = expand_tolerances({"tilt": 0.02, "defocus": 0.05})
    a = tol.monte_carlo(tolerances, 40, seed=5, percentiles=(10, 50, 90))
    b = tol.monte_carlo(tolerances, 40, seed=5, percentiles=(10, 50, 90))
    c = tol.monte_carlo(tolerances, 40, seed=6, percentiles=(10, 50, 90))
    assert a == b and a["summary"] != c["summary"]
    values = np.array([[s["misalignment"][k] for k in tolerances] for s in a["samples"]])
    limits = np.array(list(tolerances.values()))
    assert (np.abs(values) <= limits).all() and (np.abs(values).max(0) > 0.7 * limits).all()
    for metric, stats in a["summary"].items():
        v = np.array([s[metric] for s in a["samples"]])
        assert stats["p50"] == pytest.approx(np.median(v)) and stats["max"] == pytest.approx(v.max())
        assert stats["p10"] <= stats["p50"] <= stats["p90"] <= stats["max"]
    # One trial evaluated on its own gives the same numbers.
    first = a["samples"][0]
    again = tol.evaluate(first["misalignment"])
    assert again["corrected_mean_px"] == pytest.approx(first["corrected_mean_px"], rel=1e-9)
    assert a["n_failed"] == 0 and a["trials"] == 40
    # Misaligned relays are corrected worse than the aligned one.
    assert a["summary"]["corrected_mean_px"]["p10"] > tol.aligned["corrected_mean_px"]


def test_monte_carlo_normal_distribution_and_refit(tol):
    mc = tol.monte_carlo({"camera_tilt_x": 1.0}, 30, seed=1, distribution="normal", refit=True)
    values = np.array([s["misalignment"]["camera_tilt_x"] for s in mc["samples"]])
    assert 0.2 < values.std() < 0.9  # sigma = tolerance / 2
    # Refitting the model to each tilted relay gets back to about the aligned floor.
    assert mc["summary"]["refit_mean_px"]["max"] < 2 * tol.aligned["corrected_mean_px"]


def test_tolerance_groups_and_errors():
    out = expand_tolerances({"tilt": 0.1, "d1": 0.0}, {"m2_tilt_x": 0.02})
    assert out == {"m1_tilt_x": 0.1, "m1_tilt_y": 0.1, "m2_tilt_x": 0.02, "m2_tilt_y": 0.1}
    assert set().union(*GROUPS.values()) == set(PARAMETERS)  # every parameter has a group
    with pytest.raises(GeometrySpecError, match="unknown tolerance group"):
        expand_tolerances({"tip": 0.1})
    with pytest.raises(GeometrySpecError, match="unknown misalignment 'm2_tip'"):
        expand_tolerances(parameters={"m2_tip": 0.1})
    with pytest.raises(GeometrySpecError, match="must be a number >= 0"):
        expand_tolerances({"tilt": -0.1})


# ---------------------------------------------------------------- the command


def test_tolerance_command_json_and_plot(run_cli, tmp_path):
    plot = tmp_path / "tol.png"
    code, stdout, err = run_cli("tolerance", "--grid", "7", "--tilt", "0.02", "--tol", "m2_tilt_x=0.01",
                                "--trials", "20", "--seed", "3", "--percentiles", "50,99", "--plot", plot,
                                "--json")  # fmt: skip
    assert code == 0, err
    data = json.loads(stdout)
    assert data["grid"]["n"] == 7 and data["model"] == "paper"
    assert [r["parameter"] for r in data["sensitivity"]] == list(PARAMETERS)
    mc = data["monte_carlo"]
    assert mc["trials"] == 20 and mc["seed"] == 3 and mc["percentiles"] == [50.0, 99.0]
    assert mc["tolerances"]["m2_tilt_x"] == 0.01 and mc["tolerances"]["m1_tilt_y"] == 0.02
    assert set(mc["summary"]["corrected_mean_px"]) == {"mean", "std", "max", "p50", "p99"}
    assert plot.read_bytes()[:4] == b"\x89PNG"


def test_tolerance_command_tables(run_cli):
    code, stdout, err = run_cli("tolerance", "--grid", "5", "--defocus", "0.1", "--trials", "5")
    assert code == 0, err
    assert "Sensitivity per unit" in stdout and "camera_defocus" in stdout and "Monte Carlo" in stdout
    code, stdout, err = run_cli("tolerance", "--grid", "5")
    assert code == 0, err
    assert "No tolerances given" in stdout


@pytest.mark.parametrize(
    "args,pattern",
    [
        (["--tilt", "-0.1"], "--tilt must be a tolerance >= 0"),
        (["--tilt", "abc"], "'abc' is not a valid float"),
        (["--percentiles", "50,x"], "--percentiles '50,x' is not a list"),
        (["--percentiles", "120"], "each in 0..100"),
        (["--tol", "m2_tilt_x"], "is not NAME=VALUE"),
        (["--tol", "m9_tilt=1"], "unknown misalignment 'm9_tilt'"),
        (["--trials", "0", "--tilt", "0.1"], "--trials must be at least 1"),
        (["--grid", "1"], "at least 2 points"),
        (["--model", "k9"], "k9"),
        (["--d1", "-5"], "must be a positive"),
        (["--no-such-option"], "no-such-option"),
    ],
)
def test_tolerance_command_errors_are_one_line(run_cli, tmp_path, args, pattern):
    code, stdout, err = run_cli("tolerance", "--plot", tmp_path / "t.png", *args)
    assert code == 2 and err.count("\n") == 1 and pattern in err, err
    assert stdout == "" and list(tmp_path.iterdir()) == []


def test_tolerance_help_is_lazy():
    printed, loaded = run_fresh("from oapcal.cli import main; main(['tolerance', '--help'])")
    assert sorted(loaded & {"numpy", "scipy", "matplotlib", "rich"}) == [] and "--decentre" in printed


def test_monte_carlo_counts_relays_whose_rays_miss(tol):
    # OAP 2 moved by up to 500 mm: the beam misses it in some trials, which are counted
    # as lost and left out of the summary instead of poisoning it.
    mc = tol.monte_carlo({"m2_decentre_x": 500.0}, 8, seed=2)
    lost = [s for s in mc["samples"] if s["max_px"] is None]
    assert mc["n_lost"] == len(lost) and 0 < len(lost) < 8
    assert all(v is None for s in lost for k, v in s.items() if k != "misalignment")
    kept = [s["max_px"] for s in mc["samples"] if s["max_px"] is not None]
    assert mc["summary"]["max_px"]["max"] == pytest.approx(max(kept))
