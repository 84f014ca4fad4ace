"""Relay-model calibrations for the tests of the commands that use a calibration (export,
report, correct): fitted by oapcal's relay fit to points traced through a misaligned relay
(seeded), and written to a calibration file."""

import functools

import numpy as np

from oapcal.io.calibration import save_calibration
from oapcal.model import RELAY, distort
from oapcal.optics.relay_model import RelayDesign, calibrate_relay, relay_params

#: The misaligned relay the points are traced through, and the target's pose.
TRUE_MISALIGNMENT = {"m2_tilt_x": 0.03, "camera_tilt_y": 0.5}
TRUE_POSE = {"rotation": 0.3}
IMAGE_SIZE = (640, 480)
#: The subset fitted (named, so the tests do not depend on the default subset).
FREE = "tilt2,d1,camera"


@functools.cache
def relay_calibration(name: str = "relay-setup-1"):
    """A relay calibration (setup 1, 4.8 um px, 640x480 px; the pose, the second mirror's
    tip and tilt, d1 and the camera's tilts fitted) fitted to 300 traced points over the
    central part of the image with 0.05 px noise."""
    rng = np.random.default_rng(7)
    design = RelayDesign(setup=1, pixel_size_um=4.8, centre=(319.5, 239.5))
    truth = relay_params(design, TRUE_MISALIGNMENT, TRUE_POSE)
    xy_u = np.column_stack([rng.uniform(160, 480, 300), rng.uniform(120, 360, 300)])
    xy_d = distort(xy_u, truth, family=RELAY) + rng.normal(0, 0.05, (300, 2))
    return calibrate_relay(xy_u, xy_d, design, FREE, image_size=IMAGE_SIZE, name=name, source="traced.csv")


def write_relay_calibration(path):
    save_calibration(relay_calibration(), path)
    return path
