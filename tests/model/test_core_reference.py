"""The compiled core against the independent NumPy reference (``reference_model.py``),
over all 4,096 models of Eq. (1), not a sample."""

import numpy as np
import pytest

import reference_model as ref
from oapcal.fitting import fit_batch, initial_params
from oapcal.model import (
    all_masks,
    correction_errors,
    distort,
    jacobian_params,
    jacobian_point,
    min_jacobian_determinant,
    params_from_dict,
    undistort,
)
from oapcal.normalize import normalize
from oapcal.synthetic import EXAMPLE_TRUTH


@pytest.fixture(scope="module")
def all_fits():
    """All 4,096 models fitted from zero to a normalized 17 x 17 grid with 0.05 px noise."""
    gx, gy = np.meshgrid(np.linspace(0, 640, 17), np.linspace(0, 480, 17))
    xy_u = np.stack([gx.ravel(), gy.ravel()], -1)
    xy_d = ref.distort(xy_u, EXAMPLE_TRUTH) + np.random.default_rng(7).normal(0, 0.05, xy_u.shape)
    norm = normalize("grid", xy_u, xy_d)
    masks = all_masks()
    p0 = np.where(masks, initial_params("zero", norm.xy_u, norm.xy_d, np.ones(13, bool)), 0.0)
    return norm.xy_u, norm.xy_d, masks, fit_batch(norm.xy_u, norm.xy_d, masks, p0)


def test_every_model_rss_gradient_and_covariance_match_the_reference(all_fits):
    u, d, masks, batch = all_fits
    assert batch.converged.sum() > 3900  # the few others are checked for finite values only
    n = 2 * len(u)
    checked_cov = 0
    for s in range(0, len(masks), 512):
        params = batch.params[s : s + 512]
        r = (ref.distort(u, params) - d).reshape(len(params), -1)
        rss = np.sum(r * r, axis=1)
        ok = np.isfinite(rss) & np.isfinite(batch.rss[s : s + 512])
        np.testing.assert_allclose(batch.rss[s : s + 512][ok], rss[ok], rtol=1e-10)
        jac = ref.jacobian_params(u, params).reshape(len(params), -1, 13)
        for i in np.flatnonzero(batch.converged[s : s + 512]):
            mask = masks[s + i]
            jf = jac[i][:, mask]
            # Stationary point: the gradient is orthogonal to every column (reference Jacobian).
            cosine = np.abs(jf.T @ r[i]) / (np.linalg.norm(jf, axis=0) * np.linalg.norm(r[i]))
            assert cosine.max() < 1e-5, (s + i, cosine.max())
            # Covariance s^2 (J^T J)^-1 from the reference Jacobian, where well conditioned.
            jtj = jf.T @ jf
            dsc = np.sqrt(np.diag(jtj))
            scaled = jtj / np.outer(dsc, dsc)
            if np.linalg.cond(scaled) > 1e8:
                continue
            cov = np.linalg.inv(scaled) / np.outer(dsc, dsc) * rss[i] / (n - mask.sum())
            scale = np.sqrt(np.outer(np.diag(cov), np.diag(cov))).max()
            ours = batch.covariance[s + i][np.ix_(mask, mask)]
            np.testing.assert_allclose(ours, cov, rtol=1e-6, atol=1e-9 * scale)
            assert not batch.covariance[s + i][~mask].any()
            checked_cov += 1
    assert checked_cov > 3000


def test_every_model_forward_map_and_jacobians_match_the_reference(all_fits):
    u, _, _, batch = all_fits
    pts = u[::5]
    for s in range(0, len(batch.params), 1024):
        params = batch.params[s : s + 1024]
        np.testing.assert_allclose(distort(pts, params), ref.distort(pts, params), rtol=1e-13, atol=1e-13)
        np.testing.assert_allclose(jacobian_point(pts, params), ref.jacobian_point(pts, params), rtol=1e-12,
                                   atol=1e-12)  # fmt: skip
        np.testing.assert_allclose(jacobian_params(pts, params), ref.jacobian_params(pts, params), rtol=1e-12,
                                   atol=1e-12)  # fmt: skip


def test_every_model_inverse_matches_the_reference_including_failures(all_fits):
    u, d, _, batch = all_fits
    pts = d[::4]  # 73 of the 289 points, for time; every model
    ours = undistort(pts, batch.params)
    theirs = ref.undistort(pts, batch.params)
    np.testing.assert_array_equal(ours.converged, theirs.converged)
    np.testing.assert_array_equal(ours.folded, theirs.folded)
    assert (~ours.converged).any() and ours.folded.any()  # failures are exercised too
    np.testing.assert_allclose(ours.xy[ours.converged], theirs.xy[theirs.converged], rtol=0, atol=1e-12)
    # The scoring kernel is the same inverse summed without storing the points.
    rss, mean, n_bad, n_folded = correction_errors(batch.params, pts, u[::4])
    np.testing.assert_array_equal(n_bad, (~theirs.converged).sum(axis=1))
    np.testing.assert_array_equal(n_folded, theirs.folded.sum(axis=1))
    dist = np.hypot(*np.moveaxis(np.where(theirs.converged[..., None], theirs.xy - u[::4], 0.0), -1, 0))
    np.testing.assert_allclose(rss, np.sum(dist**2, axis=1), rtol=1e-10, atol=1e-300)


def test_min_jacobian_determinant_matches_the_reference():
    params = np.stack([EXAMPLE_TRUTH, params_from_dict({"k1": -0.3, "m": 1.0})])
    pts = np.random.default_rng(0).uniform(-1.2, 1.2, (200, 2))
    expected = ref.jacobian_determinant(pts, params).min(axis=1)
    np.testing.assert_allclose(min_jacobian_determinant(params, pts), expected, rtol=1e-12)
    # 1 + 3 k1 r^2 < 0 on the x axis beyond r = 1.054: the determinant written by hand
    hand = (1 - 0.3 * 3 * 1.44) * (1 - 0.3 * 1.44)
    assert min_jacobian_determinant(params[1], np.array([[1.2, 0.0]]))[0] == pytest.approx(hand, rel=1e-12)


def test_inverse_with_a_start_and_folds_matches_the_reference():
    params = np.stack([EXAMPLE_TRUTH, params_from_dict({"k1": -0.3, "m": 1.0})])
    xy_d = np.stack(np.meshgrid(np.linspace(-1.5, 1.5, 13), np.linspace(-1.5, 1.5, 11)), -1).reshape(-1, 2)
    start = xy_d * 0.9
    ours = undistort(xy_d, params, xy_start=start)
    theirs = ref.undistort(xy_d, params, xy_start=start)
    np.testing.assert_array_equal(ours.converged, theirs.converged)
    np.testing.assert_array_equal(ours.folded, theirs.folded)
    np.testing.assert_allclose(ours.xy[ours.converged], theirs.xy[theirs.converged], rtol=0, atol=1e-12)
    assert ours.folded[1].any() and ours.n_iter == theirs.n_iter
