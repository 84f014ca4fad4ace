"""``oapcal simulate relay`` through the in-process runner."""

import json
import subprocess
import sys

import numpy as np
import pytest

from fresh_python import run_fresh
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
    _, loaded = run_fresh("from oapcal.cli import main; main(['simulate', 'relay', '--help'])")
    assert sorted(loaded & {"numpy", "scipy", "matplotlib", "rich"}) == []


def test_relay_chosen_spot_fields_rings_and_csv_values(run_cli, tmp_path):
    out = tmp_path / "grid.csv"
    code, stdout, err = run_cli("simulate", "relay", "--grid", "5", "--field", "0.8", "--pixel-size", "5",
                                "--spot-field", "0.4,-0.4", "--spot-field", "0,0", "--rings", "3",
                                "--out", out, "--json")  # fmt: skip
    assert code == 0, err
    data = json.loads(stdout)
    spots = data["quality"]["spots"]
    assert [(s["orientation"], s["field_mm"]) for s in spots] == [
        ("U", [0.4, -0.4]), ("U", [0.0, 0.0]), ("Z", [0.4, -0.4]), ("Z", [0.0, 0.0])
    ]  # fmt: skip
    assert data["quality"]["rings"] == 3
    assert data["paper"] is None  # a 5 x 5 grid is not the paper's case
    rows = [line.split(",") for line in out.read_text().splitlines()[1:]]
    obj = np.array([[float(r[0]), float(r[1])] for r in rows])
    # The object grid: 5 x 5 over 0.8 mm, x fastest, both ascending.
    s = np.linspace(-0.4, 0.4, 5)
    assert np.array_equal(obj, np.stack(np.meshgrid(s, s), -1).reshape(-1, 2))
    assert {r[6] for r in rows} == {"1"}


def test_relay_paper_px_figures_only_for_the_papers_pixels(run_cli):
    code, stdout, err = run_cli("simulate", "relay", "--pixel-size", "5", "--rings", "2", "--json")
    assert code == 0, err
    paper = json.loads(stdout)["paper"]
    assert paper["max_um"] == 193.0 and "max_px" not in paper


@pytest.mark.parametrize(
    "args,pattern",
    [
        (["--spot-field", "0.5"], "is not a point like 0.5,0.5"),
        (["--spot-field", "a,b"], "is not a point like 0.5,0.5"),
        (["--rings", "0"], "--rings must be at least 1"),
    ],
)
def test_relay_bad_spot_options(run_cli, tmp_path, args, pattern):
    code, _, err = run_cli("simulate", "relay", "--out", tmp_path / "g.csv", *args)
    assert code == 2 and pattern in err
    assert list(tmp_path.iterdir()) == []


def test_simulate_relay_reports_progress_up_to_the_total():
    from oapcal.optics.summary import simulate_relay

    calls = []
    simulate_relay(1, n=9, rings=2, progress=lambda done, total: calls.append((done, total)))
    totals = {t for _, t in calls}
    assert len(totals) == 1 and calls[-1][0] == calls[-1][1]
    assert all(a[0] <= b[0] for a, b in zip(calls, calls[1:]))


def test_relay_misalignment_options(run_cli):
    code, stdout, err = run_cli("simulate", "relay", "--grid", "9", "--rings", "2", "--json")
    assert code == 0, err
    aligned = json.loads(stdout)
    args = ("--grid", "9", "--rings", "2", "--m2-tilt-x", "0.05", "--camera-defocus", "0.2",
            "--focal-length-2", "60", "--json")  # fmt: skip
    code, stdout, err = run_cli("simulate", "relay", *args)
    assert code == 0, err
    data = json.loads(stdout)
    moved = {k: v for k, v in data["relay"]["misalignment"].items() if v}
    assert moved == {"m2_tilt_x": 0.05, "camera_defocus": 0.2}
    assert data["relay"]["focal_length_2_mm"] == 60.0
    # The camera moved 0.2 mm along the light shrinks the image: the exit pupil (the stop at
    # OAP 1 imaged by OAP 2, Newton's x x' = f^2) lies f2^2 / (d1 - f2) = 4.5 mm before the
    # focus, so the chief rays converge and the image shrinks by 0.2 / 4.5 = 4.4 %.
    assert data["magnification"] == pytest.approx(60.0 / 50.8 * (1 - 0.2 * (860 - 60) / 60.0**2), rel=1e-3)
    assert data["distortion"]["max_um"] != pytest.approx(aligned["distortion"]["max_um"], rel=1e-3)
    assert data["paper"] is None and aligned["paper"] is None  # 9 x 9 is not the paper's grid
    # m2 tipped by t moves the field centre's image by about 2 t f2 along y.
    assert abs(data["paraxial_offset_mm"][1]) == pytest.approx(2 * np.radians(0.05) * 60.0, rel=0.02)
    code, stdout, err = run_cli("simulate", "relay", "--grid", "5", "--rings", "2", "--object-tilt-y", "1")
    assert code == 0, err
    assert "Misaligned: object_tilt_y +1 deg" in stdout


