"""Self-calibration: a distortion model from images of one static, textured sample moved
by the stage, without a target (``docs/selfcal.md``).

:mod:`oapcal.selfcal.matches` finds which frames overlap and many sub-pixel matches
between them (OpenCV); :mod:`oapcal.selfcal.solve` fits the model and the frames' moves
to them, with the gauge stated.  Values in, values out: the frames are arrays, the result
holds a normal :class:`~oapcal.calibration.Calibration`.

>>> from oapcal.selfcal import find_matches, self_calibrate   # doctest: +SKIP
>>> result = self_calibrate(find_matches(frames), "relay", design=RelayDesign(setup=1))  # doctest: +SKIP
"""

from oapcal.selfcal.matches import Matches, Pair, SelfcalRefused, find_matches
from oapcal.selfcal.solve import SelfCalibration, gauge_report, parse_steps, self_calibrate

__all__ = [
    "Matches",
    "Pair",
    "SelfCalibration",
    "SelfcalRefused",
    "find_matches",
    "gauge_report",
    "parse_steps",
    "self_calibrate",
]
