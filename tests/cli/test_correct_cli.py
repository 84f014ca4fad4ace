import json
import os

import cv2
import numpy as np
import pytest
import tifffile

from imaging_helpers import known_calibration, remap_reference, write_calibration
from oapcal.batch.stack import correct_stack


@pytest.fixture
def calib(tmp_path):
    return write_calibration(tmp_path / "calib.json")


@pytest.fixture
def frames():
    rng = np.random.default_rng(5)
    return rng.integers(0, 65535, (5, 480, 640), dtype=np.uint16)


def _files(d):
    """What a user sees in ``d`` (resume records in ``.oapcal/`` not included)."""
    return sorted(p.name for p in d.iterdir() if p.name != ".oapcal") if d.exists() else []


def test_batch_corrects_reports_corrupt_files_and_resumes(run_cli, tmp_path, calib, frames):
    src = tmp_path / "raw"
    src.mkdir()
    tifffile.imwrite(src / "stack.tif", frames)
    colour = np.random.default_rng(1).integers(0, 255, (480, 640, 3), dtype=np.uint8)
    cv2.imwrite(str(src / "colour.png"), colour)
    (src / "broken.tif").write_bytes(b"II*\x00not a tiff at all")
    out = tmp_path / "out"
    code, stdout, err = run_cli("correct", calib, src, "--out-dir", out)
    assert code == 4
    assert "broken.tif: cannot be read as a TIFF image" in err and "Traceback" not in err
    assert "2 corrected (6 frames), 0 skipped (complete output exists), 1 failed" in stdout
    assert _files(out) == ["colour.png", "stack.tif"]  # nothing half-written, no temporaries
    params = known_calibration().params
    got = tifffile.imread(out / "stack.tif")
    assert got.dtype == np.uint16 and got.shape == frames.shape
    for frame, corrected in zip(frames, got):
        np.testing.assert_array_equal(corrected, remap_reference(frame, params))
    np.testing.assert_array_equal(cv2.imread(str(out / "colour.png")), remap_reference(colour, params))
    with tifffile.TiffFile(out / "stack.tif") as tif:
        meta = json.loads(tif.pages[0].description)
    assert meta["oapcal_calibration"] == "bench-setup-1" and meta["um_per_px"] == 4.8

    # Resume: complete outputs are skipped, a missing one is redone.
    (out / "colour.png").unlink()
    before = os.stat(out / "stack.tif").st_mtime_ns
    (src / "broken.tif").unlink()
    code, stdout, err = run_cli("correct", calib, src, "--out-dir", out, "--json")
    assert code == 0, err
    data = json.loads(stdout)
    assert {r["input"].rsplit("/", 1)[1]: r["status"] for r in data["results"]} == {
        "colour.png": "corrected",
        "stack.tif": "skipped",
    }
    assert os.stat(out / "stack.tif").st_mtime_ns == before


