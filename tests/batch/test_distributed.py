import json
import tracemalloc
from dataclasses import replace

import numpy as np
import pytest
import tifffile
import zarr

from imaging_helpers import known_calibration, remap_reference, write_calibration
from oapcal.batch.distributed import DaskSettings, correct_stack_dask
from oapcal.errors import InputFileError
from oapcal.imaging.remap import correction_map
from oapcal.io.maps import save_map
from oapcal.model import PARAM_NAMES, params_from_dict

# A 256x256 camera: the example distortion re-centred.
SMALL = params_from_dict({"k1": 4e-6, "p1": -1e-4, "s3": 6e-4, "x_off": -128, "y_off": -128,
                          "c_x": 129, "c_y": 127, "m": 1.0})  # fmt: skip


def test_memory_stays_bounded_for_a_stack_much_larger_than_a_chunk(tmp_path):
    cal = known_calibration(params=SMALL, image_size=(256, 256))
    rng = np.random.default_rng(3)
    stack = rng.integers(0, 65535, (160, 256, 256), dtype=np.uint16)  # 21 MB, 40 chunks of 4 frames
    tifffile.imwrite(tmp_path / "s.tif", stack)
    tifffile.imwrite(tmp_path / "warm.tif", stack[:8])
    for fmt in ("zarr", "tiff"):
        options = DaskSettings(chunk_frames=4, scheduler="threads", workers=2, output_format=fmt)
        correct_stack_dask(cal, tmp_path / "warm.tif", tmp_path / "warm", settings=options)  # imports, caches
        tracemalloc.start()
        result = correct_stack_dask(cal, tmp_path / "s.tif", tmp_path / "out", settings=options)
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        assert result.frames == 160 and result.chunks == 40
        assert peak < stack.nbytes / 3, (
            f"{fmt}: peak {peak / 1e6:.1f} MB for a {stack.nbytes / 1e6:.1f} MB stack"
        )
    z = zarr.open_array(str(tmp_path / "out" / "s.zarr"), mode="r")
    assert z.chunks[0] == 4 and dict(z.attrs)["um_per_px"] == 4.8
    with tifffile.TiffFile(tmp_path / "out" / "s.tif") as tif:
        assert len(tif.pages) == 160
        for i in range(160):
            expected = remap_reference(stack[i], SMALL)
            np.testing.assert_array_equal(z[i], expected)
            np.testing.assert_array_equal(tif.pages[i].asarray(), expected)


def test_cli_dask_on_zarr_input(run_cli, tmp_path):
    calib = write_calibration(tmp_path / "calib.json", params=SMALL, image_size=(256, 256))
    stack = np.random.default_rng(4).random((6, 256, 256), dtype=np.float32)
    zarr.create_array(str(tmp_path / "in.zarr"), shape=stack.shape, chunks=(4, 256, 256), dtype="f4")[:] = (
        stack
    )
    out = tmp_path / "out"
    code, stdout, err = run_cli("correct", calib, tmp_path / "in.zarr", "--out-dir", out, "--dask",
                                "--scheduler", "synchronous", "--chunk-frames", "4", "--dask-format", "tiff",
                                "--json")  # fmt: skip
    assert code == 0, err
    assert json.loads(stdout)["results"][0]["frames"] == 6
    got = tifffile.imread(out / "in.tif")
    for i in range(6):
        np.testing.assert_array_equal(got[i], remap_reference(stack[i], SMALL))
    code, _, err = run_cli("correct", calib, tmp_path / "in.zarr", "--out-dir", out, "--dask",
                           "--scheduler", "synchronous")  # fmt: skip
    assert code == 0, err  # zarr output now written too
    code, _, err = run_cli("correct", calib, tmp_path / "calib.json", "--out-dir", out, "--dask")
    assert code == 4 and "unsupported file type '.json'" in err


