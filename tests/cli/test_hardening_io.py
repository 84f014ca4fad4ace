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
    ("correct-points {calib} {points} --out {o}", ".csv"),
    ("robustness {points} --models paper --trials 5 --json {o}", ".json"),
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


@pytest.mark.slow  # the demo runs whole before its files are moved into place
def test_demo_into_a_directory_holding_a_fifo_is_refused_and_leaves_nothing(run_cli, tmp_path):
    os.mkfifo(tmp_path / "grid.csv")
    code, _, err = run_cli("demo", "--out-dir", tmp_path, "--trials", "0", "--no-report")
    one_error(code, err)
    assert f"{tmp_path / 'grid.csv'}: is a named pipe (FIFO)" in err, err
    assert [p.name for p in tmp_path.iterdir()] == ["grid.csv"]
    assert stat.S_ISFIFO(os.stat(tmp_path / "grid.csv").st_mode)


def test_correct_into_a_directory_holding_a_fifo_output_is_refused(run_cli, files, tmp_path):
    os.mkfifo(tmp_path / "img.png")
    code, _, err = run_cli("correct", files["calib"], files["img"], "--out-dir", tmp_path)
    one_error(code, err)
    assert f"{tmp_path / 'img.png'}: is a named pipe (FIFO)" in err
    assert stat.S_ISFIFO(os.stat(tmp_path / "img.png").st_mode)


def test_dask_correct_to_a_fifo_output_is_refused(run_cli, files, tmp_path):
    pytest.importorskip("dask", reason="the dask extra is not installed")
    import tifffile

    tifffile.imwrite(tmp_path / "s.tif", np.zeros((2, 48, 64), np.uint8), photometric="minisblack")
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


# -- A2: a calibration whose map samples no pixel of the image --------------------------------


def _edited(base, **changes):
    """``base`` (a Calibration) with parameters changed by name (Eq. 1) or a relay design
    misalignment (relay)."""
    import dataclasses

    from oapcal.model import params_from_dict, params_to_dict

    if "relay" in changes:
        from oapcal.optics.relay_model import RelayDesign, relay_params

        design = RelayDesign(setup=1, pixel_size_um=4.8, centre=(319.5, 239.5))
        return dataclasses.replace(base, params=relay_params(design, changes["relay"], {}))
    return dataclasses.replace(base, params=params_from_dict({**params_to_dict(base.params), **changes}))


EMPTY_MAPS = {
    "x_off=1e29": {"x_off": 1e29},
    "m=1e12": {"m": 1e12},
    "m=1e3": {"m": 1e3},
    "relay mirror 1 tilted 44 deg": {"relay": {"m1_tilt_x": 44.0}},
    "relay mirror 2 tilted 2 deg": {"relay": {"m2_tilt_x": 2.0}},
    "relay camera defocus 1e20": {"relay": {"camera_defocus": 1e20}},
}


@pytest.fixture(scope="module")
def empty_calibrations(files, tmp_path_factory):
    from oapcal.io.calibration import load_calibration

    d = tmp_path_factory.mktemp("empty")
    base = load_calibration(files["calib"])
    relay_base = None
    out = {}
    for label, changes in EMPTY_MAPS.items():
        if "relay" in changes:
            if relay_base is None:
                import sys

                sys.path.insert(0, str(Path(__file__).parents[1]))
                from relay_helpers import relay_calibration

                relay_base = relay_calibration()
            cal = _edited(relay_base, **changes)
        else:
            cal = _edited(base, **changes)
        path = d / f"{len(out)}.json"
        save_calibration(cal, path)
        out[label] = path
    return out


