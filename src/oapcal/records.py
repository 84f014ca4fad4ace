"""Plain values from results: the one place where non-finite numbers become ``None`` and
NumPy scalars and arrays become Python numbers and lists (oapcal's JSON never holds NaN or
infinity, which are not valid JSON).

>>> import numpy as np
>>> json_safe({"a": np.float64(1.5), "b": [np.nan, np.int64(2)], "c": np.array([True])})
{'a': 1.5, 'b': [None, 2], 'c': [True]}
>>> finite_or_none(float("inf")) is None
True

An image's size is one type, :class:`ImageSize` ``(width, height)``; an array's shape is
``(rows, cols) = (height, width)``:

>>> size = ImageSize.of(np.zeros((480, 640)))
>>> size, size.shape, size == (640, 480)
(ImageSize(width=640, height=480), (480, 640), True)
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np


def finite_or_none(value) -> float | None:
    """``float(value)``, or None when it is None, NaN or infinite."""
    return float(value) if value is not None and math.isfinite(value) else None


def nan_if_none(value) -> float:
    """``float(value)``, or NaN when it is None (a JSON ``null`` read back as a number:
    what :func:`finite_or_none` wrote for a non-finite one)."""
    return math.nan if value is None else float(value)


def json_safe(value):
    """A JSON-ready copy: NumPy scalars and arrays to Python, non-finite floats to None."""
    if isinstance(value, dict):
        return {k: json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple, np.ndarray)):
        return [json_safe(v) for v in value]
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return finite_or_none(value)
    return value


class ImageSize(NamedTuple):
    """An image's size in px, ``(width, height)``: a tuple wherever one is expected (the
    ``image_size`` of calibrations, options and files), with :attr:`shape` the NumPy shape
    ``(rows, cols) = (height, width)`` and :meth:`of` the size of an array."""

    width: int
    height: int

    @property
    def shape(self) -> tuple[int, int]:
        """``(height, width)``: the ``(rows, cols)`` of an array of this size."""
        return (self.height, self.width)

    @classmethod
    def of(cls, array_or_shape) -> ImageSize:
        """The size of an array (or of a shape ``(rows, cols, ...)``): ``(shape[1], shape[0])``."""
        shape = getattr(array_or_shape, "shape", array_or_shape)
        return cls(int(shape[1]), int(shape[0]))

    def contains(self, xy, margin: float = 0.0) -> np.ndarray:
        """Which points ``xy`` ``(N, 2)`` (px, pixel centres at whole numbers) are finite and
        at least ``margin`` px inside the image: ``margin <= x <= width - 1 - margin``, and
        likewise ``y`` with the height.

        >>> ImageSize(640, 480).contains(np.array([[3.0, 3.0], [637.0, 2.0], [np.nan, 9.0]]), 3).tolist()
        [True, False, False]
        """
        xy = np.asarray(xy)
        with np.errstate(invalid="ignore"):
            return (
                np.isfinite(xy).all(axis=1)
                & (xy[:, 0] >= margin)
                & (xy[:, 0] <= self.width - 1 - margin)
                & (xy[:, 1] >= margin)
                & (xy[:, 1] <= self.height - 1 - margin)
            )
