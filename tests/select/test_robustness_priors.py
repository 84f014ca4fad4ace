"""The robustness test with relay priors (StartedModel(prior=...), robustness --priors)."""

import json

import numpy as np
import pytest

from oapcal.fitting import fit_batch
from oapcal.model import distort
from oapcal.optics.relay_model import RelayDesign, parse_priors, relay_mask, relay_params
from oapcal.subsampling import StartedModel, robustness

DESIGN = RelayDesign(setup=1, centre=(319.5, 239.5))
SPEC = "relay:decentre2,d1"


def _points(n=30, noise=0.3, seed=7):
    truth = relay_params(
        DESIGN, {"m2_decentre_y": 0.12, "d1": 25.0, "m1_decentre_x": -0.1}, {"rotation": 0.2}
    )
    rng = np.random.default_rng(seed)
    xy_u = rng.uniform([240, 160], [400, 320], (n, 2))
    return xy_u, distort(xy_u, truth) + rng.normal(0, noise, (n, 2))


def _model(prior=None):
    return StartedModel(SPEC, relay_mask(SPEC), relay_params(DESIGN), prior=prior)


def test_trials_are_map_fits_with_the_models_priors():
    xy_u, xy_d = _points()
    priors = parse_priors("base=none,d1_mm=0.5")  # d1 held to 0.5 mm: its spread collapses
    prior = priors.arrays(DESIGN, 0.3)
    plain, tight = (robustness(xy_u, xy_d, [_model(p)], trials=12, seed=3).models[0] for p in (None, prior))
    assert plain.not_converged == 0 and tight.not_converged == 0
    assert tight.param_std["d1"] < 0.2 * plain.param_std["d1"]
    # the reference fit is the MAP fit of all points (its RMS from fit_batch with the rows)
    ref = fit_batch(xy_u, xy_d, relay_mask(SPEC)[None], relay_params(DESIGN), covariance=False, prior=prior)
    assert tight.reference_rms == pytest.approx(float(np.sqrt(ref.rss[0] / len(xy_u))), rel=1e-12)
    # infinite widths: the test without priors, trial for trial
    none = (np.zeros(len(prior[0])), np.full(len(prior[0]), np.inf))
    wide = robustness(xy_u, xy_d, [_model(none)], trials=12, seed=3).models[0]
    assert wide.param_std == pytest.approx(plain.param_std, rel=1e-6)


def test_robustness_command_takes_priors(tmp_path, run_cli):
    xy_u, xy_d = _points()
    path = tmp_path / "p.csv"
    np.savetxt(
        path, np.hstack([xy_u, xy_d]), delimiter=",", header="x_u,y_u,x_d,y_d", comments="", fmt="%.17g"
    )
    args = (
        "robustness",
        path,
        "--models",
        "relay:decentre2+d1",
        "--trials",
        "6",
        "--relay-centre",
        "319.5,239.5",
    )
    runs = {}
    for priors in ("auto", "off", "d1_mm=0.5"):
        code, stdout, err = run_cli(*args, "--priors", priors, "--json", tmp_path / f"{priors}.json")
        assert code == 0, err
        assert ("maximum a posteriori fits, priors" in stdout) == (priors != "off")
        runs[priors] = json.loads((tmp_path / f"{priors}.json").read_text())["models"]["relay:decentre2,d1"]
    assert runs["d1_mm=0.5"]["param_std"]["d1"] < 0.2 * runs["off"]["param_std"]["d1"]
    assert runs["auto"]["param_std"] != runs["off"]["param_std"]
    code, _, err = run_cli("robustness", path, "--models", "paper", "--priors", "default")
    assert code == 2 and "relay model" in err and len(err.strip().splitlines()) == 1