def test_relay_misalignment_errors_are_one_line(run_cli, tmp_path):
    code, _, err = run_cli("simulate", "relay", "--m1-focal-length", "-60", "--out", tmp_path / "g.csv")
    assert code == 2 and err.count("\n") == 1 and "leaves no mirror" in err
    assert list(tmp_path.iterdir()) == []


def test_relay_layout_figure(run_cli, tmp_path):
    layout = tmp_path / "layout.png"
    code, _, err = run_cli("simulate", "relay", "--grid", "5", "--rings", "2", "--d1", "150",
                           "--m2-tilt-x", "2", "--layout", layout)  # fmt: skip
    assert code == 0, err
    assert layout.read_bytes()[:4] == b"\x89PNG"
    code, _, err = run_cli("simulate", "relay", "--layout", tmp_path / "x.png", "--plot", tmp_path / "x.png")
    assert code == 2 and "must be different files" in err


@pytest.mark.parametrize(
    "args,pattern",
    [
        (["--m2-decentre-x", "1000"], "miss a mirror surface or the image plane; give smaller misalignments"),
        (["--camera-tilt-x", "90"], "is not in the range"),
    ],
)
def test_relay_too_large_misalignments_are_user_errors(run_cli, tmp_path, args, pattern):
    code, _, err = run_cli("simulate", "relay", "--grid", "5", "--out", tmp_path / "g.csv", *args)
    assert code == 2 and err.count("\n") == 1 and pattern in err, err
    assert list(tmp_path.iterdir()) == []


def test_relay_grid_csv_to_stdout_prints_no_table(run_cli):
    code, stdout, err = run_cli("simulate", "relay", "--grid", "3", "--rings", "1", "--out", "-")
    assert code == 0, err
    lines = stdout.splitlines()
    assert lines[0] == "x_obj,y_obj,x_u,y_u,x_d,y_d,clear" and len(lines) == 10
    assert "Grid distortion" not in stdout


def test_simulate_relay_returns_typed_numbers_that_the_summary_renders():
    from oapcal.optics.relay import radial_fit
    from oapcal.optics.summary import simulate_relay

    sim = simulate_relay(2, n=5, rings=2, pixel_size_um=5.0)
    fit, forward_mm, correction_mm = radial_fit(sim.grid)  # the same fit, called directly
    assert sim.radial.converged == fit.converged
    assert sim.radial.mean_residual_mm == forward_mm
    assert sim.radial.mean_correction_residual_mm == correction_mm
    s = sim.summary
    assert s["radial_fit"]["mean_residual_px"] == pytest.approx(forward_mm * 1e3 / 5.0)
    assert s["quality"]["rayleigh_um"] == sim.limits.rayleigh_um
    assert sim.limits.sparrow_um < sim.limits.rayleigh_um  # Sparrow's criterion is the finer one
    assert s["magnification"] == pytest.approx(1.0, abs=1e-3)  # equal mirrors: unit magnification
    assert [len(v) for v in sim.spots.values()] == [4, 4] and sim.paper is None


@pytest.mark.slow  # draws every relay figure
def test_relay_figures_keep_the_callers_matplotlib_backend(tmp_path):
    """The figures are built with Figure + FigureCanvasAgg: pyplot is never loaded and a
    notebook's backend stays as it was."""
    code = (
        "import sys, matplotlib; matplotlib.use('svg');"
        "from oapcal.optics.summary import simulate_relay;"
        "from oapcal.report import optics_plots as P;"
        "sim = simulate_relay(1, n=5, rings=2);"
        f"P.plot_grid(sim.grid, {str(tmp_path / 'g.png')!r});"
        f"P.plot_spots(sim.spots, {str(tmp_path / 's.png')!r});"
        f"P.plot_layout(sim.relay, {str(tmp_path / 'l.png')!r});"
        "print(matplotlib.get_backend(), 'matplotlib.pyplot' in sys.modules)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.split() == ["svg", "False"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["g.png", "l.png", "s.png"]
    assert all(p.read_bytes()[:4] == b"\x89PNG" for p in tmp_path.iterdir())
