import math

import numpy as np

from oapcal.stats import information_criteria, residual_stats


def test_aicc_by_hand():
    rss, n, k_free = 12.5, 578, 8
    k = k_free + 1
    aic = n * math.log(rss / n) + 2 * k
    aicc = aic + 2 * k * (k + 1) / (n - k - 1)
    bic = n * math.log(rss / n) + k * math.log(n)
    ic = information_criteria(rss, n, k_free)
    assert math.isclose(ic.aic, aic, rel_tol=1e-14)
    assert math.isclose(ic.aicc, aicc, rel_tol=1e-14)
    assert math.isclose(ic.bic, bic, rel_tol=1e-14)


def test_aicc_undefined_without_degrees_of_freedom():
    ic = information_criteria([1.0, 1.0], 10, np.array([7, 8]))  # K = 8 -> n-K-1 = 1; K = 9 -> 0
    assert np.isfinite(ic.aicc[0]) and np.isnan(ic.aicc[1])


def test_table1_statistics_by_hand():
    ref = np.zeros((3, 2))
    corr = np.array([[3.0, 4.0], [0.0, 1.0], [np.nan, np.nan]])
    s = residual_stats(corr, ref, um_per_px=2.0)
    assert s.max_px == 5.0 and s.mean_px == 3.0
    assert math.isclose(s.rms_px, math.sqrt(13.0)) and math.isclose(s.total_px, math.sqrt(26.0))
    assert s.n_points == 2 and s.n_failed == 1
    d = s.to_dict()
    assert d["mean_um"] == 6.0 and d["total_um"] == 2 * math.sqrt(26.0)
    assert "max_um" not in residual_stats(corr, ref).to_dict()
