"""Regressions for the stack, TIFF and output defects found by attacking ``oapcal correct``
(multi-series and planar TIFFs, name collisions, resume, BigTIFF, huge frames, schedulers,
chunk sizes, ImageJ hyperstacks, many series, killed runs, absurd headers)."""

import json
import os
import signal
import socket
import struct
import subprocess
import sys
import threading
import time
import tracemalloc
import zipfile

import cv2
import numpy as np
import pytest
import tifffile
import zarr

from imaging_helpers import known_calibration, remap_reference, write_calibration
from oapcal.errors import InputFileError
from oapcal.imaging import remap as remap_module
from oapcal.imaging.remap import correct_image
from oapcal.io import images as images_module
from oapcal.io.images import open_frames, probe
from oapcal.io.maps import load_map
from oapcal.model import params_from_dict

SMALL = params_from_dict({"k1": 4e-6, "p1": -1e-4, "s3": 6e-4, "x_off": -32, "y_off": -24,
                          "c_x": 33, "c_y": 23, "m": 1.0})  # fmt: skip


@pytest.fixture
def calib(tmp_path):
    return write_calibration(tmp_path / "calib.json")


@pytest.fixture
def small_calib(tmp_path):
    return write_calibration(tmp_path / "small.json", params=SMALL, image_size=(64, 48))


def _frames(n=5, shape=(48, 64), dtype=np.uint16, seed=1):
    return np.random.default_rng(seed).integers(0, 60000, (n, *shape)).astype(dtype)


