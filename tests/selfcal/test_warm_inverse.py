"""The solve's warm-started inverse never decides the result: where the inverse started from
the previous evaluation's points is not the inverse from the family's own start, the solve is
run again cold (a centre left free by the data runs away and the warm inverse follows a
folded root that a fresh evaluation does not reproduce)."""

import numpy as np

from oapcal.selfcal import self_calibrate
from oapcal.selfcal import solve as S


def _residual(distorted, model="radial"):
    prob = S._problem(model, distorted.image_size, None, None, None, True)
    use = np.ones(len(distorted), bool)
    res = S._Residual(prob, distorted, use)
    t0 = S.initial_translations(distorted, prob.params0, family=prob.family)
    x0 = np.concatenate([prob.params0[prob.solved], t0[1:].ravel()])
    return res, x0


def test_a_warm_inverse_from_the_same_point_agrees_with_the_cold_one(distorted):
    res, x0 = _residual(distorted)
    res(x0)  # a first evaluation: the next one starts from these points
    x1 = x0.copy()
    x1[0] += 1e-9  # k1: the solve's small step
    assert res.agrees_cold(x1)


def test_a_warm_inverse_on_another_root_is_caught(distorted):
    res, x0 = _residual(distorted)
    names = list(res.prob.family.param_names)
    solved = [names[i] for i in np.flatnonzero(res.prob.solved)]
    x = x0.copy()
    x[solved.index("k1")] = -2e-5  # folds the map within the frame
    res.start_u = res.d + 200.0  # a start far from the principal root
    res._cache = None
    warm = res.raw(x)[0]
    cold = S._Residual(res.prob, distorted, np.ones(len(distorted), bool)).raw(x)[0]
    # the test can fail: the two inverses must really differ here
    assert np.abs(warm - cold).max() > 1.0
    assert not res.agrees_cold(x)


def test_the_solve_runs_again_cold_when_the_warm_result_is_not_reproduced(distorted, monkeypatch):
    calls = []
    real = S._Residual.agrees_cold

    def disagree_once(self, x, tol_px=1e-6):
        calls.append(self.warm)
        return False if len(calls) == 1 else real(self, x, tol_px)

    monkeypatch.setattr(S._Residual, "agrees_cold", disagree_once)
    result = self_calibrate(distorted, "radial")
    assert calls[0] is True  # the first solve was warm and was not believed
    monkeypatch.undo()
    again = self_calibrate(distorted, "radial")
    # the cold re-solve reaches the same correction as the warm one here
    np.testing.assert_allclose(result.translations, again.translations, atol=1e-3)


def test_the_start_of_a_pure_translation_scene_needs_no_cold_solve(flat):
    res, x0 = _residual(flat)
    res(x0)
    assert res.agrees_cold(x0)
