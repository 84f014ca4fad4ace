"""Hardening, round two: absurd options, degenerate data, the environment's errors,
multi-output commands, terminal safety.  Each test is a case that once crashed, hung or
wrote something wrong; every failure must be one line on stderr, exit 2 (3 for a fit that
gives no usable model) and nothing written."""

import csv
import json
from pathlib import Path

import numpy as np
import pytest

from oapcal.calibration import calibrate
from oapcal.io.calibration import save_calibration
from oapcal.io.points import write_point_pairs
from oapcal.synthetic import synthetic_pairs


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("inputs")
    data = synthetic_pairs(n_x=6, n_y=5, seed=3)
    write_point_pairs(d / "points.csv", data.xy_u, data.xy_d)
    save_calibration(calibrate(data.xy_u, data.xy_d, um_per_px=4.8, image_size=(640, 480)), d / "calib.json")
    return {"points": d / "points.csv", "calib": d / "calib.json", "xy_u": data.xy_u, "xy_d": data.xy_d}


def one_error(code, err, expect_code=2):
    assert code == expect_code, err
    assert err.startswith("oapcal: error: ") and err.count("\n") == 1, repr(err)


def nothing_in(directory: Path):
    assert [p.name for p in directory.iterdir()] == []


# -- item 6: degenerate points ------------------------------------------------------------------


@pytest.mark.parametrize("scale,shift", [(1e-300, 0), (1e-6, 1e11)])
@pytest.mark.parametrize("as_json", [False, True])
def test_fit_on_degenerate_points_is_exit_2(run_cli, files, tmp_path, scale, shift, as_json):
    path = tmp_path / "tiny.csv"  # all near 1e-300, or 1e11 +- 1e-3: the layout is lost in rounding
    write_point_pairs(path, files["xy_u"] * scale + shift, files["xy_d"] * scale + shift)
    out = tmp_path / "out"
    out.mkdir()
    code, stdout, err = run_cli("fit", path, "--out", out / "c.json", *(["--json"] if as_json else []))
    one_error(code, err)
    assert "tiny.csv: the reference points" in err and stdout == ""
    nothing_in(out)


def test_fit_with_non_finite_result_is_exit_3_and_writes_nothing(run_cli, files, tmp_path, monkeypatch):
    import oapcal.calibration as calibration_module

    real = calibration_module.calibrate

    def broken(*args, **kwargs):
        cal = real(*args, **kwargs)
        cal.params[0] = np.inf
        return cal

    monkeypatch.setattr(calibration_module, "calibrate", broken)
    code, stdout, err = run_cli("fit", files["points"], "--out", tmp_path / "c.json", "--json")
    one_error(code, err, 3)
    assert "non-finite parameters" in err and "nothing written" in err and stdout == ""
    nothing_in(tmp_path)