def _interruptible():
    """In the child: Ctrl-C back to its default. A shell without job control starts
    background jobs with SIGINT ignored, and a process inherits that (Python then installs
    no KeyboardInterrupt handler), so a suite started in the background would see Ctrl-C
    ignored, as it should be under ``nohup``; these tests are about what Ctrl-C does."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _imwrite(path, data):
    """A grey stack (tifffile would store 3 or 4 frames as one RGB image)."""
    tifffile.imwrite(path, data, photometric="minisblack")


def _visible(d):
    return sorted(p.name for p in d.iterdir() if p.name != ".oapcal")


# ------------------------------------------------------------- 1: multi-series TIFF


def _write_series_by_frame(path, frames):
    with tifffile.TiffWriter(path) as tw:
        for f in frames:
            tw.write(f)  # tifffile's default: one series per call


def test_every_series_of_a_tiff_is_corrected(run_cli, tmp_path, small_calib):
    frames = _frames(5)
    _write_series_by_frame(tmp_path / "s.tif", frames)
    with tifffile.TiffFile(tmp_path / "s.tif") as tif:
        assert len(tif.series) == 5  # the case: five series of one page
    out = tmp_path / "out"
    code, stdout, err = run_cli("correct", small_calib, tmp_path / "s.tif", "--out-dir", out)
    assert code == 0, err
    assert "1 corrected (5 frames)" in stdout
    got = tifffile.imread(out / "s.tif")
    assert got.shape == frames.shape
    for f, g in zip(frames, got):
        np.testing.assert_array_equal(g, remap_reference(f, SMALL))


def test_every_series_with_dask(run_cli, tmp_path, small_calib):
    frames = _frames(7)
    _write_series_by_frame(tmp_path / "s.tif", frames)
    code, stdout, err = run_cli("correct", small_calib, tmp_path / "s.tif", "--out-dir", tmp_path / "o",
                                "--dask", "--scheduler", "synchronous", "--chunk-frames", "3")  # fmt: skip
    assert code == 0, err
    z = zarr.open_array(str(tmp_path / "o" / "s.zarr"), mode="r")
    assert z.shape == frames.shape
    for i in range(7):
        np.testing.assert_array_equal(z[i], remap_reference(frames[i], SMALL))


def test_pages_of_different_shapes_or_types_are_refused(run_cli, tmp_path, small_calib):
    with tifffile.TiffWriter(tmp_path / "mixed.tif") as tw:
        tw.write(np.zeros((48, 64), np.uint16))
        tw.write(np.zeros((48, 64), np.uint8))
    code, stdout, err = run_cli("correct", small_calib, tmp_path / "mixed.tif", "--out-dir", tmp_path / "o")
    assert code == 4
    assert "mixed.tif: its pages differ (page 0: 64x48 uint16, page 1: 64x48 uint8)" in err
    assert _visible(tmp_path / "o") == []


def test_a_truncated_page_chain_is_refused_not_shortened(tmp_path):
    _imwrite(tmp_path / "t.tif", _frames(6))
    data = (tmp_path / "t.tif").read_bytes()
    (tmp_path / "t.tif").write_bytes(data[: len(data) * 2 // 3])  # tifffile then stops quietly
    with pytest.raises(InputFileError, match="t.tif: the file is truncated or corrupt"):
        probe(tmp_path / "t.tif")


# ------------------------------------------------------------------ 5: planar RGB


def test_planar_rgb_tiff_stays_one_planar_colour_image(run_cli, tmp_path, small_calib):
    rgb = np.random.default_rng(2).integers(0, 255, (48, 64, 3), dtype=np.uint8)
    # without tifffile's shape description (as other writers store planar RGB): tifffile's own
    # (3, rows, cols) with it is a 3-frame stack (tests/io/test_tifffile_grey_planes.py)
    tifffile.imwrite(tmp_path / "p.tif", np.moveaxis(rgb, -1, 0), photometric="rgb", planarconfig="separate",
                     metadata=None)  # fmt: skip
    code, stdout, err = run_cli("correct", small_calib, tmp_path / "p.tif", "--out-dir", tmp_path / "o")
    assert code == 0, err
    assert "1 corrected (1 frames)" in stdout
    with tifffile.TiffFile(tmp_path / "o" / "p.tif") as tif:
        assert len(tif.pages) == 1
        page = tif.pages[0]
        assert page.photometric == tifffile.PHOTOMETRIC.RGB and page.planarconfig == 2
        got = np.moveaxis(page.asarray(), 0, -1)
    np.testing.assert_array_equal(got, remap_reference(rgb, SMALL))


# ------------------------------------------------------------ 2, 3: name collisions


def test_dask_outputs_that_collide_are_refused_before_any_work(run_cli, tmp_path, small_calib):
    for name in ("a.tif", "a.tiff"):
        tifffile.imwrite(tmp_path / name, _frames(2))
    out = tmp_path / "o"
    code, _, err = run_cli("correct", small_calib, tmp_path / "a.tif", tmp_path / "a.tiff", "--out-dir", out,
                           "--dask", "--scheduler", "synchronous")  # fmt: skip
    assert code == 2
    assert "a.tiff: the input" in err and "a.tif would be written to the same output" in err
    assert "a.zarr" in err and not out.exists()


def test_save_map_that_is_an_image_output_is_refused(run_cli, tmp_path, small_calib):
    tifffile.imwrite(tmp_path / "f.tif", _frames(1)[0])
    out = tmp_path / "o"
    out.mkdir()
    for extra in ([], ["--overwrite"]):
        code, _, err = run_cli("correct", small_calib, tmp_path / "f.tif", "--out-dir", out,
                               "--save-map", out / "f.tif", *extra)  # fmt: skip
        assert code == 2, err
        assert "would be the same file as the map --save-map" in err
        assert _visible(out) == []
    code, _, err = run_cli("correct", small_calib, tmp_path / "f.tif", "--out-dir", out, "--dask",
                           "--scheduler", "synchronous", "--save-map", out / "f.zarr")  # fmt: skip
    assert code == 2 and "--save-map" in err


# ------------------------------------------------------------------------ 7: resume


def test_resume_redoes_outputs_that_do_not_match(run_cli, tmp_path, calib):
    frames = _frames(3, (480, 640))
    _imwrite(tmp_path / "s.tif", frames)
    cv2.imwrite(str(tmp_path / "c.png"), frames[0].astype(np.uint8))
    out = tmp_path / "o"
    args = ("correct", calib, tmp_path / "s.tif", tmp_path / "c.png", "--out-dir", out, "--json")

    def statuses():
        code, stdout, err = run_cli(*args)
        assert code == 0, err
        return [r["status"] for r in json.loads(stdout)["results"]]

    assert statuses() == ["corrected", "corrected"]
    good = tifffile.imread(out / "s.tif")
    assert statuses() == ["skipped", "skipped"]
    # A zero-byte output (a full disk, another program) is redone.
    (out / "s.tif").write_bytes(b"")
    assert statuses() == ["corrected", "skipped"]
    np.testing.assert_array_equal(tifffile.imread(out / "s.tif"), good)
    # An output made with another calibration is redone.
    other = write_calibration(tmp_path / "other.json", params=SMALL)
    code, _, err = run_cli("correct", other, tmp_path / "c.png", "--out-dir", out, "--allow-size-mismatch")
    assert code == 0, err
    assert statuses() == ["skipped", "corrected"]
    # A changed input (size or mtime) is redone; so are outputs of other settings.
    _imwrite(tmp_path / "s.tif", frames[:2])
    assert statuses() == ["corrected", "skipped"]
    assert tifffile.imread(out / "s.tif").shape[0] == 2
    code, stdout, err = run_cli(*args, "--interp", "cubic")
    assert [r["status"] for r in json.loads(stdout)["results"]] == ["corrected", "corrected"]


def test_dask_resume_checks_the_record_too(run_cli, tmp_path, small_calib):
    _imwrite(tmp_path / "s.tif", _frames(4))
    args = ("correct", small_calib, tmp_path / "s.tif", "--out-dir", tmp_path / "o", "--dask",
            "--scheduler", "synchronous", "--json")  # fmt: skip
    for fmt, target in (("tiff", "s.tif"), ("zarr", "s.zarr")):
        code, stdout, err = run_cli(*args, "--dask-format", fmt)
        assert json.loads(stdout)["results"][0]["status"] == "corrected", err
        code, stdout, err = run_cli(*args, "--dask-format", fmt)
        assert json.loads(stdout)["results"][0]["status"] == "skipped", err
        path = tmp_path / "o" / target
        if path.is_dir():
            import shutil

            shutil.rmtree(path)
            path.mkdir()  # an empty directory where the store was
        else:
            path.write_bytes(b"")
        code, stdout, err = run_cli(*args, "--dask-format", fmt)
        assert json.loads(stdout)["results"][0]["status"] == "corrected", err
        assert json.loads(stdout)["results"][0]["frames"] == 4


# ----------------------------------------------------------------------- 8: BigTIFF


def test_outputs_over_the_classic_tiff_limit_are_bigtiff(run_cli, tmp_path, small_calib, monkeypatch):
    # The threshold is lowered so that a small stack stands for one over 4 GiB.
    monkeypatch.setattr(images_module, "BIGTIFF_BYTES", 10_000, raising=False)
    frames = _frames(3)
    _imwrite(tmp_path / "s.tif", frames)
    tifffile.imwrite(tmp_path / "one.tif", frames[0, :8, :8])
    out = tmp_path / "o"
    code, _, err = run_cli("correct", small_calib, tmp_path / "s.tif", tmp_path / "one.tif", "--out-dir", out,
                           "--allow-size-mismatch")  # fmt: skip
    assert code == 0, err
    with tifffile.TiffFile(out / "s.tif") as tif:
        assert tif.is_bigtiff and len(tif.pages) == 3
    with tifffile.TiffFile(out / "one.tif") as tif:
        assert not tif.is_bigtiff  # 128 bytes stay classic
    code, _, err = run_cli("correct", small_calib, tmp_path / "s.tif", "--out-dir", tmp_path / "d", "--dask",
                           "--scheduler", "synchronous", "--dask-format", "tiff")  # fmt: skip
    assert code == 0, err
    with tifffile.TiffFile(tmp_path / "d" / "s.tif") as tif:
        assert tif.is_bigtiff and len(tif.pages) == 3


@pytest.mark.slow
def test_a_real_stack_over_4_gib_is_written(tmp_path):
    """A 4.3 GB uint8 stack (disk space needed: about 9 GB)."""
    from oapcal.batch.stack import correct_stack

    cal = known_calibration(params=SMALL, image_size=None)
    frames = 1100
    with tifffile.TiffWriter(tmp_path / "big.tif", bigtiff=True) as tw:
        for i in range(frames):
            tw.write(np.full((2048, 2048), i % 251, np.uint8), contiguous=True)
    report = correct_stack(cal, [tmp_path / "big.tif"], tmp_path / "o", allow_size_mismatch=True)
    assert report.ok, report.results
    with tifffile.TiffFile(tmp_path / "o" / "big.tif") as tif:
        assert tif.is_bigtiff and len(tif.pages) == frames


# --------------------------------------------------------------- 10: sides >= 32767


def test_remap_of_images_wider_than_opencv_allows(run_cli, tmp_path):
    rng = np.random.default_rng(4)
    image = rng.random((12, 40000), dtype=np.float32)
    xs, ys = np.meshgrid(np.arange(40000, dtype=np.float32), np.arange(12, dtype=np.float32))
    got = correct_image(image, (xs + np.float32(0.25), ys))
    expected = 0.75 * image[:, :-1] + 0.25 * image[:, 1:]
    np.testing.assert_allclose(got[:, :-1], expected, rtol=1e-5, atol=1e-6)
    assert (got[:, -1] == 0.75 * image[:, -1]).all() or np.allclose(got[:, -1], 0.75 * image[:, -1])
    # Through the command line: a 40000 x 16 px image is corrected, not an internal error.
    cal = write_calibration(tmp_path / "c.json", params=params_from_dict({"k1": 1e-12, "m": 1.0}),
                            image_size=None)  # fmt: skip
    cv2.imwrite(str(tmp_path / "wide.png"), (rng.random((16, 40000)) * 255).astype(np.uint8))
    code, stdout, err = run_cli("correct", cal, tmp_path / "wide.png", "--out-dir", tmp_path / "o")
    assert code == 0, err
    assert cv2.imread(str(tmp_path / "o" / "wide.png"), cv2.IMREAD_UNCHANGED).shape == (16, 40000)


@pytest.mark.parametrize("interp", ["nearest", "linear", "cubic", "lanczos"])
def test_tiled_remap_equals_one_remap(monkeypatch, interp):
    rng = np.random.default_rng(8)
    image = rng.integers(0, 65535, (90, 130, 3), dtype=np.uint16)
    cmap = remap_module.correction_map(SMALL, (90, 130), extent="full")
    # Large offsets, points outside the image: tiles near the border and inside it.
    cmap = (cmap.map_x * np.float32(2) - np.float32(30), cmap.map_y * np.float32(2) - np.float32(20))
    direct = correct_image(image, cmap, interp, border=7)
    monkeypatch.setattr(remap_module, "REMAP_LIMIT", 40)
    monkeypatch.setattr(remap_module, "REMAP_TILE", 16, raising=False)
    tiled = correct_image(image, cmap, interp, border=7)
    np.testing.assert_array_equal(tiled, direct)


# ------------------------------------------------------------------ 16: --scheduler


def _fake_server(reply: bytes | None):
    """A TCP server that accepts connections and says nothing (``reply`` None) or answers
    with ``reply``; returns its address and a stop function."""
    srv = socket.socket()
    srv.bind(("127.0.0.1", 0))
    srv.listen(8)
    srv.settimeout(0.2)
    stop = threading.Event()
    conns = []

    def serve():
        while not stop.is_set():
            try:
                conn, _ = srv.accept()
            except OSError:
                continue
            conns.append(conn)
            if reply is not None:
                conn.sendall(reply)

    threading.Thread(target=serve, daemon=True).start()

    def close():
        stop.set()
        for c in conns:
            c.close()
        srv.close()

    return f"tcp://127.0.0.1:{srv.getsockname()[1]}", close


@pytest.mark.parametrize(
    "reply", [pytest.param(None, marks=pytest.mark.slow), b"\xff" * 64], ids=["silent", "garbage"]
)
def test_a_scheduler_that_is_not_one_is_refused(run_cli, tmp_path, small_calib, monkeypatch, reply):
    from oapcal.batch import distributed

    monkeypatch.setattr(distributed, "CONNECT_TIMEOUT", 1)
    _imwrite(tmp_path / "a.tif", _frames(2))
    _imwrite(tmp_path / "b.tif", _frames(2))
    address, close = _fake_server(reply)
    try:
        start = time.monotonic()
        code, _, err = run_cli("correct", small_calib, tmp_path / "a.tif", tmp_path / "b.tif", "--out-dir",
                               tmp_path / "o", "--dask", "--scheduler", address)  # fmt: skip
        elapsed = time.monotonic() - start
    finally:
        close()
    assert code == 2, err
    assert f"scheduler {address}" in err and "(set by --scheduler)" in err
    assert "MemoryError" not in err and "Traceback" not in err
    assert err.count("oapcal: error") == 1  # connected once for the batch, not per file
    assert elapsed < 60  # a hang would never return; this bounds nothing else


def test_dask_options_without_dask_are_refused(run_cli, tmp_path, small_calib):
    _imwrite(tmp_path / "a.tif", _frames(1))
    for option in (["--scheduler", "tcp://127.0.0.1:1"], ["--chunk-frames", "4"], ["--dask-format", "tiff"]):
        code, _, err = run_cli(
            "correct", small_calib, tmp_path / "a.tif", "--out-dir", tmp_path / "o", *option
        )
        assert code == 2 and f"{option[0]} applies to --dask only" in err
        assert not (tmp_path / "o").exists()


# --------------------------------------------------------------- 17: --chunk-frames


def test_chunk_frames_is_bounded_by_the_stack_length(tmp_path):
    from dataclasses import replace

    from oapcal.batch.distributed import DaskSettings, correct_stack_dask

    cal = known_calibration(params=SMALL, image_size=(64, 48))
    frames = _frames(40, dtype=np.uint8)
    _imwrite(tmp_path / "s.tif", frames)
    options = DaskSettings(scheduler="synchronous", output_format="zarr", chunk_frames=4)
    correct_stack_dask(cal, tmp_path / "s.tif", tmp_path / "warm", settings=options)
    tracemalloc.start()
    huge = replace(options, chunk_frames=100_000)
    result = correct_stack_dask(cal, tmp_path / "s.tif", tmp_path / "o", settings=huge)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert result.frames == 40 and result.chunks == 1
    # 100,000 frames of 64x48 would be 307 MB; the stack is 123 kB.
    assert peak < 20 * frames.nbytes, f"peak {peak / 1e6:.1f} MB"
    assert zarr.open_array(str(tmp_path / "o" / "s.zarr"), mode="r").chunks[0] == 40


# ------------------------------------------------------- 18: ImageJ hyperstack, one IFD


def _imagej_single_ifd(path, frames):
    tifffile.imwrite(path, frames, imagej=True)
    data = bytearray(path.read_bytes())
    with tifffile.TiffFile(path) as tif:
        offset = tif.pages[0].offset
    (n,) = struct.unpack("<H", data[offset : offset + 2])
    data[offset + 2 + 12 * n : offset + 6 + 12 * n] = b"\0\0\0\0"  # drop every IFD after the first
    path.write_bytes(bytes(data))


def test_imagej_hyperstack_in_one_ifd_is_read_frame_by_frame(tmp_path, small_calib, run_cli):
    frames = _frames(60, (48, 64))
    _imagej_single_ifd(tmp_path / "ij.tif", frames)
    with tifffile.TiffFile(tmp_path / "ij.tif") as tif:
        assert len(tif.pages) == 1  # the case: all frames behind one IFD
    tracemalloc.start()
    with open_frames(tmp_path / "ij.tif") as (info, it):
        assert info.n_frames == 60
        for i, frame in enumerate(it):
            np.testing.assert_array_equal(frame, frames[i])
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert peak < frames.nbytes / 4, f"peak {peak / 1e6:.2f} MB for {frames.nbytes / 1e6:.2f} MB"
    code, _, err = run_cli("correct", small_calib, tmp_path / "ij.tif", "--out-dir", tmp_path / "o", "--dask",
                           "--scheduler", "synchronous", "--dask-format", "tiff")  # fmt: skip
    assert code == 0, err
    got = tifffile.imread(tmp_path / "o" / "ij.tif")
    np.testing.assert_array_equal(got[59], remap_reference(frames[59], SMALL))


# ------------------------------------------------------------- 19: very many series


@pytest.mark.slow
def test_many_series_open_in_linear_time(tmp_path):
    """tifffile's ``series`` takes quadratic time here (20,000 series: about 40 s); timed
    against itself at two sizes rather than a wall clock."""

    def build(n):
        path = tmp_path / f"m{n}.tif"
        with tifffile.TiffWriter(path) as tw:
            for _ in range(n):
                tw.write(np.zeros((1, 1), np.uint8))
        start = time.perf_counter()
        info = probe(path)
        return info, time.perf_counter() - start

    small, t_small = build(4000)
    large, t_large = build(16000)
    assert small.n_frames == 4000 and large.n_frames == 16000
    assert t_large < 8 * t_small  # quadratic would be 16x


def test_many_series_are_read_without_tifffile_series(tmp_path, monkeypatch):
    with tifffile.TiffWriter(tmp_path / "m.tif") as tw:
        for i in range(50):
            tw.write(np.full((2, 3), i, np.uint8))
    # ``TiffFile.series`` is quadratic in the number of series; oapcal must not use it.
    monkeypatch.setattr(tifffile.TiffFile, "series", property(lambda self: pytest.fail("series used")))
    with open_frames(tmp_path / "m.tif") as (info, frames):
        assert [int(f[0, 0]) for f in frames] == list(range(50))


# ------------------------------------------------------------ 21: killed runs, temps


def test_stale_temporary_files_are_removed_and_live_ones_kept(tmp_path, small_calib, run_cli):
    import fcntl

    _imwrite(tmp_path / "s.tif", _frames(2))
    out = tmp_path / "o"
    out.mkdir()
    stale = out / ".s.ab12cd_9.tmp.tif"
    stale.write_bytes(b"x" * 1000)  # left by a killed run
    stale_dir = out / ".s.zarr.zz99yy00.tmp"
    stale_dir.mkdir()
    (stale_dir / "c").write_bytes(b"x")
    live = out / ".s.qwertyui.tmp.tif"
    live.write_bytes(b"x")
    fd = os.open(live, os.O_RDONLY)
    fcntl.flock(fd, fcntl.LOCK_EX)  # another run writing now
    unrelated = out / ".notes.abcdefgh.tmp"
    unrelated.write_text("mine")
    try:
        code, _, err = run_cli("correct", small_calib, tmp_path / "s.tif", "--out-dir", out)
        assert code == 0, err
        assert not stale.exists() and live.exists() and unrelated.exists()
        code, _, err = run_cli("correct", small_calib, tmp_path / "s.tif", "--out-dir", out, "--dask",
                               "--scheduler", "synchronous")  # fmt: skip
        assert code == 0, err
        assert not stale_dir.exists() and live.exists()
    finally:
        os.close(fd)


@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGHUP, signal.SIGINT])
def test_terminated_run_leaves_no_temporary_file(tmp_path, sig):
    calib = write_calibration(tmp_path / "c.json", params=SMALL, image_size=(64, 48))
    # the signal must reach the run while it writes: a run that finished first (on a loaded
    # machine 20,000 small frames can) tested nothing, and is made again on a longer stack
    for attempt, n_frames in enumerate((20000, 80000)):
        stack = tmp_path / f"s{attempt}.tif"
        _imwrite(stack, _frames(n_frames, dtype=np.uint8))
        out = tmp_path / f"o{attempt}"
        proc = subprocess.Popen([sys.executable, "-m", "oapcal", "correct", str(calib), str(stack),
                                 "--out-dir", str(out), "--quiet", "--interp", "lanczos"],
                                stderr=subprocess.PIPE, text=True, preexec_fn=_interruptible)  # fmt: skip
        deadline = time.monotonic() + 60
        while proc.poll() is None and not any(
            p.name.startswith(f".{stack.stem}.") for p in (out.iterdir() if out.exists() else [])
        ):
            assert time.monotonic() < deadline
            time.sleep(0.05)
        proc.send_signal(sig)
        _, err = proc.communicate(timeout=60)
        if proc.returncode == 0:
            continue  # finished before the signal
        assert proc.returncode == 128 + sig, err
        assert "Traceback" not in err
        assert _visible(out) == []
        return
    pytest.fail("every run finished before the signal reached it")


@pytest.mark.slow
def test_ctrl_c_under_the_local_cluster_is_one_line(tmp_path):
    calib = write_calibration(tmp_path / "c.json", params=SMALL, image_size=(64, 48))
    _imwrite(tmp_path / "s.tif", _frames(40000, dtype=np.uint8))
    out = tmp_path / "o"
    proc = subprocess.Popen([sys.executable, "-m", "oapcal", "correct", str(calib), str(tmp_path / "s.tif"),
                             "--out-dir", str(out), "--dask", "--chunk-frames", "200", "--quiet",
                             "--interp", "lanczos"],
                            stderr=subprocess.PIPE, text=True, start_new_session=True,
                            preexec_fn=_interruptible)  # fmt: skip
    deadline = time.monotonic() + 120
    while not any(p.name.startswith(".s.zarr.") for p in (out.iterdir() if out.exists() else [])):
        assert time.monotonic() < deadline and proc.poll() is None
        time.sleep(0.05)
    time.sleep(1)
    os.killpg(proc.pid, signal.SIGINT)  # Ctrl-C reaches the whole process group
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err
    assert "Traceback" not in err and "distributed" not in err, err
    assert _visible(out) == []


# ------------------------------------------------------------ 14: absurd sizes


def test_a_zarr_header_claiming_a_billion_frames_is_refused(run_cli, tmp_path, small_calib):
    zarr.create_array(str(tmp_path / "huge.zarr"), shape=(10**9, 48, 64), chunks=(16, 48, 64), dtype="u2")
    assert sum(p.stat().st_size for p in (tmp_path / "huge.zarr").rglob("*") if p.is_file()) < 2000
    code, _, err = run_cli("correct", small_calib, tmp_path / "huge.zarr", "--out-dir", tmp_path / "o",
                           "--dask", "--scheduler", "synchronous")  # fmt: skip
    assert code == 4, err
    assert "huge.zarr" in err and ("chunks, more than" in err or "holds no data" in err)
    # With some data stored, the chunk count still bounds the graph.
    z = zarr.open_array(str(tmp_path / "huge.zarr"), mode="r+")
    z[:2] = 1
    code, _, err = run_cli("correct", small_calib, tmp_path / "huge.zarr", "--out-dir", tmp_path / "o",
                           "--dask", "--scheduler", "synchronous")  # fmt: skip
    assert code == 4 and "--chunk-frames" in err


def test_export_of_an_absurd_image_size_is_refused(run_cli, tmp_path):
    calib = write_calibration(tmp_path / "c.json", params=params_from_dict({"m": 1.0}))
    for size in ("100000000x100000000", "1000000x1000000"):
        code, _, err = run_cli("export-opencv", calib, "--out", tmp_path / "e.json", "--image-size", size,
                               "--extent", "full")  # fmt: skip
        assert code == 2, err
        assert size in err and "MemoryError" not in err
        assert not (tmp_path / "e.json").exists()


def test_a_calibration_asking_for_a_huge_map_is_refused(run_cli, tmp_path):
    calib = write_calibration(tmp_path / "c.json", image_size=(200000, 200000))
    code, _, err = run_cli("correct", calib, "--save-map", tmp_path / "m.npz")
    assert code == 2, err
    assert "200000x200000" in err and "--max-pixels" in err
    assert not (tmp_path / "m.npz").exists()


# ------------------------------------------------------------- 20: --map zip bomb


def test_a_zip_bomb_map_is_refused_from_its_header(tmp_path):
    path = tmp_path / "bomb.npz"
    header = {"descr": "<f4", "fortran_order": False, "shape": (10000, 10000)}
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as zf:
        for name in ("map_x.npy", "map_y.npy"):
            with zf.open(name, "w", force_zip64=True) as fh:
                np.lib.format.write_array_header_1_0(fh, header)
                block = bytes(2**20)
                for _ in range(100):
                    fh.write(block)
    assert path.stat().st_size < 2**20
    tracemalloc.start()
    with pytest.raises(InputFileError, match="bomb.npz: .* unpack to .*decompression bomb"):
        load_map(path)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert peak < 50 * 2**20


# ------------------------------------------------------- 20: report --image, large images


def test_target_checks_are_bounded_on_an_image_of_noise(monkeypatch):
    """An 8000 x 6000 image of noise has ~10^5 components and took over 240 s in
    ``report --image``: only the largest components are checked, each over its own box."""
    from oapcal.imaging import checks

    image = np.random.default_rng(3).random((400, 400))
    image = cv2.GaussianBlur(image, (0, 0), 1.5)
    calls = []
    original = checks._crossings

    def counting(image, labels, k, *args):
        calls.append(k)
        return original(image, labels, k, *args)

    monkeypatch.setattr(checks, "_crossings", counting)
    monkeypatch.setattr(checks, "MAX_COMPONENTS", 40, raising=False)
    from oapcal.imaging.esf import find_components

    comp = find_components(image)
    assert len(comp.boxes) > 100  # the case: many more components than are checked
    checks.check_target(image, components=comp)
    assert 0 < len(set(calls)) <= 40
    largest = set((np.argsort(-comp.areas)[:40] + 1).tolist())
    assert set(calls) <= largest


# ------------------------------------------------------------ 15: a full disk under Dask


def _limit_file_size():
    import resource

    resource.setrlimit(resource.RLIMIT_FSIZE, (200_000, 200_000))  # writes beyond fail: EFBIG


@pytest.mark.slow
@pytest.mark.parametrize("fmt", ["zarr", "tiff"])
def test_a_full_disk_under_the_local_cluster_is_one_line(tmp_path, fmt):
    calib = write_calibration(tmp_path / "c.json", params=SMALL, image_size=(64, 48))
    _imwrite(tmp_path / "s.tif", _frames(2000, dtype=np.uint8))
    out = tmp_path / "o"
    args = [sys.executable, "-m", "oapcal", "correct", str(calib), str(tmp_path / "s.tif"), "--out-dir",
            str(out), "--dask", "--chunk-frames", "200", "--quiet", "--dask-format", fmt]  # fmt: skip
    proc = subprocess.run(args, capture_output=True, text=True, preexec_fn=_limit_file_size, timeout=300)
    err = proc.stderr
    assert proc.returncode == 4, err
    assert "Traceback" not in err and "distributed" not in err, err
    # one error line; the line before it, if any, is correct's note on the trust region
    errors = [line for line in err.splitlines() if line.startswith("oapcal: error")]
    assert len(errors) == 1 and "cannot be written" in errors[0] and ".tmp" not in err, err
    assert all(line.startswith("oapcal: ") for line in err.splitlines()) and err.count("\n") <= 2, err
    assert _visible(out) == []


def test_a_tiff_output_larger_than_the_free_space_is_refused_before_writing(run_cli, tmp_path, small_calib,
                                                                            monkeypatch):  # fmt: skip
    import shutil
    from collections import namedtuple

    usage = namedtuple("usage", "total used free")
    monkeypatch.setattr(shutil, "disk_usage", lambda path: usage(10**6, 10**6 - 1000, 1000))
    _imwrite(tmp_path / "s.tif", _frames(3))  # 18 kB of output, 1 kB free
    for extra in ([], ["--dask", "--scheduler", "synchronous", "--dask-format", "tiff"]):
        out = tmp_path / "o"
        code, _, err = run_cli("correct", small_calib, tmp_path / "s.tif", "--out-dir", out, *extra)
        assert code == 4, err
        assert "s.tif: the output needs" in err and "GiB free" in err
        assert _visible(tmp_path / "o") == []


def test_a_map_too_large_for_memory_is_refused_before_it_is_built(run_cli, tmp_path):
    identity = params_from_dict({"m": 1.0})
    calib = write_calibration(tmp_path / "c.json", params=identity, image_size=(16384, 16384))
    code, _, err = run_cli("correct", calib, "--save-map", tmp_path / "m.npy", "--out-size", "30000x30000")
    assert code == 2, err
    assert "30000x30000 px output would need 6.71 GiB" in err and "MemoryError" not in err
    assert _visible(tmp_path) == ["c.json"]


@pytest.mark.parametrize("dask", [False, True])
def test_compressed_stacks_are_read_page_by_page(run_cli, tmp_path, small_calib, dask):
    frames = _frames(5)
    tifffile.imwrite(tmp_path / "z.tif", frames, photometric="minisblack", compression="zlib")
    info = probe(tmp_path / "z.tif")
    assert info.n_frames == 5 and info.segments[0][0] == "pages"  # not one contiguous block
    extra = (
        ["--dask", "--scheduler", "synchronous", "--dask-format", "tiff", "--chunk-frames", "2"]
        if dask
        else []
    )
    code, _, err = run_cli("correct", small_calib, tmp_path / "z.tif", "--out-dir", tmp_path / "o", *extra)
    assert code == 0, err
    got = tifffile.imread(tmp_path / "o" / "z.tif")
    for f, g in zip(frames, got, strict=True):
        np.testing.assert_array_equal(g, remap_reference(f, SMALL))


def test_per_file_geometry_errors_name_the_file(run_cli, tmp_path, small_calib):
    tifffile.imwrite(tmp_path / "f.tif", _frames(1)[0])
    code, _, err = run_cli("correct", small_calib, tmp_path / "f.tif", "--out-dir", tmp_path / "o",
                           "--out-size", "60000x60000")  # fmt: skip
    assert code == 4, err
    assert err.startswith(f"oapcal: error: {tmp_path / 'f.tif'}: the output would be 60000x60000 px")
    # the library names its parameters, the command line the options that set them
    assert err.rstrip().endswith("a smaller out_size, a coarser um_per_px or another extent "
                                 "(set by --out-size, --um-per-px, --extent)")  # fmt: skip


def test_single_file_outputs_remove_what_a_killed_run_left(run_cli, tmp_path, calib):
    stale = tmp_path / ".camera.yml.k1ll3d_x.tmp"  # atomic_write's name for camera.yml
    stale.write_text("half")
    stale_path = tmp_path / ".camera.abcdefgh.tmp.yml"  # atomic_path's name
    stale_path.write_text("half")
    other = tmp_path / ".notes.txt.abcdefgh.tmp"
    other.write_text("not ours to remove")
    code, _, err = run_cli("export-opencv", calib, "--out", tmp_path / "camera.yml")
    assert code == 0, err
    assert not stale.exists() and not stale_path.exists() and other.exists()


def test_a_zarr_input_without_dask_says_to_give_dask(run_cli, tmp_path):
    """Item 24: a zarr array given without --dask is named as such, not 'holds no images'."""
    calib = write_calibration(tmp_path / "c.json")
    z = zarr.create_array(str(tmp_path / "s.zarr"), shape=(2, 480, 640), chunks=(1, 480, 640), dtype="uint8")
    z[:] = 1
    code, _, err = run_cli("correct", calib, tmp_path / "s.zarr", "--out-dir", tmp_path / "out")
    assert code == 4
    assert "s.zarr: is a zarr array, which is corrected with Dask: give --dask" in err
    assert "holds no images" not in err
