"""The widgets driven in a headless viewer, checked against oapcal called directly and
against the simulation's truth."""

import numpy as np
import pytest

import oapcal
from paths import REAL


def _add(viewer, widget, name):
    viewer.window.add_dock_widget(widget, name=name)
    return widget


def test_detect_adds_the_corners_with_ids(viewer, demo, wait):
    from oapcal.napari_plugin._widgets import DetectWidget

    viewer.add_image(demo["image"], **demo["kwargs"])
    w = _add(viewer, DetectWidget(viewer), "Detect")
    assert w.image.value is viewer.layers[0]
    w.um_per_px.value = 4.8
    w.run()
    wait(w)
    assert w.last_error is None, w.status
    dist, ref = viewer.layers["distorted"], viewer.layers["reference"]
    ids = list(dist.features["id"])
    assert len(ids) == len(set(ids)) == 288 and list(ref.features["id"]) == ids
    truth = dict(zip(demo["ids"], demo["xy_d"]))
    err = np.hypot(*(dist.data[:, ::-1] - np.array([truth[i] for i in ids])).T)
    assert np.median(err) < 0.1 and err.max() < 0.5  # the corners are on the simulated bars
    assert dist.metadata["oapcal_um_per_px"] == pytest.approx(4.8)
    assert "288 of 288 corners" in w.status


@pytest.mark.slow  # the anchor itself is tested on the library (tests/imaging/test_detect_anchor.py)
def test_detect_with_an_anchor_names_the_same_corners(viewer, demo, wait):
    from oapcal.napari_plugin._widgets import DetectWidget

    viewer.add_image(demo["image"], **demo["kwargs"])
    w = _add(viewer, DetectWidget(viewer), "Detect")
    x, y = dict(zip(demo["ids"], demo["xy_d"]))["G4E2H1C0"]
    w.anchor.value = f"G4E2@{x:.0f},{y:.0f}"
    w.run()
    wait(w)
    assert w.last_error is None, w.status
    dist = viewer.layers["distorted"]
    truth = dict(zip(demo["ids"], demo["xy_d"]))
    err = np.hypot(*(dist.data[:, ::-1] - np.array([truth[i] for i in dist.features["id"]])).T)
    assert len(err) >= 0.8 * 288 and err.max() < 0.5 and "+/-" in w.status


def test_detect_failure_is_a_message_not_a_traceback(viewer, wait):
    from oapcal.napari_plugin._widgets import DetectWidget

    viewer.add_image(np.full((120, 160), 7, np.uint8), name="blank")
    w = _add(viewer, DetectWidget(viewer), "Detect")
    w.run()
    wait(w)
    assert w.last_error is not None and "uniform" in w.last_error
    assert w.status.startswith("Detect failed: ") and "Traceback" not in w.status
    assert [layer.name for layer in viewer.layers] == ["blank"]
    w.groups.value = "4-x"
    w.run()
    assert "4-x" in w.last_error and not w.busy


def test_label_by_hand_then_propose_and_refine(viewer, demo, wait):
    from oapcal.napari_plugin._widgets import LabelWidget

    viewer.add_image(demo["image"], **demo["kwargs"])
    w = _add(viewer, LabelWidget(viewer), "Label by hand")
    layer = w.start_labelling()
    assert layer.mode == "add"
    truth = dict(zip(demo["ids"], demo["xy_d"]))
    for corner in ("G4E2H0C0", "G4E6V2C2", "G5E1V0C0", "G5E6H2C2"):
        w.corner.value = corner  # what the user picks before clicking
        layer.add(truth[corner][::-1])
    assert w.clicks().keys() == {"G4E2H0C0", "G4E6V2C2", "G5E1V0C0", "G5E6H2C2"}
    placed = list(layer.features["id"])
    assert placed == ["G4E2H0C0", "G4E6V2C2", "G5E1V0C0", "G5E6H2C2"]
    assert w.corner.value not in placed  # after a click the widget offers the next free id
    w.refine.value = True
    w.run()
    wait(w)
    assert w.last_error is None, w.status
    dist = viewer.layers["distorted"]
    ids = list(dist.features["id"])
    assert set(ids) >= set(demo["ids"]) and len(ids) == len(set(ids))
    found = np.array([truth[i] for i in ids])
    err = np.hypot(*(dist.data[:, ::-1] - found).T)
    # refined by detection at the pose the clicks give (without them, detection cannot
    # find this target: no scale): every corner sub-pixel
    assert np.median(err) < 0.1 and err.max() < 0.5
    assert set(dist.features["source"]) == {"detected"}


