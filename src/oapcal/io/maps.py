"""Correction-map files: the two float32 arrays of a
:class:`~oapcal.imaging.remap.CorrectionMap` and its output geometry, written atomically
(``oapcal correct --save-map``) and read back (``--map``) without unpickling anything.

Formats, by suffix: ``.npz`` (``map_x``, ``map_y``, the geometry and the input shape),
``.npy`` (a ``(2, rows, cols) float32`` array: x then y) or ``.tif``/``.tiff`` (the same
array as two float32 pages).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from oapcal.errors import InputFileError
from oapcal.imaging.remap import MAX_GROWTH, CorrectionMap, OutputGeometry
from oapcal.io.atomic import atomic_path, atomic_write
from oapcal.io.images import read_image
from oapcal.io.userfile import MAX_PIXELS, MAX_UNPACK_RATIO, check_input_file

MAP_SUFFIXES = (".npz", ".npy", ".tif", ".tiff")


def save_map(cmap: CorrectionMap, path: str | Path) -> None:
    """Write a map atomically: ``.npz`` (``map_x``, ``map_y`` and the geometry), ``.npy``
    (a ``(2, rows, cols) float32`` array: x then y) or ``.tif``/``.tiff`` (the same array as
    two float32 pages)."""
    path = Path(path)
    suffix = path.suffix.lower()
    both = np.stack([cmap.map_x, cmap.map_y])
    if suffix == ".npz":
        g = cmap.geometry
        extra = {
            "geometry": np.array([g.x0, g.y0, g.scale, np.nan if g.um_per_px is None else g.um_per_px]),
            "input_shape": np.array(cmap.input_shape if cmap.input_shape else (-1, -1), np.int64),
        }
        with atomic_write(path, "wb") as fh:
            np.savez(fh, map_x=cmap.map_x, map_y=cmap.map_y, **extra)
    elif suffix == ".npy":
        with atomic_write(path, "wb") as fh:
            np.save(fh, both, allow_pickle=False)
    elif suffix in (".tif", ".tiff"):
        import tifffile

        with atomic_path(path) as tmp:
            tifffile.imwrite(tmp, both)
    else:
        raise InputFileError(f"{path}: a map file must end in {', '.join(MAP_SUFFIXES)}")


def _check_map_header(path: Path, shape, dtype, stored: int, unpacked: int, max_pixels: int) -> None:
    """Refuse a map from its header alone, before anything is decompressed."""
    limit = MAX_GROWTH * max_pixels
    pixels = int(np.prod(shape[-2:], dtype=np.int64)) if len(shape) >= 2 else 0
    if pixels > limit:
        raise InputFileError(
            f"{path}: the map is {shape[-1]}x{shape[-2]} px, more than the {limit} px a map for the "
            "largest image (max_pixels) can have; the file is not a map oapcal wrote"
        )
    if unpacked > 64 * 2**20 and unpacked > MAX_UNPACK_RATIO * max(
        stored, 1
    ):  # oapcal writes them uncompressed
        raise InputFileError(
            f"{path}: {stored} bytes that unpack to {unpacked} (a decompression bomb?); "
            "write the map again with save_map"
        )
    if np.dtype(dtype).kind != "f":
        raise InputFileError(f"{path}: a map must hold float arrays, got {np.dtype(dtype)}")


def _npz_headers(path: Path, max_pixels: int) -> None:
    import zipfile

    with zipfile.ZipFile(path) as zf:
        for info in zf.infolist():
            if info.filename not in ("map_x.npy", "map_y.npy"):
                if info.file_size > 2**20:
                    raise InputFileError(f"{path}: unexpected large member {info.filename!r} in a map file")
                continue
            with zf.open(info) as fh:
                version = np.lib.format.read_magic(fh)
                if version == (1, 0):
                    shape, _, dtype = np.lib.format.read_array_header_1_0(fh)
                else:
                    shape, _, dtype = np.lib.format.read_array_header_2_0(fh)
            _check_map_header(path, shape, dtype, info.compress_size, info.file_size, max_pixels)


def _tiff_map_headers(path: Path, max_pixels: int) -> None:
    import tifffile

    with tifffile.TiffFile(path) as tif:
        if len(tif.pages) > 2:
            raise InputFileError(f"{path}: a map TIFF holds two pages (x, y), this one {len(tif.pages)}")
        for page in tif.pages:
            stored = int(sum(page.databytecounts))
            _check_map_header(path, page.shape, page.dtype, stored, int(page.nbytes), max_pixels)


def load_map(path: str | Path, max_pixels: int | None = None) -> CorrectionMap:
    """Read a map written by :func:`save_map` (never unpickles anything).

    The header is checked before any data are read: a map larger than one for the largest
    image (``max_pixels`` per input frame, default :data:`oapcal.io.userfile.MAX_PIXELS`, times
    :data:`~oapcal.imaging.remap.MAX_GROWTH`) or one
    that decompresses to far more than it stores is refused.
    """
    path = check_input_file(path, "map file", MAP_SUFFIXES, missing="write one with save_map")
    suffix = path.suffix.lower()
    max_pixels = max_pixels or MAX_PIXELS
    geometry_vals = None
    input_shape = None
    try:
        if suffix == ".npz":
            _npz_headers(path, max_pixels)
            with np.load(path, allow_pickle=False) as data:
                if "map_x" not in data or "map_y" not in data:
                    raise InputFileError(f"{path}: a map .npz needs arrays 'map_x' and 'map_y'")
                both = np.stack([data["map_x"], data["map_y"]])
                if "geometry" in data:
                    geometry_vals = np.asarray(data["geometry"], float)
                if "input_shape" in data and int(data["input_shape"][0]) > 0:
                    input_shape = tuple(int(v) for v in data["input_shape"])
        elif suffix == ".npy":
            both = np.load(path, allow_pickle=False, mmap_mode="r")
            _check_map_header(path, both.shape, both.dtype, both.nbytes, both.nbytes, max_pixels)
            both = np.array(both)
        else:  # decoded by the image reader, which checks the TIFF structure and the pixel count
            _tiff_map_headers(path, max_pixels)
            both = read_image(path, MAX_GROWTH * max_pixels)
    except InputFileError:
        raise
    except (OSError, ValueError, KeyError) as exc:
        raise InputFileError(f"{path}: cannot be read as a map ({exc})") from None
    except Exception as exc:  # tifffile raises its own TiffFileError (a ValueError subclass in new versions)
        raise InputFileError(f"{path}: cannot be read as a map ({type(exc).__name__}: {exc})") from None
    if both.ndim != 3 or both.shape[0] != 2 or both.dtype.kind != "f":
        raise InputFileError(
            f"{path}: a map must hold two float arrays of the same (rows, cols) shape, "
            f"got {both.dtype} {both.shape}"
        )
    if both.shape[1] == 0 or both.shape[2] == 0:
        raise InputFileError(
            f"{path}: the map is {both.shape[2]} x {both.shape[1]} px: it has no pixels; write it again "
            "with save_map"
        )
    if not np.isfinite(both).all():
        raise InputFileError(f"{path}: the map holds NaN or inf values")
    rows, cols = both.shape[1:]
    if geometry_vals is not None and geometry_vals.shape == (4,):
        um = None if not np.isfinite(geometry_vals[3]) else float(geometry_vals[3])
        geometry = OutputGeometry((rows, cols), *(float(v) for v in geometry_vals[:3]), um)
    else:
        geometry = OutputGeometry((rows, cols), math.nan, math.nan, math.nan, None)
    both = both.astype(np.float32, copy=False)
    return CorrectionMap(both[0], both[1], geometry, input_shape)
