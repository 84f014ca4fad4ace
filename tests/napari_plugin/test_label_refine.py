"""Labelling by hand: clicks are never fitted as they were clicked when detection refines
them, the layout and scale come from the clicks' best map (known-truth corners, the demo
image with one element blanked, and the real LAB-UMK target)."""

import numpy as np
import pytest

import oapcal
from oapcal.napari_plugin._labelling import propose_corners, refine_with_detection
from paths import REAL

SIZE = (640, 480)


def _spaced_corners(um_per_px=3.6):
    """Known truth: the corners of groups 4-5 of the 'spaced' layout (the LAB-UMK target's)
    at ``um_per_px``, turned by 3 degrees, with a mild barrel distortion."""
    target = oapcal.usaf_target((4, 5), "spaced")
    xy = target.reference_px(um_per_px, SIZE, "none")
    c = (np.array(SIZE) - 1) / 2
    a = np.deg2rad(3.0)
    rot = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    d = (xy - c) @ rot.T
    r2 = (d**2).sum(1, keepdims=True) / (300.0**2)
    return dict(zip(target.corner_ids, c + d * (1 - 0.01 * r2)))


CLICKED = ("G4E1H0C0", "G4E5V2C2", "G5E1V0C0", "G5E6H2C2", "G4E3H1C3", "G5E4V1C1")


def test_the_clicks_choose_the_layout_and_give_the_scale_within_one_percent():
    truth = _spaced_corners(3.6)
    clicks = {i: tuple(truth[i]) for i in CLICKED}
    prop = propose_corners(clicks, SIZE, (4, 5))
    assert prop.layout == "spaced"
    assert prop.um_per_px == pytest.approx(3.6, rel=0.01)
    index = {i: k for k, i in enumerate(prop.ids)}
    err = [np.hypot(*(prop.xy_d[index[i]] - truth[i])) for i in truth if i in index]
    assert np.median(err) < 1.0
    # why the scale was 15 % off before: the default (compact) layout's element spacing
    forced = propose_corners(clicks, SIZE, (4, 5), layout="compact")
    assert abs(forced.um_per_px / 3.6 - 1) > 0.05 and forced.click_rms_px > 5 * prop.click_rms_px


def test_many_clicks_give_the_mean_scale_not_the_local_slope():
    truth = _spaced_corners(3.6)
    picks = list(truth)[::23][:12]
    prop = propose_corners({i: tuple(truth[i]) for i in picks}, SIZE, (4, 5))
    assert prop.map_kind == "quadratic" and prop.layout == "spaced"
    assert prop.um_per_px == pytest.approx(3.6, rel=0.01)


def _blanked_demo(demo, element="G5E3"):
    """The demo image with one element's bars painted over with the background."""
    image = demo["image"].copy()
    pts = np.array([xy for i, xy in zip(demo["ids"], demo["xy_d"]) if i.startswith(element)])
    (x0, y0), (x1, y1) = np.floor(pts.min(0) - 3).astype(int), np.ceil(pts.max(0) + 3).astype(int)
    ring = np.concatenate([image[y0 - 2, x0:x1], image[y1 + 2, x0:x1]])
    image[y0:y1, x0:x1] = np.median(ring)
    return image


@pytest.mark.slow  # one detection (about 12 s); test_refinement_keeps_only_detected_corners is fast
def test_refinement_drops_the_clicks_detection_does_not_find(demo):
    image = _blanked_demo(demo)
    truth = dict(zip(demo["ids"], demo["xy_d"]))
    rng = np.random.default_rng(5)
    clicks = {}
    for i in ("G4E2H0C0", "G4E6V2C2", "G5E1V0C0", "G5E6H2C2", "G5E3H0C0", "G5E3V2C3"):
        a = rng.uniform(0, 2 * np.pi)
        clicks[i] = tuple(truth[i] + rng.uniform(5, 8) * np.array([np.cos(a), np.sin(a)]))
    prop = propose_corners(clicks, SIZE, (4, 5))
    det = oapcal.detect_usaf(image, (4, 5), prop.um_per_px, orientation=prop.orientation,
                             mirror="yes" if prop.mirrored else "no")  # fmt: skip
    assert det.status == 0, det.message
    out = refine_with_detection(prop, det, SIZE, (4, 5))
    assert not any(i.startswith("G5E3") for i in out.ids)  # its bars are gone: not found
    assert {"G5E3H0C0", "G5E3V2C3"} <= set(out.dropped)
    assert not out.clicked.any()
    err = np.hypot(*(out.xy_d - np.array([truth[i] for i in out.ids])).T)
    assert np.median(err) < 0.1 and err.max() < 1.0  # detected corners, none of the clicks
    # the reference points are detection's own convention, at the pixel size it measured
    assert out.um_per_px == pytest.approx(det.pixel_size["um_per_px"])
    target = oapcal.usaf_target((4, 5))
    index = {i: k for k, i in enumerate(target.corner_ids)}
    rows = [index[i] for i in out.ids]
    np.testing.assert_allclose(out.xy_u, target.reference_px(out.um_per_px, SIZE, det.orientation)[rows])
    at_hint = target.reference_px(det.um_per_px, SIZE, det.orientation)[rows]
    np.testing.assert_allclose(at_hint, det.xy_u, atol=1e-9)  # the same convention as detection's