def test_label_by_hand_without_refinement_keeps_clicks_and_proposes(viewer, demo, wait):
    from oapcal.napari_plugin._widgets import LabelWidget

    viewer.add_image(demo["image"], **demo["kwargs"])
    w = _add(viewer, LabelWidget(viewer), "Label by hand")
    layer = w.start_labelling()
    truth = dict(zip(demo["ids"], demo["xy_d"]))
    for corner in ("G4E2H0C0", "G4E6V2C2", "G5E1V0C0"):
        w.corner.value = corner
        layer.add(truth[corner][::-1])
    w.refine.value = False
    w.run()
    wait(w)
    dist = viewer.layers["distorted"]
    source = dict(zip(dist.features["id"], dist.features["source"]))
    assert [i for i, s in source.items() if s == "clicked"] == ["G4E2H0C0", "G4E6V2C2", "G5E1V0C0"]
    assert len(source) > 250
    # too few clicks: the reason, no traceback
    layer.data = layer.data[:2]
    w.run()
    wait(w)
    assert "at least 3 corners" in w.last_error


def test_fit_shows_the_residuals_of_oapcals_own_fit(viewer, demo, wait, truth_layers):
    from oapcal.napari_plugin._widgets import FitWidget

    viewer.add_image(demo["image"], **demo["kwargs"])
    xy_d = truth_layers(viewer, noise=0.3, seed=1)
    w = _add(viewer, FitWidget(viewer), "Fit & inspect")
    assert w.distorted.value.name == "distorted" and w.reference.value.name == "reference"
    w.model.value = "paper"
    w.run()
    wait(w)
    assert w.last_error is None, w.status
    direct = oapcal.calibrate(demo["xy_u"], xy_d, "paper", um_per_px=4.8, image_size=(640, 480))
    np.testing.assert_allclose(w.calibration.params, direct.params, rtol=1e-9, atol=1e-9)
    residual = np.hypot(*(oapcal.undistort(xy_d, direct.params).xy - demo["xy_u"]).T)
    vectors = viewer.layers["residuals (x20)"]
    np.testing.assert_allclose(vectors.features["residual_px"], residual, rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(vectors.data[:, 0, ::-1], xy_d)  # drawn where the landmarks are
    np.testing.assert_allclose(vectors.data[:, 1, ::-1] / 20, oapcal.undistort(xy_d, direct.params).xy
                               - demo["xy_u"], atol=1e-6)  # fmt: skip
    assert f"{direct.residuals.max_px:8.4g}" in w.table1.value
    assert f"{direct.residuals.mean_um:8.4g}" in w.table1.value
    worst = [demo["ids"][k] for k in np.argsort(-residual)[:5]]
    assert list(viewer.layers["worst landmarks"].features["id"]) == worst
    assert w.worst_text.value.splitlines()[0].startswith(worst[0])
    assert [row[0] for row in w.params.data] == list(direct.free)


def test_fit_pairs_by_id_after_a_landmark_is_deleted(viewer, demo, wait, truth_layers):
    from oapcal.napari_plugin._widgets import FitWidget

    xy_d = truth_layers(viewer, noise=0.3, seed=2)
    dist = viewer.layers["distorted"]
    dist.selected_data = {0, 7}
    dist.remove_selected()
    w = _add(viewer, FitWidget(viewer), "Fit & inspect")
    w.model.value = "radial"
    w.run()
    wait(w)
    keep = np.ones(len(demo["ids"]), bool)
    keep[[0, 7]] = False
    direct = oapcal.calibrate(demo["xy_u"][keep], xy_d[keep], "radial", um_per_px=4.8)
    assert w.calibration.fit.n_points == keep.sum()
    np.testing.assert_allclose(w.calibration.params, direct.params, rtol=1e-9, atol=1e-9)


def test_correct_image_and_lazy_stack_uncertainty_hull_and_save(viewer, demo, wait, tmp_path, truth_layers):
    import dask.array as da

    from oapcal.napari_plugin._widgets import CorrectWidget, FitWidget

    image = demo["image"]
    viewer.add_image(image, name="camera")
    truth_layers(viewer, noise=0.2, seed=3)
    fit = _add(viewer, FitWidget(viewer), "Fit & inspect")
    fit.run()
    wait(fit)
    cal = fit.calibration
    w = _add(viewer, CorrectWidget(viewer), "Correct")
    assert w.source.value is cal
    w.image.value = viewer.layers["camera"]
    w.run()
    wait(w)
    assert w.last_error is None, w.status
    expected = oapcal.correct_image(image, oapcal.correction_map(cal, image.shape), "cubic")
    np.testing.assert_array_equal(viewer.layers["camera corrected"].data, expected)
    unc = viewer.layers["uncertainty (um)"]
    assert unc.data.shape == (120, 160) and tuple(unc.scale) == (4, 4)
    assert np.isfinite(unc.data).all() and unc.data.min() > 0
    hull = viewer.layers["calibration hull"].data[0]
    np.testing.assert_allclose(hull[:, ::-1], cal.hull)

    # a stack: corrected lazily, frame by frame, as napari shows it
    stack = np.stack([image, image[::-1, ::-1].copy(), image // 2])
    viewer.add_image(stack, name="stack")
    w.image.value = viewer.layers["stack"]
    w.show_uncertainty.value = False
    w.run()
    wait(w)
    out = viewer.layers["stack corrected"].data
    assert isinstance(out, da.Array) and out.shape == stack.shape
    np.testing.assert_array_equal(np.asarray(out[1]), oapcal.correct_image(stack[1], oapcal.correction_map(
        cal, image.shape), "cubic"))  # fmt: skip

    # save, and refuse a missing name
    path = tmp_path / "calib.json"
    w.save_path.value = str(path)
    w.save()
    assert oapcal.load_calibration(path).free == cal.free
    np.testing.assert_allclose(oapcal.load_calibration(path).params, cal.params, rtol=1e-12)
    w.save_path.value = str(tmp_path)
    w.save()
    assert "choose a file name" in w.last_error


def test_open_files_in_the_viewer_through_the_plugin(viewer, demo, tmp_path):
    xy_u, xy_d, ids = demo["xy_u"], demo["xy_d"], demo["ids"]
    oapcal.write_point_pairs(tmp_path / "p.csv", xy_u, xy_d, ids=ids)
    cal = oapcal.calibrate(xy_u, xy_d, "paper", image_size=(640, 480))
    oapcal.save_calibration(cal, tmp_path / "c.json")
    viewer.open(str(tmp_path / "p.csv"), plugin="oapcal")
    viewer.open(str(tmp_path / "c.json"), plugin="oapcal")
    names = [layer.name for layer in viewer.layers]
    assert names[:2] == ["distorted", "reference"] and "c: distortion field" in names
    assert list(viewer.layers["distorted"].features["id"]) == list(ids)
    # the Correct widget takes the opened calibration and never saves over its file
    from oapcal.napari_plugin._widgets import CorrectWidget

    correct = _add(viewer, CorrectWidget(viewer), "Correct")
    assert correct.source.value.free == cal.free
    before = (tmp_path / "c.json").read_bytes()
    correct.save_path.value = str(tmp_path / "c.json")
    correct.save()
    assert "read or fitted from" in correct.last_error and (tmp_path / "c.json").read_bytes() == before
    # and save the two points layers back through the plugin's writer
    viewer.layers.selection = {viewer.layers["distorted"], viewer.layers["reference"]}
    viewer.layers.save(str(tmp_path / "back.csv"), selected=True, plugin="oapcal")
    back = oapcal.read_points(tmp_path / "back.csv")
    assert list(back.ids) == list(ids)
    np.testing.assert_array_equal(back.xy_d, xy_d)


needs_real = pytest.mark.skipif(
    not (REAL / "usaf" / "labumk_negative.tif").is_file(),
    reason="../shared/real/usaf/labumk_negative.tif (the real images) is not present",
)


@needs_real
@pytest.mark.slow  # the widget's detect and fit run in the default suite on the demo's image
def test_detect_and_fit_on_a_real_image(viewer, wait):
    from oapcal.io.imagefile import read_image_grey
    from oapcal.napari_plugin._widgets import DetectWidget, FitWidget

    viewer.add_image(read_image_grey(REAL / "usaf" / "labumk_negative.tif"), name="labumk")
    w = _add(viewer, DetectWidget(viewer), "Detect")
    w.groups.value = "4-7"
    w.um_per_px.value = 3.7  # measured in SOURCES.md
    w.run()
    wait(w)
    assert w.last_error is None, w.status
    dist = viewer.layers["distorted"]
    index = {i: k for k, i in enumerate(dist.features["id"])}
    # bars identified by eye from the printed numbers (tests/imaging/test_detect_real.py)
    for bar, x, y in [("G4E3H1", 83, 63), ("G4E1H1", 284, 205), ("G5E3H1", 298, 61)]:
        corners = dist.data[[index[f"{bar}C{c}"] for c in range(4)]][:, ::-1]
        lo, hi = corners.min(axis=0), corners.max(axis=0)
        assert lo[0] < x < hi[0] and lo[1] < y < hi[1], bar
    fit = _add(viewer, FitWidget(viewer), "Fit & inspect")
    fit.run()
    wait(fit)
    assert fit.calibration.fit.converged and fit.calibration.residuals.mean_px < 1.0


@pytest.mark.slow
def test_fit_selects_the_model_by_aicc(viewer, demo, wait, truth_layers):
    from oapcal.napari_plugin._widgets import FRAME_TERMS, SELECT, FitWidget

    xy_d = truth_layers(viewer, noise=0.3, seed=4)
    w = _add(viewer, FitWidget(viewer), "Fit & inspect")
    w.model.value = SELECT
    w.run()
    wait(w, timeout=600)
    assert w.last_error is None, w.status
    best = oapcal.select_models(demo["xy_u"], xy_d, init="pixel").best.free
    assert w.calibration.free == tuple(n for n in oapcal.PARAM_NAMES if n in best or n in FRAME_TERMS)
