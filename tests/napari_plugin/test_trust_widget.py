"""The trust region in the napari widgets: the Correct widget writes only the trust region
when asked, shows the predicted error and the region as layers; Fit & inspect says how much
of the image is trusted."""

import numpy as np

import oapcal


def test_correct_widget_trust_region_and_predicted_error(viewer, demo, wait, truth_layers):
    from oapcal.napari_plugin._widgets import CorrectWidget, FitWidget

    image = demo["image"]
    viewer.add_image(image, name="camera")
    truth_layers(viewer, noise=0.2, seed=3)
    fit = FitWidget(viewer)
    viewer.window.add_dock_widget(fit, name="Fit & inspect")
    fit.run()
    wait(fit)
    cal = fit.calibration
    assert cal.error_model is not None
    # the demo's landmarks cover a small part of the frame: only part of it is trusted
    assert "predicted error <= 1 px over" in fit.status and "% of the image" in fit.status
    w = CorrectWidget(viewer)
    viewer.window.add_dock_widget(w, name="Correct")
    w.image.value = viewer.layers["camera"]
    w.trust_only.value = True
    w.max_error.value = 1.0
    w.run()
    wait(w)
    assert w.last_error is None, w.status
    cmap = oapcal.correction_map(cal, image.shape, max_error_px=1.0)
    expected = oapcal.correct_image(image, cmap, "cubic")
    np.testing.assert_array_equal(viewer.layers["camera corrected"].data, expected)
    assert 0.05 < cmap.trusted.mean() < 0.95  # some, not all, of the frame
    assert (viewer.layers["camera corrected"].data[~cmap.trusted] == 0).all()  # the rest is border
    region = viewer.layers["trust region (<= 1 px)"].data
    pred = viewer.layers["predicted error (um)"].data
    assert region.shape == pred.shape
    # the region is where the predicted error (in um here) is at most 1 px
    np.testing.assert_array_equal(region.astype(bool), pred <= 1.0 * cal.um_per_px + 1e-6)
    assert "trust region (predicted error <= 1 px)" in w.status and "only it written" in w.status
