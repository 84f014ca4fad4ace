"""``oapcal detect --target dots|chessboard``: the point-pair CSV that fit reads, the pixel-size
answer in the table and JSON, refusals (exit 3, one line naming the file) and usage errors."""

import hashlib
import json

import numpy as np
import pytest

from oapcal.imaging.grid_targets import GridTarget, render_grid
from oapcal.imaging.render import Camera


@pytest.fixture(scope="module")
def images(tmp_path_factory):
    import cv2

    d = tmp_path_factory.mktemp("grid")
    r = render_grid(GridTarget("dots", 21, 21, 50.0, 25.0), camera=Camera(oversample=3), seed=1)
    cv2.imwrite(str(d / "dots.png"), r.image)
    b = render_grid(GridTarget("chessboard", 20, 20, 50.0), camera=Camera(oversample=3), seed=2)
    cv2.imwrite(str(d / "board.png"), b.image)
    # the truth file, as detect --truth reads it
    with open(d / "truth.csv", "w") as fh:
        fh.write("id,x_d,y_d,visible\n")
        for i, (x, y), v in zip(r.ids, r.xy_d, r.in_view):
            fh.write(f"{i},{float(x)!r},{float(y)!r},{int(v)}\n")
    rng = np.random.default_rng(0)
    cv2.imwrite(str(d / "noise.png"), rng.integers(0, 255, (240, 320)).astype(np.uint8))
    return d, r


def test_dots_csv_fits_and_reports_the_pixel_size(images, run_cli, tmp_path):
    d, r = images
    out = tmp_path / "p.csv"
    grid = ("--target", "dots", "--pitch-um", 50, "--dot-um", 25, "--rows", 21, "--cols", 21)
    code, stdout, err = run_cli(
        "detect", d / "dots.png", *grid, "--out", out, "--json", "--truth", d / "truth.csv"
    )
    assert code == 0, err
    s = json.loads(stdout)
    assert s["found"] == 441 and s["ids_absolute"] is True
    assert s["image_sha256"] == hashlib.sha256((d / "dots.png").read_bytes()).hexdigest()
    assert 4.7 < s["um_per_px"] < 4.9 and 0 < s["um_per_px_sigma"] < 0.05
    assert s["field_of_view_um"] == pytest.approx([640 * s["um_per_px"], 480 * s["um_per_px"]])
    assert s["truth"]["wrong"] == 0 and s["truth"]["found_in_view"] == 441
    lines = out.read_text().splitlines()
    assert lines[0] == "id,x_u,y_u,x_d,y_d" and len(lines) == 442
    assert lines[1].startswith("R0C0,")
    code, stdout, err = run_cli("fit", out, "--model", "paper", "--um-per-px", 4.8, "--image-size", "640x480",
                                "--out", tmp_path / "cal.json")  # fmt: skip
    assert code == 0, err
    cal = json.loads((tmp_path / "cal.json").read_text())
    assert cal["residuals"]["rms_px"] < 0.05  # the detection's own precision (measured 0.021)


def test_chessboard_table(images, run_cli, tmp_path):
    d, _ = images
    code, stdout, err = run_cli("detect", d / "board.png", "--target", "chessboard", "--square-um", 50,
                                "--out", tmp_path / "b.csv", "--um-per-px", 4.8)  # fmt: skip
    assert code == 0, err
    assert "found 361 of 361" in stdout and "pixel size 4.8" in stdout and "image sha256" in stdout
    assert "x_u,y_u at the given 4.8 um/px" in stdout


def test_target_spec(images, run_cli, tmp_path):
    d, _ = images
    code, stdout, err = run_cli("detect", d / "dots.png", "--target-spec", "oapcal-dots-50um-25um",
                                "--out", tmp_path / "s.csv", "--json")  # fmt: skip
    assert code == 0, err
    s = json.loads(stdout)
    assert s["pitch_um"] == 50.0 and s["dot_um"] == 25.0 and s["ids_absolute"] is True


def test_refusal_is_exit_3_one_line(images, run_cli, tmp_path):
    d, _ = images
    out = tmp_path / "n.csv"
    code, stdout, err = run_cli("detect", d / "noise.png", "--target", "dots", "--pitch-um", 50, "--out", out)
    assert code == 3
    assert len(err.strip().splitlines()) == 1 and "noise.png" in err and "Traceback" not in err
    assert not out.exists()
    code, stdout, err = run_cli("detect", d / "noise.png", "--target", "dots", "--pitch-um", 50, "--out", out,
                                "--json")  # fmt: skip
    assert code == 3 and json.loads(stdout)["status"] == 1


@pytest.mark.parametrize(
    "args, words",
    [
        (["--target", "dots"], "--pitch-um"),
        (["--target", "chessboard"], "--square-um"),
        (["--target", "dots", "--square-um", "50"], "--square-um"),
        (["--target", "chessboard", "--pitch-um", "50"], "--pitch-um"),
        (["--target", "dots", "--pitch-um", "50", "--groups", "4-5"], "--groups"),
        (["--target", "dots", "--pitch-um", "50", "--rows", "5"], "--rows"),
        (["--target", "dots", "--pitch-um", "50", "--dot-um", "60"], "--dot-um"),
        (["--target", "usaf", "--pitch-um", "50"], "--pitch-um"),
        (["--target-spec", "nope"], "nope"),
        (["--target", "chessboard", "--target-spec", "oapcal-dots-50um-25um"], "--target-spec"),
    ],
)
def test_usage_errors(images, run_cli, tmp_path, args, words):
    d, _ = images
    code, stdout, err = run_cli("detect", d / "dots.png", "--out", tmp_path / "u.csv", *args)
    assert code == 2, err
    assert words in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "u.csv").exists()
