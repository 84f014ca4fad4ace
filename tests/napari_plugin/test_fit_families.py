"""Fit & inspect offers every model family (Eq. 1 presets, with the target's rotation, the
physical relay, AICc selection) with the recommended one preselected, and fits the relay as
``oapcal.calibrate`` does."""

import numpy as np
import pytest

import oapcal


def test_every_family_is_offered_and_the_recommended_one_chosen(viewer):
    from oapcal.napari_plugin._widgets import SELECT, FitWidget

    w = FitWidget(viewer)
    values = [c for c in w.model.choices]
    presets = list(oapcal.PRESETS)
    turned = [f"{p}+rotation" for p in presets]
    assert values == [*presets, *turned, *(f"{p}+tilt" for p in turned), "relay", SELECT]
    assert w.model.value == "paper" and w.model.current_choice == "paper (recommended)"
    assert not w.priors.visible and not w.relay_setup.visible  # relay fields only for the relay
    w.model.value = "relay"
    assert w.priors.choices == ("off", "default")
    assert w.priors.value == "default"  # as the command line's --priors auto for a relay
    w.model.value = "full+rotation"
    assert not w.microscope.visible


@pytest.mark.slow  # a relay fit (about 8 s); the choices are tested above
def test_relay_fit_in_the_widget_is_calibrates(viewer, demo, wait, truth_layers):
    from oapcal.napari_plugin._widgets import FitWidget
    from oapcal.optics.relay_model import RelayDesign, parse_priors

    viewer.add_image(demo["image"], name="camera")
    xy_d = truth_layers(viewer, noise=0.2, seed=7)
    w = FitWidget(viewer)
    viewer.window.add_dock_widget(w, name="Fit & inspect")
    w.model.value = "relay"
    w.relay_setup.value = 1
    w.relay_pixel.value = 4.8
    w.run()
    wait(w, timeout=300)
    assert w.last_error is None, w.status
    direct = oapcal.calibrate(demo["xy_u"], xy_d, "relay", design=RelayDesign(setup=1, pixel_size_um=4.8),
                              um_per_px=4.8, image_size=(640, 480),
                              priors=parse_priors("default"))  # the widget's default  # fmt: skip
    np.testing.assert_allclose(w.calibration.params, direct.params, rtol=1e-7, atol=1e-9)
    assert w.calibration.residuals.mean_px < 0.3  # the demo's own relay, with 0.2 px noise
