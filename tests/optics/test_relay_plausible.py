"""A relay fit whose misalignment is not plausible is not a success (issue 24, A3)."""

import dataclasses

import numpy as np

from oapcal.model import RELAY, distort
from oapcal.optics.relay_model import RelayDesign, calibrate_relay, implausible, relay_params


def _fit():
    design = RelayDesign(setup=1, centre=(319.5, 239.5))
    rng = np.random.default_rng(0)
    truth = relay_params(design, {"m2_decentre_x": 0.1, "d1": 10.0, "camera_tilt_x": 0.5})
    xy_u = rng.uniform([215, 135], [424, 344], (60, 2))
    return calibrate_relay(xy_u, distort(xy_u, truth) + rng.normal(0, 0.05, (60, 2)), design)


def _with(cal, **values):
    p = np.array(cal.params)
    for name, v in values.items():
        p[RELAY.param_names.index(name)] = v
    return dataclasses.replace(cal, params=p)


def test_a_plausible_fit_passes_and_runaway_values_are_named():
    cal = _fit()
    assert cal.fit.converged and implausible(cal) == ""
    msg = implausible(_with(cal, camera_tilt_x=354.9, d1=155e6))
    assert "camera_tilt_x = 354.9 deg is beyond +/- 45 deg" in msg
    assert "d1 = 1.55e+08 mm is beyond the design's d1 of 860 mm" in msg
    assert "units" in msg and "priors" in msg
    assert "m2_decentre_x = 60 mm" in implausible(_with(cal, m2_decentre_x=60.0))
    res = dataclasses.replace(cal.residuals, n_failed=45)
    assert "45 of 60 calibration points cannot be corrected" in implausible(
        dataclasses.replace(cal, residuals=res)
    )


def test_fit_refuses_an_implausible_relay_fit(tmp_path, run_cli, monkeypatch):
    import oapcal.optics.relay_model as rm

    cal = _fit()
    rows = ["x_u,y_u,x_d,y_d"]
    rng = np.random.default_rng(1)
    xy_u = rng.uniform([215, 135], [424, 344], (40, 2))
    xy_d = distort(xy_u, cal.params)
    rows += [f"{a},{b},{c},{d}" for (a, b), (c, d) in zip(xy_u, xy_d)]
    points = tmp_path / "p.csv"
    points.write_text("\n".join(rows) + "\n")
    out = tmp_path / "c.json"
    code, _, err = run_cli("fit", points, "--model", "relay", "--relay-centre", "319.5,239.5", "--out", out)
    assert code == 0 and out.exists(), err
    out.unlink()
    monkeypatch.setattr(rm, "implausible", lambda c: "the relay fit is not a plausible misalignment (x)")
    code, _, err = run_cli("fit", points, "--model", "relay", "--relay-centre", "319.5,239.5", "--out", out)
    assert code == 3 and not out.exists()
    assert "not a plausible misalignment" in err and "nothing written" in err
