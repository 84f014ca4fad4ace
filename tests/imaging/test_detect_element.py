"""An element registered as a whole (``triplet.refine_element``) and the dense path's second
refinement of the triplets its first pass dropped (``core._refine_twice``, issue 20)."""

from dataclasses import replace

import numpy as np
import pytest

from oapcal.imaging.detect import core
from oapcal.imaging.detect import triplet as T
from oapcal.imaging.detect.warp import PolyWarp


def test_the_local_correction_is_the_registration_plus_the_affine_term_as_one_polywarp():
    """``_with_affine`` gives the registration plus ``[1, (x - x_t) / l_t] @ coef`` (the
    local fit's basis), and its Jacobian, to rounding."""
    rng = np.random.default_rng(3)
    warp = PolyWarp(
        np.array([300.0, 200.0]), 250.0, rng.normal(size=(10, 2)) * [[100], [200], [200], *[[5]] * 7], 3
    )
    x_t, l_t = np.array([120.0, 340.0]), 17.0
    local = T._Local(None, x_t, l_t, 4.0)
    coef = rng.normal(size=(3, 2)) * [[1.5], [0.3], [0.3]]
    x = rng.uniform(0, 640, size=(50, 2))
    both = T._with_affine(warp, local, coef)
    expected = warp(x) + np.column_stack([np.ones(len(x)), (x - x_t) / l_t]) @ coef
    np.testing.assert_allclose(both(x), expected, rtol=0, atol=1e-9)
    jac = warp.jacobian(x) + (coef[1:].T / l_t)[None]
    np.testing.assert_allclose(both.jacobian(x), jac, rtol=0, atol=1e-9)


@pytest.fixture(scope="module")
def registration():
    """The dense path's triplet context on a simulated image of groups 4-5 through the
    setup-1 field, and its first refinement of every triplet."""
    from oapcal.imaging.field import setup1_like_field
    from oapcal.imaging.simulate import simulate_image

    sim = simulate_image((4, 5), setup1_like_field(), sigma_px=0.8, snr=50, seed=7)
    seen = {}
    real = core._refine_twice

    def spy(ctx, *args):
        seen["ctx"] = ctx
        return real(ctx, *args)

    core._refine_twice = spy
    try:
        det = core.detect_usaf(sim.image, (4, 5))
    finally:
        core._refine_twice = real
    assert det.ok
    return seen["ctx"], sim


def _element(ctx, g, e):
    t = ctx.target
    bars = np.array([b for b in range(len(t.bar_group)) if t.bar_group[b] == g and t.bar_element[b] == e])
    return bars, core._corner_indices(bars)


def _shifted(ctx, shift_ref):
    """``ctx`` with its registration off by ``shift_ref`` reference px everywhere."""
    coef = ctx.warp.coef.copy()
    coef[0] += shift_ref
    warp = ctx.warp.with_coef(coef)
    return replace(ctx, warp=warp, pred=warp.inverse(ctx.corners_u, x0=ctx.pred))


def test_an_element_off_by_more_than_half_a_bar_is_registered_again(registration):
    """The registration off by 1.3 bar widths (diagonally) at G5E1: each triplet's own
    refinement moves too far and is dropped; the element registered as a whole brings both
    triplets' corners back to where the right registration puts them."""
    ctx, _ = registration
    bars, idx = _element(ctx, 5, 1)
    h_bars, v_bars = bars[:3], bars[3:]
    w_ref = float(ctx.target.bar_width[bars[0]]) / ctx.um_per_px
    right = {}
    for tb in (h_bars, v_bars):
        ti = core._corner_indices(tb)
        reason, xy, _, _ = T.refine_triplet(ctx, tb, ti)
        assert reason is None
        right[tuple(tb)] = xy
    off = _shifted(ctx, 1.3 * w_ref / np.sqrt(2) * np.array([1.0, 1.0]))
    for tb in (h_bars, v_bars):
        reason, _, _, _ = T.refine_triplet(off, tb, core._corner_indices(tb))
        assert reason == "moved"
    again = T.refine_element(off, bars, idx)
    assert again is not None
    for tb in (h_bars, v_bars):
        reason, xy, _, _ = T.refine_triplet(again, tb, core._corner_indices(tb))
        assert reason is None
        assert np.hypot(*(xy - right[tuple(tb)]).T).max() < 0.05


def _twice_on_g5e1(ctx, sim, **changes):
    """``_refine_twice`` on G5E1 alone, the registration (``ctx`` with ``changes``) shifted
    by 1.3 bar widths diagonally there: ``(first, both)``."""
    bars, idx = _element(ctx, 5, 1)
    w_ref = float(ctx.target.bar_width[bars[0]]) / ctx.um_per_px
    off = _shifted(replace(ctx, **changes), 1.3 * w_ref / np.sqrt(2) * np.array([1.0, 1.0]))
    h, w = sim.image.shape
    inside = np.zeros(len(ctx.corners_u), bool)
    inside[idx] = True
    return core._refine_twice(off, ctx.target, inside, w, h, 3.0, _Quiet())


