"""Reading and writing camera images: PNG, TIFF (single and multi-page), JPEG, BMP.

* The dtype is kept: 8-bit, 16-bit and float images come back as ``uint8``, ``uint16``,
  ``float32``/``float64`` (``int16`` too); grey images are ``(rows, cols)``, colour
  ``(rows, cols, ch)`` with 3 or 4 channels.  PNG/JPEG/BMP are decoded by OpenCV (colour
  in OpenCV's BGR order, and written back by OpenCV, so the order round-trips); TIFF by
  tifffile (RGB order, written back by tifffile).
* **Decompression bombs**: the image size is read from the file's header and checked
  against a pixel-count limit (per frame) *before* any pixel is decoded.
* Every problem with a file raises :class:`~oapcal.errors.InputFileError` naming the file.
* TIFF outputs carry metadata: the calibration's name and the pixel size (in the
  ``ImageDescription`` JSON and as the standard ``XResolution``/``YResolution`` tags in
  pixels per cm).
"""

from __future__ import annotations

import contextlib
import struct
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from oapcal.errors import InputFileError

TIFF_SUFFIXES = (".tif", ".tiff")
OPENCV_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp")
IMAGE_SUFFIXES = TIFF_SUFFIXES + OPENCV_SUFFIXES
#: Files that keep every value of an 8- or 16-bit grey image (no JPEG, no 8-bit-only BMP).
LOSSLESS_SUFFIXES = (".png",) + TIFF_SUFFIXES
#: dtypes that ``cv2.remap`` can correct.
DTYPES = ("uint8", "uint16", "int16", "float32", "float64")
#: Default per-frame pixel limit (``--max-pixels``): 2**28, e.g. 16384 x 16384.
MAX_PIXELS = 2**28


@dataclass(frozen=True)
class ImageInfo:
    """What the header says: ``n_frames`` frames of ``frame_shape`` ``(rows, cols[, ch])``."""

    path: Path
    kind: str  # "tiff" or "opencv"
    n_frames: int
    frame_shape: tuple[int, ...]
    dtype: np.dtype | None  # None until decoded for PNG/JPEG/BMP


def is_image_path(path: str | Path) -> bool:
    return Path(path).suffix.lower() in IMAGE_SUFFIXES


def _check_pixels(path: Path, width: int, height: int, max_pixels: int) -> None:
    if width <= 0 or height <= 0:
        raise InputFileError(f"{path}: the header gives an empty image ({width}x{height} px)")
    if width * height > max_pixels:
        raise InputFileError(
            f"{path}: {width}x{height} = {width * height} pixels per frame exceeds the limit of "
            f"{max_pixels} (a guard against decompression bombs); raise --max-pixels if the image is genuine"
        )


def header_size(path: str | Path) -> tuple[int, int]:
    """``(width, height)`` of a PNG, JPEG or BMP file from its header, without decoding.

    Written by hand because OpenCV has no header-only reader and Pillow applies its own
    global decompression-bomb limit; tested against Pillow's header parser.
    """
    path = Path(path)
    try:
        with open(path, "rb") as fh:
            head = fh.read(32)
            if head.startswith(b"\x89PNG\r\n\x1a\n") and head[12:16] == b"IHDR":
                return struct.unpack(">II", head[16:24])
            if head.startswith(b"BM") and len(head) >= 26:
                (dib,) = struct.unpack("<I", head[14:18])
                if dib == 12:
                    return struct.unpack("<HH", head[18:22])
                w, h = struct.unpack("<ii", head[18:26])
                return abs(w), abs(h)
            if head.startswith(b"\xff\xd8"):
                return _jpeg_size(fh)
    except OSError as exc:
        raise InputFileError(f"{path}: cannot be read ({exc.strerror})") from None
    except struct.error:
        pass
    raise InputFileError(
        f"{path}: not a valid {path.suffix.lstrip('.').upper() or 'image'} file (unrecognised or "
        "truncated header); the file may be corrupt"
    )


