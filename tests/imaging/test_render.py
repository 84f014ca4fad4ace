"""Rendering a real picture through a distortion model: the affine case against OpenCV's own
warp, the truth against the model's forward map, the microscope's inversion."""

import cv2
import numpy as np
import pytest

from oapcal.errors import DataError
from oapcal.imaging.render import Camera, Microscope, Placement, Scene, auto_oversample, render_scene
from oapcal.model import distort, identity_params


def smooth_source(shape=(150, 200), seed=0):
    rng = np.random.default_rng(seed)
    src = cv2.GaussianBlur(rng.uniform(0, 255, shape).astype(np.float32), (0, 0), 2.0)
    return src


def grid(w, h):
    gx, gy = np.meshgrid(np.arange(float(w)), np.arange(float(h)))
    return np.stack([gx, gy], -1)


def test_identity_model_equals_cv2_warp_affine_of_the_turned_mirrored_source():
    src = smooth_source()
    w, h, pitch, um, theta = 160, 120, 4.8, 3.0, 30.0
    cam = Camera(size=(w, h), pixel_size_um=pitch, sigma_px=0, snr=None, bits=16, oversample=1)
    place = Placement(um, (97.3, 71.6), rotation_deg=theta, mirror=True)
    r = render_scene(src, Scene(identity_params(), place, cam))
    # camera px p -> object X = (p - c) pitch; target T = F R(-theta) X; source s = s0 + T / um
    t = np.radians(theta)
    a = pitch / um * np.array([[-np.cos(t), -np.sin(t)], [-np.sin(t), np.cos(t)]])
    c = np.array([(w - 1) / 2, (h - 1) / 2])
    m = np.column_stack([a, np.array(place.centre_px) - a @ c])
    np.testing.assert_allclose(r.source_px, grid(w, h) @ a.T + m[:, 2], atol=1e-9)
    rel = src / np.percentile(src, 99.5)
    background = float(np.median(rel))
    warped = cv2.warpAffine(rel.astype(np.float32), m, (w, h), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                            borderMode=cv2.BORDER_CONSTANT, borderValue=background)  # fmt: skip
    inside = r.valid
    assert inside.mean() > 0.3 and (~inside).sum() > 100  # both the source and its surround are seen
    np.testing.assert_allclose(r.clean, warped, atol=2e-3)
    sx, sy = r.source_px[..., 0], r.source_px[..., 1]
    far = (sx < -1.5) | (sy < -1.5) | (sx > src.shape[1] + 0.5) | (sy > src.shape[0] + 0.5)
    assert far.sum() > 100
    np.testing.assert_allclose(r.clean[far], background, atol=1e-6)
    # 16 bits, no noise: the brightest level (1) at 80 % of full scale
    np.testing.assert_allclose(r.image / (0.8 * 65535), np.clip(r.clean, 0, 1.25), atol=1e-5)


def test_oversampled_blurred_linear_ramp_is_the_ramp_at_each_pixel_centre():
    # bilinear sub-pixels of an affine map, a linear source, a symmetric blur and the pixel
    # average all keep a linear function: the image is the ramp at each pixel's source point
    yy, xx = np.mgrid[0:400, 0:500].astype(np.float32)
    src = 10.0 + 0.3 * xx + 0.1 * yy
    cam = Camera(size=(64, 48), pixel_size_um=4.8, sigma_px=0.8, snr=None, bits=16, oversample=3)
    r = render_scene(src, Scene(identity_params(), Placement(2.0, (250.0, 200.0), rotation_deg=15.0), cam))
    top = np.percentile(src, 99.5)
    s = r.source_px
    expected = (10.0 + 0.3 * s[..., 0] + 0.1 * s[..., 1]) / top
    core = (slice(4, -4), slice(4, -4))  # the blur's replicated border is not linear
    np.testing.assert_allclose(r.clean[core], expected[core], rtol=0, atol=2e-4)