def _g5e1_bar_px(ctx):
    bars, _ = _element(ctx, 5, 1)
    return float(ctx.target.bar_width[bars[0]]) / ctx.um_per_px


def test_the_second_pass_keeps_what_the_first_kept_and_adds_the_element(registration):
    """``_refine_twice`` on the shifted registration of one element's neighbourhood: the
    first pass drops G5E1 (moved), the union has its 24 corners back."""
    ctx, sim = registration
    _, idx = _element(ctx, 5, 1)
    first, both = _twice_on_g5e1(ctx, sim)
    assert len(first.idx) == 0 and first.dropped["moved"] == 24
    assert sorted(both.idx) == sorted(idx) and both.dropped["moved"] == 0


class _Quiet:
    def advance(self, *_):
        pass


def test_bars_narrower_than_the_bar_finder_looks_for_are_not_registered_again(registration, monkeypatch):
    """Only triplets whose bars the bar finder would look for (``bars.MIN_BAR_PX``) are
    refined again: with the limit above G5E1's 3.3 px the shifted element stays dropped."""
    ctx, sim = registration
    monkeypatch.setattr(core, "MIN_BAR_PX", 1.1 * _g5e1_bar_px(ctx))
    first, both = _twice_on_g5e1(ctx, sim)
    assert both is first and len(both.idx) == 0


def test_bars_under_a_blur_wider_than_themselves_are_not_registered_again(registration):
    """Nor those narrower than the registration's blur: under a blur of 5 px the detection
    sweep's G5 corners came 1-2 px off their truth when registered on their own."""
    ctx, sim = registration
    first, both = _twice_on_g5e1(ctx, sim, sigma=1.1 * _g5e1_bar_px(ctx))
    assert both is first


def _curved(ctx, x_e, amplitude_ref, half_px):
    """``ctx`` with a spurious curvature in its registration round the camera point ``x_e``:
    ``amplitude_ref`` reference px at ``half_px`` camera px from it along x and y, nothing
    (value and slope) at ``x_e`` itself."""
    warp = ctx.warp
    rng = np.random.default_rng(0)
    x = rng.uniform([0, 0], [640, 480], size=(400, 2))
    z = (x - x_e) / half_px
    bump = amplitude_ref * np.column_stack([z[:, 0] ** 2 + 0.5 * z[:, 1] ** 2, z[:, 0] * z[:, 1]])
    extra = PolyWarp.fit(x, bump, warp.degree, centre=warp.centre, scale=warp.scale)
    curved = warp.with_coef(warp.coef + extra.coef)
    return replace(ctx, warp=curved, pred=curved.inverse(ctx.corners_u, x0=ctx.pred))


def test_the_tangent_touches_the_registration_and_is_affine():
    rng = np.random.default_rng(4)
    warp = PolyWarp(
        np.array([300.0, 200.0]), 250.0, rng.normal(size=(15, 2)) * [[100], [200], [200], *[[5]] * 12], 4
    )
    x0 = np.array([410.0, 95.0])
    tan = warp.tangent(x0)
    assert tan.degree == 1
    np.testing.assert_allclose(tan(x0[None]), warp(x0[None]), rtol=0, atol=1e-9)
    np.testing.assert_allclose(tan.jacobian(x0[None]), warp.jacobian(x0[None]), rtol=0, atol=1e-12)
    x = rng.uniform(0, 640, size=(20, 2))
    np.testing.assert_allclose(tan(x), warp(x0[None]) + (x - x0) @ warp.jacobian(x0[None])[0].T, atol=1e-9)


