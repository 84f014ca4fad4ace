"""Synthetic point pairs from known parameters: the built-in example data and test data.

:data:`EXAMPLE_TRUTH` is a ``paper``-model distortion of a 640 x 480 px camera with up to
about 40 px of distortion, more in y than in x, like the paper's setup 1.

>>> data = synthetic_pairs(seed=1)
>>> data.xy_u.shape, 30 < data.max_distortion_px < 50
((252, 2), True)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from oapcal.model import as_model, params_from_dict

#: Known parameters of the example data (px units, ``paper`` model).
EXAMPLE_TRUTH = params_from_dict(
    {"k1": 4.0e-7, "p1": -3.5e-5, "s3": 3.0e-4, "x_off": -318.0, "y_off": -243.0,
     "c_x": 321.5, "c_y": 238.0, "m": 1.01}
)  # fmt: skip


@dataclass(frozen=True)
class SyntheticPairs:
    xy_u: np.ndarray
    xy_d: np.ndarray
    xy_d_true: np.ndarray
    params: np.ndarray
    noise_px: float

    @property
    def max_distortion_px(self) -> float:
        return float(np.hypot(*(self.xy_d_true - self.xy_u).T).max())


def synthetic_pairs(
    params: np.ndarray | None = None,
    *,
    n_x: int = 18,
    n_y: int = 14,
    size: tuple[int, int] = (640, 480),
    margin: float = 40.0,
    noise_px: float = 0.3,
    seed: int = 0,
) -> SyntheticPairs:
    """Reference points on a jittered ``n_x x n_y`` grid over an image of ``size`` (w, h)
    (minus ``margin``), distorted by ``params`` (default :data:`EXAMPLE_TRUTH`), plus
    Gaussian noise of ``noise_px`` per coordinate on the distorted points."""
    rng = np.random.default_rng(seed)
    model = as_model(EXAMPLE_TRUTH if params is None else np.asarray(params, float))
    w, h = size
    gx, gy = np.meshgrid(np.linspace(margin, w - margin, n_x), np.linspace(margin, h - margin, n_y))
    xy_u = np.stack([gx.ravel(), gy.ravel()], -1)
    xy_u = xy_u + rng.uniform(-3, 3, xy_u.shape)
    xy_d_true = model(xy_u)
    xy_d = xy_d_true + rng.normal(0.0, noise_px, xy_d_true.shape)
    return SyntheticPairs(xy_u, xy_d, xy_d_true, model.params, noise_px)
