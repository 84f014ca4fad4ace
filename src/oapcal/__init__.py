"""oapcal: calibrate and remove the distortion of off-axis parabolic mirror relays.

The public API is this top level; everything is loaded on first use, so ``import oapcal``
is cheap (it imports neither NumPy's heavy users nor Numba, Matplotlib or Dask).

>>> import oapcal
>>> from oapcal.synthetic import synthetic_pairs
>>> data = synthetic_pairs(seed=0)                      # (N, 2) reference and distorted px
>>> cal = oapcal.calibrate(data.xy_u, data.xy_d, model="paper")
>>> cal.fit.converged, bool(cal.residuals.mean_px < 1.0)
(True, True)

Layers (``docs/architecture.md``), imports flowing one way::

    errors <- model <- fitting <- select, calibration <- imaging, optics <- io <- batch <- report <- cli
"""

from __future__ import annotations

import importlib

__version__ = "0.1.0"

#: Public name -> ``module:attribute`` it is loaded from on first use.
_API: dict[str, str] = {
    # the model (Eq. 1) and its parameters
    "PARAM_NAMES": "oapcal.model:PARAM_NAMES",
    "PRESETS": "oapcal.model:PRESETS",
    "parse_model": "oapcal.model:parse_model",
    "distort": "oapcal.model:distort",
    "undistort": "oapcal.model:undistort",
    "Model": "oapcal.model:Model",
    "InverseResult": "oapcal.model:InverseResult",
    # fitting, calibration, model choice
    "fit": "oapcal.fitting:fit",
    "FitResult": "oapcal.fitting:FitResult",
    "BatchFit": "oapcal.fitting:BatchFit",
    "calibrate": "oapcal.entry:calibrate",
    "UnusableFitError": "oapcal.calibration:UnusableFitError",
    "correction_residuals": "oapcal.stats:correction_residuals",
    "ResidualStats": "oapcal.stats:ResidualStats",
    "select_models": "oapcal.select:select_models",
    "Selection": "oapcal.select:Selection",
    "ModelScore": "oapcal.select:ModelScore",
    "with_frame_terms": "oapcal.select:with_frame_terms",
    "cross_validate": "oapcal.select:cross_validate",
    "robustness": "oapcal.subsampling:robustness",
    "Robustness": "oapcal.subsampling:Robustness",
    "ModelRobustness": "oapcal.subsampling:ModelRobustness",
    # the calibration record and point files
    "Calibration": "oapcal.calibration:Calibration",
    "FitSummary": "oapcal.calibration:FitSummary",
    "load_calibration": "oapcal.io.calibration:load_calibration",
    "save_calibration": "oapcal.io.calibration:save_calibration",
    "PointPairs": "oapcal.io.points:PointPairs",
    "read_points": "oapcal.io.points:read_points",
    "write_point_pairs": "oapcal.io.points:write_point_pairs",
    # correcting images
    "correction_map": "oapcal.imaging.remap:correction_map",
    "CorrectionMap": "oapcal.imaging.remap:CorrectionMap",
    "correct_image": "oapcal.imaging.remap:correct_image",
    # the optics and the target
    "relay_distortion": "oapcal.optics.field:relay_distortion",
    "DistortionField": "oapcal.optics.field:DistortionField",
    # the physical relay as a model, and choosing across model families
    "RelayDesign": "oapcal.optics.relay_model:RelayDesign",
    "calibrate_relay": "oapcal.optics.relay_model:calibrate_relay",
    "select_families": "oapcal.families:select_families",
    "FamilySelection": "oapcal.families:FamilySelection",
    "usaf_target": "oapcal.imaging.usaf:usaf_target",
    "UsafTarget": "oapcal.imaging.usaf:UsafTarget",
    "simulate_image": "oapcal.imaging.simulate:simulate_image",
    "SimulatedImage": "oapcal.imaging.simulate:SimulatedImage",
    "detect_usaf": "oapcal.imaging.detect:detect_usaf",
    "Detection": "oapcal.imaging.detect:Detection",
    # calibration in place, without a target
    "find_matches": "oapcal.selfcal.matches:find_matches",
    "Matches": "oapcal.selfcal.matches:Matches",
    "self_calibrate": "oapcal.selfcal.solve:self_calibrate",
    "SelfCalibration": "oapcal.selfcal.solve:SelfCalibration",
    # errors
    "OapcalError": "oapcal.errors:OapcalError",
    "InputFileError": "oapcal.errors:InputFileError",
    "DataError": "oapcal.errors:DataError",
    "ModelSpecError": "oapcal.errors:ModelSpecError",
}

__all__ = ["__version__", *_API]


def __getattr__(name: str):
    try:
        target = _API[name]
    except KeyError:
        raise AttributeError(f"module 'oapcal' has no attribute {name!r}") from None
    module, _, attr = target.partition(":")
    value = getattr(importlib.import_module(module), attr)
    globals()[name] = value  # later look-ups skip __getattr__
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_API))