@pytest.mark.slow
def test_default_local_cluster_from_the_command_line(tmp_path):
    import subprocess
    import sys

    calib = write_calibration(tmp_path / "calib.json", params=SMALL, image_size=(256, 256))
    stack = np.random.default_rng(5).integers(0, 255, (10, 256, 256), dtype=np.uint8)
    tifffile.imwrite(tmp_path / "s.tif", stack)
    out = subprocess.run([sys.executable, "-m", "oapcal", "correct", str(calib), str(tmp_path / "s.tif"),
                          "--out-dir", str(tmp_path / "o"), "--dask", "--chunk-frames", "3", "--quiet"],
                         capture_output=True, text=True)  # fmt: skip
    assert out.returncode == 0, out.stderr
    z = zarr.open_array(str(tmp_path / "o" / "s.zarr"), mode="r")
    for i in range(10):
        np.testing.assert_array_equal(z[i], remap_reference(stack[i], SMALL))


def test_a_prebuilt_map_is_the_one_applied_from_its_file_or_from_memory(run_cli, tmp_path):
    # The map comes from other parameters than the calibration: the output must follow the map.
    other = SMALL.copy()
    other[PARAM_NAMES.index("k1")] = 9e-6
    cmap = correction_map(other, (256, 256))
    save_map(cmap, tmp_path / "m.npz")
    calib = write_calibration(tmp_path / "calib.json", params=SMALL, image_size=(256, 256))
    stack = np.random.default_rng(5).integers(0, 255, (5, 256, 256), dtype=np.uint8)
    tifffile.imwrite(tmp_path / "s.tif", stack)
    dask = ("--dask", "--scheduler", "synchronous", "--map", tmp_path / "m.npz")
    code, _, err = run_cli(
        "correct", calib, tmp_path / "s.tif", "--out-dir", tmp_path / "a", *dask, "--chunk-frames", "2"
    )
    assert code == 0, err
    cal = known_calibration(params=SMALL, image_size=(256, 256))
    settings = DaskSettings(scheduler="synchronous", chunk_frames=2)
    result = correct_stack_dask(cal, tmp_path / "s.tif", tmp_path / "b", cmap, settings)
    assert result.frames == 5 and result.chunks == 3
    from_file = zarr.open_array(str(tmp_path / "a" / "s.zarr"), mode="r")
    in_memory = zarr.open_array(str(tmp_path / "b" / "s.zarr"), mode="r")
    for i in range(5):
        expected = remap_reference(stack[i], other)
        np.testing.assert_array_equal(from_file[i], expected)
        np.testing.assert_array_equal(in_memory[i], expected)
    # A stack of another size than the map was built for is refused, naming both sizes.
    tifffile.imwrite(tmp_path / "small.tif", stack[:, :128])
    code, _, err = run_cli("correct", calib, tmp_path / "small.tif", "--out-dir", tmp_path / "c", *dask)
    assert code == 4 and "small.tif: frames are 256x128 px but the calibration is for 256x256 px" in err
    no_size = replace(cal, image_size=None)  # only the map's input size is left to check
    with pytest.raises(InputFileError, match=r"frames are 256x128 px but the map was built for 256x256 px"):
        correct_stack_dask(no_size, tmp_path / "small.tif", tmp_path / "d", cmap, settings)
    loose = replace(settings, allow_size_mismatch=True)
    assert correct_stack_dask(no_size, tmp_path / "small.tif", tmp_path / "d", cmap, loose).frames == 5


@pytest.mark.parametrize("fmt", ["zarr", "tiff"])
def test_progress_is_reported_through_a_callback_per_window_of_frames(tmp_path, fmt):
    cal = known_calibration(params=SMALL, image_size=(256, 256))
    tifffile.imwrite(tmp_path / "s.tif", np.zeros((5, 256, 256), np.uint8))
    calls = []
    settings = DaskSettings(scheduler="synchronous", chunk_frames=2, output_format=fmt,
                            progress=lambda *a: calls.append(a))  # fmt: skip
    result = correct_stack_dask(cal, tmp_path / "s.tif", tmp_path / "o", settings=settings)
    assert result.frames == 5 and result.chunks == 3
    assert calls[0] == (0, 5, "s.tif frames") and calls[-1] == (5, 5, "s.tif frames")
    assert [c[0] for c in calls] == sorted(c[0] for c in calls)
