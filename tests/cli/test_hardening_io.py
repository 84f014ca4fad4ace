"""Hardening, round three (issue 24): outputs that are not regular files, full disks and
size limits, maps that sample nothing, absurd output geometries, numbers in point files,
multi-page images where one is expected, Dask schedulers.  Every refusal is one line on
stderr, a non-zero exit, and nothing written."""

import errno
import os
import stat
from pathlib import Path

import numpy as np
import pytest

from oapcal.calibration import calibrate
from oapcal.io.calibration import save_calibration
from oapcal.io.points import write_point_pairs
from oapcal.synthetic import synthetic_pairs


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    import cv2

    d = tmp_path_factory.mktemp("inputs")
    data = synthetic_pairs(n_x=6, n_y=5, seed=3)
    write_point_pairs(d / "points.csv", data.xy_u, data.xy_d)
    save_calibration(calibrate(data.xy_u, data.xy_d, um_per_px=4.8, image_size=(64, 48)), d / "calib.json")
    cv2.imwrite(str(d / "img.png"), (np.arange(48 * 64) % 251).reshape(48, 64).astype(np.uint8))
    return {"points": d / "points.csv", "calib": d / "calib.json", "img": d / "img.png", "dir": d}


def one_error(code, err, expect_code=2):
    assert code == expect_code, err
    assert err.startswith("oapcal: error: ") and err.count("\n") == 1, repr(err)


# -- A6: an output that is not a regular file is never replaced --------------------------------

#: Every command with a file output, the output given as {o} (suffix as the command needs).
OUTPUT_COMMANDS = [
    ("fit {points} --out {o}", ".json"),
    ("report {calib} --out {o}", ".html"),
    ("export-opencv {calib} --out {o}", ".yml"),
    ("correct {calib} --save-map {o}", ".npz"),
    ("landmarks convert --distorted {points} --x-column x_d --y-column y_d --out {o}", ".csv"),
    ("simulate relay --grid 5 --out {o}", ".csv"),
    ("simulate relay --grid 5 --out {d}/g.csv --plot {o}", ".png"),
    ("simulate image --image-size 64x48 --out {o}", ".png"),
    ("simulate image --image-size 64x48 --out {d}/s.png --truth {o}", ".csv"),
    ("select {points} --json {o}", ".json"),
    ("detect {img} --out {o}", ".csv"),
    ("esf {img} --plot {o}", ".png"),
    ("tolerance --trials 2 --grid 3 --plot {o}", ".png"),
]


def _special(kind: str, path: Path, tmp_path: Path) -> Path:
    """A FIFO at ``path``, or a symbolic link at ``path`` to a FIFO elsewhere."""
    if kind == "fifo":
        os.mkfifo(path)
        return path
    target = tmp_path / "elsewhere.fifo"
    os.mkfifo(target)
    path.symlink_to(target)
    return target


@pytest.mark.parametrize("kind", ["fifo", "link to a fifo"])
@pytest.mark.parametrize("argv,suffix", OUTPUT_COMMANDS, ids=[a.split()[0] + s for a, s in OUTPUT_COMMANDS])
def test_an_output_that_is_a_fifo_is_refused_and_kept(run_cli, files, tmp_path, argv, suffix, kind):
    out = tmp_path / f"out{suffix}"
    fifo = _special(kind, out, tmp_path)
    names = {k: v for k, v in files.items()} | {"o": out, "d": tmp_path}
    code, stdout, err = run_cli(*argv.format(**names).split())
    one_error(code, err)
    assert f"{out}: is {'a link to ' if kind != 'fifo' else ''}a named pipe (FIFO)" in err, err
    assert stat.S_ISFIFO(os.stat(fifo).st_mode) and (kind == "fifo" or out.is_symlink())
    assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith(".")) == []


