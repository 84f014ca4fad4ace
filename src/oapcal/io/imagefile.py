"""Reading single images for analysis (edge spread, correction checks, reports).

Files are read by :mod:`oapcal.io.images` (the path checked by
:func:`~oapcal.io.userfile.check_input_file`, the pixel-count limit and the frame count
checked on the header before decoding: a multi-page TIFF is refused unread; errors naming
the file), TIFF through tifffile and everything else through OpenCV.  Colour
images are converted to grey (ITU-R BT.601 weights, as OpenCV does); the result is a
``float64 (rows, cols)`` array in the file's own intensity units.  Problems raise
:class:`~oapcal.errors.InputFileError` naming the file.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from oapcal.errors import InputFileError


def read_image_grey(path: str | Path) -> np.ndarray:
    """One grey image ``(rows, cols)`` as float64.

    >>> import tempfile, pathlib, cv2
    >>> p = pathlib.Path(tempfile.mkdtemp()) / "a.png"
    >>> _ = cv2.imwrite(str(p), np.full((8, 9), 7, np.uint8))
    >>> read_image_grey(p)[:2, :3]
    array([[7., 7., 7.],
           [7., 7., 7.]])
    """
    from oapcal.io.images import open_frames, probe

    name = str(path)
    p = Path(path)
    # The header first (the path, the pixel count, the frame count): a stack is refused before
    # any page is decoded, as 'oapcal correct' decides from the header.
    info = probe(p)
    if info.n_frames != 1:
        raise InputFileError(
            f"{name}: is a stack of {info.n_frames} frames (pages); give one grey or colour image, "
            "e.g. one page saved on its own"
        )
    with open_frames(p, info=info) as (_, frames):
        image = next(iter(frames))
    if image.ndim == 3 and image.shape[-1] in (3, 4) and p.suffix.lower() not in (".tif", ".tiff"):
        image = image[..., [2, 1, 0]]  # OpenCV decodes colour as BGR
    image = np.asarray(image)
    if image.ndim == 3 and image.shape[-1] in (3, 4):
        weights = np.array([0.299, 0.587, 0.114])
        image = image[..., :3] @ weights
    if image.ndim != 2:
        raise InputFileError(f"{name}: has shape {image.shape}; give one grey or colour image, not a stack")
    if min(image.shape) < 8:
        raise InputFileError(f"{name}: is only {image.shape[1]} x {image.shape[0]} px; too small to analyse")
    image = image.astype(np.float64)
    if not np.isfinite(image).all():
        raise InputFileError(f"{name}: contains NaN or infinite pixel values")
    return image