def _jpeg_size(fh) -> tuple[int, int]:
    """Walk the JPEG markers to the first start-of-frame (SOF0..SOF15 but DHT/JPG/DAC)."""
    fh.seek(2)
    while True:
        byte = fh.read(1)
        if not byte:
            raise struct.error("no SOF marker")
        if byte != b"\xff":
            continue
        marker = fh.read(1)
        while marker == b"\xff":
            marker = fh.read(1)
        if not marker:
            raise struct.error("truncated")
        code = marker[0]
        if code in (0x01, 0xD8) or 0xD0 <= code <= 0xD7:
            continue
        (length,) = struct.unpack(">H", fh.read(2))
        if 0xC0 <= code <= 0xCF and code not in (0xC4, 0xC8, 0xCC):
            _precision, height, width = struct.unpack(">BHH", fh.read(5))
            return width, height
        if code == 0xD9 or length < 2:
            raise struct.error("no SOF marker")
        fh.seek(length - 2, 1)


def _tiff_error(path: Path, exc: Exception) -> InputFileError:
    return InputFileError(f"{path}: cannot be read as a TIFF image ({type(exc).__name__}: {exc})")


def _tiff_layout(path: Path, series) -> tuple[int, tuple[int, ...]]:
    shape = tuple(int(v) for v in series.shape)
    axes = series.axes
    n_frame_axes = 3 if axes.endswith("S") else 2
    if len(shape) < 2 or (axes.endswith("S") and len(shape) < 3):
        raise InputFileError(f"{path}: TIFF series of shape {shape} is not an image")
    frame = shape[-n_frame_axes:]
    n_frames = int(np.prod(shape[:-n_frame_axes], dtype=np.int64)) if len(shape) > n_frame_axes else 1
    return n_frames, frame