def test_refinement_keeps_only_detected_corners(demo):
    """Without running detection: a detection that found every corner but those of G5E3."""
    from types import SimpleNamespace

    truth = dict(zip(demo["ids"], demo["xy_d"]))
    clicks = {i: tuple(truth[i] + 6.0) for i in ("G4E2H0C0", "G4E6V2C2", "G5E1V0C0", "G5E3H0C0")}
    prop = propose_corners(clicks, SIZE, (4, 5))
    ids = [i for i in demo["ids"] if not i.startswith("G5E3")]
    det = SimpleNamespace(status=0, ids=tuple(ids), xy_d=np.array([truth[i] for i in ids]),
                          um_per_px=prop.um_per_px, pixel_size={"um_per_px": 4.75},
                          orientation="rot180", pose={"layout": "compact"})  # fmt: skip
    out = refine_with_detection(prop, det, SIZE, (4, 5))
    assert out.ids == tuple(ids) and not out.clicked.any() and out.um_per_px == 4.75
    np.testing.assert_array_equal(out.xy_d, det.xy_d)
    assert "G5E3H0C0" in out.dropped and "G4E2H0C0" not in out.dropped
    assert set(out.dropped) == set(prop.ids) - set(ids)
    # the user's scale wins over the measured one
    assert refine_with_detection(prop, det, SIZE, (4, 5), um_per_px=4.8).um_per_px == 4.8
    # a failed detection leaves the proposal as it was
    failed = SimpleNamespace(**{**vars(det), "status": 1})
    assert refine_with_detection(prop, failed, SIZE, (4, 5)) is prop


needs_real = pytest.mark.skipif(
    not (REAL / "usaf" / "labumk_negative.tif").is_file(),
    reason="../shared/real/usaf/labumk_negative.tif (the real images) is not present",
)


@needs_real
@pytest.mark.slow  # two detections of a real image (about 15 s)
def test_real_target_clicks_5_to_19_px_off_are_left_out_and_the_scale_is_detections():
    from oapcal.io.imagefile import read_image_grey

    image = read_image_grey(REAL / "usaf" / "labumk_negative.tif")
    size = (image.shape[1], image.shape[0])
    found = oapcal.detect_usaf(image, (4, 5), um_per_px=3.7)  # 3.7: measured in SOURCES.md
    assert found.status == 0
    truth = dict(zip(found.ids, found.xy_d))
    rng = np.random.default_rng(0)
    picks = rng.choice(len(found.ids), 10, replace=False)
    exact = {found.ids[k]: tuple(found.xy_d[k]) for k in picks}
    # exact clicks: the layout of this target and its scale (3.61 um/px found by detection
    # without a scale, docs/detection.md) within 1 %
    prop = propose_corners(exact, size, (4, 5))
    assert prop.layout == "spaced" and prop.um_per_px == pytest.approx(3.61, rel=0.01)
    clicks = {}
    for i, xy in exact.items():
        a = rng.uniform(0, 2 * np.pi)
        clicks[i] = tuple(np.asarray(xy) + rng.uniform(5, 19) * np.array([np.cos(a), np.sin(a)]))
    prop = propose_corners(clicks, size, (4, 5))
    det = oapcal.detect_usaf(image, (4, 5), prop.um_per_px, orientation=prop.orientation,
                             mirror="yes" if prop.mirrored else "no")  # fmt: skip
    out = refine_with_detection(prop, det, size, (4, 5))
    assert out.um_per_px == pytest.approx(3.61, rel=0.01)
    assert not out.clicked.any()
    err = np.hypot(*(out.xy_d - np.array([truth[i] for i in out.ids])).T)
    assert np.median(err) < 0.05  # the detected corners, not the clicks
    cal = oapcal.calibrate(out.xy_u, out.xy_d, "paper", um_per_px=out.um_per_px, image_size=size)
    assert cal.residuals.mean_px < 0.3  # 4.12 px with the clicks kept


def test_the_status_line_names_the_clicks_left_out(demo):
    from types import SimpleNamespace

    from oapcal.napari_plugin._widgets import _proposal_words

    truth = dict(zip(demo["ids"], demo["xy_d"]))
    clicks = {i: tuple(truth[i]) for i in ("G4E2H0C0", "G4E6V2C2", "G5E1V0C0", "G5E3H0C0")}
    prop = propose_corners(clicks, SIZE, (4, 5))
    ids = [i for i in demo["ids"] if not i.startswith("G5E3")]
    det = SimpleNamespace(status=0, ids=tuple(ids), xy_d=np.array([truth[i] for i in ids]), message="ok",
                          um_per_px=4.8, pixel_size=None, orientation="rot180",
                          pose={"layout": "compact"})  # fmt: skip
    words = _proposal_words(refine_with_detection(prop, det, SIZE, (4, 5)), det, clicks)
    assert "left out 1 clicked corner that detection did not find (G5E3H0C0;" in words
    assert f"found {len(ids)}, all sub-pixel" in words and "4.8 um/px" in words
    assert "neither is sub-pixel" in _proposal_words(prop, None, clicks)
