"""The plugin's widgets fit a 1080 px screen: every widget scrolls inside its dock, so the
window does not grow with the docked widgets (it grew to 1,255 px with three docked)."""

import pytest

#: A 1080 px screen less the task bar and title bar: what a window may take.
SCREEN_PX = 1080 - 80


@pytest.mark.parametrize("names", [("Detect", "Label by hand", "Fit & inspect", "Correct")])
def test_docked_widgets_fit_a_1080_px_screen(viewer, qtbot, names):
    from oapcal.napari_plugin import _widgets as W

    classes = {"Detect": W.DetectWidget, "Label by hand": W.LabelWidget, "Fit & inspect": W.FitWidget,
               "Correct": W.CorrectWidget}  # fmt: skip
    window = viewer.window._qt_window
    window.resize(1400, 900)
    window.show()
    widgets = []
    for name in names:
        w = classes[name](viewer)
        viewer.window.add_dock_widget(w, name=name, area="right")
        widgets.append(w)
        qtbot.wait(50)
    assert window.minimumSizeHint().height() <= SCREEN_PX
    assert window.minimumSize().height() <= SCREEN_PX
    window.resize(1400, 900)
    qtbot.wait(100)
    assert window.height() <= SCREEN_PX, window.height()
    for w in widgets:  # each can still show all of its fields (by scrolling)
        assert w.native.minimumSizeHint().height() < 400


def test_a_docked_widget_scrolls_only_vertically(viewer):
    from qtpy.QtCore import Qt

    from oapcal.napari_plugin._widgets import MAX_WIDTH_PX, FitWidget

    w = FitWidget(viewer)
    viewer.window.add_dock_widget(w, name="Fit & inspect")
    assert w.native.horizontalScrollBarPolicy() == Qt.ScrollBarPolicy.ScrollBarAlwaysOff
    assert w.native.widget().maximumWidth() < MAX_WIDTH_PX
    assert w.native.minimumWidth() == w.native.maximumWidth() == MAX_WIDTH_PX  # nothing clipped
