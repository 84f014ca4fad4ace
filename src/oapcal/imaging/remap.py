"""Correction maps: for each output (corrected) pixel, the source pixel in the distorted
image; applied with ``cv2.remap``.

With the paper's model the map needs no inversion: an output pixel at undistorted
coordinates ``(x_u, y_u)`` samples the distorted image at ``distort((x_u, y_u))``.
By default the output has the input's size and the calibration's undistorted coordinates
(output pixel ``(col, row)`` is the undistorted point ``(col, row)``).

>>> import numpy as np
>>> from oapcal.model import identity_params
>>> mx, my = correction_map(identity_params(), (3, 4))
>>> mx.shape, mx.dtype.name, float(mx[2, 3]), float(my[2, 3])
((3, 4), 'float32', 3.0, 2.0)
"""

from __future__ import annotations

import numpy as np

from oapcal.model import distort

INTERPOLATIONS = ("nearest", "linear", "cubic", "lanczos")


def _params_of(calibration_or_params) -> np.ndarray:
    params = getattr(calibration_or_params, "params", calibration_or_params)
    return np.asarray(params, dtype=float)


def correction_map(calibration_or_params, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """``(map_x, map_y)``, each ``float32 (rows, cols)``, for ``cv2.remap``.

    ``shape`` is the output image's ``(rows, cols)``; output pixel ``(col, row)`` is the
    undistorted point ``(x_u, y_u) = (col, row)`` and samples the distorted image at
    ``distort((col, row))``.
    """
    rows, cols = int(shape[0]), int(shape[1])
    params = _params_of(calibration_or_params)
    xs = np.arange(cols, dtype=float)
    out_x = np.empty((rows, cols), np.float32)
    out_y = np.empty((rows, cols), np.float32)
    # Row by row keeps the float64 temporaries small for large frames.
    block = max(1, 2_000_000 // max(cols, 1))
    for r0 in range(0, rows, block):
        r1 = min(rows, r0 + block)
        gx, gy = np.meshgrid(xs, np.arange(r0, r1, dtype=float))
        src = distort(np.stack([gx, gy], -1), params)
        out_x[r0:r1] = src[..., 0]
        out_y[r0:r1] = src[..., 1]
    return out_x, out_y


def correct_image(image: np.ndarray, maps, interp: str = "linear", border: float = 0) -> np.ndarray:
    """Correct one image (grey ``(rows, cols)`` or colour ``(rows, cols, ch)``) with a map
    from :func:`correction_map`; the output keeps the input's dtype."""
    import cv2

    flags = {
        "nearest": cv2.INTER_NEAREST,
        "linear": cv2.INTER_LINEAR,
        "cubic": cv2.INTER_CUBIC,
        "lanczos": cv2.INTER_LANCZOS4,
    }[interp]
    map_x, map_y = maps
    return cv2.remap(image, map_x, map_y, flags, borderMode=cv2.BORDER_CONSTANT, borderValue=border)
