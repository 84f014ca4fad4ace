"""Synthetic bar-and-square targets, blurred by a Gaussian point spread function.

A rectangle ``[a, b] x [c, d]`` (in px, edges anywhere, x = column, y = row) blurred by an
isotropic Gaussian PSF of standard deviation ``sigma`` has, at the point ``(x, y)``, the
exact intensity ``(Phi((x-a)/s) - Phi((x-b)/s)) (Phi((y-c)/s) - Phi((y-d)/s))`` with
``Phi`` the standard normal CDF.  Images are that function *sampled* at pixel centres, so
each straight edge's profile is exactly an error function of standard deviation
``sigma``: the ground truth for the edge-spread tests.

A distorted image is rendered by sampling the target at the undistorted position of every
camera pixel (``oapcal.model.undistort``), i.e. it is what the relay would show.

>>> img, rects = bar_target((40, 60), bars=[(10.5, 5.5, 20.5, 35.5)], sigma=1.0)
>>> img.shape, round(float(img[20, 15]), 3), round(float(img[20, 40]), 3)
((40, 60), 1.0, 0.0)
"""

from __future__ import annotations

import numpy as np
from scipy.special import ndtr

from oapcal.model import as_model


def rectangles_intensity(x, y, rects, sigma: float) -> np.ndarray:
    """Sum over rectangles ``(x0, y0, x1, y1)`` of their Gaussian-blurred indicator at ``(x, y)``."""
    x = np.asarray(x, float)
    y = np.asarray(y, float)
    shape = np.broadcast_shapes(x.shape, y.shape)
    x = np.broadcast_to(x, shape).ravel()
    y = np.broadcast_to(y, shape).ravel()
    out = np.zeros(x.shape)
    reach = 8.0 * sigma  # Phi(-8) ~ 6e-16: beyond this the rectangle contributes nothing
    for x0, y0, x1, y1 in rects:
        # Only points near the rectangle (speed: the erf is the costly part).
        near = np.flatnonzero((x > x0 - reach) & (x < x1 + reach) & (y > y0 - reach) & (y < y1 + reach))
        xs, ys = x[near], y[near]
        if sigma > 0:
            fx = ndtr((xs - x0) / sigma) - ndtr((xs - x1) / sigma)
            fy = ndtr((ys - y0) / sigma) - ndtr((ys - y1) / sigma)
        else:
            fx = ((xs >= x0) & (xs < x1)).astype(float)
            fy = ((ys >= y0) & (ys < y1)).astype(float)
        out[near] += fx * fy
    return out.reshape(shape)


def bar_target(
    shape: tuple[int, int],
    bars=None,
    *,
    sigma: float = 1.0,
    low: float = 0.0,
    high: float = 1.0,
    params: np.ndarray | None = None,
    noise: float = 0.0,
    seed: int = 0,
) -> tuple[np.ndarray, list[tuple[float, float, float, float]]]:
    """Render ``bars`` (rectangles ``(x0, y0, x1, y1)`` in undistorted px; default
    :func:`demo_layout`) into an image of ``shape = (rows, cols)``.

    With ``params`` (a Model, a calibration or a vector: :func:`oapcal.model.as_model`) the
    image is distorted by that model (each pixel shows the target at its
    undistorted position; pixels whose inverse fails show ``low``).  ``noise`` adds seeded
    Gaussian noise of that standard deviation.  Returns ``(image float64, rectangles)``.
    """
    rows, cols = int(shape[0]), int(shape[1])
    rects = demo_layout((rows, cols)) if bars is None else [tuple(map(float, r)) for r in bars]
    yy, xx = np.mgrid[0:rows, 0:cols].astype(float)
    if params is not None:
        inverse = as_model(params).inverse(np.stack([xx, yy], -1).reshape(-1, 2))
        xx = inverse.xy[:, 0].reshape(rows, cols)
        yy = inverse.xy[:, 1].reshape(rows, cols)
    value = rectangles_intensity(xx, yy, rects, sigma)
    image = low + (high - low) * np.nan_to_num(value, nan=0.0)
    if noise:
        image = image + np.random.default_rng(seed).normal(0.0, noise, image.shape)
    return image, rects


def demo_layout(shape: tuple[int, int], bar: float = 8.0) -> list[tuple[float, float, float, float]]:
    """A field of resolution-target-like elements: in each cell three vertical and three
    horizontal bars of 5:1 aspect ratio (width ``bar`` px, pitch ``2 bar``) and one square
    of side ``3 bar``; the cells tile the image with a margin.  Edges fall half-way between
    pixel centres."""
    rows, cols = int(shape[0]), int(shape[1])
    length = 5 * bar
    cell_w = 2 * (5 * bar) + 2 * bar  # the two bar groups side by side + a gap
    cell_h = length + 3 * bar + 2 * bar
    n_x = max(1, int((cols - 2 * bar) // cell_w))
    n_y = max(1, int((rows - 2 * bar) // cell_h))
    x_start = np.floor((cols - n_x * cell_w) / 2) + 0.5
    y_start = np.floor((rows - n_y * cell_h) / 2) + 0.5
    rects = []
    for j in range(n_y):
        for i in range(n_x):
            x0 = x_start + i * cell_w
            y0 = y_start + j * cell_h
            for b in range(3):  # vertical bars
                bx = x0 + 2 * b * bar
                rects.append((bx, y0, bx + bar, y0 + length))
            hx = x0 + 5 * bar + bar
            for b in range(3):  # horizontal bars
                by = y0 + 2 * b * bar
                rects.append((hx, by, hx + length, by + bar))
            sy = y0 + length + bar
            rects.append((x0, sy, x0 + 3 * bar, sy + 3 * bar))
    return rects
