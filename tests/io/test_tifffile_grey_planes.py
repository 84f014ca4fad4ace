"""A stack of 3 or 4 frames written by tifffile without ``photometric`` is read as that many
grey frames (tifffile stores it as one page of RGB planes and reads it back as the stack),
while a colour image stays one colour frame."""

import warnings

import numpy as np
import pytest
import tifffile

from oapcal.io.images import open_frames, probe, read_tiff_frames


def _write(path, data, **kwargs):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)  # tifffile's note on its future default
        tifffile.imwrite(path, data, **kwargs)


@pytest.mark.parametrize("n", [3, 4])
@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.float32])
def test_a_3_or_4_frame_stack_is_read_as_frames(tmp_path, n, dtype):
    stack = (np.random.default_rng(n).random((n, 30, 40)) * 200).astype(dtype)
    _write(tmp_path / "s.tif", stack)
    with tifffile.TiffFile(tmp_path / "s.tif") as tif:  # how tifffile stored it: one RGB page
        assert len(tif.pages) == 1 and tif.pages[0].samplesperpixel == n
        np.testing.assert_array_equal(tif.asarray(), stack)  # and what it reads back
    info = probe(tmp_path / "s.tif")
    assert (info.n_frames, info.frame_shape, info.planar) == (n, (30, 40), False)
    with open_frames(tmp_path / "s.tif") as (_, frames):
        np.testing.assert_array_equal(np.stack(list(frames)), stack)
    np.testing.assert_array_equal(read_tiff_frames(info, 1, n), stack[1:])


def test_colour_images_stay_colour(tmp_path):
    rgb = np.random.default_rng(0).integers(0, 255, (30, 40, 3), dtype=np.uint8)
    _write(tmp_path / "rgb.tif", rgb)  # interleaved: tifffile's colour image
    info = probe(tmp_path / "rgb.tif")
    assert (info.n_frames, info.frame_shape) == (1, (30, 40, 3))
    # planar RGB written by another writer (no tifffile shape in the description): colour
    _write(tmp_path / "planar.tif", np.moveaxis(rgb, -1, 0), photometric="rgb", planarconfig="separate",
           metadata=None)  # fmt: skip
    info = probe(tmp_path / "planar.tif")
    assert (info.n_frames, info.frame_shape, info.planar) == (1, (30, 40, 3), True)
    with open_frames(tmp_path / "planar.tif") as (_, frames):
        np.testing.assert_array_equal(next(frames), rgb)
    # a 3-frame stack written as grey pages: 3 frames, as before
    _write(tmp_path / "grey.tif", np.moveaxis(rgb, -1, 0), photometric="minisblack")
    assert probe(tmp_path / "grey.tif").n_frames == 3