@pytest.mark.parametrize("label", list(EMPTY_MAPS))
@pytest.mark.parametrize("command", ["correct", "correct --save-map", "export-opencv"])
def test_a_map_that_samples_nothing_is_refused_before_writing(run_cli, files, empty_calibrations, tmp_path,
                                                               label, command):  # fmt: skip
    import cv2

    calib = empty_calibrations[label]
    size = (640, 480) if "relay" in label else (64, 48)
    cv2.imwrite(str(tmp_path / "img.png"), np.full(size[::-1], 100, np.uint8))
    out = tmp_path / "out"
    argv = {
        "correct": ["correct", calib, tmp_path / "img.png", "--out-dir", out],
        "correct --save-map": ["correct", calib, "--save-map", tmp_path / "m.npz"],
        "export-opencv": ["export-opencv", calib, "--out", tmp_path / "cv.yml"],
    }[command]
    code, stdout, err = run_cli(*argv)
    one_error(code, err)
    assert "the map samples no pixel of the image" in err, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["img.png"]


def test_dask_correct_of_a_map_that_samples_nothing_is_refused(run_cli, empty_calibrations, tmp_path):
    pytest.importorskip("dask", reason="the dask extra is not installed")
    import tifffile

    tifffile.imwrite(tmp_path / "s.tif", np.full((5, 48, 64), 100, np.uint8))
    code, _, err = run_cli("correct", empty_calibrations["x_off=1e29"], tmp_path / "s.tif", "--out-dir",
                           tmp_path / "out", "--dask", "--scheduler", "synchronous")  # fmt: skip
    one_error(code, err)
    assert "the map samples no pixel of the image" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.tif"]


def test_a_map_file_made_for_another_camera_is_refused(run_cli, files, tmp_path):
    import cv2

    from oapcal.imaging.remap import CorrectionMap, OutputGeometry
    from oapcal.io.maps import save_map

    far = np.full((48, 64), 5000.0, np.float32)  # every source 5000 px away
    save_map(CorrectionMap(far, far, OutputGeometry((48, 64))), tmp_path / "m.npy")
    cv2.imwrite(str(tmp_path / "img.png"), np.full((48, 64), 100, np.uint8))
    code, _, err = run_cli("correct", files["calib"], tmp_path / "img.png", "--map", tmp_path / "m.npy",
                           "--out-dir", tmp_path / "out")  # fmt: skip
    one_error(code, err)
    assert "the map samples no pixel of the image" in err
    assert not (tmp_path / "out").exists() or list((tmp_path / "out").iterdir()) == []


from hypothesis import given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402


@settings(max_examples=60, deadline=None)
@given(dx=st.integers(-90, 90), dy=st.integers(-70, 70))
def test_the_refusal_follows_the_overlap_of_a_shifted_map(dx, dy):
    """A pure shift by (dx, dy) px samples exactly (40 - |dx|)(30 - |dy|) of the 40 x 30
    output pixels: the map is refused exactly when that is under 0.1 % (here: none)."""
    from oapcal.imaging.remap import MIN_SAMPLED_FRACTION, EmptyMapError, correction_map, sampled_fraction
    from oapcal.model import params_from_dict

    rows, cols = 30, 40
    expected = max(0, cols - abs(dx)) * max(0, rows - abs(dy)) / (rows * cols)
    params = params_from_dict({"c_x": float(dx), "c_y": float(dy)})
    if expected < MIN_SAMPLED_FRACTION:
        with pytest.raises(EmptyMapError, match="samples no pixel of the image"):
            correction_map(params, (rows, cols))
    else:
        assert sampled_fraction(correction_map(params, (rows, cols)), (rows, cols)) == expected


# -- A5: correct_image refuses what the command refuses -----------------------------------------


@pytest.fixture(scope="module")
def small_map(files):
    from oapcal.imaging.remap import correction_map
    from oapcal.io.calibration import load_calibration

    return correction_map(load_calibration(files["calib"]), (48, 64))


@pytest.mark.parametrize(
    "shape,dtype",
    [((5, 48, 64), "uint8"), ((48, 64, 256), "uint8"), ((48, 64, 300), "float32"), ((48, 64, 2), "uint8"),
     ((2, 48, 64, 3), "uint8"), ((64,), "uint8"), ((48, 64), "int64"), ((48, 64), "bool"),
     ((0, 64), "uint8")],
)  # fmt: skip
def test_correct_image_refuses_stacks_many_channels_and_odd_types(small_map, shape, dtype):
    from oapcal.errors import DataError
    from oapcal.imaging.remap import correct_image

    refused = r"cannot be corrected|has pixel type|has no pixels|must be a \(rows, cols\)"
    with pytest.raises(DataError, match=refused):
        correct_image(np.ones(shape, dtype), small_map)


