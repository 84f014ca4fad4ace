"""The demo runs end to end (the README's first command) and its numbers hold up."""

import json

import pytest


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    from oapcal.demo import run_demo

    out = tmp_path_factory.mktemp("demo")
    return run_demo(out, trials=200)


def test_demo_writes_every_output(demo):
    for label in ("relay grid", "model selection", "simulated image", "ground truth", "detected points",
                  "calibration", "robustness", "corrected image", "report"):  # fmt: skip
        path = demo.files[label]
        assert path.exists() and path.stat().st_size > 0, label
    cal = json.loads(demo.files["calibration"].read_text())
    assert cal["format"] == "oapcal-calibration" and cal["fit"]["converged"]
    sel = json.loads(demo.files["model selection"].read_text())
    assert len(sel["models"]) == 4096


def test_demo_numbers(demo):
    # the relay's distortion is the paper's order of magnitude (docs/optics.md compares)
    assert 150 < demo.relay["distortion"]["max_um"] < 240
    # detection at paper-like conditions: the detection goal
    assert demo.detection["coverage"] >= 0.95 and demo.detection["mismatches"] == 0
    assert demo.detection["median_error_px"] <= 0.25
    # the fitted model reproduces the ray-traced distortion at the corners to ~ a pixel
    assert demo.truth_error["mean_px"] < 1.0
    assert demo.calibration.residuals.mean_px < 1.0


@pytest.mark.slow  # a second run of the demo; the default suite runs it once (the fixture above)
def test_demo_command(run_cli, tmp_path):
    code, out, err = run_cli("demo", "--out-dir", tmp_path / "d", "--trials", "0", "--no-report")
    assert code == 0, err
    assert "Model selection by AICc" in out and "Table 1" in out and "wrote calibration:" in out
    assert not (tmp_path / "d" / "report.html").exists()
