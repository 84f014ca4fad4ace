"""Detection on real USAF-1951 images (../shared/real/usaf) and on images without a target.

The real images' ids are checked against bars identified by eye from the numbers printed on
the target (the middle bar of a few triplets, a point on it): the detected corners of that
bar must surround the point.  See benchmarks/real_usaf.py for the full measurement.
"""

import numpy as np
import pytest

from oapcal.imaging.detect import detect_usaf
from paths import REAL as SHARED_REAL

REAL = SHARED_REAL / "usaf"
needs_real = pytest.mark.skipif(
    not REAL.is_dir(), reason="../shared/real/usaf (the real images) is not present"
)

#: file, groups in view, pixel size measured in SOURCES.md, [(bar id, a point on that bar)]
CASES = [
    ("fpm_brightfield.png", (3, 4, 5, 6, 7), 1.02,
     [("G4E2H1", 360, 272), ("G5E1H1", 988, 246), ("G4E1V1", 730, 860), ("G6E2H1", 674, 496)]),
    ("labumk_negative.tif", (4, 5, 6, 7), 3.7,
     [("G4E3H1", 83, 63), ("G4E1H1", 284, 205), ("G5E3H1", 298, 61)]),
    ("whole_target.png", (-2, -1, 0, 1), 130.0,
     [("G-2E2H1", 100, 155), ("G-1E1H1", 445, 140), ("G-2E1H1", 425, 459), ("G0E2H1", 327, 272)]),
]  # fmt: skip


def _read(name):
    from oapcal.io.imagefile import read_image_grey

    return read_image_grey(REAL / name)


@pytest.mark.slow
@needs_real
@pytest.mark.parametrize("name,groups,measured,anchors", CASES, ids=[c[0] for c in CASES])
def test_real_image_scale_found_and_ids_match_the_printed_numbers(name, groups, measured, anchors):
    det = detect_usaf(_read(name), groups)  # no --um-per-px: the scale is found
    assert det.status == 0, det.message
    assert abs(det.um_per_px / measured - 1) < 0.03
    assert det.coverage >= 0.9
    index = {i: k for k, i in enumerate(det.ids)}
    for bar, x, y in anchors:
        corners = det.xy_d[[index[f"{bar}C{c}"] for c in range(4)]]
        lo, hi = corners.min(axis=0), corners.max(axis=0)
        assert lo[0] < x < hi[0] and lo[1] < y < hi[1], (bar, corners, (x, y))


@pytest.mark.slow
@needs_real
def test_single_element_view_is_refused_without_enough_information():
    # one element (group 7 element 1, turned) in view: neither the element nor a mirror can be
    # told from the bars alone, so without a scale the detection must refuse, not guess
    det = detect_usaf(_read("highmag_g7e1.jpg"), (7,))
    assert det.status != 0 and "ambiguous" in det.message and len(det.ids) == 0


def _photo_without_target(rng):
    """Smooth shading, circles, a few lines and text, noise: a picture with edges but no
    three equal parallel bars."""
    import cv2

    y, x = np.mgrid[0:480, 0:640]
    img = 80 + 60 * np.sin(x / 90.0) * np.cos(y / 70.0)
    for _ in range(25):
        c = (int(rng.integers(0, 640)), int(rng.integers(0, 480)))
        cv2.circle(img, c, int(rng.integers(5, 60)), float(rng.integers(0, 255)), -1)
    img = np.clip(img, 0, 255).astype(np.uint8)
    cv2.putText(img, "oapcal 2026", (40, 400), cv2.FONT_HERSHEY_SIMPLEX, 2.0, 230, 3)
    cv2.line(img, (10, 20), (600, 60), 250, 4)
    return np.clip(img + rng.normal(0, 4, img.shape), 0, 255).astype(np.uint8)


