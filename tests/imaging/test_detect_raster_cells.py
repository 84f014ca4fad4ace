"""A triplet's reference raster blurred by many cells is built with cells of a quarter of its
blur (``registration.CELLS_PER_SIGMA``): the blurred values it samples are those of the fine
raster at a blur larger by 0.8 % (the cell's box and the bilinear sampling add about h^2 / 4
of variance, which the fitted blur absorbs), to a fraction of a percent of the contrast."""

import numpy as np
import pytest

from oapcal.imaging.detect.registration import CELLS_PER_SIGMA, RASTER_OVERSAMPLE, Reference

# three bars 33 reference px wide (group 7 element 1 at 0.118 um/px, a soft high-magnification view)
RECTS = np.array([[0, 0, 33, 165], [66, 0, 99, 165], [132, 0, 165, 165]], float)


@pytest.mark.parametrize("sigma", [4.0, 8.0, 12.0])
def test_coarse_cells_sample_the_blurred_raster_as_the_fine_ones(sigma):
    fine = Reference(RECTS, margin=60)
    coarse = Reference(RECTS, margin=60, min_step=sigma / CELLS_PER_SIGMA)
    assert fine.step == 1 / RASTER_OVERSAMPLE and coarse.step == pytest.approx(sigma / CELLS_PER_SIGMA)
    rng = np.random.default_rng(0)
    u = np.column_stack([rng.uniform(-30, 195, 5000), rng.uniform(-30, 195, 5000)])
    wider = sigma * np.sqrt(1 + 1 / (4 * CELLS_PER_SIGMA**2))  # measured best: +0.8-0.9 %
    r_f, gu_f, gv_f, ds_f = fine.sample(u, wider, with_sigma=True)
    r_c, gu_c, gv_c, ds_c = coarse.sample(u, sigma, with_sigma=True)
    assert np.abs(r_c - r_f).max() < 0.004  # of a contrast of 1 (measured 0.1-0.3 %)
    scale = np.abs(gu_f).max()
    assert np.abs(gu_c - gu_f).max() < 0.03 * scale and np.abs(gv_c - gv_f).max() < 0.03 * scale
    assert np.sqrt(np.mean((ds_c - ds_f) ** 2)) < 0.03 * np.sqrt(np.mean(ds_f**2))
    # and no edge moves: the fine raster shifted by a tenth of a px fits worse
    shifted = fine.sample(u + [0.1, 0.0], wider)[0]
    assert np.abs(r_c - r_f).max() < np.abs(r_c - shifted).max()


def test_a_sharp_raster_keeps_its_half_pixel_cells():
    assert Reference(RECTS, margin=60, min_step=1.0 / CELLS_PER_SIGMA).step == 1 / RASTER_OVERSAMPLE


def _cover_blur(ref, sigma):
    """cv2's Gaussian blur of the whole raster, the library operation that ``Reference``
    replaces for wide blurs (``_blurred``) and for the blur's derivative."""
    import cv2

    return cv2.GaussianBlur(ref.cover, (0, 0), sigmaX=sigma / ref.step, borderType=cv2.BORDER_CONSTANT)


@pytest.mark.parametrize("shape", [(50, 70), (2, 9), (300, 200)])
@pytest.mark.parametrize("step", [0.5, 0.613, 1.3])
def test_the_rasters_gradient_is_numpys_bit_for_bit(shape, step):
    from oapcal.imaging.detect.registration import _gradient

    r = np.random.default_rng(1).random(shape).astype(np.float32)
    gu, gv = _gradient(r, step)
    ev, eu = np.gradient(r, step)
    assert gu.dtype == np.float32 and np.array_equal(gu, eu) and np.array_equal(gv, ev)


@pytest.mark.parametrize("cells", [1.5, 2.0, 3.0, 6.0, 12.0])
def test_the_blurs_derivative_from_the_laplacian_is_the_difference_of_two_blurs(cells):
    """``dR/dsigma = sigma * Laplacian(R_sigma)`` against the central difference of two cv2
    blurs (what it replaced): within 1.2 % (rms over the raster's points) from 1.5 cells per
    sigma, 0.5 % from 2 (measured 1.1 % and 0.2-0.5 %)."""
    from oapcal.imaging.detect.registration import LAPLACIAN_MIN_CELLS

    assert LAPLACIAN_MIN_CELLS <= cells
    ref = Reference(RECTS, margin=60)
    sigma = cells * ref.step
    rng = np.random.default_rng(2)
    u = np.column_stack([rng.uniform(-30, 195, 5000), rng.uniform(-30, 195, 5000)])
    coords = ref._coords(u)
    got = ref.sigma_derivative(coords, sigma)
    h = 0.01 * sigma
    from oapcal.imaging.detect.registration import _bilinear

    hi, lo = (_bilinear(_cover_blur(ref, sigma + d), coords) for d in (h, -h))
    want = (hi - lo) / (2 * h)
    rel = np.sqrt(np.mean((got - want) ** 2) / np.mean(want**2))
    assert rel < (0.012 if cells < 2 else 0.005)


