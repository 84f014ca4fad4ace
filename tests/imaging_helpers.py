"""Shared builders for the image-correction tests: a calibration with known parameters and
maps computed independently of oapcal's fast grid code (through ``model.distort``)."""

import numpy as np

from oapcal.calibration import Calibration, FitSummary
from oapcal.io.calibration import save_calibration
from oapcal.model import PRESETS, distort
from oapcal.stats import ResidualStats
from oapcal.synthetic import EXAMPLE_TRUTH


def known_calibration(**changes) -> Calibration:
    """The built-in example truth as a calibration: 640x480 px camera, 4.8 um per px."""
    free = PRESETS["paper"]
    fields = dict(
        free=free,
        params=EXAMPLE_TRUTH.copy(),
        stderr=np.full(13, np.nan),
        covariance=np.zeros((len(free), len(free))),
        fit=FitSummary(n_points=252, rss=1.0, converged=True),
        residuals=ResidualStats(max_px=1.0, mean_px=0.5, rms_px=0.5, total_px=8.0, n_points=252),
        um_per_px=4.8,
        image_size=(640, 480),
        bounds=(40.0, 40.0, 600.0, 440.0),
        name="bench-setup-1",
    )
    fields.update(changes)
    return Calibration(**fields)


def write_calibration(path, **changes):
    save_calibration(known_calibration(**changes), path)
    return path


def reference_maps(params, shape, x0=0.0, y0=0.0, scale=1.0):
    """Maps from ``model.distort`` on the stacked grid of output pixels (the definition)."""
    rows, cols = shape
    gx, gy = np.meshgrid(x0 + scale * np.arange(cols), y0 + scale * np.arange(rows))
    src = distort(np.stack([gx, gy], -1), params)
    return src[..., 0].astype(np.float32), src[..., 1].astype(np.float32)


def remap_reference(image, params, interp_flag=1, **geometry):
    import cv2

    mx, my = reference_maps(params, image.shape[:2], **geometry)
    return cv2.remap(image, mx, my, interp_flag, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
