import numpy as np
import pytest

from oapcal.errors import ModelSpecError
from oapcal.model import (
    INDEX,
    PARAM_NAMES,
    PRESETS,
    all_masks,
    bits_from_mask,
    distort,
    jacobian_determinant,
    jacobian_params,
    jacobian_point,
    mask_from_bits,
    names_from_mask,
    pack,
    params_from_dict,
    parse_model,
    scale_params,
    undistort,
    unpack,
)
from oapcal.synthetic import EXAMPLE_TRUTH


def random_params(rng, scale=0.02):
    p = rng.normal(0, scale, 13)
    p[INDEX["m"]] = 1.0 + rng.normal(0, 0.05)
    return p


def test_parameter_names_are_the_contract():
    assert PARAM_NAMES == ("k1", "k2", "p1", "p2", "s1", "s2", "s3", "s4",
                           "x_off", "y_off", "c_x", "c_y", "m")  # fmt: skip


def test_golden_values_written_out_by_hand():
    # Eq. (1) evaluated by hand for one point with every parameter non-zero.
    p = params_from_dict({"k1": 0.1, "k2": 0.01, "p1": 0.02, "p2": 0.03, "s1": 0.04, "s2": 0.05,
                          "s3": 0.06, "s4": 0.07, "x_off": 0.5, "y_off": -0.25, "c_x": 2.0,
                          "c_y": 3.0, "m": 2.0})  # fmt: skip
    xb, yb = 2.0 * (1.0 + 0.5), 2.0 * (2.0 - 0.25)  # 3.0, 3.5
    r2 = xb**2 + yb**2  # 21.25
    rad = 1 + 0.1 * r2 + 0.01 * r2**2
    xd = xb * rad + 2 * 0.02 * xb * yb + 0.03 * (r2 + 2 * xb**2) + 0.04 * r2 + 0.05 * r2**2 + 2.0
    yd = yb * rad + 0.02 * (r2 + 2 * yb**2) + 2 * 0.03 * xb * yb + 0.06 * r2 + 0.07 * r2**2 + 3.0
    np.testing.assert_allclose(distort(np.array([[1.0, 2.0]]), p), [[xd, yd]], rtol=1e-14)


def test_tangential_terms_follow_opencv_and_the_fold_symmetry():
    # p1 gives an x shift odd in x and a y shift even in x (OpenCV's convention): under
    # the mirror x -> -x the distortion of the 'paper' model (k1, p1, s3) is mirrored.
    p = params_from_dict({"k1": 0.05, "p1": 0.03, "s3": 0.04})
    xy = np.array([[0.3, 0.2], [-0.3, 0.2]])
    d = distort(xy, p) - xy
    np.testing.assert_allclose(d[1], [-d[0, 0], d[0, 1]], atol=1e-15)
    # and p2 breaks that symmetry
    p2 = params_from_dict({"p2": 0.03})
    d2 = distort(xy, p2) - xy
    assert not np.allclose(d2[1], [-d2[0, 0], d2[0, 1]])


def test_jacobian_params_matches_finite_differences(rng):
    xy = rng.uniform(-1, 1, (40, 2))
    p = random_params(rng)
    jac = jacobian_params(xy, p)
    eps = 1e-6
    for i in range(13):
        dp = np.zeros(13)
        dp[i] = eps
        fd = (distort(xy, p + dp) - distort(xy, p - dp)) / (2 * eps)
        np.testing.assert_allclose(jac[..., i], fd, atol=1e-8, err_msg=PARAM_NAMES[i])


def test_jacobian_point_matches_finite_differences(rng):
    xy = rng.uniform(-1, 1, (40, 2))
    p = random_params(rng)
    jac = jacobian_point(xy, p)
    eps = 1e-6
    for j in range(2):
        dx = np.zeros(2)
        dx[j] = eps
        fd = (distort(xy + dx, p) - distort(xy - dx, p)) / (2 * eps)
        np.testing.assert_allclose(jac[..., :, j], fd, atol=1e-8)


def test_batched_params_broadcast_like_a_loop(rng):
    xy = rng.uniform(-1, 1, (10, 2))
    ps = np.stack([random_params(rng) for _ in range(5)])
    batched = distort(xy, ps)
    assert batched.shape == (5, 10, 2)
    for b in range(5):
        np.testing.assert_array_equal(batched[b], distort(xy, ps[b]))
    own = rng.uniform(-1, 1, (5, 10, 2))
    jb = jacobian_params(own, ps)
    for b in range(5):
        np.testing.assert_allclose(jb[b], jacobian_params(own[b], ps[b]), rtol=1e-15)


