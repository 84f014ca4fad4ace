"""Reading and writing camera images: PNG, TIFF (single and multi-page), JPEG, BMP, video
(AVI, MP4, MOV, MKV: :mod:`oapcal.io.video`), and writing OME-TIFF and OME-Zarr
(:mod:`oapcal.io.ome`).

* The dtype is kept: 8-bit, 16-bit and float images come back as ``uint8``, ``uint16``,
  ``float32``/``float64`` (``int16`` too); grey images are ``(rows, cols)``, colour
  ``(rows, cols, ch)`` with 3 or 4 channels.  PNG/JPEG/BMP are decoded by OpenCV (colour
  in OpenCV's BGR order, and written back by OpenCV, so the order round-trips); TIFF by
  tifffile (RGB order, written back by tifffile).
* **Decompression bombs**: the image size is read from the file's header and checked
  against a pixel-count limit (per frame) *before* any pixel is decoded.
* Every problem with a file raises :class:`~oapcal.errors.InputFileError` naming the file.
* **One way in** for the files users give (:mod:`oapcal.io.userfile`): images and stacks
  pass its :func:`~oapcal.io.userfile.check_input_file` (suffix, there, a file) and its
  per-frame limit :data:`~oapcal.io.userfile.MAX_PIXELS`; maps (:mod:`oapcal.io.maps`)
  the same limit times the output's largest growth
  (:data:`oapcal.imaging.remap.MAX_GROWTH`) and :data:`~oapcal.io.userfile.MAX_UNPACK_RATIO`.
* TIFF outputs carry metadata: the calibration's name and the pixel size (in the
  ``ImageDescription`` JSON and as the standard ``XResolution``/``YResolution`` tags in
  pixels per cm); OME-TIFF and OME-Zarr outputs the pixel size and the calibration's
  provenance in their OME metadata.
* Frames stream: a video is decoded, and every output is written, one frame at a time.
* Colour order: OpenCV's files (PNG, JPEG, BMP, video) hold BGR frames, TIFF and zarr RGB;
  a :class:`FrameWriter` told the order of its frames (``bgr``) converts between them.
"""

from __future__ import annotations

import contextlib
import struct
from collections.abc import Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from oapcal.errors import InputFileError
from oapcal.io.ome import OME_ZARR_SUFFIX, is_ome_tiff_path
from oapcal.io.userfile import MAX_PIXELS, check_input_file
from oapcal.io.video import VIDEO_SUFFIXES
from oapcal.records import ImageSize
from oapcal.validate import IMAGE_DTYPES

TIFF_SUFFIXES = (".tif", ".tiff")
OPENCV_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp")
IMAGE_SUFFIXES = TIFF_SUFFIXES + OPENCV_SUFFIXES + VIDEO_SUFFIXES
#: The writers of :class:`FrameWriter`: the input's own formats and the OME outputs.
WRITER_KINDS = ("tiff", "opencv", "video", "ome-tiff", "ome-zarr")
#: Kinds whose colour frames are BGR (OpenCV's order); the others hold RGB.
BGR_KINDS = ("opencv", "video")
#: Files that keep every value of an 8- or 16-bit grey image (no JPEG, no 8-bit-only BMP).
LOSSLESS_SUFFIXES = (".png",) + TIFF_SUFFIXES
#: dtypes that ``cv2.remap`` can correct.
DTYPES = IMAGE_DTYPES
#: TIFF outputs with more pixel data than this are written as BigTIFF (as tifffile.imwrite
#: decides: 4 GiB less 32 MiB for the headers).
BIGTIFF_BYTES = 2**32 - 2**25