@pytest.mark.parametrize("channels", [(), (1,), (3,), (4,)])
def test_correct_image_writes_into_out_and_refuses_a_wrong_one(small_map, channels):
    from oapcal.errors import DataError
    from oapcal.imaging.remap import correct_image

    image = (np.arange(48 * 64 * int(np.prod(channels))) % 200).astype(np.uint8).reshape((48, 64, *channels))
    expected = correct_image(image, small_map)
    out = np.full((48, 64, *channels), 7, np.uint8)
    assert correct_image(image, small_map, out=out) is out
    np.testing.assert_array_equal(out.reshape(expected.shape), expected)
    for wrong in (np.empty((48, 63, *channels), np.uint8), np.empty((48, 64, *channels), np.float32),
                  np.empty((64, 48, *channels), np.uint8)[::-1], [[0] * 64] * 48):  # fmt: skip
        with pytest.raises(DataError, match="out must be"):
            correct_image(image, small_map, out=wrong)


def test_correct_image_refuses_an_image_of_another_size_unless_allowed(small_map):
    from oapcal.errors import DataError
    from oapcal.imaging.remap import correct_image

    with pytest.raises(DataError, match="the image is 80x60 px but the map was built for 64x48 px") as info:
        correct_image(np.ones((60, 80), np.uint8), small_map)
    assert info.value.param == "allow_size_mismatch"
    assert correct_image(np.ones((60, 80), np.uint8), small_map, allow_size_mismatch=True).shape == (48, 64)
    # a bare (map_x, map_y) pair does not know its input size: nothing to compare
    assert correct_image(np.ones((60, 80), np.uint8), tuple(small_map)).shape == (48, 64)


# -- A7: collapsing output geometries, a NaN border, numbers that only Python reads -------------


@pytest.mark.parametrize("um", ["1e300", "1000", "500"])
def test_an_output_scale_that_collapses_the_output_is_refused(run_cli, files, tmp_path, um):
    out = tmp_path / "out"
    code, _, err = run_cli("correct", files["calib"], files["img"], "--out-dir", out, "--um-per-px", um)
    one_error(code, err, expect_code=4)  # a geometry error, reported with the file as the others are
    assert f"{files['img']}: the output would be" in err, err
    assert "under 2 px on a side: the output region collapses" in err and "--um-per-px" in err, err
    assert not out.exists() or list(out.iterdir()) == []


def test_the_coarsest_output_scale_named_in_the_refusal_is_accepted(files):
    import re

    from oapcal.errors import DataError
    from oapcal.imaging.remap import output_geometry
    from oapcal.io.calibration import load_calibration

    cal = load_calibration(files["calib"])
    with pytest.raises(DataError) as info:
        output_geometry(cal, (48, 64), um_per_px=1e300)
    limit = float(re.search(r"at most ([0-9.e+-]+) um per px", str(info.value))[1])
    assert min(output_geometry(cal, (48, 64), um_per_px=limit * 0.999).shape) == 2
    with pytest.raises(DataError, match="collapses"):
        output_geometry(cal, (48, 64), um_per_px=limit * 1.01)
    with pytest.raises(DataError, match="more than 16 times"):  # the other end, a tiny scale
        output_geometry(cal, (48, 64), um_per_px=1e-300)


@pytest.mark.parametrize("value", ["nan", "inf", "-inf", "NaN"])
def test_border_refuses_non_finite_values_like_every_float_option(run_cli, files, tmp_path, value):
    out = tmp_path / "o"
    code, _, err = run_cli("correct", files["calib"], files["img"], "--out-dir", out, "--border", value)
    assert code == 2 and "--border" in err and "is not a finite number" in err, err
    assert not (tmp_path / "o").exists()


