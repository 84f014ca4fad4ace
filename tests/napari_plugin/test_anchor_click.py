"""The Detect widget's anchor by a click: the element's name typed, its place clicked."""

import numpy as np
import pytest


def _detect_widget(viewer, demo):
    from oapcal.napari_plugin._widgets import DetectWidget

    viewer.add_image(demo["image"], **demo["kwargs"])
    w = DetectWidget(viewer)
    viewer.window.add_dock_widget(w, name="Detect")
    return w


def test_a_click_gives_the_named_element_its_place(viewer, demo):
    w = _detect_widget(viewer, demo)
    w.anchor.value = "G4E2"
    assert w.anchor_text() == "G4E2"  # no click yet: the name alone
    layer = w.pick_anchor()
    assert layer.name == "anchor" and layer.mode == "add" and viewer.layers.selection.active is layer
    x, y = dict(zip(demo["ids"], demo["xy_d"]))["G4E2H1C0"]
    layer.add(np.array([[y, x]]))  # napari: row, column
    assert w.anchor_text() == f"G4E2@{x:.0f},{y:.0f}"
    layer.add(np.array([[y + 10, x + 20]]))  # the last click counts
    assert w.anchor_text() == f"G4E2@{x + 20:.0f},{y + 10:.0f}"
    # a place typed, or several elements, are taken as typed
    w.anchor.value = "G4E2@5,6"
    assert w.anchor_text() == "G4E2@5,6"
    w.anchor.value = "G4E2 G5E1"
    assert w.anchor_text() == "G4E2 G5E1"
    assert w.pick_anchor() is layer  # the same layer again, not a second one
    assert [lay.name for lay in viewer.layers].count("anchor") == 1


@pytest.mark.slow  # a whole detection (the typed anchor's: tests/napari_plugin/test_widgets.py)
def test_detect_with_a_clicked_anchor_names_the_corners(viewer, demo, wait):
    w = _detect_widget(viewer, demo)
    truth = dict(zip(demo["ids"], demo["xy_d"]))
    x, y = truth["G4E2H1C0"]
    w.pick_anchor().add(np.array([[y, x]]))
    w.anchor.value = "G4E2"
    w.run()
    wait(w)
    assert w.last_error is None, w.status
    dist = viewer.layers["distorted"]
    err = np.hypot(*(dist.data[:, ::-1] - np.array([truth[i] for i in dist.features["id"]])).T)
    assert len(err) >= 0.8 * 288 and err.max() < 0.5
