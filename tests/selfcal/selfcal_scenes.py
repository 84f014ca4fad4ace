"""Seeded scenes for the self-calibration tests: a smooth random texture moved under a
camera, rendered through a known model by :func:`oapcal.imaging.render.render_scene`
(the truth of every pixel), small enough to keep the default suite fast."""

from __future__ import annotations

import cv2
import numpy as np

from oapcal.imaging.render import Camera, Placement, Scene, render_scene
from oapcal.model import params_from_dict

#: Object um per camera px (Eq. 1 scenes: the camera's pitch) and per texture px.
PIXEL_UM = 4.8
TEXTURE_UM = 2.4
SIZE = (200, 150)


def texture(seed: int = 0, shape=(700, 900)) -> np.ndarray:
    """A band-limited random texture (blobs of a few px to a few tens of px), 0..1."""
    rng = np.random.default_rng(seed)
    img = np.zeros(shape, np.float32)
    for sigma, amp in ((1.5, 0.5), (4.0, 1.0), (12.0, 1.0)):
        img += amp * cv2.GaussianBlur(rng.random(shape, dtype=np.float32), (0, 0), sigma) * sigma
    img -= img.min()
    return img / img.max()


def grid_moves(step=(50.0, 37.5)) -> np.ndarray:
    """A 3 x 3 grid of image moves (px), a quarter of the 200 x 150 frame apart."""
    return np.array([(i * step[0], j * step[1]) for j in (-1, 0, 1) for i in (-1, 0, 1)])


def truth_params(centre=(101.0, 73.0)) -> np.ndarray:
    """An Eq. (1) truth with ~3 px of radial and decentring distortion over the frame."""
    c = np.asarray(centre)
    return params_from_dict(
        {
            "k1": 2.0e-6,
            "p1": 4e-6,
            "s3": 2e-6,
            "x_off": -c[0],
            "y_off": -c[1],
            "c_x": c[0],
            "c_y": c[1],
            "m": 1.0,
        }
    )


def render_moves(params, moves_px, tex, *, snr=200.0, seed=0, size=SIZE) -> list[np.ndarray]:
    """Frames of ``tex`` moved so that its image moves by ``moves_px`` (reference px) each."""
    rows, cols = tex.shape
    centre = np.array([(cols - 1) / 2.0, (rows - 1) / 2.0])
    frames = []
    for i, move in enumerate(np.asarray(moves_px, float)):
        # the object under a reference point moves by -PIXEL_UM * move
        src = centre - np.asarray(move) * PIXEL_UM / TEXTURE_UM
        scene = Scene(params, Placement(TEXTURE_UM, tuple(src)), Camera(size=size, snr=snr, sigma_px=0.7))
        frames.append(render_scene(tex, scene, seed=seed * 100 + i).image)
    return frames


def frame_points(size=SIZE, step=5.0) -> np.ndarray:
    gx, gy = np.meshgrid(np.arange(0, size[0], step), np.arange(0, size[1], step))
    return np.stack([gx.ravel(), gy.ravel()], -1)


def affine_error(u, v) -> np.ndarray:
    """Distances after the best affine map of the points ``u`` onto ``v`` (least squares)."""
    a = np.hstack([u, np.ones((len(u), 1))])
    coef = np.linalg.lstsq(a, v, rcond=None)[0]
    return np.linalg.norm(a @ coef - v, axis=1)
