"""Reading and writing single grey images (PNG, TIFF) for simulation and detection.

Outputs are written atomically (:func:`oapcal.io.atomic.atomic_path`); PNG through OpenCV
(8 or 16 bit), TIFF through tifffile.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from oapcal.errors import InputFileError, OutputError
from oapcal.io.atomic import atomic_path

IMAGE_SUFFIXES = (".png", ".tif", ".tiff")


def read_grey_image(path: str | Path) -> np.ndarray:
    """A 2-D array from a PNG, TIFF, JPEG or BMP file (colour is averaged to grey)."""
    p = Path(path)
    if not p.exists():
        raise InputFileError(f"{path}: no such file; check the path")
    if p.is_dir():
        raise InputFileError(f"{path}: is a directory, not an image")
    if p.suffix.lower() in (".tif", ".tiff"):
        import tifffile

        try:
            img = tifffile.imread(p)
        except Exception as exc:  # tifffile raises many types for bad files
            raise InputFileError(f"{path}: not a readable TIFF ({exc})") from None
    else:
        import cv2

        img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise InputFileError(f"{path}: not a readable image; give a PNG, TIFF, JPEG or BMP file")
    img = np.asarray(img)
    if img.ndim == 3 and img.shape[-1] in (3, 4):
        img = img[..., :3].mean(axis=-1)
    if img.ndim != 2:
        raise InputFileError(f"{path}: has shape {img.shape}; give a single grey or colour image")
    return img


def write_image(path: str | Path, image: np.ndarray) -> None:
    """Write an image as PNG or TIFF (chosen by the suffix), atomically."""
    p = Path(path)
    suffix = p.suffix.lower()
    if suffix not in IMAGE_SUFFIXES:
        raise OutputError(f"{path}: unknown image type {suffix or '(none)'}; use .png, .tif or .tiff")
    with atomic_path(p) as tmp:
        if suffix == ".png":
            import cv2

            if not cv2.imwrite(str(tmp), np.asarray(image)):
                raise OutputError(f"{path}: OpenCV could not write this image")
        else:
            import tifffile

            tifffile.imwrite(tmp, np.asarray(image))
