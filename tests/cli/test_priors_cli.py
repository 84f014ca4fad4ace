"""fit --priors and select --priors/--region on the command line."""

import json

import numpy as np

from oapcal.model import distort
from oapcal.optics.relay_model import RelayDesign, relay_params


def _points(tmp_path, n=40, noise=0.3, seed=2):
    design = RelayDesign(setup=1, centre=(319.5, 239.5))
    truth = relay_params(design, {"m2_decentre_y": 0.1, "d1": 15.0, "camera_defocus": 0.1}, {"rotation": 0.3})
    rng = np.random.default_rng(seed)
    xy_u = rng.uniform([277, 197], [362, 282], (n, 2))
    xy_d = distort(xy_u, truth) + rng.normal(0, noise, (n, 2))
    path = tmp_path / "p.csv"
    rows = ["x_u,y_u,x_d,y_d"] + [
        f"{a!r},{b!r},{c!r},{d!r}" for (a, b), (c, d) in zip(xy_u.tolist(), xy_d.tolist())
    ]
    path.write_text("\n".join(rows) + "\n")
    return path


def test_fit_with_priors_writes_them_and_refuses_bad_values(tmp_path, run_cli):
    points = _points(tmp_path)
    out = tmp_path / "c.json"
    args = ("fit", points, "--model", "relay", "--relay-centre", "319.5,239.5")
    code, stdout, err = run_cli(*args, "--priors", "default", "--out", out)
    assert code == 0, err
    data = json.loads(out.read_text())
    assert data["priors"]["spec"] == "default" and data["fit"]["k_eff"] < data["fit"]["k"]
    assert "maximum a posteriori fit" in stdout
    spec = tmp_path / "pri.json"
    spec.write_text(json.dumps({"tilt": 0.1, "noise_px": 0.3}))
    code, _, err = run_cli("fit", points, "--model", "relay", "--priors", spec, "--out", out)
    assert code == 0, err
    assert json.loads(out.read_text())["priors"]["widths"]["tilt"] == 0.1
    spec.write_text(json.dumps({"wobble": 1}))
    code, _, err = run_cli("fit", points, "--model", "relay", "--priors", spec)
    assert code == 2 and "pri.json" in err and "unknown prior 'wobble'" in err and "--priors" in err
    assert len(err.strip().splitlines()) == 1
    code, _, err = run_cli("fit", points, "--model", "paper", "--priors", "default")
    assert code == 2 and "relay model" in err
    code, _, err = run_cli("fit", points, "--model", "relay", "--priors", "tilt=abc")
    assert code == 2 and "not a number" in err


def test_select_priors_and_region_need_families(tmp_path, run_cli):
    points = _points(tmp_path)
    code, _, err = run_cli("select", points, "--priors", "default")
    assert code == 2 and "--families" in err
    code, _, err = run_cli("select", points, "--families", "relay", "--region", "1,2,3")
    assert code == 2 and "--region" in err
