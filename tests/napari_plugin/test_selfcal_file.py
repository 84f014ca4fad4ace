"""A self-calibration's file in napari: opened by the reader, used by the Correct widget as
any calibration (issue 22: "a normal calibration file")."""

import importlib.util

import numpy as np

import oapcal
from paths import TESTS


def _scenes():
    spec = importlib.util.spec_from_file_location("selfcal_scenes", TESTS / "selfcal" / "selfcal_scenes.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_a_selfcal_file_opens_and_corrects(viewer, wait, tmp_path):
    from oapcal.napari_plugin._widgets import CorrectWidget

    sc = _scenes()
    frames = sc.render_moves(sc.truth_params(), sc.grid_moves(), sc.texture(0))
    result = oapcal.self_calibrate(oapcal.find_matches(frames), "radial")
    path = tmp_path / "selfcal.json"
    oapcal.save_calibration(result.calibration, path)
    layers = viewer.open(str(path), plugin=None)
    names = [layer.name for layer in layers]
    assert "selfcal: distortion (px)" in names and "selfcal: distortion field" in names
    magnitude = viewer.layers["selfcal: distortion (px)"].data
    assert np.isfinite(magnitude).all() and magnitude.max() > 0.5  # the truth bends ~1.8 px
    image = np.asarray(frames[4] * 255, np.uint8)
    viewer.add_image(image, name="frame")
    w = CorrectWidget(viewer)
    viewer.window.add_dock_widget(w, name="Correct")
    w.file.value = str(path)
    w.image.value = viewer.layers["frame"]
    w.show_uncertainty.value = False
    w.run()
    wait(w)
    assert w.last_error is None, w.status
    cal = oapcal.load_calibration(path)
    expected = oapcal.correct_image(image, oapcal.correction_map(cal, image.shape), "cubic")
    np.testing.assert_array_equal(viewer.layers["frame corrected"].data, expected)