def test_fit_whose_model_folds_inside_the_image_is_not_written(run_cli, tmp_path):
    from oapcal.model import distort, params_from_dict

    # barrel distortion fitted on 640x480: it turns back about 1300 px from the centre
    gx, gy = np.meshgrid(np.linspace(0, 639, 12), np.linspace(0, 479, 9))
    xy_u = np.stack([gx.ravel(), gy.ravel()], -1)
    truth = params_from_dict({"k1": -2e-7, "x_off": -320, "y_off": -240, "c_x": 320, "c_y": 240, "m": 1})
    write_point_pairs(tmp_path / "p.csv", xy_u, distort(xy_u, truth))
    out = tmp_path / "out"
    out.mkdir()
    code, _, err = run_cli("fit", tmp_path / "p.csv", "--out", out / "c.json", "--image-size", "640x480")
    assert code == 0, err
    (out / "c.json").unlink()
    # the fold lies beyond the points' bounds, where the model extrapolates: kept, with a note
    # (a correction's trust region ends before it; the whole frame is refused)
    code, _, err = run_cli("fit", tmp_path / "p.csv", "--out", out / "c.json", "--image-size", "4000x4000")
    assert code == 0, err
    assert "folds over beyond the reference points' bounds" in err and "4000x4000 px image" in err, err
    assert (out / "c.json").is_file()
    (out / "c.json").unlink()
    # --json carries the same note (a script reading stdout sees what stderr says)
    code, stdout, err = run_cli(
        "fit", tmp_path / "p.csv", "--out", out / "c.json", "--image-size", "4000x4000", "--json"
    )
    assert code == 0, err
    notes = json.loads(stdout)["notes"]
    assert len(notes) == 1 and "folds over beyond the reference points' bounds" in notes[0], notes
    assert notes[0] in err
    # the rotation policy's undo hint is not appended to the fold's note (its kind is "fold")
    assert "--rotation none" not in err
    (out / "c.json").unlink()
    # within the points' bounds it is refused: exit 3, nothing written
    strong = params_from_dict({"k1": -4e-6, "x_off": -320, "y_off": -240, "c_x": 320, "c_y": 240, "m": 1})
    write_point_pairs(tmp_path / "q.csv", xy_u, distort(xy_u, strong))
    code, _, err = run_cli("fit", tmp_path / "q.csv", "--out", out / "c.json", "--image-size", "640x480")
    one_error(code, err, 3)
    assert "folds over" in err and "inside the reference points' bounds" in err and "nothing written" in err
    nothing_in(out)


# -- item 13: the environment's errors ----------------------------------------------------------

_NO_WRITE = Path("/sys")


def _unwritable_dir() -> Path:
    """A directory in which not even root may create files (sysfs)."""
    import tempfile

    try:
        fd, name = tempfile.mkstemp(dir=_NO_WRITE)
    except OSError:
        return _NO_WRITE
    import os

    os.close(fd)
    os.unlink(name)
    pytest.skip("/sys accepts new files here, so there is no unwritable directory to test with")


@pytest.mark.parametrize(
    "argv",
    [
        "fit {points} --out {d}/c.json",
        "report {calib} --out {d}/r.html",
        "export-opencv {calib} --out {d}/cv.yml",
        "correct {calib} {img} --out-dir {tmp}/o --save-map {d}/m.npz",
        "landmarks convert --distorted {points} --x-column x_d --y-column y_d --out {d}/p.csv",
        "simulate relay --grid 5 --out {d}/g.csv",
        "select {points} --json {d}/s.json",
    ],
)
def test_unwritable_output_directory_is_a_user_error(run_cli, files, tmp_path, argv):
    import cv2

    d = _unwritable_dir()
    cv2.imwrite(str(tmp_path / "img.png"), np.zeros((48, 64), np.uint8))
    names = {
        "points": files["points"],
        "calib": files["calib"],
        "d": d,
        "tmp": tmp_path,
        "img": tmp_path / "img.png",
    }
    code, _, err = run_cli(*argv.format(**names).split())
    one_error(code, err)
    assert f"{d}/" in err and "cannot create files in /sys" in err and ".tmp" not in err


def test_a_write_failing_midway_names_the_output_not_the_temp_file(run_cli, files, tmp_path, monkeypatch):
    import errno
    import os

    import oapcal.io.atomic

    def full(tmp, path):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(tmp))

    monkeypatch.setattr(oapcal.io.atomic, "_publish", full)
    code, _, err = run_cli("fit", files["points"], "--out", tmp_path / "calib.json")
    one_error(code, err)
    assert f"{tmp_path / 'calib.json'}: No space left on device; the disk is full" in err, err
    nothing_in(tmp_path)


def test_unreadable_input_directory_is_a_user_error(run_cli, files, tmp_path, monkeypatch):
    import errno

    (tmp_path / "raw").mkdir()

    real = Path.iterdir

    def denied(self):  # as chmod 000 would for a user other than root
        if self.name == "raw":
            raise PermissionError(errno.EACCES, "Permission denied", str(self))
        return real(self)

    monkeypatch.setattr(Path, "iterdir", denied)
    code, _, err = run_cli("correct", files["calib"], tmp_path / "raw", "--out-dir", tmp_path / "out")
    assert code in (2, 4) and "raw: Permission denied" in err and "internal error" not in err, err


