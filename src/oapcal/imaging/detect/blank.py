"""Where an image shows nothing: blank areas, padding at one grey level.

An image turned, shifted or cropped onto a larger canvas has its padding at one grey level.
No bar can be seen there, so neither the pose search nor the registration expects a triplet
or a corner there (a single element turned by 30 degrees had its neighbours predicted in the
padding, counted missing, and was refused even when named).  An area is blank where every
pixel of a ``BLANK_WINDOW_PX`` square round it has the same value, and that value lies
strictly between the image's darkest and brightest: a real sensor's noise varies between
neighbours, and a constant area at the darkest or brightest level may be the target's own
background, clipped by the sensor or rendered without noise, where a missing triplet is
evidence against a pose (such areas are not blank).
"""

from __future__ import annotations

import numpy as np

#: Side (px) of the square that must be of one value for its centre to be blank.
BLANK_WINDOW_PX = 5


def blank_mask(image: np.ndarray) -> np.ndarray | None:
    """Pixels of ``image`` (2-D) in a blank area (module docstring; bool, the image's shape),
    or None when there are none (the usual case: nothing to check later)."""
    import cv2

    img = np.ascontiguousarray(image, dtype=np.float32)
    k = cv2.getStructuringElement(cv2.MORPH_RECT, (BLANK_WINDOW_PX, BLANK_WINDOW_PX))
    blank = (cv2.dilate(img, k) == cv2.erode(img, k)) & (img > img.min()) & (img < img.max())
    return blank if blank.any() else None


def blank_near(blank: np.ndarray | None, xy: np.ndarray, radius=0.0) -> np.ndarray:
    """Which points ``xy`` (..., 2) (px, pixel centres at whole numbers) lie in a blank area,
    at their place or at ``radius`` (scalar or ``xy.shape[:-1]``) px from it along x or y
    (a triplet's footprint); False everywhere when ``blank`` is None.  Points off the image
    are looked up at its nearest pixel."""
    xy = np.asarray(xy, float)
    if blank is None:
        return np.zeros(xy.shape[:-1], bool)
    h, w = blank.shape
    r = np.broadcast_to(np.asarray(radius, float), xy.shape[:-1])
    out = np.zeros(xy.shape[:-1], bool)
    for dx, dy in ((0, 0), (1, 0), (-1, 0), (0, 1), (0, -1)):
        x = np.nan_to_num(xy[..., 0] + dx * r, nan=-1.0)
        y = np.nan_to_num(xy[..., 1] + dy * r, nan=-1.0)
        col = np.clip(np.rint(x), 0, w - 1).astype(np.intp)
        row = np.clip(np.rint(y), 0, h - 1).astype(np.intp)
        out |= blank[row, col]
    return out
