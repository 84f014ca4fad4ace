"""Compressed TIFFs (what cv2.imwrite, cameras and Fiji write) are read by every command:
LZW, deflate, zstd and JPEG, single frames and stacks, through tifffile with imagecodecs."""

import numpy as np
import pytest
import tifffile

from oapcal.io.imagefile import read_image_grey
from oapcal.io.images import open_frames, probe

CODECS = ["lzw", "deflate", "zstd", "jpeg"]


def _frames(dtype=np.uint8, n=3):
    rng = np.random.default_rng(0)
    return [(rng.random((48, 64)) * (200 if dtype == np.uint8 else 60000)).astype(dtype) for _ in range(n)]


@pytest.mark.parametrize("codec", CODECS)
def test_compressed_stack_reads_back_exactly(tmp_path, codec):
    frames = _frames()
    path = tmp_path / f"stack_{codec}.tif"
    options = {"compressionargs": {"level": 100}} if codec == "jpeg" else {}
    tifffile.imwrite(path, np.stack(frames), photometric="minisblack", compression=codec, **options)
    info = probe(path)
    assert info.n_frames == 3 and info.frame_shape[:2] == (48, 64)
    with open_frames(path) as (_, stream):
        read = list(stream)
    assert len(read) == 3
    for got, frame in zip(read, frames):
        if codec == "jpeg":  # lossy even at quality 100
            assert np.abs(got.astype(int) - frame).max() <= 8
        else:
            assert np.array_equal(got, frame)


def test_a_tiff_written_by_opencv_is_read(tmp_path):
    # cv2.imwrite compresses TIFFs with LZW by default: the case users met first
    import cv2

    frame = _frames(np.uint16, 1)[0]
    path = tmp_path / "camera.tif"
    assert cv2.imwrite(str(path), frame)
    with tifffile.TiffFile(path) as tif:
        assert tif.pages[0].compression == tifffile.COMPRESSION.LZW
    assert np.array_equal(read_image_grey(path), frame.astype(read_image_grey(path).dtype))


def test_correct_reads_and_writes_a_compressed_stack(run_cli, tmp_path):
    from oapcal.calibration import calibrate
    from oapcal.io.calibration import save_calibration
    from oapcal.synthetic import synthetic_pairs

    data = synthetic_pairs(seed=1)
    calib = tmp_path / "c.json"
    save_calibration(calibrate(data.xy_u, data.xy_d, "paper", image_size=(64, 48)), calib)
    stack = tmp_path / "in.tif"
    tifffile.imwrite(stack, np.stack(_frames(np.uint16)), photometric="minisblack", compression="zstd")
    code, _, err = run_cli("correct", calib, stack, "--out-dir", tmp_path / "out", "--quiet")
    assert code == 0, err
    out = tifffile.imread(tmp_path / "out" / "in.tif")
    assert out.shape == (3, 48, 64) and out.dtype == np.uint16