def test_interrupted_stack_leaves_no_output(tmp_path, frames):
    tifffile.imwrite(tmp_path / "s.tif", frames)
    data = (tmp_path / "s.tif").read_bytes()
    (tmp_path / "s.tif").write_bytes(data[: len(data) * 2 // 3])  # last frame truncated
    report = correct_stack(known_calibration(), [tmp_path / "s.tif"], tmp_path / "out")
    (result,) = report.results
    assert result.status == "failed" and "s.tif" in result.message
    assert _files(tmp_path / "out") == []


def test_interpolation_border_and_globs(run_cli, tmp_path, calib):
    image = np.full((480, 640), 100, np.uint8)
    for name in ("a.bmp", "b.bmp"):
        cv2.imwrite(str(tmp_path / name), image)
    out = tmp_path / "out"
    code, _, err = run_cli("correct", calib, tmp_path / "*.bmp", "--out-dir", out, "--interp", "nearest",
                           "--border", "7", "--workers", "2")  # fmt: skip
    assert code == 0, err
    got = cv2.imread(str(out / "b.bmp"), cv2.IMREAD_UNCHANGED)
    expected = remap_reference(image, known_calibration().params, cv2.INTER_NEAREST)
    outside = expected == 0  # source outside the input: the border value
    assert outside.any() and (got[outside] == 7).all() and (got[~outside] == 100).all()


def test_saved_map_reproduces_the_correction(run_cli, tmp_path, calib, frames):
    tifffile.imwrite(tmp_path / "f.tif", frames[0])
    a, b = tmp_path / "a", tmp_path / "b"
    code, _, err = run_cli("correct", calib, tmp_path / "f.tif", "--out-dir", a, "--extent", "full",
                           "--save-map", tmp_path / "m.npz")  # fmt: skip
    assert code == 0, err
    code, _, err = run_cli("correct", calib, tmp_path / "f.tif", "--out-dir", b, "--map", tmp_path / "m.npz")
    assert code == 0, err
    first, second = tifffile.imread(a / "f.tif"), tifffile.imread(b / "f.tif")
    assert first.shape != frames[0].shape  # the full field is larger than the frame
    np.testing.assert_array_equal(first, second)


def test_output_scale_is_in_the_metadata(run_cli, tmp_path, calib, frames):
    tifffile.imwrite(tmp_path / "f.tif", frames[0])
    code, _, err = run_cli(
        "correct", calib, tmp_path / "f.tif", "--out-dir", tmp_path / "o", "--um-per-px", "9.6"
    )
    assert code == 0, err
    with tifffile.TiffFile(tmp_path / "o" / "f.tif") as tif:
        assert tif.pages[0].shape == (240, 320)
        assert json.loads(tif.pages[0].description)["um_per_px"] == 9.6


def test_size_mismatch_is_an_error_unless_allowed(run_cli, tmp_path, calib):
    cv2.imwrite(str(tmp_path / "small.png"), np.zeros((100, 120), np.uint8))
    code, _, err = run_cli("correct", calib, tmp_path / "small.png", "--out-dir", tmp_path / "o")
    assert code == 4
    assert "small.png: image is 120x100 px but the calibration is for 640x480 px" in err
    assert "--allow-size-mismatch" in err and not (tmp_path / "o" / "small.png").exists()
    code, _, err = run_cli("correct", calib, tmp_path / "small.png", "--out-dir", tmp_path / "o",
                           "--allow-size-mismatch")  # fmt: skip
    assert code == 0, err
    assert cv2.imread(str(tmp_path / "o" / "small.png"), cv2.IMREAD_UNCHANGED).shape == (100, 120)


@pytest.mark.parametrize(
    "args,pattern",
    [
        (["{tmp}/missing.json", "{img}", "--out-dir", "{tmp}/o"], "no such calibration file"),
        (["{calib}", "{img}", "--out-dir", "{tmp}"], "the output directory contains the input"),
        (["{calib}", "{tmp}", "--out-dir", "{tmp}/.."], "is or contains the input directory"),
        (["{calib}", "{img}"], "give --out-dir DIR"),
        (["{calib}", "{img}", "--out-dir", "{tmp}/o", "--map", "{img}"], "a map file must end in"),
        (
            ["{calib}", "{img}", "--out-dir", "{tmp}/o", "--extent", "calibrated", "--map", "{tmp}/m.npz"],
            "--map fixes the output geometry",
        ),
        (["{calib}", "{img}", "--out-dir", "{tmp}/o", "--save-map", "{calib}"], "would overwrite the input"),
    ],
)
def test_user_errors_exit_2_and_write_nothing(run_cli, tmp_path, calib, args, pattern):
    cv2.imwrite(str(tmp_path / "img.png"), np.zeros((480, 640), np.uint8))
    before = _files(tmp_path)
    sub = {"tmp": tmp_path, "calib": calib, "img": tmp_path / "img.png"}
    code, _, err = run_cli("correct", *(a.format(**sub) for a in args))
    assert code == 2, err
    assert pattern in err and "Traceback" not in err
    assert _files(tmp_path) == before


def test_unsupported_and_missing_inputs_are_reported(run_cli, tmp_path, calib):
    (tmp_path / "notes.txt").write_text("hello")
    tifffile.imwrite(tmp_path / "c.tif", np.zeros((480, 640), np.complex64))
    code, stdout, err = run_cli("correct", calib, tmp_path / "notes.txt", tmp_path / "nope.png",
                                tmp_path / "c.tif", "--out-dir", tmp_path / "o")  # fmt: skip
    assert code == 4
    assert "notes.txt: unsupported file type '.txt'" in err
    assert "nope.png: no such file or directory" in err
    assert "c.tif: pixel type complex64 is not supported" in err
    assert "0 corrected" in stdout and "3 failed" in stdout
