"""``oapcal selfcal``: a normal calibration file that ``correct`` uses; refusals as one line."""

import csv
import json

import cv2
import numpy as np
import pytest
from selfcal_scenes import PIXEL_UM, grid_moves


@pytest.fixture
def frames(scene_frames):
    return scene_frames[:9]


@pytest.fixture
def frame_dir(tmp_path, frames):
    d = tmp_path / "frames"
    d.mkdir()
    for i, f in enumerate(frames):
        cv2.imwrite(str(d / f"f{i}.png"), f)
    return d


def test_selfcal_writes_a_calibration_that_correct_uses(run_cli, tmp_path, frame_dir, frames):
    out = tmp_path / "calib.json"
    res = tmp_path / "res.csv"
    plot = tmp_path / "matches.png"
    code, stdout, err = run_cli(
        "selfcal",
        frame_dir,
        "--model",
        "radial",
        "--out",
        out,
        "--residuals",
        res,
        "--plot",
        plot,
        "--no-progress",
        "--max-matches-per-pair",
        60,
    )
    assert code == 0, err
    assert "Self-calibration" in stdout and "Gauge" in stdout
    data = json.loads(out.read_text())
    assert data["model_family"] == "brown-conrady" and data["image_size"] == [200, 150]
    rows = list(csv.DictReader(res.read_text().splitlines()))
    assert {"frame_a", "frame_b", "x_a", "y_a", "x_b", "y_b", "weight", "e_x", "e_y", "inlier"} <= set(
        rows[0]
    )
    assert len(rows) > 300
    assert plot.stat().st_size > 0 and (tmp_path / "matches-residuals.png").stat().st_size > 0
    # oapcal correct reads it and corrects with it: the same image as the library's remap
    code, _, err = run_cli("correct", out, frame_dir / "f4.png", "--out-dir", tmp_path / "corr")
    assert code == 0, err
    got = cv2.imread(str(tmp_path / "corr" / "f4.png"), cv2.IMREAD_UNCHANGED)
    from oapcal.imaging.remap import correct_image, correction_map
    from oapcal.io.calibration import load_calibration

    cal = load_calibration(out)
    want = correct_image(frames[4], correction_map(cal, frames[4].shape))
    assert got.shape == want.shape
    assert np.abs(got.astype(int) - want.astype(int)).max() <= 1
    assert np.abs(got.astype(int) - frames[4].astype(int)).max() > 10  # it did change the image
    code, _, err = run_cli("export-opencv", out, "--out", tmp_path / "cam.yml")
    assert code == 0, err


def test_selfcal_stack_with_steps_json(run_cli, tmp_path, frames):
    import tifffile

    stack = tmp_path / "stack.tif"
    tifffile.imwrite(stack, np.stack(frames))
    steps = tmp_path / "steps.csv"
    lines = ["frame,x_um,y_um"] + [
        f"{i},{x * PIXEL_UM},{y * PIXEL_UM}" for i, (x, y) in enumerate(grid_moves())
    ]
    steps.write_text("\n".join(lines) + "\n")
    out = tmp_path / "c.json"
    code, stdout, err = run_cli(
        "selfcal",
        stack,
        "--model",
        "radial",
        "--steps",
        steps,
        "--um-per-px",
        PIXEL_UM,
        "--out",
        out,
        "--json",
    )
    assert code == 0, err
    summary = json.loads(stdout)
    assert summary["frames"] == 9 and abs(summary["stage_rotation_deg"]) < 0.05
    assert summary["params"]["m"] == pytest.approx(1.0, rel=1e-3)
    assert json.loads(out.read_text())["um_per_px"] == PIXEL_UM


def _one_line(err):
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1, err
    assert "Traceback" not in err
    return lines[0]


def test_refusals_are_one_line(run_cli, tmp_path, frame_dir, frames):
    out = tmp_path / "c.json"
    # too few frames: a user error (2)
    code, _, err = run_cli(
        "selfcal", frame_dir / "f0.png", frame_dir / "f1.png", "--model", "radial", "--out", out
    )
    assert code == 2 and "too few" in _one_line(err)
    # no texture: the frames cannot give a calibration (3), nothing written
    flat = tmp_path / "flat"
    flat.mkdir()
    for i in range(3):
        cv2.imwrite(str(flat / f"f{i}.png"), np.full((150, 200), 90, np.uint8))
    code, _, err = run_cli("selfcal", flat, "--model", "radial", "--out", out)
    assert code == 3 and "no texture" in _one_line(err) and not out.exists()
    # a steps file without one of the frames
    steps = tmp_path / "steps.csv"
    steps.write_text("frame,x_um,y_um\n0,0,0\n1,10,0\n")
    code, _, err = run_cli(
        "selfcal", frame_dir, "--model", "radial", "--steps", steps, "--um-per-px", "4.8", "--out", out
    )
    assert code == 2 and "steps.csv: no position for frame 2" in _one_line(err)
    # an Eq. (1) model with steps needs the scale
    steps.write_text("frame,x_um,y_um\n" + "".join(f"{i},{i},{i % 3}\n" for i in range(9)))
    code, _, err = run_cli("selfcal", frame_dir, "--model", "radial", "--steps", steps, "--out", out)
    assert code == 2 and "um_per_px" in _one_line(err)
    code, _, err = run_cli("selfcal", tmp_path / "missing", "--out", out)
    assert code == 2 and "no such file" in _one_line(err)
    code, _, err = run_cli("selfcal", frame_dir, "--model", "k9", "--out", out)
    assert code == 2 and "k9" in _one_line(err)