def test_scale_params_is_an_exact_reparametrization(rng):
    xy = rng.uniform(0, 640, (30, 2))
    p = EXAMPLE_TRUTH
    for f in (7.0, 640.0):
        np.testing.assert_allclose(distort(xy / f, scale_params(p, f)), distort(xy, p) / f, rtol=1e-12)


def test_undistort_round_trip_over_the_whole_field():
    g = np.stack(np.meshgrid(np.linspace(0, 639, 81), np.linspace(0, 479, 61)), -1).reshape(-1, 2)
    xy_d = distort(g, EXAMPLE_TRUTH)
    inv = undistort(xy_d, EXAMPLE_TRUTH)
    assert inv.converged.all()
    assert not inv.folded.any()
    assert np.abs(distort(inv.xy, EXAMPLE_TRUTH) - xy_d).max() < 1e-9
    np.testing.assert_allclose(inv.xy, g, atol=1e-8)


def test_undistort_reports_fold_over_instead_of_a_wrong_answer():
    # Strong barrel distortion folds over beyond r^2 = 1/(3|k1|): points outside come back
    # as not converged, never as a confident wrong answer.
    p = params_from_dict({"k1": -0.3})
    xy_u = np.array([[0.2, 0.0], [1.5, 0.0]])  # det > 0 at the first, < 0 at the second
    det = jacobian_determinant(xy_u, p)
    assert det[0] > 0 > det[1]
    xy_d = distort(xy_u, p)
    inv = undistort(xy_d, p, xy_start=xy_u)  # Newton started right at the folded point
    assert inv.converged[0] and not inv.converged[1]
    assert inv.folded[1]
    assert np.isnan(inv.xy[1]).all()
    # a point beyond the extreme value of the map has no preimage at all
    inv2 = undistort(np.array([[0.5, 0.0]]), p)  # max of x(1 - 0.3x^2) is ~0.70; 0.5 < 0.70 ok
    assert inv2.converged[0]
    inv3 = undistort(np.array([[0.9, 0.0]]), p)
    assert not inv3.converged[0]


def test_presets_and_specs():
    assert names_from_mask(parse_model("paper")) == PRESETS["paper"]
    assert names_from_mask(parse_model("radial")) == PRESETS["radial"]
    assert parse_model("full").all()
    assert names_from_mask(parse_model(" k1 , s3")) == ("k1", "s3", "m")
    with pytest.raises(ModelSpecError, match="unknown parameter or preset 'k3'"):
        parse_model("k1,k3")
    with pytest.raises(ModelSpecError, match="empty"):
        parse_model(" , ")


def test_masks_bits_pack_unpack(rng):
    masks = all_masks()
    assert masks.shape == (4096, 13) and masks[:, -1].all()
    assert len({tuple(m) for m in masks}) == 4096
    np.testing.assert_array_equal(bits_from_mask(masks), np.arange(4096))
    np.testing.assert_array_equal(mask_from_bits(5)[:3], [True, False, True])
    mask = parse_model("paper")
    p = random_params(rng)
    free = pack(p, mask)
    assert free.shape == (8,)
    full = unpack(free, mask)
    np.testing.assert_array_equal(full[mask], p[mask])
    assert (full[~mask] == 0).all()


def test_finite_difference_parameter_jacobian_matches_the_analytic_one(rng):
    xy = rng.uniform(-1, 1, (40, 2))
    p = random_params(rng)
    np.testing.assert_allclose(
        jacobian_params(xy, p, finite_difference=True), jacobian_params(xy, p), atol=1e-8
    )


def test_shapes_broadcast_and_bad_shapes_are_named_errors(rng):
    xy = rng.uniform(-1, 1, (3, 4, 2))
    p = random_params(rng)
    assert distort(xy, p).shape == (3, 4, 2) and jacobian_point(xy, p).shape == (3, 4, 2, 2)
    assert undistort(distort(xy, p), p).xy.shape == (3, 4, 2)
    assert distort(np.zeros((0, 2)), p).shape == (0, 2)
    with pytest.raises(ModelSpecError, match=r"shape \(\.\.\., 13\)"):
        distort(xy, p[:12])
    with pytest.raises(ModelSpecError, match=r"shape \(\.\.\., N, 2\)"):
        distort(np.zeros(3), p)