@dataclass(frozen=True)
class ImageInfo:
    """What the header says: ``n_frames`` frames of ``frame_shape`` ``(rows, cols[, ch])``.

    For TIFF files ``planar`` is True when colour samples are stored in separate planes
    (PlanarConfiguration 2; frames still come back as ``(rows, cols, ch)`` and are written
    back planar) and ``segments`` says where each frame is stored (see :func:`read_tiff_frames`).
    """

    path: Path
    kind: str  # "tiff", "opencv" or "video"
    n_frames: int
    frame_shape: tuple[int, ...]
    dtype: np.dtype | None  # None until decoded for PNG/JPEG/BMP
    planar: bool = False
    segments: tuple = field(default=(), repr=False, compare=False)
    fps: float | None = None  # videos: frames per second

    @property
    def frame_bytes(self) -> int:
        """Bytes of one frame (8 per value when the dtype is not known yet)."""
        itemsize = self.dtype.itemsize if self.dtype is not None else 8
        return int(np.prod(self.frame_shape, dtype=np.int64)) * itemsize


def is_image_path(path: str | Path) -> bool:
    return Path(path).suffix.lower() in IMAGE_SUFFIXES


def _check_pixels(path: Path, width: int, height: int, max_pixels: int) -> None:
    if width <= 0 or height <= 0:
        raise InputFileError(f"{path}: the header gives an empty image ({width}x{height} px)")
    if width * height > max_pixels:
        raise InputFileError(
            f"{path}: {width}x{height} = {width * height} pixels per frame exceeds the limit of "
            f"{max_pixels} (a guard against decompression bombs); raise max_pixels if the image is genuine",
            param="max_pixels",
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


def _page_frame(path: Path, page) -> tuple[tuple[int, ...], bool]:
    """The frame shape ``(rows, cols[, ch])`` one TIFF page holds, and whether it is planar."""
    shape = tuple(int(v) for v in page.shape)
    if getattr(page, "imagedepth", 1) > 1:
        raise InputFileError(
            f"{path}: page {page.index} is a volume ({page.imagedepth} planes in one page); oapcal "
            "corrects stacks of 2-D frames: save the volume one plane per page"
        )
    if page.samplesperpixel > 1 and page.planarconfig == 2 and len(shape) == 3:
        return (shape[1], shape[2], shape[0]), True
    if len(shape) not in (2, 3):
        raise InputFileError(f"{path}: page {page.index} of shape {shape} is not an image")
    return shape, False


def _imagej_single_ifd(path: Path, tif, n_pages: int):
    """An ImageJ hyperstack stored with one IFD (how ImageJ writes stacks over 4 GB): its
    frames as one contiguous block, or None for any other file."""
    if not tif.is_imagej:
        return None
    images = int((tif.imagej_metadata or {}).get("images", 1) or 1)
    if images <= n_pages:
        return None
    series = tif.series[0]
    page = series.pages[0]
    frame, planar = _page_frame(path, page)
    n_frames = int(np.prod(series.shape, dtype=np.int64)) // int(np.prod(page.shape, dtype=np.int64))
    if series.dataoffset is None or n_frames < 1:
        raise InputFileError(
            f"{path}: an ImageJ hyperstack of {images} images in one page that is not stored "
            "contiguously; save it again from ImageJ"
        )
    dtype = np.dtype(series.dtype)
    return n_frames, frame, dtype, planar, (("raw", int(series.dataoffset), n_frames),)


def _scan_tiff(path: Path, tif):
    """Frame count, frame shape, dtype, planarity and storage segments of a TIFF, from the
    page headers alone, in time linear in the page count (tifffile's ``series`` is quadratic
    in the number of series).  Every page is one frame; pages of different shapes or pixel
    types are refused."""
    n_pages = len(tif.pages)
    _check_ifd_chain(path, tif, n_pages)
    if n_pages == 0:
        raise InputFileError(
            f"{path}: cannot be read as a TIFF image (no image found; the file may be corrupt)"
        )
    single = _imagej_single_ifd(path, tif, n_pages)
    if single is not None:
        return single
    first = tif.pages[0]
    frame, planar = _page_frame(path, first)
    dtype = np.dtype(first.dtype)
    ifds = []
    contiguous = True
    next_offset = None
    for i in range(n_pages):
        page = tif.pages[i]
        if i:
            shape, page_planar = _page_frame(path, page)
            if shape != frame or np.dtype(page.dtype) != dtype or page_planar != planar:
                raise InputFileError(
                    f"{path}: its pages differ (page 0: {_describe(frame, dtype)}, page {i}: "
                    f"{_describe(shape, np.dtype(page.dtype))}); oapcal corrects a TIFF as one stack "
                    "of equal frames: save each kind of page to its own file"
                )
        ifds.append(int(page.offset))
        if contiguous:
            ok = page.is_contiguous and (next_offset is None or page.dataoffsets[0] == next_offset)
            contiguous = bool(ok)
            if contiguous:
                next_offset = int(page.dataoffsets[0]) + int(page.nbytes)
    if contiguous:
        segments = (("raw", int(first.dataoffsets[0]), n_pages),)
        if planar and _tifffile_grey_stack(tif, n_pages, frame):
            # the planes are the frames, stored one after the other
            return frame[2], frame[:2], dtype, False, (("raw", segments[0][1], frame[2]),)
    else:
        segments = (("pages", tuple(ifds)),)
    return n_pages, frame, dtype, planar, segments


def _tifffile_grey_stack(tif, n_pages: int, frame: tuple[int, ...]) -> bool:
    """Whether a one-page TIFF of 3 or 4 separate sample planes is a stack of grey frames:
    tifffile stores an array ``(3 or 4, rows, cols)`` written without ``photometric`` so
    (as RGB planes; its future default: separate grey pages), and records the array's shape
    in its description, ``{"shape": [3, rows, cols]}``, which is what it reads back.  A
    colour image from tifffile is ``(rows, cols, 3)`` (interleaved, not planar)."""
    if n_pages != 1 or not tif.is_shaped:
        return False
    shape = (tif.shaped_metadata or [{}])[0].get("shape")
    return list(shape or ()) == [frame[2], frame[0], frame[1]]


def _check_ifd_chain(path: Path, tif, n_pages: int) -> None:
    """Refuse a file whose chain of pages does not end after the last page read (tifffile
    stops quietly at a page offset past the end: a truncated stack would lose frames)."""
    if n_pages == 0:
        return
    tiff = tif.tiff
    fh = tif.filehandle
    offset = int(tif.pages[n_pages - 1].offset)
    fh.seek(offset)
    (tagno,) = struct.unpack(tiff.tagnoformat, fh.read(tiff.tagnosize))
    fh.seek(offset + tiff.tagnosize + tagno * tiff.tagsize)
    data = fh.read(tiff.offsetsize)
    following = struct.unpack(tiff.offsetformat, data)[0] if len(data) == tiff.offsetsize else -1
    if following != 0:
        raise InputFileError(
            f"{path}: the file is truncated or corrupt: only {n_pages} pages can be read and the "
            "next one is missing"
        )


def _describe(shape, dtype) -> str:
    dims = f"{shape[1]}x{shape[0]}" + (f"x{shape[2]}" if len(shape) == 3 else "")
    return f"{dims} {dtype.name}"


@contextlib.contextmanager
def quiet_tifffile():
    """Keep tifffile's log messages about broken files off the terminal: oapcal reports the
    problem itself, in one line naming the file."""
    import logging

    logger = logging.getLogger("tifffile")
    level = logger.level
    logger.setLevel(logging.CRITICAL)
    try:
        yield
    finally:
        logger.setLevel(level)


def probe(path: str | Path, max_pixels: int = MAX_PIXELS) -> ImageInfo:
    """Read the header only: frame count, frame shape and (TIFF) dtype; checks the pixel limit."""
    path = check_input_file(path, "image file", IMAGE_SUFFIXES)
    if path.suffix.lower() in TIFF_SUFFIXES:
        import tifffile

        try:
            with quiet_tifffile(), tifffile.TiffFile(path) as tif:
                n_frames, frame, dtype, planar, segments = _scan_tiff(path, tif)
        except InputFileError:
            raise
        except Exception as exc:  # tifffile raises TiffFileError, ValueError, struct.error, ...
            raise _tiff_error(path, exc) from None
        _check_pixels(path, frame[1], frame[0], max_pixels)
        return ImageInfo(path, "tiff", n_frames, frame, dtype, planar, segments)
    if path.suffix.lower() in VIDEO_SUFFIXES:
        from oapcal.io.video import video_header

        width, height, n_frames, fps = video_header(path)
        _check_pixels(path, width, height, max_pixels)
        return ImageInfo(path, "video", n_frames, (height, width, 3), np.dtype(np.uint8), fps=fps)
    size = ImageSize(*header_size(path))
    _check_pixels(path, size.width, size.height, max_pixels)
    return ImageInfo(path, "opencv", 1, size.shape, None)


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
def open_frames(
    path: str | Path, max_pixels: int = MAX_PIXELS, info: ImageInfo | None = None
) -> Iterator[tuple[ImageInfo, Iterator]]:
    """``with open_frames(p) as (info, frames):`` iterates the frames one at a time, so a long
    stack never sits in memory whole (every TIFF page in order, whatever its series;
    contiguous uncompressed data are memory-mapped).  Raises :class:`InputFileError` for
    unreadable files, also while iterating.  ``info`` is a :func:`probe` result to reuse."""
    info = info or probe(path, max_pixels)
    path = info.path
    if info.kind == "opencv":
        yield info, iter([_read_opencv(path)])
        return
    if info.kind == "video":
        from oapcal.io.video import video_frames

        yield info, video_frames(path, info.n_frames)
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


def _stored_shape(info: ImageInfo) -> tuple[int, ...]:
    f = info.frame_shape
    return (f[2], f[0], f[1]) if info.planar else f


def _as_frame(info: ImageInfo, stored: np.ndarray) -> np.ndarray:
    frame = stored.reshape(_stored_shape(info))
    if info.planar:
        frame = np.moveaxis(frame, 0, -1)
    return np.ascontiguousarray(frame, dtype=frame.dtype.newbyteorder("="))


def _segment_frames(path: Path, tif, info: ImageInfo, segment, start: int, stop: int) -> Iterator[np.ndarray]:
    """Frames ``start:stop`` of one storage segment."""
    import tifffile

    if segment[0] == "raw":
        offset, n = segment[1], segment[2]
        dtype = np.dtype(tif.byteorder + info.dtype.str[1:])
        shape = _stored_shape(info)
        frame_items = int(np.prod(shape, dtype=np.int64))
        if offset + n * frame_items * dtype.itemsize > path.stat().st_size:
            raise InputFileError(f"{path}: the file is truncated (its last frames are missing)")
        data = np.memmap(path, dtype=dtype, mode="r", offset=offset, shape=(n, *shape))
        try:
            for i in range(start, stop):
                yield _as_frame(info, data[i])
        finally:
            del data
        return
    fh = tif.filehandle
    for i in range(start, stop):
        fh.seek(segment[1][i])
        page = tifffile.TiffPage(tif, index=i)
        yield _as_frame(info, page.asarray())


def _segments_between(info: ImageInfo, start: int, stop: int):
    """``(segment, lo, hi)`` for the frames ``start:stop`` (frame numbers within segments)."""
    first = 0
    for segment in info.segments:
        n = segment[2] if segment[0] == "raw" else len(segment[1])
        lo, hi = max(start, first), min(stop, first + n)
        if lo < hi:
            yield segment, lo - first, hi - first
        first += n


def _tiff_frames(path: Path, tif, info: ImageInfo) -> Iterator[np.ndarray]:
    try:
        for segment, lo, hi in _segments_between(info, 0, info.n_frames):
            for frame in _segment_frames(path, tif, info, segment, lo, hi):
                check_frame(path, frame)
                yield frame
    except InputFileError:
        raise
    except Exception as exc:
        raise _tiff_error(path, exc) from None


def info_slice(info: ImageInfo, start: int, stop: int) -> ImageInfo:
    """``info`` for the frames ``start:stop`` alone (what one Dask task needs to read them)."""
    segments = []
    stored = int(np.prod(_stored_shape(info), dtype=np.int64)) * info.dtype.itemsize
    for segment, lo, hi in _segments_between(info, start, stop):
        if segment[0] == "raw":
            segments.append(("raw", segment[1] + lo * stored, hi - lo))
        else:
            segments.append(("pages", segment[1][lo:hi]))
    return replace(info, n_frames=stop - start, segments=tuple(segments))


def read_tiff_frames(info: ImageInfo, start: int, stop: int) -> np.ndarray:
    """Frames ``start:stop`` of the TIFF described by ``info`` (a :func:`probe` result) as
    one array ``(stop - start, rows, cols[, ch])``; opens the file by itself (for Dask
    workers)."""
    import tifffile

    path = info.path
    try:
        with tifffile.TiffFile(path) as tif:
            out = np.empty((stop - start, *info.frame_shape), info.dtype.newbyteorder("="))
            k = 0
            for segment, lo, hi in _segments_between(info, start, stop):
                for frame in _segment_frames(path, tif, info, segment, lo, hi):
                    out[k] = frame
                    k += 1
    except InputFileError:
        raise
    except Exception as exc:
        raise _tiff_error(path, exc) from None
    return out


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
    """Write frames one by one to ``path``; use as a context manager with an
    already-temporary path (:func:`oapcal.io.atomic.atomic_path`, or for ``ome-zarr``
    :func:`oapcal.io.atomic.atomic_dir`).

    ``kind`` is one of :data:`WRITER_KINDS`. TIFF frames are appended to one contiguous
    series (a multi-page stack) with the metadata of :func:`tiff_metadata`, colour samples
    interleaved or, with ``planar``, in separate planes (as the input had them); the file is
    a BigTIFF when ``expected_bytes`` (the pixel data to be written) could pass the 4 GiB
    limit of classic TIFF.  PNG/JPEG/BMP take exactly one frame; videos any number
    (:class:`oapcal.io.video.VideoWriter`, at ``fps``).  ``ome-tiff`` and ``ome-zarr``
    (:mod:`oapcal.io.ome`) need ``n_frames``, the number of frames that will be written,
    and record ``source`` (the input) and ``calibration`` (the record) in their provenance
    (:func:`oapcal.io.ome.provenance`).  ``bgr`` says the frames'
    colour order (True: BGR, as OpenCV decodes; False: RGB, as tifffile does; None: the
    writer's own), so that a video corrected into a TIFF keeps its colours.
    """

    # 12 parameters: the output's format and the metadata every kind records, keywords that
    # batch.stack, batch.distributed and the napari plugin pass by name (one per property of
    # the output; a record of them would only be unpacked here again).
    def __init__(
        self, path: Path, kind: str, calibration_name=None, um_per_px=None, *, planar=False, expected_bytes=0,
        n_frames=None, source=None, fps=None, bgr=None, calibration=None,
    ):  # fmt: skip
        if kind not in WRITER_KINDS:
            kinds = ", ".join(WRITER_KINDS)
            raise InputFileError(f"{path}: unknown output kind {kind!r}; use one of {kinds}")
        if kind in ("ome-tiff", "ome-zarr") and n_frames is None:
            raise InputFileError(f"{path}: an {kind} output needs the number of frames before the first")
        self.path = Path(path)
        self.kind = kind
        self.n = 0
        self.planar = planar
        self.bigtiff = expected_bytes > BIGTIFF_BYTES
        self.calibration_name = calibration_name
        self.um_per_px = um_per_px
        self.n_frames = n_frames
        self.source = source
        self.calibration = calibration
        self._swap = bgr is not None and bgr != (kind in BGR_KINDS)
        self._meta = tiff_metadata(calibration_name, um_per_px)
        self._tw = None
        self._other = None
        self._fps = fps

    def _description(self) -> dict:
        from oapcal.io.ome import provenance

        return provenance(self.calibration_name, self.um_per_px, self.source, self.calibration)

    def __enter__(self):
        if self.kind in ("tiff", "ome-tiff"):
            import tifffile

            self._tw = tifffile.TiffWriter(self.path, bigtiff=self.bigtiff)
        elif self.kind == "video":
            from oapcal.io.video import VideoWriter

            self._other = VideoWriter(self.path, self._fps)
        elif self.kind == "ome-zarr":
            from oapcal.io.ome import OmeZarrWriter

            name = "oapcal" if self.source is None else Path(self.source).name
            self._other = OmeZarrWriter(self.path, self.n_frames, self.um_per_px, self._description(), name)
        return self

    def write(self, frame: np.ndarray) -> None:
        colour = frame.ndim == 3 and frame.shape[2] in (3, 4)
        if self._swap and colour:
            frame = frame[..., [2, 1, 0, 3][: frame.shape[2]]]
        if self.kind == "tiff":
            photometric = "rgb" if colour else "minisblack"
            extra = dict(self._meta) if self.n == 0 else {}
            if self.planar and colour:
                frame = np.moveaxis(frame, -1, 0)
                extra["planarconfig"] = "separate"
            self._tw.write(frame, contiguous=True, photometric=photometric, **extra)
        elif self.kind == "ome-tiff":
            extra = {}
            if self.n == 0:
                from oapcal.io.ome import ome_xml

                name = Path(self.source).name if self.source is not None else self.path.name
                xml = ome_xml(
                    self.n_frames, frame.shape, frame.dtype, self.um_per_px, self._description(), name
                )
                extra = {k: v for k, v in self._meta.items() if k != "metadata"}
                extra.update(description=xml, metadata=None)
            self._tw.write(frame, contiguous=True, photometric="rgb" if colour else "minisblack", **extra)
        elif self._other is not None:
            self._other.write(frame)
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
        if self._other is not None and hasattr(self._other, "close"):
            self._other.close()
        return False


def output_kind(path: str | Path) -> str:
    """The :class:`FrameWriter` kind for an output path, from its name.

    >>> [output_kind(p) for p in ("a.tif", "a.ome.tif", "a.png", "a.avi", "a.ome.zarr")]
    ['tiff', 'ome-tiff', 'opencv', 'video', 'ome-zarr']
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if path.name.lower().endswith(OME_ZARR_SUFFIX):
        return "ome-zarr"
    if is_ome_tiff_path(path):
        return "ome-tiff"
    if suffix in TIFF_SUFFIXES:
        return "tiff"
    if suffix in VIDEO_SUFFIXES:
        return "video"
    return "opencv"


def count_frames(path: str | Path) -> int:
    """Frames in a written output (pages of a TIFF, a video's frame count, the frames of an
    OME-Zarr; 1 for other images), from the headers."""
    path = Path(path)
    if path.is_dir():
        from oapcal.io.ome import ome_zarr_frames

        return ome_zarr_frames(path)
    if path.suffix.lower() in VIDEO_SUFFIXES:
        from oapcal.io.video import count_video_frames

        return count_video_frames(path)
    if path.suffix.lower() not in TIFF_SUFFIXES:
        return 1
    import tifffile

    with tifffile.TiffFile(path) as tif:
        return len(tif.pages)


def write_image(
    path: str | Path, image: np.ndarray, *, stack: bool = False, calibration_name=None, um_per_px=None,
    fps: float | None = None, bgr: bool | None = None,
) -> None:  # fmt: skip
    """Write one frame, or with ``stack=True`` frames ``(frames, rows, cols[, ch])`` as a
    multi-page TIFF, an OME-TIFF (``.ome.tif``), a video (``.avi`` ...) or an OME-Zarr
    (``.ome.zarr``), atomically; the kind comes from the name (:func:`output_kind`)."""
    from oapcal.io.atomic import atomic_dir, atomic_path

    path = Path(path)
    kind = output_kind(path)
    if stack and kind == "opencv":
        raise InputFileError(f"{path}: a {path.suffix} file holds one frame; write a stack to TIFF or video")
    frames = image if stack else [image]
    size = int(np.asarray(image).nbytes)
    temporary = atomic_dir(path) if kind == "ome-zarr" else atomic_path(path)
    with (
        temporary as tmp,
        FrameWriter(tmp, kind, calibration_name, um_per_px, expected_bytes=size, n_frames=len(frames),
                    source=path.name, fps=fps, bgr=bgr) as writer,
    ):  # fmt: skip
        for frame in frames:
            writer.write(frame)
