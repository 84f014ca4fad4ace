"""The fold-over check of a calibration evaluates Eq. (1) in closed form (NumPy) instead of
the compiled kernels (which a command would otherwise load before its first frame): the
same finiteness, determinants and verdicts as the kernels."""

import numpy as np
import pytest

from oapcal.calibration import CHECK_GRID, _eq1_region_check, _kernel_region_check, check_model_region
from oapcal.errors import InputFileError
from oapcal.model import PARAM_NAMES, params_from_dict
from oapcal.synthetic import EXAMPLE_TRUTH
from reference_model import random_eq1_models


def _grid(x1=639.0, y1=479.0):
    gx, gy = np.meshgrid(np.linspace(0, x1, CHECK_GRID), np.linspace(0, y1, CHECK_GRID))
    return np.stack([gx.ravel(), gy.ravel()], -1)


@pytest.mark.parametrize("rotation", [False, True], ids=["eq1", "eq1+rotation"])
def test_closed_form_matches_the_kernels(rotation):
    xy = _grid()
    folds = 0
    for p in random_eq1_models(300, 5 + rotation, rotation):
        finite_np, det_np = _eq1_region_check(xy, p)
        finite_k, det_k = _kernel_region_check(xy, p)
        np.testing.assert_array_equal(finite_np, finite_k)
        # rounding only: the kernels may contract and reassociate (fastmath) the same sums
        scale = np.abs(det_k).max()
        np.testing.assert_allclose(det_np, det_k, rtol=1e-9, atol=1e-12 * scale)
        # the verdict of every grid point (those within rounding of zero excepted)
        clear = np.abs(det_k) > 1e-9 * scale
        np.testing.assert_array_equal((det_np > 0)[clear], (det_k > 0)[clear])
        folds += bool((det_k <= 0).any())
    assert 30 < folds < 270  # the sample holds folding and regular models alike


def test_the_verdicts_and_messages_are_those_of_the_kernels(monkeypatch):
    """check_model_region gives the same result and message through either evaluation."""
    import oapcal.calibration as calibration

    cases = [params_from_dict({"k1": 1e-7}), params_from_dict({"k1": -1e-5}), EXAMPLE_TRUTH,
             np.append(EXAMPLE_TRUTH, 30.0), params_from_dict({"k1": np.inf}),
             params_from_dict({"s2": 3e-8, "m": 1.0}), *random_eq1_models(40, 9, False),
             *random_eq1_models(40, 10, True)]  # fmt: skip

    def verdict(p):
        try:
            check_model_region(p, (640, 480), source="c.json", boxes=[((-100, -50, 700, 500), "box")])
        except InputFileError as exc:
            return str(exc)
        return None

    closed = [verdict(p) for p in cases]
    monkeypatch.setattr(calibration, "_eq1_region_check", calibration._kernel_region_check)
    kernels = [verdict(p) for p in cases]
    assert closed == kernels
    assert sum(v is None for v in closed) > 5 and sum(v is not None for v in closed) > 5
    assert "is not finite" in closed[4] and "folds over" in closed[1]


def test_the_rotation_column_is_read():
    assert len(PARAM_NAMES) == 13
    xy = _grid()
    _, det0 = _eq1_region_check(xy, np.append(EXAMPLE_TRUTH, 0.0))
    _, det30 = _eq1_region_check(xy, np.append(EXAMPLE_TRUTH, 30.0))
    _, det_eq1 = _eq1_region_check(xy, EXAMPLE_TRUTH)
    np.testing.assert_array_equal(det0, det_eq1)
    assert not np.allclose(det30, det0)
