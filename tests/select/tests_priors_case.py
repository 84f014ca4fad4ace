"""A seeded relay with few central landmarks (shared by the selection tests)."""

import numpy as np

from oapcal.model import distort
from oapcal.optics.relay_model import RelayDesign, relay_params


def few_central_case(seed=5, n=40, noise=0.3):
    design = RelayDesign(setup=1, centre=(319.5, 239.5))
    rng = np.random.default_rng(seed)
    mis = {"m2_tilt_x": 0.03, "m1_tilt_y": -0.04, "m2_decentre_y": 0.15, "d1": 20.0, "camera_tilt_x": 0.6,
           "camera_defocus": 0.12}  # fmt: skip
    truth = relay_params(design, mis, {"rotation": 0.4})
    lo, hi = np.array([215.0, 135.0]), np.array([424.0, 344.0])  # the 1 mm field
    mid, half = (lo + hi) / 2, 0.2 * (hi - lo)
    xy_u = rng.uniform(mid - half, mid + half, (n, 2))
    return design, xy_u, distort(xy_u, truth) + rng.normal(0, noise, (n, 2)), (*lo.tolist(), *hi.tolist())