def test_correct_into_a_directory_holding_a_fifo_output_is_refused(run_cli, files, tmp_path):
    os.mkfifo(tmp_path / "img.png")
    code, _, err = run_cli("correct", files["calib"], files["img"], "--out-dir", tmp_path)
    one_error(code, err)
    assert f"{tmp_path / 'img.png'}: is a named pipe (FIFO)" in err
    assert stat.S_ISFIFO(os.stat(tmp_path / "img.png").st_mode)


def test_dask_correct_to_a_fifo_output_is_refused(run_cli, files, tmp_path):
    pytest.importorskip("dask", reason="the dask extra is not installed")
    import tifffile

    tifffile.imwrite(tmp_path / "s.tif", np.zeros((2, 48, 64), np.uint8))
    out = tmp_path / "out"
    out.mkdir()
    os.mkfifo(out / "s.tif")
    code, _, err = run_cli("correct", files["calib"], tmp_path / "s.tif", "--out-dir", out, "--dask",
                           "--scheduler", "synchronous", "--dask-format", "tiff")  # fmt: skip
    assert code != 0 and f"{out / 's.tif'}: is a named pipe (FIFO)" in err, err
    assert stat.S_ISFIFO(os.stat(out / "s.tif").st_mode)


@pytest.mark.parametrize("writer", ["atomic_write", "atomic_path", "atomic_dir"])
def test_the_atomic_writers_refuse_special_files(tmp_path, writer):
    import oapcal.io.atomic as atomic
    from oapcal.errors import OutputError

    os.mkfifo(tmp_path / "p")
    with pytest.raises(OutputError, match="is a named pipe"), getattr(atomic, writer)(tmp_path / "p"):
        pytest.fail("the writer must refuse before yielding")
    assert stat.S_ISFIFO(os.stat(tmp_path / "p").st_mode)
    # /dev/null is a character device: refused before anything is created or replaced
    with (
        pytest.raises(OutputError, match="/dev/null: is a character device"),
        getattr(atomic, writer)("/dev/null"),
    ):
        pytest.fail("the writer must refuse before yielding")
    assert stat.S_ISCHR(os.stat("/dev/null").st_mode)


def test_a_fifo_appearing_while_writing_is_not_replaced(tmp_path):
    from oapcal.errors import OutputError
    from oapcal.io.atomic import atomic_write

    with pytest.raises(OutputError, match="named pipe"), atomic_write(tmp_path / "a.json") as fh:
        fh.write("{}")
        os.mkfifo(tmp_path / "a.json")  # another program made it meanwhile
    assert stat.S_ISFIFO(os.stat(tmp_path / "a.json").st_mode)
    assert [p.name for p in tmp_path.iterdir()] == ["a.json"]


# -- D17: a full disk or a file-size limit names the output ------------------------------------


class _FullFile:
    """A file object whose writes fail as on a full disk or past ``ulimit -f``."""

    def __init__(self, fh, code):
        self._fh, self._code = fh, code

    def write(self, data):
        raise OSError(self._code, os.strerror(self._code))

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self._fh.close()

    def __getattr__(self, name):
        return getattr(self._fh, name)


@pytest.mark.parametrize("code_", [errno.ENOSPC, errno.EFBIG])
@pytest.mark.parametrize(
    "argv,out",
    [("fit {points} --out {o}", "calib.json"), ("correct {calib} --save-map {o}", "map.npy")],
)
def test_a_write_that_does_not_fit_names_the_output(run_cli, files, tmp_path, monkeypatch, code_, argv, out):
    real = os.fdopen
    monkeypatch.setattr(os, "fdopen", lambda *a, **k: _FullFile(real(*a, **k), code_))
    names = {**files, "o": tmp_path / out}
    code, _, err = run_cli(*argv.format(**names).split())
    one_error(code, err)
    assert err.startswith(f"oapcal: error: {tmp_path / out}: {os.strerror(code_)}"), err
    assert "standard output" not in err and "a file" not in err
    assert list(tmp_path.iterdir()) == []
