import csv
import json
import subprocess
import sys

import numpy as np
import pytest

from fresh_python import run_fresh
from oapcal.io.points import write_point_pairs


@pytest.fixture
def points_csv(tmp_path, pairs):
    path = tmp_path / "points.csv"
    write_point_pairs(path, pairs.xy_u, pairs.xy_d, ids=range(len(pairs.xy_u)))
    return path


def test_fit_json_contract(run_cli, points_csv, tmp_path, pairs):
    out = tmp_path / "calib.json"
    code, stdout, err = run_cli("fit", points_csv, "--model", "paper", "--um-per-px", "4.8",
                                "--out", out, "--json")  # fmt: skip
    assert code == 0, err
    data = json.loads(stdout)
    assert set(data) == {"free", "params", "stderr", "converged", "aicc", "residuals"}
    assert data["free"] == ["k1", "p1", "s3", "x_off", "y_off", "c_x", "c_y", "m"]
    assert len(data["params"]) == 13 and set(data["stderr"]) == set(data["free"])
    assert data["converged"] is True
    for key in ("max", "mean", "rms", "total"):
        assert data["residuals"][f"{key}_um"] == pytest.approx(4.8 * data["residuals"][f"{key}_px"])
    assert json.loads(out.read_text())["format"] == "oapcal-calibration"


def test_fit_table_output(run_cli, points_csv):
    code, stdout, _ = run_cli("fit", points_csv, "--model", "radial")
    assert code == 0
    assert "Fitted parameters" in stdout and "Table 1" in stdout and "0 (fixed)" in stdout


def test_correct_points_adds_columns(run_cli, points_csv, tmp_path, pairs):
    calib = tmp_path / "calib.json"
    assert run_cli("fit", points_csv, "--out", calib)[0] == 0
    out = tmp_path / "corrected.csv"
    code, _, err = run_cli("correct-points", calib, points_csv, "--out", out)
    assert code == 0, err
    with open(out) as fh:
        rows = list(csv.DictReader(fh))
    assert list(rows[0]) == ["id", "x_u", "y_u", "x_d", "y_d", "x_c", "y_c", "converged"]
    xy_c = np.array([[float(r["x_c"]), float(r["y_c"])] for r in rows])
    assert all(r["converged"] == "1" for r in rows)
    assert np.hypot(*(xy_c - pairs.xy_u).T).mean() < 0.6  # corrected onto the references


@pytest.mark.parametrize(
    "args,pattern",
    [
        (["fit", "{missing}"], "no such file"),
        (["fit", "{points}", "--model", "k1,kk"], "unknown parameter or preset 'kk'"),
        (["fit", "{few}", "--model", "full"], "too few for a model with 13 free parameters"),
        (["fit", "{points}", "--out", "{points}"], "would overwrite the input"),
        (["correct-points", "{points}", "{points}", "--out", "{tmp}/o.csv"], "line 1: malformed JSON"),
        (["fit", "{points}", "--init", "k1"], "bad initial value 'k1'"),
    ],
)
def test_user_errors_are_one_line_exit_2_and_write_nothing(run_cli, points_csv, tmp_path, args, pattern):
    few = tmp_path / "few.csv"
    few.write_text("x_u,y_u,x_d,y_d\n0,0,0,0\n1,0,1,0\n0,1,0,1\n1,1,1.1,1\n")
    before = sorted(p.name for p in tmp_path.iterdir())
    sub = {"missing": tmp_path / "missing.csv", "points": points_csv, "few": few, "tmp": tmp_path}
    code, stdout, err = run_cli(*(a.format(**sub) for a in args))
    assert code == 2
    assert err.count("\n") == 1 and pattern in err and "Traceback" not in err
    assert sorted(p.name for p in tmp_path.iterdir()) == before


def test_version_and_fast_help():
    _, loaded = run_fresh("from oapcal.cli import main; main(['--help']); main(['fit', '--help'])")
    assert sorted(loaded & {"numpy", "scipy", "cv2", "matplotlib", "rich", "dask"}) == []
    out = subprocess.run([sys.executable, "-m", "oapcal", "--version"], capture_output=True, text=True)
    assert out.returncode == 0 and "0.1.0" in out.stdout


def test_library_errors_name_parameters_and_the_cli_adds_the_flag(run_cli, tmp_path):
    import pytest

    from oapcal.errors import DataError
    from oapcal.io.points import write_point_pairs
    from oapcal.subsampling import robustness
    from oapcal.synthetic import synthetic_pairs

    d = synthetic_pairs(seed=4)
    with pytest.raises(DataError) as err:
        robustness(d.xy_u, d.xy_d, ["paper"], trials=2, fraction=0.001)
    assert err.value.param == "fraction" and "--" not in str(err.value)
    write_point_pairs(tmp_path / "p.csv", d.xy_u, d.xy_d)
    code, _, stderr = run_cli("robustness", tmp_path / "p.csv", "--fraction", "0.001", "--trials", "2")
    assert code == 2
    assert stderr.strip().endswith("change fraction (set by --fraction)"), stderr


def test_help_shows_no_empty_ranges(run_cli):
    """Unbounded float options (made finite by harden) show no ``[x<=None]`` in --help."""
    for command in (["simulate", "relay"], ["simulate", "image"], ["tolerance"], ["correct"], ["fit"]):
        code, out, _ = run_cli(*command, "--help")
        assert code == 0 and "None]" not in out, command
