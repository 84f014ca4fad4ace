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