#: Text Python's float reads as 47.5 (or 47) but no point file means.
NOT_ASCII_NUMBERS = [
    "4_7.5", "\u0664\u0667.\u0665", "\uff14\uff17.\uff15", "4\u00b7\u0037", "\u09ea\u09ed", "47.5\u200b"
]  # fmt: skip


@pytest.mark.parametrize("bad", NOT_ASCII_NUMBERS)
def test_point_files_read_only_ascii_numbers(run_cli, tmp_path, bad):
    from oapcal.synthetic import synthetic_pairs

    data = synthetic_pairs(n_x=5, n_y=4, seed=1)
    write_point_pairs(tmp_path / "p.csv", data.xy_u, data.xy_d)
    lines = (tmp_path / "p.csv").read_text().splitlines()
    cells = lines[3].split(",")
    col = lines[0].split(",").index("x_d")
    cells[col] = bad
    lines[3] = ",".join(cells)
    (tmp_path / "p.csv").write_text("\n".join(lines) + "\n", encoding="utf-8")
    code, _, err = run_cli("fit", tmp_path / "p.csv", "--out", tmp_path / "c.json")
    one_error(code, err)
    assert f"p.csv: line 4, column 'x_d': {bad!r}"[:30] in err and "is not a number" in err, err
    assert not (tmp_path / "c.json").exists()


@pytest.mark.parametrize("bad", NOT_ASCII_NUMBERS)
def test_landmark_and_roi_readers_read_only_ascii_numbers(tmp_path, bad):
    from oapcal.errors import InputFileError
    from oapcal.io.landmarks import read_landmarks
    from oapcal.io.rois import read_rois

    (tmp_path / "l.csv").write_text(f"name,x,y\nA,10,12\nB,{bad},11\nC,31,40\n", encoding="utf-8")
    with pytest.raises(InputFileError, match=r"l\.csv: line 3: column 'x' is .* not a number"):
        read_landmarks(tmp_path / "l.csv")
    (tmp_path / "r.csv").write_text(f"label,x0,y0,x1,y1\na,1,2,{bad},60\n", encoding="utf-8")
    with pytest.raises(InputFileError, match=r"r\.csv: line 2, column 'x1': .* is not a number"):
        read_rois(tmp_path / "r.csv")


from hypothesis import HealthCheck  # noqa: E402


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(text=st.text(min_size=1, max_size=12))
def test_parse_number_reads_exactly_ascii_notation(text):
    """Whatever the text, parse_number gives float's value when the text is ASCII decimal
    or scientific notation (or nan/inf), and refuses it otherwise."""
    import re

    from oapcal.io.userfile import parse_number

    ascii_number = re.fullmatch(
        r"[+-]?([0-9]+\.?[0-9]*|\.[0-9]+)([eE][+-]?[0-9]+)?|[+-]?(nan|inf|infinity)",
        text.strip(),
        re.IGNORECASE | re.ASCII,
    )
    if ascii_number:
        value = parse_number(text)
        assert value == float(text.strip()) or (np.isnan(value) and np.isnan(float(text.strip())))
    else:
        with pytest.raises(ValueError):
            parse_number(text)


# -- B9: a multi-page TIFF where one image is expected is refused from its header ------------


@pytest.fixture(scope="module")
def tall_stack(tmp_path_factory):
    """64 zlib-compressed pages of 1024 x 1024 px: 0.2 MB on disk, 64 MiB decoded."""
    import tifffile

    path = tmp_path_factory.mktemp("stack") / "stack.tif"
    with tifffile.TiffWriter(path) as tif:
        page = np.zeros((1024, 1024), np.uint8)
        for _ in range(64):
            tif.write(page, compression="zlib", photometric="minisblack")
    return path


