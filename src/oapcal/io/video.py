"""Video files (AVI, MP4, MOV, MKV) through OpenCV's ``cv2.VideoCapture`` and
``cv2.VideoWriter`` (the FFmpeg backend of the OpenCV wheels), one frame at a time.

* **Reading**: frames come back as OpenCV decodes them, ``uint8`` colour in BGR order
  ``(rows, cols, 3)`` (a grey video too: OpenCV converts it); the size and frame count
  are read from the container before any frame is decoded, and the size is checked against
  the pixel limit.  AVI files carry an index, so their frame count is exact and a file
  that ends early is refused; MP4/MOV/MKV counts are the container's estimate, and what
  decodes is what is corrected.
* **Writing**: ``.avi`` and ``.mkv`` outputs are FFV1 (lossless: every value of every
  frame kept), ``.mp4`` and ``.mov`` are MPEG-4 Part 2 (``mp4v``, lossy: for viewing, not
  for measuring).  The frame rate is the input's.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np

from oapcal.errors import InputFileError, OutputError
from oapcal.records import ImageSize

VIDEO_SUFFIXES = (".avi", ".mp4", ".mov", ".mkv")
#: The codec each output container is written with (FourCC).
FOURCC = {".avi": "FFV1", ".mkv": "FFV1", ".mp4": "mp4v", ".mov": "mp4v"}
#: Containers whose frame count is exact (an index): a shorter decode is a truncated file.
EXACT_COUNT = (".avi",)
#: Frame rate written when the input's is unknown (0 or absurd).
DEFAULT_FPS = 25.0


def is_video_path(path: str | Path) -> bool:
    return Path(path).suffix.lower() in VIDEO_SUFFIXES


def _capture(path: Path):
    import cv2

    capture = cv2.VideoCapture(str(path), cv2.CAP_FFMPEG)
    if not capture.isOpened():
        capture.release()
        raise InputFileError(
            f"{path}: cannot be opened as a video (OpenCV's FFmpeg backend does not read it); the file "
            "may be corrupt, or convert it to AVI"
        )
    return capture


def video_header(path: str | Path) -> tuple[int, int, int, float]:
    """``(width, height, n_frames, fps)`` from the container, no frame decoded."""
    import cv2

    path = Path(path)
    capture = _capture(path)
    try:
        width = int(capture.get(cv2.CAP_PROP_FRAME_WIDTH))
        height = int(capture.get(cv2.CAP_PROP_FRAME_HEIGHT))
        n_frames = int(capture.get(cv2.CAP_PROP_FRAME_COUNT))
        fps = float(capture.get(cv2.CAP_PROP_FPS))
    finally:
        capture.release()
    if n_frames < 1:
        raise InputFileError(f"{path}: the video holds no frames (or its header does not say how many)")
    return width, height, n_frames, fps


def video_frames(path: str | Path, n_frames: int) -> Iterator[np.ndarray]:
    """The frames of a video one at a time (BGR uint8); an AVI that ends before its
    ``n_frames`` raises :class:`InputFileError`, as does a video of which no frame decodes."""
    path = Path(path)
    capture = _capture(path)
    n = 0
    try:
        while True:
            ok, frame = capture.read()
            if not ok:
                break
            n += 1
            yield frame
    finally:
        capture.release()
    if n == 0:
        raise InputFileError(f"{path}: no frame of the video can be decoded; the file may be corrupt")
    if n != n_frames and path.suffix.lower() in EXACT_COUNT:
        raise InputFileError(
            f"{path}: the file is truncated or corrupt: its index lists {n_frames} frames but only {n} "
            "can be decoded"
        )


def count_video_frames(path: str | Path) -> int:
    """Frames in a written video, from its container (0 if it cannot be opened)."""
    import cv2

    capture = cv2.VideoCapture(str(path), cv2.CAP_FFMPEG)
    try:
        return int(capture.get(cv2.CAP_PROP_FRAME_COUNT)) if capture.isOpened() else 0
    finally:
        capture.release()


class VideoWriter:
    """Frames appended to a video (the codec from :data:`FOURCC` by the suffix); the
    writer opens at the first frame, whose size and channels fix the video's.  Frames must
    be ``uint8`` grey or BGR(A) colour (alpha dropped)."""

    def __init__(self, path: str | Path, fps: float | None):
        self.path = Path(path)
        self.fps = fps if fps and 0 < fps <= 10_000 else DEFAULT_FPS
        self._writer = None
        self._colour = True

    def write(self, frame: np.ndarray) -> None:
        import cv2

        if frame.dtype != np.uint8:
            raise InputFileError(
                f"{self.path}: a video holds 8-bit frames, not {frame.dtype}; write {frame.dtype} frames to "
                "TIFF (or OME-TIFF, OME-Zarr) instead"
            )
        if frame.ndim == 3 and frame.shape[2] == 4:
            frame = np.ascontiguousarray(frame[..., :3])
        if frame.ndim == 3 and frame.shape[2] == 1:
            frame = frame[..., 0]
        if self._writer is None:
            self._colour = frame.ndim == 3
            fourcc = cv2.VideoWriter_fourcc(*FOURCC.get(self.path.suffix.lower(), "FFV1"))
            size = ImageSize.of(frame)
            path = str(self.path)
            self._writer = cv2.VideoWriter(path, cv2.CAP_FFMPEG, fourcc, self.fps, size, self._colour)
            if not self._writer.isOpened():
                raise OutputError(
                    f"{self.path}: OpenCV cannot write a {self.path.suffix} video of {size[0]}x{size[1]} px "
                    "here; choose an .avi output (FFV1) or TIFF"
                )
        if not self._colour and frame.ndim == 3:
            frame = cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)
        elif self._colour and frame.ndim == 2:
            frame = cv2.cvtColor(frame, cv2.COLOR_GRAY2BGR)
        self._writer.write(frame)

    def close(self) -> None:
        if self._writer is not None:
            self._writer.release()
            self._writer = None