def test_json_to_a_full_stdout_is_exit_2():
    import subprocess
    import sys

    if not Path("/dev/full").exists():
        pytest.skip("/dev/full is absent on this system")
    data = synthetic_pairs(n_x=5, n_y=4, seed=3)
    rows = "".join(f"{a},{b},{c},{d}\n" for (a, b), (c, d) in zip(data.xy_u, data.xy_d))
    argv = ["robustness", "-", "--models", "paper", "--trials", "3", "--json", "-"]
    with open("/dev/full", "w") as full:
        proc = subprocess.run(
            [sys.executable, "-m", "oapcal", *argv], input="x_u,y_u,x_d,y_d\n" + rows,
            stdout=full, stderr=subprocess.PIPE, text=True, timeout=300,
        )  # fmt: skip
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr == "oapcal: error: standard output: cannot be written (No space left on device)\n"


# -- items 9, 14, 24: absurd and NaN options are refused before any work --------------------------


@pytest.mark.parametrize(
    "argv,expect",
    [
        ("simulate image --sigma-px 1e6", "--sigma-px"),  # once a segfault in cv2.GaussianBlur
        ("simulate image --sigma-px 1000", "--sigma-px"),  # once minutes of blurring
        ("simulate image --sigma-px nan", "'nan' is not a finite number"),
        ("simulate image --image-size 200x200 --sigma-px 60", "--sigma-px"),
        ("simulate image --image-size 100000x100000", "a side over 16384 px"),
        ("simulate image --image-size 16000x16000", "GiB of memory, over the 4 GiB limit"),
        ("simulate image --na 1e-6 --wavelength-um 0.85", "gives an Airy disc of radius"),
        ("simulate image --snr inf", "'inf' is not a finite number"),
        ("simulate image --um-per-px nan", "'nan' is not a finite number"),
        ("simulate image --seed -1", "-1 is not in the range"),
        ("simulate relay --d1 1e9", "--d1"),
        ("simulate relay --d1 3000", "no ray of the 20 mm beam from the field point"),
        ("simulate relay --field 1e6", "--field"),
        ("simulate relay --field 4", "passes both mirrors"),
        ("simulate relay --grid 100000", "--grid"),
        ("simulate relay --grid 2", "--grid"),  # once "4 point pairs are too few"
        ("simulate relay --rings 100000", "--rings"),
        ("simulate relay --focal-length nan", "not a finite number"),
        ("simulate relay --spot-field nan,0", "--spot-field"),
        ("simulate relay --plot {tmp}/g.xyz", "unsupported figure type .xyz"),
        ("simulate relay --spots {tmp}/s", "unsupported figure type (no suffix)"),
    ],
)
def test_absurd_simulate_options_are_refused_up_front(run_cli, tmp_path, argv, expect):
    out = tmp_path / "out"
    out.mkdir()
    args = argv.format(tmp=out).split()
    if args[1] == "image":
        args += ["--out", str(out / "x.png"), "--truth", str(out / "t.csv")]
    code, stdout, err = run_cli(*args)
    assert code == 2 and expect in err and "internal error" not in err, err
    nothing_in(out)


# -- item 22: several outputs, all or nothing -----------------------------------------------------


def test_simulate_image_writes_both_outputs_or_neither(run_cli, tmp_path, monkeypatch):
    import oapcal.io.points

    def fails(path, sim):
        raise OSError(28, "No space left on device", str(path))

    monkeypatch.setattr(oapcal.io.points, "write_truth", fails)
    argv = ["simulate", "image", "--image-size", "160x120", "--groups", "4", "--out", tmp_path / "x.png"]
    code, _, err = run_cli(*argv, "--truth", tmp_path / "t.csv")
    one_error(code, err)
    assert "t.csv: No space left on device" in err
    nothing_in(tmp_path)
    code, _, err = run_cli(*argv, "--truth", tmp_path / "nodir" / "t.csv")
    one_error(code, err)
    assert "nodir does not exist" in err
    nothing_in(tmp_path)


