"""Automatic detection of USAF-1951 bar corners (``docs/detection.md``).

* :mod:`~oapcal.imaging.detect.bars`: bar triplets found bottom-up (any pose, scale, polarity);
* :mod:`~oapcal.imaging.detect.pose`: which triplet is which (similarity with mirror), with
  the checks against the one-element and two-group slips;
* :mod:`~oapcal.imaging.detect.triplet`: local refinement of each triplet's corners;
* :mod:`~oapcal.imaging.detect.registration`: warps, the bounded reference raster and fits;
* :mod:`~oapcal.imaging.detect.checks`: global consistency, scoring against a truth;
* :mod:`~oapcal.imaging.detect.core`: :func:`detect_usaf` that runs them.
"""

from oapcal.imaging.detect.checks import Consistency, check_consistency, evaluate_detection
from oapcal.imaging.detect.core import DROP_REASONS, Detection, detect_usaf, work_estimate

__all__ = [
    "DROP_REASONS",
    "Consistency",
    "Detection",
    "check_consistency",
    "detect_usaf",
    "evaluate_detection",
    "work_estimate",
]
