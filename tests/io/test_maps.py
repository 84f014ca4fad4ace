"""Correction-map files (``oapcal correct --save-map`` / ``--map``): round trips and refusals."""

import zipfile

import numpy as np
import pytest

from imaging_helpers import known_calibration
from oapcal.errors import InputFileError
from oapcal.imaging.remap import correction_map
from oapcal.io.images import MAX_PIXELS
from oapcal.io.maps import load_map, save_map


@pytest.mark.parametrize("suffix", [".npz", ".npy", ".tiff"])
def test_map_files_round_trip(tmp_path, suffix):
    cmap = correction_map(known_calibration(), (48, 64), extent="full", allow_size_mismatch=True)
    save_map(cmap, tmp_path / f"m{suffix}")
    back = load_map(tmp_path / f"m{suffix}")
    np.testing.assert_array_equal(back.map_x, cmap.map_x)
    np.testing.assert_array_equal(back.map_y, cmap.map_y)
    if suffix == ".npz":
        assert back.geometry == cmap.geometry and back.input_shape == (48, 64)


def test_bad_map_files_are_refused_without_unpickling(tmp_path):
    np.save(tmp_path / "obj.npy", np.array([{"a": 1}], dtype=object), allow_pickle=True)
    with pytest.raises(InputFileError, match="obj.npy: cannot be read as a map"):
        load_map(tmp_path / "obj.npy")
    np.save(tmp_path / "shape.npy", np.zeros((3, 4, 5), np.float32))
    with pytest.raises(InputFileError, match=r"two float arrays .* got float32 \(3, 4, 5\)"):
        load_map(tmp_path / "shape.npy")
    with pytest.raises(InputFileError, match="must end in"):
        load_map(tmp_path / "m.csv")


def _npz_claiming(path, shape):
    """A small .npz whose two members' headers claim ``shape`` (float32) with no data."""
    header = {"descr": "<f4", "fortran_order": False, "shape": shape}
    with zipfile.ZipFile(path, "w") as zf:
        for name in ("map_x.npy", "map_y.npy"):
            with zf.open(name, "w") as fh:
                np.lib.format.write_array_header_1_0(fh, header)


def test_the_default_map_limit_is_16_times_the_default_image_limit(tmp_path):
    # 2**14 x 2**19 = 2**33 px: more than 16 x 2**28 = 2**32 px, refused from the header alone
    _npz_claiming(tmp_path / "big.npz", (2**14, 2**19))
    assert MAX_PIXELS == 2**28
    with pytest.raises(
        InputFileError, match=r"big.npz: the map is 524288x16384 px, more than the 4294967296 px"
    ):
        load_map(tmp_path / "big.npz")
    # with a larger per-frame limit the header passes, and the missing data are what is refused
    with pytest.raises(InputFileError, match="big.npz: cannot be read as a map"):
        load_map(tmp_path / "big.npz", max_pixels=2**30)


def test_an_unknown_map_suffix_is_refused_when_writing(tmp_path):
    # a 640x480 camera's map over a 10x8 image: another size, and it samples none of the image
    cmap = correction_map(known_calibration(), (8, 10), check=False, allow_size_mismatch=True)
    with pytest.raises(InputFileError, match="m.csv: a map file must end in .npz, .npy, .tif, .tiff"):
        save_map(cmap, tmp_path / "m.csv")
    assert list(tmp_path.iterdir()) == []
