"""The public API: the names at the top level, what they are, and a cheap ``import oapcal``."""

import inspect

import pytest

import oapcal
from fresh_python import run_fresh

#: The curated top level. A change here is a change of the public API: update the
#: README and docs/architecture.md with it.
PUBLIC = {
    "__version__",
    "PARAM_NAMES",
    "PRESETS",
    "parse_model",
    "distort",
    "undistort",
    "fit",
    "FitResult",
    "calibrate",
    "correction_residuals",
    "select_models",
    "Selection",
    "cross_validate",
    "robustness",
    "Robustness",
    "Calibration",
    "load_calibration",
    "save_calibration",
    "PointPairs",
    "read_points",
    "write_point_pairs",
    "correction_map",
    "CorrectionMap",
    "correct_image",
    "relay_distortion",
    "RelayDesign",
    "calibrate_relay",
    "select_families",
    "usaf_target",
    "simulate_image",
    "detect_usaf",
    "find_matches",
    "self_calibrate",
    "OapcalError",
    "InputFileError",
    "DataError",
    "ModelSpecError",
    # the records the public functions return, and the error calibrate raises
    "Model",
    "InverseResult",
    "BatchFit",
    "UnusableFitError",
    "ResidualStats",
    "ModelScore",
    "with_frame_terms",
    "ModelRobustness",
    "FitSummary",
    "DistortionField",
    "FamilySelection",
    "UsafTarget",
    "SimulatedImage",
    "Detection",
    "Matches",
    "SelfCalibration",
}

#: Each public function and the public record it returns (the API exports what it returns).
RETURNS = {
    "undistort": "InverseResult",
    "fit": "FitResult",
    "calibrate": "Calibration",
    "correction_residuals": "ResidualStats",
    "select_models": "Selection",
    "robustness": "Robustness",
    "load_calibration": "Calibration",
    "read_points": "PointPairs",
    "correction_map": "CorrectionMap",
    "relay_distortion": "DistortionField",
    "select_families": "FamilySelection",
    "usaf_target": "UsafTarget",
    "simulate_image": "SimulatedImage",
    "detect_usaf": "Detection",
    "find_matches": "Matches",
    "self_calibrate": "SelfCalibration",
}


def test_all_is_pinned():
    assert set(oapcal.__all__) == PUBLIC
    assert len(oapcal.__all__) == len(set(oapcal.__all__))


@pytest.mark.parametrize("name", sorted(PUBLIC - {"__version__"}))
def test_each_name_resolves_and_is_documented(name):
    value = getattr(oapcal, name)
    if callable(value):
        assert inspect.getdoc(value), f"oapcal.{name} has no docstring"
    assert name in dir(oapcal)


def test_functions_are_not_shadowed_by_submodules():
    """``oapcal.calibrate`` stays the function after every submodule has been imported (a
    submodule of the same name would replace it on import)."""
    import pkgutil

    for info in pkgutil.walk_packages(oapcal.__path__, "oapcal."):
        if info.name.split(".")[1] not in {"cli", "__main__"}:
            __import__(info.name)
    shadowed = [n for n in PUBLIC - {"__version__"} if inspect.ismodule(getattr(oapcal, n))]
    assert shadowed == []
    assert inspect.isfunction(oapcal.fit) and oapcal.fit.__module__ == "oapcal.fitting"


def test_unknown_name_is_an_attribute_error():
    with pytest.raises(AttributeError, match="no attribute 'nonexistent'"):
        oapcal.nonexistent  # noqa: B018


def test_errors_are_value_errors():
    assert issubclass(oapcal.DataError, oapcal.OapcalError)
    assert issubclass(oapcal.OapcalError, ValueError)


def test_import_is_cheap():
    _, loaded = run_fresh("import oapcal")
    assert sorted(loaded & {"numba", "matplotlib", "dask", "cv2", "scipy"}) == []


def test_the_readme_example_runs(tmp_path):
    """The README's Python example, against the top level only."""
    import numpy as np

    from oapcal.synthetic import synthetic_pairs

    data = synthetic_pairs(seed=1)
    cal = oapcal.calibrate(data.xy_u, data.xy_d, model="paper", um_per_px=4.8, image_size=(640, 480))
    oapcal.save_calibration(cal, tmp_path / "calib.json")
    back = oapcal.load_calibration(tmp_path / "calib.json")
    np.testing.assert_allclose(back.params, cal.params)
    corrected = oapcal.undistort(data.xy_d, back.params)
    assert corrected.converged.all()
    assert np.abs(corrected.xy - data.xy_u).max() < 2.0  # the synthetic pairs' noise is 0.3 px


@pytest.mark.parametrize("function", sorted(RETURNS))
def test_functions_return_records_the_api_exports(function):
    """The annotated return type of each public function is a public name, and that name
    is the very class the module defines (not a copy or another class of the same name)."""
    annotation = inspect.signature(getattr(oapcal, function)).return_annotation
    name = annotation if isinstance(annotation, str) else annotation.__name__
    assert name == RETURNS[function]
    record = getattr(oapcal, name)
    assert inspect.isclass(record)
    module = inspect.getmodule(getattr(oapcal, function))
    assert getattr(module, name) is record


def test_records_carry_the_model():
    """The calibration and its fit carry their family by name and give their Model."""
    from oapcal.synthetic import synthetic_pairs

    data = synthetic_pairs(seed=2)
    cal = oapcal.calibrate(data.xy_u, data.xy_d, "paper", error_model=False)
    assert isinstance(cal.model, oapcal.Model) and isinstance(cal.fit, oapcal.FitSummary)
    assert cal.model.family is cal.family and cal.model.free == cal.free
    assert cal.model_family in ("brown-conrady", "brown-conrady+rotation")
    inverse = cal.model.inverse(data.xy_d)
    assert isinstance(inverse, oapcal.InverseResult) and inverse.converged.all()
