"""The priors are the default of a relay fit on the command line (fit, select --families,
robustness); --priors off is the least-squares fit exactly."""

import json

import numpy as np
import pytest

from oapcal.model import distort
from oapcal.optics.relay_model import RelayDesign, calibrate_relay, relay_params

DESIGN = RelayDesign(setup=1, centre=(319.5, 239.5))


def _central_points(tmp_path, n=40, noise=0.3, seed=5):
    """40 landmarks over the central 40 % of the 1 mm field through a misaligned relay."""
    truth = relay_params(DESIGN, {"m2_decentre_y": 0.1, "d1": 15.0, "camera_defocus": 0.1}, {"rotation": 0.3})
    rng = np.random.default_rng(seed)
    xy_u = rng.uniform([277, 197], [362, 282], (n, 2))
    xy_d = distort(xy_u, truth) + rng.normal(0, noise, (n, 2))
    path = tmp_path / "p.csv"
    np.savetxt(
        path, np.hstack([xy_u, xy_d]), delimiter=",", header="x_u,y_u,x_d,y_d", comments="", fmt="%.17g"
    )
    return path, xy_u, xy_d


def test_fit_relay_uses_the_default_priors_unless_off(tmp_path, run_cli):
    points, xy_u, xy_d = _central_points(tmp_path)
    args = ("fit", points, "--model", "relay", "--relay-centre", "319.5,239.5")
    code, stdout, err = run_cli(*args, "--out", tmp_path / "auto.json")
    assert code == 0, err
    auto = json.loads((tmp_path / "auto.json").read_text())
    assert auto["priors"]["spec"] == "default" and auto["fit"]["k_eff"] < auto["fit"]["k"]
    assert "maximum a posteriori fit" in stdout
    # the same as asking for them
    code, _, err = run_cli(*args, "--priors", "default", "--out", tmp_path / "default.json")
    assert code == 0, err
    assert json.loads((tmp_path / "default.json").read_text())["params"] == auto["params"]
    # off: the least-squares fit exactly (the library's fit without priors), no priors key
    code, stdout, err = run_cli(*args, "--priors", "off", "--out", tmp_path / "off.json")
    assert code == 0, err
    off = json.loads((tmp_path / "off.json").read_text())
    assert "priors" not in off and "maximum a posteriori" not in stdout
    plain = calibrate_relay(xy_u, xy_d, DESIGN, "default")
    got = np.array([off["params"][n] for n in plain.family.param_names])
    np.testing.assert_array_equal(got, plain.params)
    assert off["params"] != auto["params"]


def test_eq1_fit_and_select_take_no_priors_by_default(tmp_path, run_cli):
    points, _, _ = _central_points(tmp_path)
    code, _, err = run_cli("fit", points, "--model", "paper", "--out", tmp_path / "c.json")
    assert code == 0, err
    assert "priors" not in json.loads((tmp_path / "c.json").read_text())
    code, _, err = run_cli("select", points, "--top", "3")
    assert code == 0, err


def test_select_families_passes_the_default_priors_unless_off(tmp_path, run_cli, monkeypatch):
    """Fast: what select --families hands to select_families (the slow test below runs it)."""
    import oapcal.families
    from oapcal.errors import DataError

    seen = []

    def capture(*args, priors=None, **kwargs):
        seen.append(priors)
        raise DataError("stop here")

    monkeypatch.setattr(oapcal.families, "select_families", capture)
    points, _, _ = _central_points(tmp_path)
    for priors in ("auto", "off", "tilt=0.1"):
        code, _, err = run_cli("select", points, "--families", "relay", "--priors", priors)
        assert code != 0 and "stop here" in err
    assert seen[0].spec == "default" and dict(seen[0].widths)["tilt"] == 0.05
    assert seen[1] is None and dict(seen[2].widths)["tilt"] == 0.1


@pytest.mark.slow
def test_select_families_uses_the_default_priors(tmp_path, run_cli):
    points, _, _ = _central_points(tmp_path)
    args = ("select", points, "--families", "relay", "--relay-centre", "319.5,239.5", "--top", "2", "--json")
    code, _, err = run_cli(*args, tmp_path / "auto.json")
    assert code == 0, err
    assert json.loads((tmp_path / "auto.json").read_text())["priors"]["spec"] == "default"
    code, _, err = run_cli(*args, tmp_path / "off.json", "--priors", "off")
    assert code == 0, err
    assert json.loads((tmp_path / "off.json").read_text())["priors"] is None