def probe(path: str | Path, max_pixels: int = MAX_PIXELS) -> ImageInfo:
    """Read the header only: frame count, frame shape and (TIFF) dtype; checks the pixel limit."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in IMAGE_SUFFIXES:
        raise InputFileError(
            f"{path}: unsupported file type {suffix or '(no suffix)'!r}; oapcal reads "
            f"{', '.join(IMAGE_SUFFIXES)}"
        )
    if not path.is_file():
        raise InputFileError(f"{path}: no such image file")
    if suffix in TIFF_SUFFIXES:
        import tifffile

        try:
            with tifffile.TiffFile(path) as tif:
                if not tif.series:
                    raise InputFileError(
                        f"{path}: cannot be read as a TIFF image (no image found; the file may be corrupt)"
                    )
                series = tif.series[0]
                n_frames, frame = _tiff_layout(path, series)
                dtype = np.dtype(series.dtype)
        except InputFileError:
            raise
        except Exception as exc:  # tifffile raises TiffFileError, ValueError, struct.error, ...
            raise _tiff_error(path, exc) from None
        _check_pixels(path, frame[1], frame[0], max_pixels)
        return ImageInfo(path, "tiff", n_frames, frame, dtype)
    width, height = header_size(path)
    _check_pixels(path, width, height, max_pixels)
    return ImageInfo(path, "opencv", 1, (height, width), None)


def check_frame(path: Path, frame: np.ndarray) -> None:
    """Refuse frames ``cv2.remap`` cannot correct (dtype, channel count)."""
    if frame.dtype.name not in DTYPES:
        raise InputFileError(
            f"{path}: pixel type {frame.dtype.name} is not supported; oapcal corrects "
            f"{', '.join(DTYPES)} images (convert the file, e.g. to 16-bit or float32)"
        )
    if frame.ndim == 3 and frame.shape[2] not in (1, 3, 4) or frame.ndim not in (2, 3):
        raise InputFileError(
            f"{path}: frames of shape {frame.shape} are not supported; give grey (rows, cols) "
            "or colour (rows, cols, 3 or 4) images"
        )


@contextlib.contextmanager
def open_frames(path: str | Path, max_pixels: int = MAX_PIXELS) -> Iterator[tuple[ImageInfo, Iterator]]:
    """``with open_frames(p) as (info, frames):`` iterates the frames one at a time, so a long
    stack never sits in memory whole.  Raises :class:`InputFileError` for unreadable files,
    also while iterating."""
    info = probe(path, max_pixels)
    path = info.path
    if info.kind == "opencv":
        yield info, iter([_read_opencv(path)])
        return
    import tifffile

    try:
        tif = tifffile.TiffFile(path)
    except Exception as exc:
        raise _tiff_error(path, exc) from None
    try:
        yield info, _tiff_frames(path, tif, info)
    finally:
        tif.close()


def _tiff_frames(path: Path, tif, info: ImageInfo) -> Iterator[np.ndarray]:
    series = tif.series[0]
    per_page = len(series.pages) == info.n_frames and all(p is not None for p in series.pages[:1])
    try:
        if per_page:
            for i in range(info.n_frames):
                frame = series.pages[i].asarray()
                if frame.shape != info.frame_shape:
                    frame = frame.reshape(info.frame_shape)
                check_frame(path, frame)
                yield frame
        else:  # frames do not map to pages (e.g. a volume in one page): read the series
            data = series.asarray().reshape((info.n_frames, *info.frame_shape))
            for frame in data:
                check_frame(path, frame)
                yield frame
    except InputFileError:
        raise
    except Exception as exc:
        raise _tiff_error(path, exc) from None


def _read_opencv(path: Path) -> np.ndarray:
    import cv2

    data = np.fromfile(path, dtype=np.uint8)
    image = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
    if image is None:
        raise InputFileError(f"{path}: cannot be decoded as an image; the file may be corrupt or truncated")
    check_frame(path, image)
    return image


def read_image(path: str | Path, max_pixels: int = MAX_PIXELS) -> np.ndarray:
    """All frames of an image file: one frame ``(rows, cols[, ch])``, or a stack
    ``(frames, rows, cols[, ch])`` for a multi-page TIFF."""
    with open_frames(path, max_pixels) as (info, frames):
        data = list(frames)
    return data[0] if info.n_frames == 1 else np.stack(data)


def tiff_metadata(calibration_name: str | None, um_per_px: float | None) -> dict:
    """Keyword arguments for ``tifffile`` writes: JSON description and resolution tags."""
    meta = {
        "software": "oapcal",
        "metadata": {"oapcal_calibration": calibration_name, "um_per_px": um_per_px},
    }
    if um_per_px:
        meta["resolution"] = (1e4 / um_per_px, 1e4 / um_per_px)  # pixels per cm
        meta["resolutionunit"] = "CENTIMETER"
    return meta


class FrameWriter:
    """Write frames one by one to ``path`` (same format as the input); use as a context
    manager with an already-temporary path (:func:`oapcal.io.atomic.atomic_path`).

    TIFF frames are appended to one contiguous series (a multi-page stack) with the
    metadata of :func:`tiff_metadata`; PNG/JPEG/BMP take exactly one frame.
    """

    def __init__(self, path: Path, kind: str, calibration_name=None, um_per_px=None):
        self.path = Path(path)
        self.kind = kind
        self.n = 0
        self._meta = tiff_metadata(calibration_name, um_per_px)
        self._tw = None

    def __enter__(self):
        if self.kind == "tiff":
            import tifffile

            self._tw = tifffile.TiffWriter(self.path)
        return self

    def write(self, frame: np.ndarray) -> None:
        if self.kind == "tiff":
            photometric = "rgb" if frame.ndim == 3 and frame.shape[2] in (3, 4) else "minisblack"
            extra = self._meta if self.n == 0 else {}
            self._tw.write(frame, contiguous=True, photometric=photometric, **extra)
        else:
            if self.n:
                raise InputFileError(f"{self.path}: a {self.path.suffix} file holds one frame only")
            import cv2

            ok, buf = cv2.imencode(self.path.suffix, frame)
            if not ok:
                raise InputFileError(
                    f"{self.path}: OpenCV cannot encode a {frame.dtype} image as {self.path.suffix}"
                )
            buf.tofile(self.path)
        self.n += 1

    def __exit__(self, *exc):
        if self._tw is not None:
            self._tw.close()
        return False


def write_image(
    path: str | Path, image: np.ndarray, *, stack: bool = False, calibration_name=None, um_per_px=None
) -> None:
    """Write one frame, or with ``stack=True`` frames ``(frames, rows, cols[, ch])`` as a
    multi-page TIFF, atomically."""
    from oapcal.io.atomic import atomic_path

    path = Path(path)
    kind = "tiff" if path.suffix.lower() in TIFF_SUFFIXES else "opencv"
    if stack and kind != "tiff":
        raise InputFileError(f"{path}: only TIFF files hold a stack of frames")
    frames = image if stack else [image]
    with atomic_path(path) as tmp, FrameWriter(tmp, kind, calibration_name, um_per_px) as writer:
        for frame in frames:
            writer.write(frame)