def test_relay_truth_is_the_model_forward_map(relay_params_misaligned):
    params, cam = relay_params_misaligned
    src = smooth_source((300, 400))
    scene = Scene(params, Placement(8.0, (199.5, 149.5), rotation_deg=1.0), cam)
    r = render_scene(src, scene, seed=3)
    w, h = cam.size
    ok = np.isfinite(r.reference_px).all(axis=-1)
    assert ok.all()
    pix = grid(w, h)
    np.testing.assert_allclose(distort(r.reference_px[ok], params), pix[ok], atol=1e-6)
    np.testing.assert_allclose(scene.camera_from_source(r.source_px.reshape(-1, 2)), pix.reshape(-1, 2),
                               atol=1e-5)  # fmt: skip
    # the aligned relay turns the image by 180 degrees: the object right of the centre is left
    centre = np.array([(w - 1) / 2, (h - 1) / 2])
    right = r.object_um[h // 2, w - 10]
    assert right[0] < -0.5 * (w / 2 - 10) * cam.pixel_size_um
    # the distortion of the misaligned relay is present (tens of px at this pitch's scale)
    para = -(pix - centre) * cam.pixel_size_um
    assert np.abs(r.object_um - para).max() / cam.pixel_size_um > 2.0
    assert r.image.dtype == np.uint8 and r.peak_electrons is not None


@pytest.fixture(scope="module")
def relay_params_misaligned():
    from oapcal.optics.relay_model import RelayDesign, relay_params

    # a coarse camera over the same field as the paper's (640 x 480 at 4.8 um): 80 x 60 at 38.4 um
    cam = Camera(size=(80, 60), pixel_size_um=38.4, sigma_px=0.8, snr=50.0, oversample=2)
    design = RelayDesign(setup=1, pixel_size_um=38.4, centre=(39.5, 29.5))
    mis = {"m2_tilt_x": 0.04, "m1_decentre_y": 0.15, "d1": -30.0, "camera_tilt_y": 0.8, "camera_defocus": 0.1}
    return relay_params(design, mis, {"rotation": 0.5}), cam


def test_microscope_behind_the_model_magnifies_and_inverts():
    src = smooth_source()
    cam = Camera(size=(60, 40), pixel_size_um=4.8, sigma_px=0, snr=None, oversample=2)
    scene = Scene(
        identity_params(), Placement(1.0, (100.0, 75.0)), cam, microscope=Microscope(5.0, inverted=True)
    )
    assert scene.camera_um_per_px == pytest.approx(0.96)
    r = render_scene(src, scene)
    c = np.array([29.5, 19.5])
    np.testing.assert_allclose(r.object_um, -(grid(60, 40) - c) * 0.96, atol=1e-9)
    back = scene.camera_from_source(r.source_px.reshape(-1, 2))
    np.testing.assert_allclose(back, grid(60, 40).reshape(-1, 2), atol=1e-9)
    upright = Scene(
        identity_params(), Placement(1.0, (100.0, 75.0)), cam, microscope=Microscope(5.0, inverted=False)
    )
    np.testing.assert_allclose(render_scene(src, upright).object_um, (grid(60, 40) - c) * 0.96, atol=1e-9)


def test_noise_is_seeded_and_oversampling_follows_the_source_pixel():
    src = smooth_source()
    scene = Scene(identity_params(), Placement(4.0, (100.0, 75.0)), Camera(size=(40, 30)))
    a, b, c = (render_scene(src, scene, seed=s) for s in (1, 1, 2))
    assert np.array_equal(a.image, b.image) and not np.array_equal(a.image, c.image)
    assert a.oversample == 2  # 4.8 um camera px over 4 um source px
    assert (
        auto_oversample(4.8, 1.02) == 5 and auto_oversample(0.96, 1.02) == 2 and auto_oversample(48, 1) == 8
    )


def test_bad_inputs_are_refused_with_the_parameter_named():
    with pytest.raises(DataError) as e:
        Placement(0.0, (1.0, 1.0))
    assert e.value.param == "um_per_px"
    with pytest.raises(DataError):
        Microscope(-5.0)
    with pytest.raises(DataError):
        Camera(bits=12)
    scene = Scene(identity_params(), Placement(1.0, (1.0, 1.0)), Camera(size=(8, 6)))
    with pytest.raises(DataError):
        render_scene(np.zeros(10), scene)
    with pytest.raises(DataError):
        render_scene(np.zeros((10, 10)), scene)
