"""The napari Correct widget refuses an image of another size than the calibration's, as
``oapcal correct`` does (without --allow-size-mismatch)."""

import numpy as np

import oapcal


def test_correct_widget_refuses_an_image_of_another_size(viewer, demo, wait, tmp_path):
    from oapcal.napari_plugin._widgets import CorrectWidget

    cal = oapcal.calibrate(demo["xy_u"], demo["xy_d"], "paper", image_size=(640, 480))
    oapcal.save_calibration(cal, tmp_path / "c.json")
    viewer.add_image(np.zeros((60, 80), np.uint8), name="small")
    w = CorrectWidget(viewer)
    viewer.window.add_dock_widget(w, name="Correct")
    w.file.value = str(tmp_path / "c.json")
    w.image.value = viewer.layers["small"]
    w.run()
    wait(w)
    assert "small is 80x60 px but the calibration is for 640x480 px" in (w.last_error or ""), w.status
    assert "small corrected" not in [layer.name for layer in viewer.layers]