@pytest.mark.parametrize(
    "argv", ["esf {s}", "report {calib} --image {s} --out {d}/r.html", "detect {s} --out {d}/p.csv"]
)
def test_one_image_commands_refuse_a_stack_without_decoding_it(run_cli, files, tmp_path, tall_stack, argv):
    import tracemalloc

    tracemalloc.start()
    try:
        code, _, err = run_cli(*argv.format(s=tall_stack, calib=files["calib"], d=tmp_path).split())
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert code == 2 and f"{tall_stack}: is a stack of 64 frames (pages)" in err, err
    assert peak < 16 * 2**20, f"{peak / 2**20:.0f} MiB allocated: pages were decoded"  # 64 MiB if decoded


# -- B10, D20: Dask schedulers ------------------------------------------------------------------


@pytest.mark.parametrize(
    "address,why",
    [("THREADS", "not a scheduler name"), ("sync", "not a scheduler name"),
     ("tcp://127.0.0.1", "has no port"), ("http://127.0.0.1:8786", "protocol http://"),
     ("127.0.0.1:70000", "port 70000"),
     ("tcp://", "is not HOST:PORT"), ("a b:1", "not a scheduler name or address")],
)  # fmt: skip
def test_a_malformed_scheduler_address_is_refused_before_connecting(run_cli, files, tmp_path, address, why):
    pytest.importorskip("distributed", reason="the dask extra is not installed")
    import tifffile

    tifffile.imwrite(tmp_path / "s.tif", np.zeros((4, 48, 64), np.uint8), photometric="minisblack")
    out = tmp_path / "o"
    code, _, err = run_cli("correct", files["calib"], tmp_path / "s.tif", "--out-dir", out, "--dask",
                           "--scheduler", address)  # fmt: skip
    one_error(code, err)
    assert f"scheduler {address!r}: {why}" in err and "--scheduler" in err, err
    assert not (tmp_path / "o").exists()


def test_a_malformed_address_prints_one_line_and_nothing_at_exit(files, tmp_path):
    pytest.importorskip("distributed", reason="the dask extra is not installed")
    import subprocess
    import sys

    import tifffile

    tifffile.imwrite(tmp_path / "s.tif", np.zeros((4, 48, 64), np.uint8), photometric="minisblack")
    run = subprocess.run([sys.executable, "-m", "oapcal", "correct", str(files["calib"]),
                          str(tmp_path / "s.tif"), "--out-dir", str(tmp_path / "o"), "--dask", "--scheduler",
                          "THREADS"],
                         capture_output=True, text=True, timeout=120)  # fmt: skip
    assert run.returncode == 2 and run.stderr.count("\n") == 1, run.stderr
    assert "Traceback" not in run.stderr and "Exception ignored" not in run.stderr


def test_a_scheduler_without_workers_is_refused_after_the_timeout():
    pytest.importorskip("distributed", reason="the dask extra is not installed")
    from distributed import LocalCluster

    from oapcal.batch.distributed import dask_scheduler
    from oapcal.errors import InputFileError

    with LocalCluster(
        n_workers=0, processes=False, protocol="tcp", host="127.0.0.1", dashboard_address=None
    ) as cluster:
        address = cluster.scheduler_address
        with pytest.raises(InputFileError, match=f"scheduler {address}: has no workers after 1 s"):
            with dask_scheduler(address, worker_timeout=1):
                pytest.fail("a scheduler without workers must be refused")