@pytest.mark.parametrize("cells", [12.0, 24.0, 30.0, 50.0, 100.0])
def test_a_wide_blur_on_coarser_cells_is_the_direct_blur(cells):
    """A blur of many cells is done on cells ``floor(cells / COARSE_BLUR_CELLS)`` times
    larger and interpolated back: within 0.1 % of the contrast of cv2's blur of the whole
    raster (measured 0.03-0.07 %), at a fraction of its time (a blur of 31 cells of a 1.8 M-cell
    raster took 0.1 s per trial step of a fit)."""
    from oapcal.imaging.detect.registration import COARSE_BLUR_CELLS

    ref = Reference(RECTS, margin=200)
    sigma = cells * ref.step
    got = ref.rasters(sigma, gradients=False)[0]
    want = _cover_blur(ref, sigma)
    assert got.shape == want.shape and got.dtype == np.float32
    assert np.abs(got - want).max() < 0.001
    if cells < 2 * COARSE_BLUR_CELLS:
        assert np.array_equal(got, want)  # below twice the limit: the direct blur itself


def test_a_coarser_copy_of_a_reference_keeps_its_region():
    ref = Reference(RECTS, margin=60, window=((-20, -20), (150, 180)))
    ref.lo, ref.hi = ref.lo + 5, ref.hi - 5
    assert ref.with_min_step(0.1) is ref
    coarse = ref.with_min_step(2.0)
    assert coarse.step == pytest.approx(2.0) and coarse.cover.size < ref.cover.size / 10
    np.testing.assert_array_equal(coarse.lo, ref.lo)
    np.testing.assert_array_equal(coarse.hi, ref.hi)
    u = np.array([[16.5, 80.0], [50.0, 80.0], [120.0, 10.0]])
    got, want = (r.sample(u, 4.0, derivatives=False)[0] for r in (coarse, ref))
    np.testing.assert_allclose(got, want, atol=0.01)


def _shift_fit(sigma_true, follow=True):
    """A translation-and-blur fit of pixels of the three-bar raster blurred by ``sigma_true``
    and shifted by (0.3, -0.2) px, from the 1 px hint: (result, rasters rebuilt)."""
    from unittest import mock

    from oapcal.imaging.detect import registration as R

    ref = Reference(RECTS, margin=60)
    yy, xx = np.mgrid[-10:176:0.5, -10:176:0.5]
    u = np.column_stack([xx.ravel(), yy.ravel()])
    values = 0.1 + 0.8 * ref.sample(u + [0.3, -0.2], sigma_true, derivatives=False)[0]
    data = R.PixelData(values, u, np.ones((len(u), 1)), Reference(RECTS, margin=60))
    built = []
    real = Reference.with_min_step

    def spy(self, min_step):
        built.append(min_step)
        return real(self, min_step)

    factor = R.FOLLOW_BLUR_FACTOR if follow else np.inf
    start = R.FitStart(np.zeros((1, 2)), 0.0, 1.0, 1.04)
    with mock.patch.object(Reference, "with_min_step", spy):
        with mock.patch.object(R, "FOLLOW_BLUR_FACTOR", factor):
            res = R.fit_pixels(data, start, R.FitOptions(fit_sigma=True))
    return res, built


def test_a_fit_of_a_wide_blur_follows_it_with_coarser_cells():
    """From the 1 px hint to a 6 px blur: the raster is rebuilt as the blur grows (cells of a
    quarter of it), and the fit ends where the fit on the fine raster throughout ends (the
    shift within 0.005 px, the blur within 1 %), in fewer blurs of a smaller raster."""
    res, built = _shift_fit(6.0)
    fine, none = _shift_fit(6.0, follow=False)
    assert built and not none
    assert max(built) >= 4.0 / CELLS_PER_SIGMA
    assert res.converged and fine.converged
    np.testing.assert_allclose(res.coef, fine.coef, atol=0.005)
    assert res.sigma == pytest.approx(fine.sigma, rel=0.01)
    np.testing.assert_allclose(res.coef[0], [0.3, -0.2], atol=0.01)


def test_a_sharp_fit_keeps_its_raster():
    res, built = _shift_fit(1.2)
    fine, _ = _shift_fit(1.2, follow=False)
    assert not built
    np.testing.assert_array_equal(res.coef, fine.coef)
    assert res.sigma == fine.sigma
