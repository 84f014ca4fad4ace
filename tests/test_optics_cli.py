"""``oapcal simulate relay`` through the in-process runner."""

import json
import subprocess
import sys

import numpy as np
import pytest

from oapcal.io.points import read_points


def test_relay_grid_csv_and_json(run_cli, tmp_path):
    out = tmp_path / "grid.csv"
    code, stdout, err = run_cli("simulate", "relay", "--setup", "1", "--units", "px", "--out", out, "--json")
    assert code == 0, err
    data = json.loads(stdout)
    assert data["paper"]["max_um"] == 193.0
    assert data["distortion"]["max_um"] == pytest.approx(193.0, rel=0.02)
    assert data["distortion"]["max_px"] == pytest.approx(data["distortion"]["max_um"] / 4.8)
    assert data["radial_fit"]["converged"] is True
    pairs = read_points(out)
    assert len(pairs) == 289
    # px columns: image mm / 4.8 um; the largest |real - paraxial| matches the summary.
    assert np.hypot(*(pairs.xy_d - pairs.xy_u).T).max() == pytest.approx(data["distortion"]["max_px"])
    header = out.read_text().splitlines()[0]
    assert header == "x_obj,y_obj,x_u,y_u,x_d,y_d,clear"


def test_relay_table_and_figures(run_cli, tmp_path):
    code, stdout, err = run_cli("simulate", "relay", "--setup", "2", "--grid", "5",
                                "--plot", tmp_path / "g.png", "--spots", tmp_path / "s.png")  # fmt: skip
    assert code == 0, err
    assert "Grid distortion" in stdout and "RMS spot radius" in stdout and "d1 = 660 mm" in stdout
    assert (tmp_path / "g.png").read_bytes()[:4] == b"\x89PNG"
    assert (tmp_path / "s.png").read_bytes()[:4] == b"\x89PNG"


@pytest.mark.parametrize(
    "args,pattern",
    [
        (["--stop-distance", "2000"], "outside the collimated path"),
        (["--d1", "-3"], "must be a positive"),
        (["--image-size", "640x480"], "--image-size needs --units px"),
        (["--grid", "1"], "at least 2 points"),
        (["--pixel-size", "0"], "--pixel-size must be positive"),
    ],
)
def test_relay_user_errors(run_cli, tmp_path, args, pattern):
    code, _, err = run_cli("simulate", "relay", "--out", tmp_path / "g.csv", *args)
    assert code == 2 and err.count("\n") == 1 and pattern in err
    assert list(tmp_path.iterdir()) == []


def test_relay_help_is_lazy():
    code = (
        "import sys; from oapcal.cli import main; main(['simulate', 'relay', '--help']);"
        "print('HEAVY', [m for m in ('numpy', 'scipy', 'matplotlib', 'rich') if m in sys.modules])"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert "HEAVY []" in out
