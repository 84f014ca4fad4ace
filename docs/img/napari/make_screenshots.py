"""Redraw the screenshots of docs/napari.md from a headless napari viewer.

    xvfb-run -a -s "-screen 0 1600x1200x24" env QT_QPA_PLATFORM=xcb \
        .venv/bin/python docs/img/napari/make_screenshots.py

(Qt's xcb platform on a virtual X display: Xvfb and the libraries from
scripts/ensure-qt-libs.sh.  Qt's offscreen platform, which the tests use, draws the widgets
but leaves the OpenGL canvas out of a window screenshot.)  Each step of the walkthrough is done as a
user would, through the plugin's widgets, and the window is saved after it.
"""

import sys
import time
from pathlib import Path

import numpy as np

OUT = Path(__file__).resolve().parent
SIZE = (1500, 950)


def wait(widget, app, timeout=300):
    t0 = time.time()
    while widget.busy and time.time() - t0 < timeout:
        app.processEvents()
        time.sleep(0.02)
    app.processEvents()
    if widget.last_error:
        sys.exit(f"{widget.step_name}: {widget.last_error}")


def shot(viewer, app, name, canvas=False):
    app.processEvents()
    viewer.screenshot(str(OUT / name), canvas_only=canvas, flash=False)
    print("wrote", OUT / name)


def main():
    import napari
    from qtpy.QtWidgets import QApplication

    from oapcal.napari_plugin._widgets import CorrectWidget, DetectWidget, FitWidget, LabelWidget

    viewer = napari.Viewer(show=True)
    app = QApplication.instance()
    viewer.window._qt_window.resize(*SIZE)

    # 1. open an image: the plugin's sample (File > Open Sample > oapcal)
    viewer.open_sample("oapcal", "demo")
    image = viewer.layers[0]
    detect = DetectWidget(viewer)
    dock = viewer.window.add_dock_widget(detect, name="Detect", area="right")
    shot(viewer, app, "1-open.png")

    # 2. detect (the scale given: 4.8 um per camera pixel)
    detect.um_per_px.value = 4.8
    detect.run()
    wait(detect, app)
    viewer.layers["reference"].visible = True
    viewer.layers["reference"].opacity = 0.5
    shot(viewer, app, "2-detect.png")

    # 3. where detection fails: label a few corners by hand, oapcal proposes the others
    viewer.window.remove_dock_widget(dock)
    for name in ("distorted", "reference"):
        viewer.layers.remove(name)
    label = LabelWidget(viewer)
    dock = viewer.window.add_dock_widget(label, name="Label by hand", area="right")
    truth = dict(zip(image.metadata["oapcal_truth"]["ids"], image.metadata["oapcal_truth"]["xy_d"]))
    hand = label.start_labelling()
    for corner in ("G4E2H0C0", "G4E6V2C2", "G5E1V0C0", "G5E6H2C2"):
        label.corner.value = corner
        hand.add(np.asarray(truth[corner])[::-1] + np.array([0.6, -0.4]))  # a hand click is not exact
    label.refine.value = False
    label.run()
    wait(label, app)
    viewer.layers["reference"].visible = False
    shot(viewer, app, "3-label.png")
    # fix a corner: the proposed corner farthest from its bar corner, dragged onto it
    dist = viewer.layers["distorted"]
    ids = list(dist.features["id"])
    off = [np.hypot(*(dist.data[k, ::-1] - truth[i])) if i in truth else 0 for k, i in enumerate(ids)]
    k = int(np.argmax(off))
    viewer.camera.center = tuple(dist.data[k])
    viewer.camera.zoom = 10
    dist.size = 1.2  # points are sized in image px: small ones when zoomed in
    viewer.layers.selection.active = dist
    dist.mode = "select"
    dist.selected_data = {k}
    shot(viewer, app, "3b-before.png", canvas=True)
    data = dist.data.copy()
    data[k] = np.asarray(truth[ids[k]])[::-1]
    dist.data = data
    dist.selected_data = {k}
    shot(viewer, app, "3c-after.png", canvas=True)
    print(f"moved {ids[k]} by {off[k]:.1f} px")
    dist.size = 5
    # then let detection refine everything at the pose the clicks give
    label.refine.value = True
    label.run()
    wait(label, app)
    viewer.reset_view()

    # 4. fit and inspect
    viewer.window.remove_dock_widget(dock)
    fit = FitWidget(viewer)
    dock = viewer.window.add_dock_widget(fit, name="Fit & inspect", area="right")
    fit.model.value = "paper"
    fit.run()
    wait(fit, app)
    viewer.layers["hand labels"].visible = False
    shot(viewer, app, "4-fit.png")
    worst = viewer.layers["worst landmarks"].data[0]
    viewer.camera.center = tuple(worst)
    viewer.camera.zoom = 5
    viewer.layers["distorted"].visible = False
    shot(viewer, app, "4b-residuals.png", canvas=True)
    viewer.reset_view()

    # 5. correct, uncertainty, hull; save the calibration
    viewer.window.remove_dock_widget(dock)
    correct = CorrectWidget(viewer)
    viewer.window.add_dock_widget(correct, name="Correct", area="right")
    correct.image.value = image
    correct.run()
    wait(correct, app)
    for layer in viewer.layers:
        layer.visible = layer.name in (f"{image.name} corrected", "uncertainty (um)", "calibration hull")
    shot(viewer, app, "5-correct.png")
    correct.save_path.value = str(OUT / "calibration.json")
    correct.save()
    print(correct.status)
    (OUT / "calibration.json").unlink()
    viewer.close()


if __name__ == "__main__":
    main()
