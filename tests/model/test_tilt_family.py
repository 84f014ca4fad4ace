"""Eq. (1) with the perspective (keystone) terms, ``brown-conrady+tilt``: the compiled point
function and both Jacobians against the formula of docs/models.md written out in NumPy (on
the NumPy Eq. 1 of tests/reference_model.py) and its central differences; a known tilt
recovered from synthetic points; the two terms counted in AICc."""

import numpy as np
import pytest

import reference_model as ref
from oapcal.fitting import fit
from oapcal.model import (
    BROWN_CONRADY_TILT,
    PARAM_NAMES,
    Model,
    family_of_spec,
    names_from_mask,
    params_from_dict,
    parse_any_model,
)
from oapcal.stats import information_criteria

#: Eq. (1) about (320, 240) with the target turned 0.4 deg and seen in perspective.
EQ1 = params_from_dict({"k1": 2e-7, "p1": 3e-5, "s3": -2e-5, "x_off": -320.0, "y_off": -240.0,
                        "c_x": 322.0, "c_y": 238.0, "m": 1.01})  # fmt: skip
P = np.concatenate([EQ1, [0.4, 4e-5, -6e-5]])
XY = np.random.default_rng(11).uniform([0, 0], [639, 479], (200, 2))


def tilt_numpy(xy, p):
    """docs/models.md's formula: turn, divide the offset coordinates by
    w = 1 + tilt_x s + tilt_y t, then Eq. (1) (the NumPy reference)."""
    th = np.deg2rad(p[13])
    x, y = xy[..., 0], xy[..., 1]
    s = np.cos(th) * x - np.sin(th) * y + p[8]
    t = np.sin(th) * x + np.cos(th) * y + p[9]
    w = 1.0 + p[14] * s + p[15] * t
    return ref.distort(np.stack([s / w - p[8], t / w - p[9]], -1), p[:13])


def central_differences(f, x0, h):
    """Columns ``d f / d x0_i`` by central differences with steps ``h`` (vector)."""
    cols = []
    for i in range(len(x0)):
        e = np.zeros_like(x0)
        e[i] = h[i]
        cols.append((f(x0 + e) - f(x0 - e)) / (2 * h[i]))
    return np.stack(cols, -1)


def test_tilt_point_function_and_jacobians_match_the_numpy_formula():
    model = Model(BROWN_CONRADY_TILT, P, BROWN_CONRADY_TILT.param_names)
    np.testing.assert_allclose(model(XY), tilt_numpy(XY, P), rtol=0, atol=1e-9)
    for i in range(0, len(XY), 40):
        num = central_differences(lambda q, i=i: tilt_numpy(q[None], P)[0], XY[i], np.full(2, 1e-3))
        np.testing.assert_allclose(model.jacobian(XY[i : i + 1])[0], num, atol=1e-7)
    # parameter columns: steps relative to each value (1e-6, at least 1e-6 absolute)
    h = 1e-6 * np.maximum(np.abs(P), 1.0)
    h[[0, 2, 6, 14, 15]] = 1e-9  # k1, p1, s3 and the tilts act through r^2 ~ 1e5 px^2
    num = central_differences(lambda q: tilt_numpy(XY, q), P, h)  # (N, 2, 16)
    got = model.jacobian_params(XY)
    scale = np.abs(num).max(axis=(0, 1))
    np.testing.assert_allclose(got / scale, num / scale, atol=1e-6)


def test_tilt_inverse_through_the_model():
    model = Model(BROWN_CONRADY_TILT, P, ("k1", "m"))
    inv = model.inverse(tilt_numpy(XY, P))
    assert inv.converged.all()
    np.testing.assert_allclose(inv.xy, XY, atol=1e-8)


def test_tilt_specs_name_the_family_and_its_terms():
    assert family_of_spec("paper+tilt") is BROWN_CONRADY_TILT
    assert names_from_mask(parse_any_model("k1,c_x+tilt")) == ("k1", "c_x", "m", "tilt_x", "tilt_y")
    assert "rotation" in names_from_mask(parse_any_model("paper+rotation+tilt"))
    from oapcal.cli.select import _robustness_spec  # robustness --models: '+'-joined names

    assert _robustness_spec("k1+s3+rotation+tilt") == "k1,s3+rotation+tilt"
    assert _robustness_spec("paper+tilt") == "paper+tilt"