@pytest.mark.parametrize("amplitude", [0.0, 1.0])
def test_an_element_is_registered_again_on_the_registration_or_its_tangent(registration, amplitude):
    """The registration off by 1.3 bar widths at G5E1, and wrongly curved there by
    ``amplitude`` reference px at 18 px from the element's centre (as a degree-4 polynomial
    can be where the image shows little of the target).  Right curvature: the element is
    registered on the registration itself, its corners where the right registration puts
    them.  Wrong curvature: on the tangent, within the field's own curvature over a triplet
    (0.15-0.16 px in this simulated field); registered on the curved registration, as
    before, both triplets were dropped again as moved."""
    ctx, _ = registration
    bars, idx = _element(ctx, 5, 1)
    w_ref = float(ctx.target.bar_width[bars[0]]) / ctx.um_per_px
    right = {}
    for tb in (bars[:3], bars[3:]):
        reason, xy, _, _ = T.refine_triplet(ctx, tb, core._corner_indices(tb))
        assert reason is None
        right[tuple(tb)] = xy
    curved = _curved(ctx, ctx.pred[idx].mean(axis=0), amplitude, 18.0)
    off = _shifted(curved, 1.3 * w_ref / np.sqrt(2) * np.array([1.0, 1.0]))
    again = T.refine_element(off, bars, idx)
    assert again is not None
    assert again.warp.degree == (ctx.warp.degree if amplitude == 0 else 1)
    for tb in (bars[:3], bars[3:]):
        reason, xy, _, _ = T.refine_triplet(again, tb, core._corner_indices(tb))
        assert reason is None
        assert np.hypot(*(xy - right[tuple(tb)]).T).max() < (0.02 if amplitude == 0 else 0.2)


def test_an_elements_fit_blurs_at_most_a_few_times_the_registrations_blur(registration, monkeypatch):
    """The element pass fits where an element is in the image's blur: on pixels blurred far
    beyond it (a canvas's fill, or a region that is not the element's bars) its fitted blur
    stops at :data:`~oapcal.imaging.detect.triplet.ELEMENT_MAX_BLUR` times the registration's
    (it ran to 33 times, and blurring the raster that much cost most of the detection's
    time), while a triplet's own fit may still reach 1.2 bar widths."""
    import cv2

    ctx, _ = registration
    bars, idx = _element(ctx, 4, 1)
    w_ref = float(ctx.target.bar_width[bars[0]]) / ctx.um_per_px
    cap = T.ELEMENT_MAX_BLUR * ctx.sigma
    assert 1.2 * w_ref > 2 * cap  # the triplet's own limit lies well above the cap here
    fits = []
    real = T.fit_pixels

    def spy(data, start, options):
        res = real(data, start, options)
        fits.append((options.sigma_max, res.sigma))
        return res

    monkeypatch.setattr(T, "fit_pixels", spy)
    # smeared by 1.5 bar widths: the bars' modulation is gone, the triplets' blobs remain
    # (their pixels vary by 8 % of the contrast; by 3.5 % under 3 bar widths, which
    # FLAT_FRACTION calls no bars at all: the next test)
    smeared = replace(ctx, img=cv2.GaussianBlur(ctx.img, (0, 0), 1.5 * w_ref))
    T.refine_element(smeared, bars, idx)
    assert fits and all(limit <= cap + 1e-9 and sigma <= cap + 1e-9 for limit, sigma in fits)
    assert max(sigma for _, sigma in fits) > 0.9 * cap  # the smeared pixels ask for more
    fits.clear()
    T.refine_triplet(smeared, bars[:3], core._corner_indices(bars[:3]))
    assert fits[0][0] == pytest.approx(max(1.2 * w_ref, 1.5 * ctx.sigma, 1.0))


@pytest.mark.parametrize("flat", ["fill", "smeared"])
def test_an_element_with_a_triplet_showing_no_bars_is_not_registered_again(registration, monkeypatch, flat):
    """One triplet of G5E1 in a turned canvas's uniform fill (its box set to one value), or
    the element smeared by 3 bar widths (its pixels vary by 3.5 % of the contrast): the other
    triplet alone does not pin a move of two bar widths, so the element is not fitted at
    all (a canvas's fill cost seconds of fitting on a large image, and nothing was kept);
    with both triplets in view it is (the tests above)."""
    import cv2

    ctx, _ = registration
    bars, idx = _element(ctx, 5, 1)
    w_ref = float(ctx.target.bar_width[bars[0]]) / ctx.um_per_px
    img = ctx.img.copy()
    if flat == "fill":
        h_bars = bars[ctx.target.bar_orientation[bars] == "H"]
        xy = ctx.pred[core._corner_indices(h_bars)]
        pad = int(np.ceil(2 * w_ref))  # the box and the registration's shift below
        c0, r0 = np.floor(xy.min(axis=0)).astype(int) - pad
        c1, r1 = np.ceil(xy.max(axis=0)).astype(int) + pad
        img[r0 : r1 + 1, c0 : c1 + 1] = float(np.median(img))
    else:
        img = cv2.GaussianBlur(img, (0, 0), 3 * w_ref)
    fits = []
    real = T.fit_pixels
    monkeypatch.setattr(T, "fit_pixels", lambda *a: fits.append(1) or real(*a))
    shift = 1.3 * w_ref / np.sqrt(2) * np.array([1.0, 1.0])
    assert T.refine_element(_shifted(replace(ctx, img=img), shift), bars, idx) is None and fits == []
    assert T.refine_element(_shifted(ctx, shift), bars, idx) is not None