@pytest.mark.slow  # ~17 s: a worker process starts and compiles the model
def test_distributed_workers_get_absolute_paths(files, tmp_path, monkeypatch):
    """Workers in another directory than the client (as on a cluster) still find the input
    and write the output where the client asked."""
    pytest.importorskip("distributed", reason="the dask extra is not installed")
    import tifffile
    import zarr
    from distributed import Client, LocalCluster

    from oapcal.batch.distributed import DaskSettings, correct_stack_dask
    from oapcal.io.calibration import load_calibration

    stack = (np.arange(4 * 48 * 64) % 200).astype(np.uint8).reshape(4, 48, 64)
    (tmp_path / "work").mkdir()
    (tmp_path / "elsewhere").mkdir()
    tifffile.imwrite(tmp_path / "work" / "s.tif", stack, photometric="minisblack")
    monkeypatch.chdir(tmp_path / "work")
    with (
        LocalCluster(n_workers=1, threads_per_worker=1, host="127.0.0.1", dashboard_address=None) as cluster,
        Client(cluster) as client,
    ):
        client.run(os.chdir, str(tmp_path / "elsewhere"))
        settings = DaskSettings(scheduler=cluster.scheduler_address, chunk_frames=2)
        result = correct_stack_dask(load_calibration(files["calib"]), "s.tif", "out", settings=settings)
    assert result.frames == 4 and result.output == "out/s.zarr"
    assert list((tmp_path / "elsewhere").iterdir()) == []
    z = zarr.open_array(str(tmp_path / "work" / "out" / "s.zarr"), mode="r")
    assert z.shape == (4, 48, 64) and np.asarray(z).any()


# -- D19: correct into a directory where nothing can be written is refused before the work -----


@pytest.mark.parametrize("dask", [False, True])
@pytest.mark.parametrize("sub", ["", "new/dir"])
def test_correct_into_an_unwritable_out_dir_is_refused_up_front(
    run_cli, files, tmp_path, monkeypatch, dask, sub
):
    import sys

    sys.path.insert(0, str(Path(__file__).parent))
    from test_hardening2 import _unwritable_dir

    if dask:
        pytest.importorskip("dask", reason="the dask extra is not installed")
    import oapcal.batch.stack as stack_module

    def never(*args, **kwargs):
        pytest.fail("an input was corrected before the output directory was checked")

    monkeypatch.setattr(stack_module, "_correct_file", never)
    target = _unwritable_dir() / sub if sub else _unwritable_dir()
    import tifffile

    tifffile.imwrite(tmp_path / "s.tif", np.zeros((2, 48, 64), np.uint8), photometric="minisblack")
    extra = ["--dask", "--scheduler", "synchronous"] if dask else []
    code, _, err = run_cli("correct", files["calib"], tmp_path / "s.tif", "--out-dir", target, *extra)
    one_error(code, err)
    assert f"{target}: cannot create files in /sys" in err, err


# -- D22: CR-only line endings ------------------------------------------------------------------


@pytest.mark.parametrize("ending", ["\r", "\r\n"])
def test_text_inputs_with_cr_line_endings_read_like_lf(tmp_path, ending, files):
    from oapcal.io.landmarks import read_landmarks
    from oapcal.io.points import read_points
    from oapcal.io.rois import read_rois

    def written(name, text):
        (tmp_path / name).write_bytes(text.replace("\n", ending).encode())
        (tmp_path / f"lf-{name}").write_bytes(text.encode())
        return tmp_path / name, tmp_path / f"lf-{name}"

    points = files["points"].read_text()
    cr, lf = written("p.csv", points)
    np.testing.assert_array_equal(read_points(cr).xy_d, read_points(lf).xy_d)
    cr, lf = written("l.csv", "name,x,y\nA,10,12\nB,50,11\nC,31,40\n")
    assert [(p.x, p.y, p.attrs) for p in read_landmarks(cr).landmarks] == [
        (p.x, p.y, p.attrs) for p in read_landmarks(lf).landmarks
    ]
    cr, lf = written("r.csv", "label,x0,y0,x1,y1\na,1,2,30,60\n")
    assert read_rois(cr) == read_rois(lf)


def test_fit_reads_a_cr_only_point_file(run_cli, files, tmp_path):
    (tmp_path / "p.csv").write_bytes(
        files["points"].read_bytes().replace(b"\r\n", b"\n").replace(b"\n", b"\r")
    )
    code, _, err = run_cli("fit", tmp_path / "p.csv", "--out", tmp_path / "c.json")
    assert code == 0 and "universal-newline" not in err, err