def test_a_known_tilt_is_recovered_and_counted_in_aicc():
    truth = P.copy()
    truth[13] = 0.0  # paper+tilt fixes the rotation at 0
    sigma = 0.05
    xy_d = tilt_numpy(XY, truth) + np.random.default_rng(12).normal(0, sigma, XY.shape)
    tilted = fit(XY, xy_d, "paper+tilt")
    plain = fit(XY, xy_d, "paper")
    assert tilted.converged and tilted.k == 10 and plain.k == 8
    # the tilts within 4 standard errors of the truth, and far from 0
    for name, i in (("tilt_x", 14), ("tilt_y", 15)):
        assert abs(tilted.value(name) - truth[i]) < 4 * tilted.stderr_dict[name]
        assert abs(truth[i]) > 10 * tilted.stderr_dict[name]
    # the fit's AICc is the textbook formula with K = k + 1 (the error variance)
    n = 2 * len(XY)
    k1 = tilted.k + 1
    want = n * np.log(tilted.rss / n) + 2 * k1 + 2 * k1 * (k1 + 1) / (n - k1 - 1)
    assert tilted.aicc == pytest.approx(want, rel=1e-12)
    assert tilted.aicc == pytest.approx(information_criteria(tilted.rss, n, 10).aicc, rel=1e-12)
    # noise-level residuals with the tilt; without it, the keystone stays
    assert np.sqrt(tilted.rss / n) == pytest.approx(sigma, rel=0.2)
    assert plain.rss > 5 * tilted.rss and tilted.aicc < plain.aicc - 100
    eq1_free = tuple(n for n in PARAM_NAMES if n in tilted.model.free)
    assert eq1_free == names_from_mask(parse_any_model("paper"))


def test_opencv_export_is_exact_through_a_homography_r():
    # cv2.initUndistortRectifyMap on the exported coefficients gives, at every output pixel,
    # the tilt formula's distorted point (the map's float32 rounding aside)
    from oapcal.imaging.opencv import opencv_export, opencv_maps

    export = opencv_export(Model(BROWN_CONRADY_TILT, P, ("k1", "m")), (640, 480))
    assert export["exact"] and export["model_family"] == "brown-conrady+tilt"
    map_x, map_y = opencv_maps(export)
    gx, gy = np.meshgrid(np.arange(640.0), np.arange(480.0))
    want = tilt_numpy(np.stack([gx, gy], -1), P)
    np.testing.assert_allclose(map_x, want[..., 0], atol=2e-3)
    np.testing.assert_allclose(map_y, want[..., 1], atol=2e-3)
    assert np.abs(np.array(export["R"])[2, :2]).max() > 1e-3  # R is no rotation: the keystone is in it


@pytest.mark.slow  # 8,192 fits and their cross-validation: 4-8 s on 2 shared cores
def test_select_families_ranks_the_tilt_variant_with_its_terms_counted():
    from oapcal.families import select_families

    truth = P.copy()
    truth[13] = 0.0
    xy_u = XY[:60]  # few points: 8,192 fits
    xy_d = tilt_numpy(xy_u, truth) + np.random.default_rng(13).normal(0, 0.05, xy_u.shape)
    sel = select_families(xy_u, xy_d, None, "bc,bc+tilt", cv=2, cv_top=1)  # no relay: no design
    best = sel.candidates[0]
    assert best.family == "brown-conrady+tilt" and best.spec.endswith("+tilt")
    assert {"tilt_x", "tilt_y"} <= set(best.free) and "rotation" not in best.free
    assert best.k == len(best.free)  # the two terms count in AICc like every other
    plain = min(c.aicc for c in sel.candidates if c.family == "brown-conrady" and c.valid)
    assert best.aicc < plain - 50
    assert sel.recommended.family == "brown-conrady+tilt"


@pytest.mark.slow  # four fits with their checks and error model: the default suite keeps the fit test above
def test_calibrate_fits_the_rotation_of_paper_plus_tilt_by_the_aicc_rule():
    import oapcal

    xy_d = tilt_numpy(XY, P) + np.random.default_rng(14).normal(0, 0.05, XY.shape)  # turned 0.4 deg
    cal = oapcal.calibrate(XY, xy_d, "paper+tilt", image_size=(640, 480))
    assert cal.model.family is BROWN_CONRADY_TILT and "rotation" in cal.model.free
    assert any("paper+rotation+tilt" in n for n in cal.notes)
    assert cal.model.value("rotation") == pytest.approx(0.4, abs=0.01)
    kept = oapcal.calibrate(XY, xy_d, "paper+tilt", image_size=(640, 480), rotation="none")
    assert "rotation" not in kept.model.free and kept.model.value("rotation") == 0.0
