"""Image simulation: zero distortion and blur reproduce the rendering; truth agrees with the image."""

import numpy as np
import pytest

from oapcal.errors import DataError
from oapcal.imaging.field import ModelDistortionField, distortion_stats, identity_field, setup1_like_field
from oapcal.imaging.simulate import (
    airy_kernel,
    bilinear_upsample,
    peak_electrons_for_snr,
    simulate_image,
)
from oapcal.imaging.usaf import render_usaf, usaf_target
from oapcal.model import distort


def test_zero_distortion_and_blur_reproduce_the_rendered_target():
    # bars and reference squares are area-sampled in both: equal to rounding
    sim = simulate_image((4, 5), identity_field(), sigma_px=0, snr=None, bits=16, oversample=3, digits=False)
    ref = render_usaf((4, 5), um_per_px=4.8, digits=False)
    np.testing.assert_allclose(sim.clean, ref.image, atol=1e-6)
    # 16-bit quantization: brightest level at 80 % of 65535
    np.testing.assert_allclose(sim.image / (0.8 * 65535), ref.image, atol=1e-5)
    np.testing.assert_allclose(sim.xy_d, ref.corners_px, atol=1e-9)
    np.testing.assert_allclose(sim.xy_u, ref.corners_px, atol=1e-9)
    assert sim.visible.all()
    # the square of layer 4-5 is in both images: 4.486 w1 (G4E1) on a side
    t = usaf_target((4, 5))
    side = t.squares[0, 2] - t.squares[0, 0]
    assert side == pytest.approx(4.486 * 31.25, rel=1e-3)
    x0, y0, x1, y1 = t.boxes_px(t.squares, 4.8, (640, 480))[0]
    # pixels whose whole square lies in the square (pixel i covers i - 1/2 .. i + 1/2)
    inner = ref.image[
        int(np.ceil(y0 + 0.5)) : int(np.floor(y1 - 0.5)) + 1,
        int(np.ceil(x0 + 0.5)) : int(np.floor(x1 - 0.5)) + 1,
    ]
    assert inner.size > 400 and np.allclose(inner, 1.0, rtol=0, atol=1e-12)


def test_printed_numbers_are_drawn_in_their_boxes():
    sim = simulate_image((4, 5), identity_field(), sigma_px=0, snr=None, bits=16, oversample=3)
    ref = render_usaf((4, 5), um_per_px=4.8)
    bare = render_usaf((4, 5), um_per_px=4.8, digits=False)
    t = usaf_target((4, 5))
    ink = ref.image - bare.image  # the numbers alone
    boxes = t.boxes_px(t.labels, 4.8, (640, 480))
    yy, xx = np.mgrid[0:480, 0:640]
    in_box = np.zeros((480, 640), bool)
    for x0, y0, x1, y1 in boxes:
        in_box |= (xx >= x0 - 1) & (xx <= x1 + 1) & (yy >= y0 - 1) & (yy <= y1 + 1)
    assert ink[~in_box].max() < 1e-9 and ink[in_box].sum() > 0
    # each box holds 20-60 % ink (strokes of a digit), in the simulation as in the rendering
    sim_ink = sim.clean - bare.image
    for x0, y0, x1, y1 in boxes:
        sel = (xx >= x0 - 1) & (xx <= x1 + 1) & (yy >= y0 - 1) & (yy <= y1 + 1)
        area = (x1 - x0) * (y1 - y0)
        assert 0.15 < ink[sel].sum() / 0.95 / area < 0.6
        assert sim_ink[sel].sum() == pytest.approx(ink[sel].sum(), rel=0.1)


def test_setup1_like_field_has_the_papers_magnitudes():
    s = distortion_stats(setup1_like_field())
    assert 38 < s["max_px"] < 42.5 and 10 < s["mean_px"] < 15  # paper: 40.2 px max, 12.1 px mean
    assert s["max_y_px"] > 3 * s["max_x_px"]


