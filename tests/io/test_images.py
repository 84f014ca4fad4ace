import json
import struct
import zlib

import cv2
import numpy as np
import pytest
import tifffile
from PIL import Image

from oapcal.errors import InputFileError, OutputError
from oapcal.io.atomic import safe_output_path
from oapcal.io.images import header_size, probe, read_image, write_image


@pytest.mark.parametrize("fmt,kw", [("png", {}), ("bmp", {}), ("jpeg", {}), ("jpeg", {"progressive": True})])
def test_header_size_agrees_with_pillow(tmp_path, fmt, kw):
    path = tmp_path / f"a.{fmt}"
    Image.fromarray(np.zeros((37, 53, 3), np.uint8)).save(path, **kw)
    with Image.open(path) as im:
        assert header_size(path) == im.size == (53, 37)


def _png_claiming(width, height) -> bytes:
    """A PNG whose header claims ``width x height`` but whose data is garbage."""
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    chunk = b"IHDR" + ihdr
    return (b"\x89PNG\r\n\x1a\n" + struct.pack(">I", 13) + chunk
            + struct.pack(">I", zlib.crc32(chunk)) + b"garbage")  # fmt: skip


def test_pixel_limit_is_checked_before_decoding(tmp_path):
    bomb = tmp_path / "bomb.png"
    bomb.write_bytes(_png_claiming(100_000, 100_000))
    # A decoder would fail on the garbage; the limit fires first, from the header alone.
    with pytest.raises(
        InputFileError, match=r"bomb.png: 100000x100000 = 10000000000 pixels.*raise max_pixels"
    ) as err:
        probe(bomb)
    assert err.value.param == "max_pixels"  # the command line names its option
    small = tmp_path / "small.tif"
    tifffile.imwrite(small, np.zeros((5, 20, 30), np.uint8))
    with pytest.raises(InputFileError, match="30x20 = 600 pixels per frame exceeds the limit of 599"):
        probe(small, max_pixels=599)
    assert probe(small, max_pixels=600).n_frames == 5


@pytest.mark.parametrize(
    "name,image",
    [
        ("g8.png", np.arange(12 * 10, dtype=np.uint8).reshape(12, 10)),
        ("c16.png", np.arange(12 * 10 * 3, dtype=np.uint16).reshape(12, 10, 3) * 50),
        ("g8.bmp", np.arange(12 * 10, dtype=np.uint8).reshape(12, 10)),
        ("f32.tif", np.linspace(-1, 1, 120, dtype=np.float32).reshape(12, 10)),
        ("rgb16.tiff", np.arange(360, dtype=np.uint16).reshape(12, 10, 3)),
    ],
)
def test_lossless_formats_round_trip_with_their_dtype(tmp_path, name, image):
    write_image(tmp_path / name, image)
    back = read_image(tmp_path / name)
    assert back.dtype == image.dtype
    np.testing.assert_array_equal(back, image)


def test_tiff_stack_and_metadata(tmp_path):
    stack = np.arange(4 * 6 * 5, dtype=np.uint16).reshape(4, 6, 5)
    write_image(tmp_path / "s.tif", stack, stack=True, calibration_name="setup-1", um_per_px=2.5)
    np.testing.assert_array_equal(read_image(tmp_path / "s.tif"), stack)
    with tifffile.TiffFile(tmp_path / "s.tif") as tif:
        meta = json.loads(tif.pages[0].description)
        assert meta["oapcal_calibration"] == "setup-1" and meta["um_per_px"] == 2.5
        num, den = tif.pages[0].tags["XResolution"].value
        assert num / den == pytest.approx(1e4 / 2.5)  # pixels per cm
        assert tif.pages[0].tags["ResolutionUnit"].value == 3  # centimetre


def test_bad_images_raise_one_clear_error(tmp_path):
    (tmp_path / "t.tif").write_bytes(b"II*\x00garbage")
    with pytest.raises(InputFileError, match="t.tif: cannot be read as a TIFF image"):
        read_image(tmp_path / "t.tif")
    png = tmp_path / "trunc.png"
    cv2.imwrite(str(png), np.full((40, 40), 7, np.uint8))
    png.write_bytes(png.read_bytes()[:60])
    with pytest.raises(InputFileError, match="trunc.png: cannot be decoded"):
        read_image(png)
    tifffile.imwrite(tmp_path / "i32.tif", np.zeros((4, 4), np.int32))
    with pytest.raises(InputFileError, match="pixel type int32 is not supported"):
        read_image(tmp_path / "i32.tif")
    (tmp_path / "a.gif").write_bytes(b"GIF89a")
    with pytest.raises(InputFileError, match="unsupported file type '.gif'"):
        probe(tmp_path / "a.gif")


def test_safe_output_path_refuses_escapes(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    assert safe_output_path(out, "a.tif") == out / "a.tif"
    (tmp_path / "elsewhere").mkdir()
    (out / "link").symlink_to(tmp_path / "elsewhere")
    (out / "b.tif").symlink_to(tmp_path / "elsewhere" / "b.tif")
    for name in ["../a.tif", "/etc/passwd", "sub/../../a.tif", "link/a.tif", "b.tif", ""]:
        with pytest.raises(OutputError, match="must stay inside the output directory"):
            safe_output_path(out, name)


@pytest.mark.parametrize("kind", ["probe", "read_image_grey", "load_map"])
def test_every_binary_input_is_checked_by_one_routine(tmp_path, kind):
    from oapcal.io.imagefile import read_image_grey
    from oapcal.io.maps import load_map

    read, what, good = {
        "probe": (probe, "an image file", "a.png"),
        "read_image_grey": (read_image_grey, "an image file", "a.png"),
        "load_map": (load_map, "a map file", "a.npz"),
    }[kind]
    kind_name = what.split(" ", 1)[1]
    (tmp_path / "d" / good).mkdir(parents=True)
    cases = [
        (tmp_path / "nope" / good, f"nope/{good}: no such {kind_name}; "),
        (tmp_path / "d" / good, f"d/{good}: is a directory, not {what}"),
        (tmp_path / "a.gif", f"a.gif: unsupported file type '.gif'; {what} must end in "),
    ]
    for path, message in cases:
        with pytest.raises(InputFileError) as err:
            read(path)
        assert message in str(err.value)