@settings(max_examples=80, deadline=None)
@given(
    shape=st.lists(st.integers(0, 6), min_size=0, max_size=4),
    dtype=st.sampled_from(["uint8", "uint16", "int16", "float32", "float64", "int8", "int64", "bool"]),
)
def test_correct_image_accepts_exactly_one_grey_or_colour_image(shape, dtype):
    """Whatever the array, correct_image corrects it when it is one grey or colour image of a
    supported type (the output has the map's shape and the image's channels and dtype) and
    refuses it with DataError otherwise."""
    from oapcal.errors import DataError
    from oapcal.imaging.remap import correct_image

    mx, my = np.meshgrid(np.arange(5, dtype=np.float32), np.arange(4, dtype=np.float32))
    image = np.ones(shape, dtype)
    ok = (
        (len(shape) == 2 or (len(shape) == 3 and shape[2] in (1, 3, 4)))
        and 0 not in shape
        and dtype in ("uint8", "uint16", "int16", "float32", "float64")
    )
    if ok:
        out = correct_image(image, (mx, my))
        assert out.dtype == image.dtype and out.shape[:2] == (4, 5)
        assert out.size == 20 * int(np.prod(shape[2:]))
    else:
        with pytest.raises(DataError):
            correct_image(image, (mx, my))


def test_correct_frames_refuses_a_single_image_and_corrects_a_stack(small_map):
    from oapcal.batch.stack import correct_frames
    from oapcal.errors import DataError
    from oapcal.imaging.remap import correct_image

    stack = (np.arange(3 * 48 * 64) % 250).astype(np.uint8).reshape(3, 48, 64)
    with pytest.raises(DataError, match="a stack must be"):
        correct_frames(stack[0], small_map)
    out = correct_frames(stack, small_map)
    np.testing.assert_array_equal(out[2], correct_image(stack[2], small_map))


@pytest.mark.parametrize("writer", ["atomic_path", "atomic_dir"])
@pytest.mark.parametrize("code_", [errno.ENOSPC, errno.EFBIG, errno.EDQUOT])
def test_writers_by_name_name_the_output_of_a_write_that_does_not_fit(tmp_path, writer, code_):
    """A library writing by file name (tifffile, OpenCV, zarr) that hits a full disk raises
    an OSError without a file name: it comes out naming the output."""
    import oapcal.io.atomic as atomic

    with pytest.raises(OSError) as info, getattr(atomic, writer)(tmp_path / "out.tif"):
        raise OSError(code_, os.strerror(code_))
    assert info.value.filename == str(tmp_path / "out.tif") and info.value.errno == code_
    assert list(tmp_path.iterdir()) == []
    # an error of reading an input (not a write that did not fit) is left as it is
    with pytest.raises(OSError) as info, getattr(atomic, writer)(tmp_path / "out.tif"):
        raise OSError(errno.EIO, os.strerror(errno.EIO))
    assert info.value.filename is None


def test_correction_map_refuses_an_image_of_another_size_than_the_calibrations(files):
    from oapcal.errors import DataError
    from oapcal.imaging.remap import correction_map
    from oapcal.io.calibration import load_calibration

    cal = load_calibration(files["calib"])  # image_size 64 x 48
    with pytest.raises(DataError, match="the image is 80x60 px but the calibration is for 64x48 px") as info:
        correction_map(cal, (60, 80))
    assert info.value.param == "allow_size_mismatch"
    assert correction_map(cal, (60, 80), allow_size_mismatch=True).shape == (60, 80)
    assert correction_map(cal.params, (60, 80)).shape == (60, 80)  # bare parameters know no size


def test_report_refuses_an_image_of_another_size(run_cli, files, tmp_path):
    import cv2

    cv2.imwrite(str(tmp_path / "big.png"), np.zeros((60, 80), np.uint8))
    big, out = tmp_path / "big.png", tmp_path / "r.html"
    code, _, err = run_cli("report", files["calib"], "--image", big, "--out", out)
    one_error(code, err)
    assert f"{tmp_path / 'big.png'}: is 80x60 px but the calibration is for 64x48 px" in err, err
    assert not (tmp_path / "r.html").exists()
