"""Checks of the values a caller passes to the public API: points, images, seeds, counts and
memory estimates.  Each raises :class:`~oapcal.errors.DataError` naming the parameter (in
the message and in ``error.param``), what is wrong and what to do, so that a bad value never
surfaces as NumPy's, SciPy's or OpenCV's own exception.

>>> point_pairs([[0, 0], [1, float("nan")]], [[0, 0], [1, 1]])  # doctest: +ELLIPSIS
Traceback (most recent call last):
oapcal.errors.DataError: xy_u: point 1 is not finite (x = 1, y = nan); remove the point or fix ...
>>> seed(-1)
Traceback (most recent call last):
oapcal.errors.DataError: seed must be a whole number from 0 to 2**63 - 1, got -1
"""

from __future__ import annotations

import operator

import numpy as np

from oapcal.errors import DataError
from oapcal.records import ImageSize

#: Pixel types ``cv2.remap`` corrects (and the image readers accept).
IMAGE_DTYPES = ("uint8", "uint16", "int16", "float32", "float64")
#: Largest memory estimate of one library call's work (4 GiB), checked before the work.
MAX_WORK_BYTES = 4 * 2**30
#: Largest seed (NumPy's generators take any integer >= 0; files and options keep int64).
MAX_SEED = 2**63 - 1


def points(xy, name: str = "xy") -> np.ndarray:
    """``xy`` as a float ``(N, 2)`` array of finite x, y coordinates."""
    try:
        arr = np.asarray(xy, dtype=float)
    except (TypeError, ValueError) as exc:
        reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise DataError(
            f"{name} must be an (N, 2) array of x, y coordinates (numbers), not {type(xy).__name__} "
            f"({reason})",
            param=name,
        ) from None
    if arr.ndim != 2 or arr.shape[1] != 2:
        raise DataError(
            f"{name} must be an (N, 2) array of x, y coordinates, got shape {arr.shape}", param=name
        )
    bad = ~np.isfinite(arr).all(axis=1)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        more = f" and {int(bad.sum()) - 1} more" if bad.sum() > 1 else ""
        raise DataError(
            f"{name}: point {i} is not finite (x = {arr[i, 0]:g}, y = {arr[i, 1]:g}){more}; remove the "
            "point or fix its coordinates",
            param=name,
        )
    return arr


def point_pairs(xy_u, xy_d, names: tuple[str, str] = ("xy_u", "xy_d")) -> tuple[np.ndarray, np.ndarray]:
    """Reference and distorted points as float ``(N, 2)`` arrays of finite numbers, one
    distorted point for each reference point."""
    u = points(xy_u, names[0])
    d = points(xy_d, names[1])
    if len(u) != len(d):
        raise DataError(
            f"{names[0]} has {len(u)} points but {names[1]} has {len(d)}; give one distorted point for "
            "each reference point, in the same order",
            param=names,
        )
    return u, d


def image(img, name: str = "image") -> np.ndarray:
    """``img`` as an array :func:`cv2.remap` can correct: numbers of one of
    :data:`IMAGE_DTYPES`, at least ``(rows, cols)``, with pixels."""
    if isinstance(img, (str, bytes)) or img is None:
        raise DataError(
            f"{name} must be an array of pixels, not {type(img).__name__} (read an image file with "
            "oapcal.io.images.read_image first)",
            param=name,
        )
    try:
        arr = np.asarray(img)
    except (TypeError, ValueError) as exc:  # ragged nested lists
        raise DataError(
            f"{name} must be an array of pixels ({str(exc).splitlines()[0]})", param=name
        ) from None
    if arr.dtype.name not in IMAGE_DTYPES:
        raise DataError(
            f"{name} has pixel type {arr.dtype.name}; images of {', '.join(IMAGE_DTYPES)} are corrected "
            "(convert it, e.g. image.astype(numpy.float32))",
            param=name,
        )
    if arr.ndim < 2:
        raise DataError(
            f"{name} must be a (rows, cols) or (rows, cols, channels) array, got shape {arr.shape}",
            param=name,
        )
    if arr.shape[0] == 0 or arr.shape[1] == 0:
        raise DataError(f"{name} has no pixels (shape {arr.shape})", param=name)
    return arr


def whole_number(value, name: str, lo: int, hi: int | None = None) -> int:
    """``value`` as an int in ``lo .. hi`` (a bool, a float or a string is refused)."""
    if isinstance(value, (bool, np.bool_)):
        value = "bool"
    try:
        n = operator.index(value)
    except TypeError:
        raise DataError(f"{name} must be a whole number, got {value!r}", param=name) from None
    if n < lo or (hi is not None and n > hi):
        upper = f" to {hi:,}" if hi is not None else " or more"
        raise DataError(f"{name} must be a whole number from {lo:,}{upper}, got {n:,}", param=name)
    return n


def positive(value, name: str) -> float:
    """``value`` as a finite float above 0 (a bool or a string is refused)."""
    try:
        if isinstance(value, (bool, np.bool_, str, bytes)):
            raise TypeError
        x = float(value)
    except (TypeError, ValueError):
        raise DataError(f"{name} must be a positive number, got {value!r}", param=name) from None
    if not (np.isfinite(x) and x > 0):
        raise DataError(f"{name} must be a positive finite number, got {x:g}", param=name)
    return x


def image_size(value, name: str = "image_size") -> ImageSize:
    """An image size ``(width, height)`` in px: two whole numbers of at least 1, as an
    :class:`~oapcal.records.ImageSize`."""
    try:
        w, h = value
    except (TypeError, ValueError):
        raise DataError(f"{name} must be (width, height) in px, got {value!r}", param=name) from None
    return ImageSize(whole_number(w, f"{name} width", 1), whole_number(h, f"{name} height", 1))


def seed(value, name: str = "seed") -> int:
    """A random seed: a whole number from 0 to :data:`MAX_SEED`."""
    try:
        return whole_number(value, name, 0, MAX_SEED)
    except DataError:
        raise DataError(
            f"{name} must be a whole number from 0 to 2**63 - 1, got {value!r}", param=name
        ) from None


def memory(estimate_bytes: float, what: str, fix: str, param=None, limit: float = MAX_WORK_BYTES) -> None:
    """Refuse, before any work, a call whose memory estimate exceeds ``limit`` bytes: one
    line saying what it would need and what to change (``fix``)."""
    if not estimate_bytes <= limit:
        raise DataError(
            f"{what} would need about {_bytes(estimate_bytes)} of memory, over the {_bytes(limit)} "
            f"limit; {fix}",
            param=param,
        )


def _bytes(n: float) -> str:
    for unit, size in (("TiB", 2**40), ("GiB", 2**30), ("MiB", 2**20)):
        if n >= size:
            return f"{n / size:.3g} {unit}"
    return f"{n:.0f} B"