def test_simulate_relay_writes_all_outputs_or_none(run_cli, tmp_path, monkeypatch):
    import oapcal.report.optics_plots

    def fails(*args, **kwargs):
        raise OSError(28, "No space left on device", str(args[1]))

    monkeypatch.setattr(oapcal.report.optics_plots, "plot_spots", fails)
    argv = ["simulate", "relay", "--grid", "5", "--out", tmp_path / "g.csv", "--plot", tmp_path / "g.png"]
    code, _, err = run_cli(*argv, "--spots", tmp_path / "s.png")
    one_error(code, err)
    nothing_in(tmp_path)
    monkeypatch.undo()
    code, _, err = run_cli(*argv, "--spots", tmp_path / "s.png")
    assert code == 0, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["g.csv", "g.png", "s.png"]


# -- item 23: nothing from a file reaches the terminal raw ----------------------------------------

ESC = "\x1b]0;pwned\x07\x1b[2J\x9b31m"


def test_landmark_labels_with_escape_sequences_print_as_text(run_cli, tmp_path):
    rows = [("a", 0, 0), ("b", 10, 0), ("c", 0, 10), ("d", 10, 10), ("e", 5, 3), ("f", 2, 8)]
    with open(tmp_path / "d.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["id", "x", "y"])
        w.writerows([*rows, (f"label{ESC}", 7, 7)])
    with open(tmp_path / "r.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["id", "x", "y"])
        w.writerows([*rows, (f"other{ESC}", 7, 7)])
    code, out, err = run_cli(
        "landmarks", "convert", "--distorted", tmp_path / "d.csv", "--reference", tmp_path / "r.csv",
        "--pair-by", "id", "--out", tmp_path / "p.csv",
    )  # fmt: skip
    assert code == 0, err
    assert "label\\x1b]0;pwned\\x07" in err  # the unpaired label, shown as visible text
    for text in (out, err):
        assert not any(c in text for c in "\x1b\x07\x9b"), repr(text)


def test_file_names_with_escape_sequences_print_as_text(run_cli, tmp_path):
    code, out, err = run_cli("fit", tmp_path / f"x{ESC}.csv")
    one_error(code, err)
    assert "x\\x1b]0;pwned" in err and not any(c in err for c in "\x1b\x07\x9b")


def test_console_tables_sanitize_cells():
    import io

    from oapcal.cli._common import console

    con = console()
    con.file = io.StringIO()
    from rich.table import Table

    table = Table()
    table.add_column(f"h{ESC}")
    table.add_row(f"cell{ESC}")
    con.print(table)
    con.print(f"[bold]title[/bold] {ESC}\nsecond line")
    text = con.file.getvalue()
    assert "cell\\x1b" in text and "second line" in text and not any(c in text for c in "\x1b\x07\x9b")


# -- item 12: negative seeds; the demo leaves nothing behind -------------------------------------


@pytest.mark.parametrize(
    "argv",
    [
        "select {points} --seed -1 --cv 3",
        "robustness {points} --seed -1 --trials 5",
        "simulate image --seed -1 --out {out}/x.png",
        "demo --seed -1 --out-dir {out}/demo",
    ],
)
def test_negative_seed_is_a_usage_error(run_cli, files, tmp_path, argv):
    out = tmp_path / "out"
    out.mkdir()
    code, _, err = run_cli(*argv.format(points=files["points"], out=out).split())
    one_error(code, err)
    assert "--seed" in err and "-1 is not in the range" in err
    nothing_in(out)


def test_every_float_option_of_every_command_refuses_nan():
    import click

    from oapcal.cli import COMMANDS, cli
    from oapcal.cli._common import NON_FINITE_OK, Finite

    ctx = click.Context(cli)
    seen = 0
    for name in COMMANDS:
        command = cli.get_command(ctx, name)
        subs = (
            [command.get_command(ctx, n) for n in command.list_commands(ctx)]
            if hasattr(command, "list_commands")
            else [command]
        )
        for sub in subs:
            for param in sub.params:
                if (
                    isinstance(param.type, click.FloatRange | type(click.FLOAT))
                    and param.name not in NON_FINITE_OK
                ):
                    assert isinstance(param.type, Finite), f"{name} {sub.name} --{param.name}"
                    seen += 1
                if param.name == "seed":
                    assert isinstance(param.type, click.IntRange) and param.type.min == 0, f"{name} --seed"
    assert seen > 20


def test_demo_that_fails_midway_leaves_nothing(run_cli, tmp_path, monkeypatch):
    import oapcal.select

    def fails(*args, **kwargs):
        raise OSError(28, "No space left on device", str(tmp_path / "demo" / "selection.json"))

    monkeypatch.setattr(oapcal.select, "select_models", fails)
    code, _, err = run_cli("demo", "--out-dir", tmp_path / "demo", "--trials", "0", "--no-report")
    one_error(code, err)
    nothing_in(tmp_path)
    (tmp_path / "kept").mkdir()
    (tmp_path / "kept" / "mine.txt").write_text("x")
    code, _, err = run_cli("demo", "--out-dir", tmp_path / "kept", "--trials", "0", "--no-report")
    one_error(code, err)
    assert [p.name for p in (tmp_path / "kept").iterdir()] == ["mine.txt"]


@pytest.mark.parametrize(
    "argv,expect",
    [
        ("robustness {points} --trials 1000000000", "--trials"),
        ("robustness {points} --trials 5000000 --models paper,full", "GiB of memory, over the 4 GiB limit"),
        ("esf {img} --um-per-px nan", "'nan' is not a finite number"),
        ("esf {img} --rois {roi}", "roi.csv: line 2, column 'x0': 'nan' is not a pixel index"),
        ("fit {points} --um-per-px inf", "'inf' is not a finite number"),
        ("correct {calib} {img} --out-dir {out}/c --um-per-px inf", "'inf' is not a finite number"),
    ],
)
def test_absurd_options_of_other_commands_are_refused(run_cli, files, tmp_path, argv, expect):
    import cv2

    cv2.imwrite(str(tmp_path / "img.png"), np.zeros((48, 64), np.uint8))
    (tmp_path / "roi.csv").write_text("x0,y0,x1,y1\nnan,0,10,10\n")
    out = tmp_path / "out"
    out.mkdir()
    names = {"points": files["points"], "calib": files["calib"], "img": tmp_path / "img.png",
             "roi": tmp_path / "roi.csv", "out": out}  # fmt: skip
    code, _, err = run_cli(*argv.format(**names).split())
    one_error(code, err)
    assert expect in err, err
    nothing_in(out)


# -- item 24: progress only on a terminal, even when FORCE_COLOR says otherwise --------------------


def test_no_progress_bar_off_a_terminal_even_with_force_color(tmp_path):
    import os
    import subprocess
    import sys

    argv = ["simulate", "image", "--image-size", "96x64", "--groups", "4", "--out", str(tmp_path / "x.png")]
    proc = subprocess.run(
        [sys.executable, "-m", "oapcal", *argv], capture_output=True, text=True,
        env={**os.environ, "FORCE_COLOR": "1"}, timeout=300,
    )  # fmt: skip
    assert proc.returncode == 0 and proc.stderr == "" and "\x1b" not in proc.stdout, proc.stdout


def test_progress_helpers_ask_isatty(monkeypatch):
    import io

    from oapcal.cli._common import progress_bar

    monkeypatch.setenv("FORCE_COLOR", "1")
    monkeypatch.setattr("sys.stderr", io.StringIO())
    bar, _ = progress_bar("x")
    assert bar.disable


def test_a_corrupt_image_gives_only_the_oapcal_line(tmp_path):
    """OpenCV's ``[ WARN:0@...] ... PNG input buffer is incomplete`` once came beside the error."""
    import subprocess
    import sys

    import cv2

    cv2.imwrite(str(tmp_path / "x.png"), np.random.default_rng(1).integers(0, 255, (64, 96), np.uint8))
    (tmp_path / "trunc.png").write_bytes((tmp_path / "x.png").read_bytes()[:3000])
    proc = subprocess.run(
        [sys.executable, "-m", "oapcal", "esf", str(tmp_path / "trunc.png"), "--auto"],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert proc.returncode == 2 and proc.stderr.startswith("oapcal: error: "), proc.stderr
    assert proc.stderr.count("\n") == 1, proc.stderr


def test_numpy_runtime_warnings_stay_off_the_terminal(run_cli, files, tmp_path, monkeypatch):
    import warnings

    import oapcal.io.points

    real = oapcal.io.points.read_points

    def noisy(*args, **kwargs):
        warnings.warn("overflow encountered in multiply", RuntimeWarning, stacklevel=1)
        return real(*args, **kwargs)

    monkeypatch.setattr(oapcal.io.points, "read_points", noisy)
    code, _, err = run_cli("fit", files["points"], "--out", tmp_path / "c.json")
    assert code == 0 and err == "", err


@pytest.mark.parametrize("name", ["a" * 250 + ".json", "é" * 124 + "xx.json"])
def test_output_names_at_the_255_byte_limit(run_cli, files, tmp_path, name):
    """Once refused because the temporary name beside them (14 bytes longer) was too long."""
    assert len(name.encode()) == 255
    code, _, err = run_cli("fit", files["points"], "--out", tmp_path / name)
    assert code == 0, err
    assert [p.name for p in tmp_path.iterdir()] == [name]
    code, _, err = run_cli(
        "simulate",
        "image",
        "--image-size",
        "96x64",
        "--groups",
        "4",
        "--out",
        tmp_path / ("b" * 251 + ".png"),
    )
    assert code == 0, err


# -- item 24: messages that misled ---------------------------------------------------------------


def test_report_on_a_huge_image_does_not_suggest_an_option_it_lacks(run_cli, files, tmp_path):
    import struct
    import zlib

    ihdr = struct.pack(">IIBBBBB", 20000, 20000, 8, 0, 0, 0, 0)
    chunk = b"IHDR" + ihdr
    png = b"\x89PNG\r\n\x1a\n" + struct.pack(">I", len(ihdr)) + chunk + struct.pack(">I", zlib.crc32(chunk))
    (tmp_path / "huge.png").write_bytes(png + b"\x00" * 64)
    code, _, err = run_cli(
        "report", files["calib"], "--image", tmp_path / "huge.png", "--out", tmp_path / "r.html"
    )
    one_error(code, err)
    assert "huge.png: 20000x20000" in err and "--max-pixels" not in err and "crop" in err, err


def test_semicolon_csv_gets_a_delimiter_hint(run_cli, tmp_path):
    (tmp_path / "semi.csv").write_text("x_u;y_u;x_d;y_d\n0;0;1;1\n10;0;11;1\n0;10;1;12\n")
    code, _, err = run_cli("fit", tmp_path / "semi.csv")
    one_error(code, err)
    assert "the file separates its columns with ';': save it with ','" in err
    (tmp_path / "semi_l.csv").write_text("id;x;y\na;1;2\n")
    code, _, err = run_cli(
        "correct-points", files_calib(tmp_path), "--distorted", tmp_path / "semi_l.csv", "--out", "-"
    )
    one_error(code, err)
    assert "separates its columns with ';'" in err


def files_calib(tmp_path):
    data = synthetic_pairs(n_x=5, n_y=4, seed=3)
    save_calibration(calibrate(data.xy_u, data.xy_d), tmp_path / "c.json")
    return tmp_path / "c.json"


def test_missing_column_hint_does_not_name_a_required_column(run_cli, tmp_path):
    (tmp_path / "p.csv").write_text("x_u,y_u\n1,2\n")
    code, _, err = run_cli("fit", tmp_path / "p.csv")
    one_error(code, err)
    assert "missing columns 'x_d', 'y_d';" in err and "rename" not in err, err


# -- item 4: a model that folds inside the image it is applied to ---------------------------------


def test_correct_and_export_refuse_a_model_folding_inside_their_image(run_cli, files, tmp_path):
    import json

    import cv2

    data = json.loads(files["calib"].read_text())
    data["image_size"] = None
    data["params"]["k1"] = -1e-6  # fine over the points (0..640 x 0..480), folds ~580 px from the centre
    (tmp_path / "c.json").write_text(json.dumps(data))
    cv2.imwrite(str(tmp_path / "small.png"), np.zeros((480, 640), np.uint8))
    cv2.imwrite(str(tmp_path / "large.png"), np.zeros((1200, 1600), np.uint8))
    code, _, err = run_cli(
        "correct", tmp_path / "c.json", tmp_path / "small.png", "--out-dir", tmp_path / "o1"
    )
    assert code == 0, err
    # the whole frame written: refused
    large = tmp_path / "large.png"
    code, _, err = run_cli(
        "correct", tmp_path / "c.json", large, "--out-dir", tmp_path / "o2", "--extent", "input"
    )
    assert code in (2, 4) and "folds over" in err and "inside the 1600x1200 px image" in err, err
    assert "beyond the reference points' bounds" in err, err
    assert not any(p.is_file() for p in (tmp_path / "o2").rglob("*") if not p.name.startswith("."))
    # the trust region (the default) ends before the fold, beyond the landmarks: written, and
    # nothing at or beyond the fold (~580 px from the centre) is corrected
    code, _, err = run_cli(
        "correct", tmp_path / "c.json", tmp_path / "large.png", "--out-dir", tmp_path / "o3", "--border", "7"
    )
    assert code == 0, err
    out = cv2.imread(str(tmp_path / "o3" / "large.png"), cv2.IMREAD_UNCHANGED)
    yy, xx = np.mgrid[0:1200, 0:1600]
    assert (out[np.hypot(xx - 320, yy - 240) > 560] == 7).all()
    code, _, err = run_cli(
        "export-opencv", tmp_path / "c.json", "--image-size", "1600x1200", "--out", tmp_path / "cv.yml"
    )
    one_error(code, err)
    assert "folds over" in err and not (tmp_path / "cv.yml").exists()


def test_output_names_with_escape_sequences_print_as_text(run_cli, tmp_path):
    out = tmp_path / f"x{ESC}.png"
    code, stdout, err = run_cli("simulate", "image", "--image-size", "96x64", "--groups", "4", "--out", out)
    assert code == 0, err
    assert "x\\x1b]0;pwned" in stdout and not any(c in stdout + err for c in "\x1b\x07\x9b"), repr(stdout)


def test_libpng_warnings_stay_off_the_terminal(tmp_path):
    """libpng writes ``libpng warning: tEXt: CRC error`` straight to descriptor 2."""
    import struct
    import subprocess
    import sys

    import cv2

    cv2.imwrite(str(tmp_path / "x.png"), np.full((64, 96), 128, np.uint8))
    data = (tmp_path / "x.png").read_bytes()
    chunk = b"tEXtComment\x00hello"
    at = 8 + 8 + 13 + 4  # after IHDR
    bad = struct.pack(">I", len(chunk) - 4) + chunk + struct.pack(">I", 12345)  # wrong CRC
    (tmp_path / "bad.png").write_bytes(data[:at] + bad + data[at:])
    plain = subprocess.run(
        [sys.executable, "-c", "import sys, cv2; cv2.imread(sys.argv[1])", str(tmp_path / "bad.png")],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    if "libpng warning" not in plain.stderr:
        pytest.skip("this OpenCV build's libpng does not warn about the CRC")
    proc = subprocess.run(
        [sys.executable, "-m", "oapcal", "esf", str(tmp_path / "bad.png"), "--auto", "--json"],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert "libpng warning" not in proc.stderr, proc.stderr
    proc = subprocess.run(
        [sys.executable, "-m", "oapcal", "esf", str(tmp_path / "nothere.png"), "--auto"],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert proc.returncode == 2 and proc.stderr.startswith("oapcal: error: "), proc.stderr