def test_truth_is_the_forward_model_and_agrees_with_the_image():
    field = setup1_like_field()
    sim = simulate_image((4,), field, sigma_px=0.5, snr=None, oversample=3)
    t = usaf_target((4,))
    paraxial = (
        319.5 + (t.corners_um[:, 0] - t.centre_um[0]) / 4.8,
        239.5 + (t.corners_um[:, 1] - t.centre_um[1]) / 4.8,
    )
    np.testing.assert_allclose(sim.xy_u, np.column_stack(paraxial), atol=1e-9)
    np.testing.assert_allclose(sim.xy_d, distort(sim.xy_u, field.params), atol=1e-9)
    # The intensity-weighted centre of a bar in the image (made through the inverse map)
    # equals the area centroid of the bar's forward image, by quadrature over the bar:
    # int distort(u) |det J(u)| du / int |det J(u)| du.
    from oapcal.model import jacobian_determinant

    x0, y0 = sim.xy_u[0]
    x1, y1 = sim.xy_u[2]
    g = (np.arange(200) + 0.5) / 200
    uu = np.stack(np.meshgrid(x0 + g * (x1 - x0), y0 + g * (y1 - y0)), -1).reshape(-1, 2)
    det = jacobian_determinant(uu, field.params)
    c_true = (distort(uu, field.params) * det[:, None]).sum(axis=0) / det.sum()
    gap = t.bar_width[0] / 4.8  # px
    yy, xx = np.mgrid[0:480, 0:640]
    pix = np.stack([xx, yy], -1).reshape(-1, 2).astype(float)
    near = np.hypot(*(pix - c_true).T) < 40
    back = np.full(len(pix), np.inf)
    back[near] = 0
    u = field.inverse(pix[near])
    inside = (
        (u[:, 0] > x0 - gap / 2)
        & (u[:, 0] < x1 + gap / 2)
        & (u[:, 1] > y0 - gap / 2)
        & (u[:, 1] < y1 + gap / 2)
    )
    sel = np.flatnonzero(near)[inside]
    wgt = sim.clean.reshape(-1)[sel] - 0.05
    c_img = (pix[sel] * wgt[:, None]).sum(axis=0) / wgt.sum()
    assert np.hypot(*(c_img - c_true)) < 0.05


def test_noise_level_follows_the_peak_snr():
    assert peak_electrons_for_snr(50, 0) == pytest.approx(2500)
    n = peak_electrons_for_snr(50, 5)
    assert n / np.sqrt(n + 25) == pytest.approx(50)
    sim = simulate_image((2,), identity_field(), sigma_px=0, snr=40, bits=16, oversample=1, seed=3)
    t = usaf_target((2,))
    rects = t.rectangles_px(4.8, (640, 480))
    ok = (rects[:, :2].min(axis=1) > 5) & (rects[:, 2] < 634) & (rects[:, 3] < 474)
    area = (rects[:, 2] - rects[:, 0]) * (rects[:, 3] - rects[:, 1]) * ok
    x0, y0, x1, y1 = rects[np.argmax(area)]  # a bar > 20 px wide, > 100 px long
    inner = sim.image[int(y0) + 3 : int(y1) - 3, int(x0) + 3 : int(x1) - 3].astype(float)
    assert inner.size > 1000
    assert inner.mean() / inner.std() == pytest.approx(40, rel=0.1)


def test_airy_kernel_encircled_energy():
    # Physics: 83.8 % of the energy lies inside the first dark ring, 91.0 % inside the second.
    na, lam, px = 0.2, 0.8, 0.05
    k = airy_kernel(na, lam, px, radius_zeros=3.0)
    n = k.shape[0] // 2
    yy, xx = np.mgrid[-n : n + 1, -n : n + 1] * px
    r = np.hypot(xx, yy)
    e1 = k[r < 0.61 * lam / na].sum()
    e2 = k[r < 1.116 * lam / na].sum()
    assert e1 / e2 == pytest.approx(0.838 / 0.910, abs=0.01)


def test_bilinear_upsample_matches_scipy():
    from scipy.ndimage import map_coordinates

    rng = np.random.default_rng(2)
    coarse = rng.normal(size=(7 + 2, 9 + 2, 2))
    q = 3
    fine = bilinear_upsample(coarse, q, (7, 9))
    pos_x = (np.arange(9 * q) + 0.5) / q - 0.5 + 1
    pos_y = (np.arange(7 * q) + 0.5) / q - 0.5 + 1
    gy, gx = np.meshgrid(pos_y, pos_x, indexing="ij")
    for c in range(2):
        expected = map_coordinates(coarse[..., c], [gy, gx], order=1)
        np.testing.assert_allclose(fine[..., c], expected, atol=1e-12)


def test_corners_outside_the_image_are_not_visible():
    p = setup1_like_field().params.copy()
    p[10] += 300.0  # c_x: shift the image 300 px to the right
    sim = simulate_image((4, 5), ModelDistortionField(p), snr=None, oversample=1)
    inside = (sim.xy_d[:, 0] >= 3) & (sim.xy_d[:, 0] <= 636)
    np.testing.assert_array_equal(sim.visible, inside)
    assert 0 < sim.visible.sum() < len(sim.visible)


@pytest.mark.parametrize(
    "kwargs",
    [{"bits": 12}, {"oversample": 0}, {"sigma_px": -1}, {"snr": 0}, {"na": 0.2}, {"polarity": "grey"}],
)
def test_bad_simulation_arguments(kwargs):
    with pytest.raises(DataError):
        simulate_image(
            (5,), identity_field(image_size=(64, 48)), oversample=kwargs.pop("oversample", 1), **kwargs
        )