@pytest.mark.parametrize(
    "kind",
    [pytest.param("noise", marks=pytest.mark.slow), "checkerboard", "photo",
     pytest.param("almost_blank", marks=pytest.mark.slow)],
)  # fmt: skip
def test_images_without_a_target_are_refused_with_a_reason(kind):
    rng = np.random.default_rng(1)
    if kind == "noise":
        img = rng.integers(0, 255, (480, 640)).astype(np.uint8)
    elif kind == "checkerboard":
        y, x = np.mgrid[0:480, 0:640]
        img = (((x // 24) + (y // 24)) % 2 * 200 + 20).astype(np.uint8)
    elif kind == "photo":
        img = _photo_without_target(rng)
    else:
        img = (100 + rng.normal(0, 1, (480, 640))).astype(np.float32)
    for um in (None, 4.8):
        det = detect_usaf(img, (4, 5), um)
        assert det.status != 0 and det.message and len(det.ids) == 0
        assert "um_per_px" in det.summary() and det.summary()["reason"] == det.message


def test_blank_image_is_a_target_not_found():
    det = detect_usaf(np.zeros((100, 120)), (4, 5))
    assert det.status != 0 and "the image is uniform" in det.message and len(det.ids) == 0


def test_an_absurd_scale_is_refused_quickly_not_rendered():
    # at 1e-4 um/px the target would be millions of px wide: refused before any raster is made
    rng = np.random.default_rng(0)
    det = detect_usaf(rng.integers(0, 255, (200, 300)).astype(np.uint8), (4, 5), 1e-4)
    assert det.status != 0 and not det.ok and "check um_per_px" in det.message and det.param == ("um_per_px",)


def test_fit_parameters_are_bounded():
    """The blur of a triplet fit cannot run away (it once grew 15 -> 90 -> 3397 px): a step
    outside the bound is rejected like a step that raises the cost."""
    from oapcal.imaging.detect.registration import FitOptions, FitStart, PixelData, Reference, fit_pixels

    rects = np.array([[10.0, 10.0, 15.0, 35.0], [20.0, 10.0, 25.0, 35.0], [30.0, 10.0, 35.0, 35.0]])
    ref = Reference(rects, margin=10)
    gy, gx = np.mgrid[0:45, 0:45]
    xs = np.stack([gx.ravel(), gy.ravel()], -1).astype(float)
    values = np.full(len(xs), 0.5) + np.random.default_rng(0).normal(0, 0.01, len(xs))  # no bars at all
    basis = np.column_stack([np.ones(len(xs)), xs / 20.0])
    res = fit_pixels(PixelData(values, xs, basis, ref), FitStart(np.zeros((3, 2)), 0.1, 0.8, 1.0),
                     FitOptions(fit_sigma=True, sigma_max=6.0, max_shift=5.0))  # fmt: skip
    assert res.sigma <= 6.0
    assert np.abs(basis @ res.coef).max() <= 5.0 + 1e-9


def test_cli_failure_prints_one_json_object_and_still_draws_the_picture(run_cli, tmp_path):
    import json

    import cv2

    y, x = np.mgrid[0:240, 0:320]
    cv2.imwrite(str(tmp_path / "checker.png"), (((x // 16) + (y // 16)) % 2 * 200 + 20).astype(np.uint8))
    code, stdout, err = run_cli("detect", tmp_path / "checker.png", "--out", tmp_path / "p.csv",
                                "--plot", tmp_path / "why.png", "--json")  # fmt: skip
    assert code == 3
    data = json.loads(stdout)
    assert data["status"] == 1 and data["reason"] and data["found"] == 0
    assert {"um_per_px", "pose", "triplets_found", "work"} <= set(data)
    assert (tmp_path / "why.png").stat().st_size > 1000  # the picture of what was found
    assert not (tmp_path / "p.csv").exists()  # never a points file on failure
    assert "Traceback" not in err and "detection failed" in err


def test_cli_um_per_px_is_bounded(run_cli, tmp_path):
    import cv2

    cv2.imwrite(str(tmp_path / "a.png"), np.full((48, 64), 7, np.uint8))
    code, _, err = run_cli("detect", tmp_path / "a.png", "--um-per-px", "1e-6", "--out", tmp_path / "p.csv")
    assert code == 2 and "--um-per-px" in err and "Traceback" not in err
    assert "--max-pixels" not in err


@pytest.mark.slow
@needs_real
def test_single_element_with_scale_and_no_mirror_is_group_7_element_1():
    # given the scale (from the bar period, 68 px = 2 w) and that the image is not mirrored,
    # the element is named: its H triplet (vertical in this turned image) keeps its corners
    det = detect_usaf(_read("highmag_g7e1.jpg"), (7,), 0.11, mirror="no")
    assert det.status == 0, det.message
    assert det.ids and all(i.startswith("G7E1") for i in det.ids)
    index = {i: k for k, i in enumerate(det.ids)}
    if "G7E1H1C0" in index:  # the middle bar of the H triplet is the one through (257, 567)
        corners = det.xy_d[[index[f"G7E1H1C{c}"] for c in range(4)]]
        assert (
            corners[:, 0].min() < 257 < corners[:, 0].max()
            and corners[:, 1].min() < 567 < corners[:, 1].max()
        )


@pytest.mark.parametrize(
    "angle,flip",
    [
        (30.0, False),
        pytest.param(-63.0, True, marks=pytest.mark.slow),
        pytest.param(135.0, False, marks=pytest.mark.slow),
    ],
)
def test_any_rotation_mirror_unknown_scale_shading_and_jpeg(angle, flip):
    """A simulated target turned by any angle (optionally mirrored), scaled by 0.8, shaded
    from 45 % to 100 % across the image and JPEG-compressed (quality 70): found without
    --um-per-px, with the scale, the turn and every id right."""
    import cv2

    from oapcal.imaging.detect import evaluate_detection
    from oapcal.imaging.field import ModelDistortionField, setup1_like_field
    from oapcal.imaging.simulate import simulate_image

    p = setup1_like_field().params.copy()
    p[:8] = 0.0  # no distortion: the truth is the turned simulated truth
    sim = simulate_image((4, 5), ModelDistortionField(p), sigma_px=0.8, snr=50, seed=3)
    h, w = sim.image.shape
    img, xy = sim.image.copy(), sim.xy_d.copy()
    if flip:
        img, xy[:, 0] = img[:, ::-1].copy(), w - 1 - xy[:, 0]
    m = cv2.getRotationMatrix2D(((w - 1) / 2, (h - 1) / 2), angle, 0.8)
    turned = cv2.warpAffine(img, m, (w, h), flags=cv2.INTER_LINEAR, borderValue=float(np.median(img)))
    xy = xy @ m[:, :2].T + m[:, 2]
    visible = (xy[:, 0] >= 3) & (xy[:, 0] <= w - 4) & (xy[:, 1] >= 3) & (xy[:, 1] <= h - 4)
    shaded = np.clip(turned.astype(float) * (0.45 + 0.55 * np.arange(w) / w)[None, :], 0, 255).astype(
        np.uint8
    )
    jpeg = cv2.imdecode(cv2.imencode(".jpg", shaded, [cv2.IMWRITE_JPEG_QUALITY, 70])[1], 0)

    det = detect_usaf(jpeg, (4, 5))
    assert det.status == 0, det.message
    score = evaluate_detection(det, sim.ids, xy, visible)
    assert score["mismatches"] == 0
    # group 5's narrowest bars are under 2 px at this scale and are not expected
    assert score["coverage"] >= 0.7 and score["median_error_px"] < 0.05
    assert det.um_per_px == pytest.approx(sim.um_per_px / 0.8, rel=0.01)
    assert det.pose["best"]["mirrored"] == flip
    # cv2 turns counter-clockwise on the displayed image (y down): -angle in the pose's
    # convention; the pose writes a left-right mirror as a top-bottom one turned by 180
    expected = -angle if not flip else -180.0 - angle
    assert abs((det.pose["best"]["rotation_deg"] - expected + 180) % 360 - 180) < 1.0