def test_cli_layout_and_bars_only(run_cli, tmp_path):
    from oapcal.cli.simulate_image import simulate_image_command
    from oapcal.imaging.usaf import LAYOUTS
    from oapcal.io.points import read_points

    choice = next(p for p in simulate_image_command.params if p.name == "layout")
    assert list(choice.type.choices) == list(LAYOUTS)
    code, out, err = run_cli("simulate", "image", "--field", "none", "--groups", "4-5", "--layout", "spaced",
                             "--no-noise", "--sigma-px", "0", "--oversample", "2",
                             "--out", tmp_path / "s.png", "--truth", tmp_path / "s.csv")  # fmt: skip
    assert code == 0, err
    pairs = read_points(tmp_path / "s.csv")
    t = usaf_target((4, 5), "spaced")
    i = pairs.ids.index("G4E6V2C2")
    expected = t.to_reference_px(t.corners_um[t.corner_ids.index("G4E6V2C2")], 4.8, (640, 480))
    np.testing.assert_allclose(pairs.xy_u[i], expected, atol=1e-9)
    code, out, err = run_cli("simulate", "image", "--field", "none", "--groups", "4-5", "--bars-only",
                             "--no-noise", "--sigma-px", "0", "--oversample", "2",
                             "--out", tmp_path / "b.png")  # fmt: skip
    assert code == 0, err
    import cv2

    bars = cv2.imread(str(tmp_path / "b.png"), cv2.IMREAD_UNCHANGED) / (0.8 * 255)
    ref = render_usaf((4, 5), um_per_px=4.8, squares=False, digits=False).image
    np.testing.assert_allclose(bars, ref, atol=0.6 / 255 / 0.8 + 1e-9)


def test_settings_object_and_keywords_are_the_same_simulation():
    from dataclasses import FrozenInstanceError

    from oapcal.imaging.simulate import ImageSettings

    settings = ImageSettings(sigma_px=0.6, snr=30, bits=16, oversample=2, digits=False)
    by_object = simulate_image((5,), identity_field(), settings=settings, seed=4)
    by_keywords = simulate_image((5,), identity_field(), sigma_px=0.6, snr=30, bits=16, oversample=2,
                                 digits=False, seed=4)  # fmt: skip
    np.testing.assert_array_equal(by_object.image, by_keywords.image)
    assert by_object.image.dtype == np.uint16
    # a keyword overrides the settings object; the object itself is frozen
    noiseless = simulate_image((5,), identity_field(), settings=settings, snr=None, seed=4)
    assert noiseless.peak_electrons is None and settings.snr == 30
    with pytest.raises(FrozenInstanceError):
        settings.snr = 10
    with pytest.raises(TypeError, match="unexpected keyword argument 'sigma'"):
        simulate_image((5,), identity_field(), sigma=1.0)
    with pytest.raises(DataError, match="bits 12: use 8 or 16") as err:
        ImageSettings(bits=12)
    assert err.value.param == "bits"


@pytest.mark.parametrize("model", ["paper+rotation", "relay"])
def test_simulate_image_through_a_rotation_or_relay_calibration(run_cli, tmp_path, model):
    # every family's calibration is a distortion field (was refused: "needs 13 finite parameters")
    from oapcal.calibration import calibrate
    from oapcal.imaging.field import ModelDistortionField
    from oapcal.io.calibration import load_calibration, save_calibration
    from oapcal.model import distort
    from oapcal.optics.relay_model import RelayDesign, calibrate_relay, relay_params
    from oapcal.synthetic import synthetic_pairs

    data = synthetic_pairs(seed=2, noise_px=0.05)
    if model == "relay":
        design = RelayDesign(setup=1, pixel_size_um=4.8, centre=(319.5, 239.5))
        truth = relay_params(design, {"m2_tilt_x": 0.02, "camera_tilt_y": 0.3})
        xy_d = distort(data.xy_u, truth)
        cal = calibrate_relay(data.xy_u, xy_d, design, "relay", um_per_px=4.8, image_size=(640, 480))
    else:
        cal = calibrate(data.xy_u, data.xy_d, model, um_per_px=4.8, image_size=(640, 480))
    path = tmp_path / "c.json"
    save_calibration(cal, path)
    code, _, err = run_cli("simulate", "image", "--calibration", path, "--groups", "4-5", "--no-noise",
                           "--out", tmp_path / "i.png", "--truth", tmp_path / "t.csv")  # fmt: skip
    assert code == 0, err
    field = ModelDistortionField.from_calibration(load_calibration(path))
    xy = np.array([[100.0, 80.0], [500.0, 400.0]])
    assert np.allclose(field.forward(xy), distort(xy, cal.params))
    assert np.allclose(field.inverse(field.forward(xy)), xy, atol=1e-6)


def test_a_distortion_field_refuses_a_vector_of_no_family():
    from oapcal.errors import DataError
    from oapcal.imaging.field import ModelDistortionField

    with pytest.raises(DataError, match="13, 14, 36 or 39 values"):
        ModelDistortionField(np.zeros(12))
