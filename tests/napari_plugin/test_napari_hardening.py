"""Hostile inputs to the plugin (issue 24): 'Save calibration' never writes over a file open in
the viewer nor under another suffix than .json; the reader never opens a file that is not a
regular file."""

import os

import numpy as np
import pytest

import oapcal
from oapcal.synthetic import synthetic_pairs


@pytest.fixture
def saved_calibration(tmp_path):
    data = synthetic_pairs(seed=4)
    cal = oapcal.calibrate(data.xy_u, data.xy_d, "paper", image_size=(640, 480))
    path = tmp_path / "in.json"
    oapcal.save_calibration(cal, path)
    return path


def test_save_calibration_refuses_layer_sources_and_other_suffixes(viewer, saved_calibration, tmp_path):
    import tifffile
    from napari.layers._source import layer_source

    from oapcal.napari_plugin._widgets import CorrectWidget

    image = tmp_path / "camera.tif"
    tifffile.imwrite(image, np.arange(64 * 80, dtype=np.uint16).reshape(64, 80))
    viewer.open(str(image))
    with layer_source(path=str(tmp_path / "scan.json")):  # an image file misnamed .json
        viewer.add_image(np.zeros((8, 8)), name="scan")
    (tmp_path / "scan.json").write_bytes(b"not json, an image")
    (tmp_path / "link.json").symlink_to(image)  # a link to the open image, named .json
    os.link(saved_calibration, tmp_path / "hard.json")  # the calibration's file, by another name
    before = {p: p.read_bytes() for p in tmp_path.iterdir() if p.is_file()}

    w = CorrectWidget(viewer)
    viewer.window.add_dock_widget(w, name="Correct")
    w.file.value = str(saved_calibration)
    refused = {
        str(image): "ending in .json",
        str(tmp_path / "new.tif"): "ending in .json",
        str(tmp_path / "new"): "ending in .json",
        str(tmp_path / "new.json.csv"): "ending in .json",
        str(tmp_path / "link.json"): "source of the layer 'camera'",
        str(tmp_path / "sub" / ".." / "scan.json"): "source of the layer 'scan'",
        str(tmp_path / "hard.json"): "read or fitted from",
        str(saved_calibration): "read or fitted from",
    }
    for path, why in refused.items():
        w.save_path.value = path
        w.last_error = None
        w.save()
        assert w.last_error is not None and why in w.last_error, (path, w.last_error)
    assert {p: p.read_bytes() for p in tmp_path.iterdir() if p.is_file()} == before
    assert not (tmp_path / "new.tif").exists() and not (tmp_path / "new").exists()

    for name in ("out.json", "OUT.JSON"):  # any case of .json, at a new name
        w.save_path.value = str(tmp_path / name)
        w.last_error = None
        w.save()
        assert w.last_error is None, w.last_error
        expected = oapcal.load_calibration(saved_calibration).free
        assert oapcal.load_calibration(tmp_path / name).free == expected


def test_the_reader_declines_fifos_devices_and_directories_without_opening_them(tmp_path):
    import threading

    from oapcal.napari_plugin._io import napari_get_reader

    fifo = tmp_path / "points.csv"
    os.mkfifo(fifo)
    (tmp_path / "calib.json").symlink_to(fifo)
    (tmp_path / "zero.csv").symlink_to("/dev/zero")
    (tmp_path / "folder.tsv").mkdir()
    names = ["points.csv", "calib.json", "zero.csv", "folder.tsv"]
    out = {}
    paths = [str(tmp_path / n) for n in names]
    worker = threading.Thread(target=lambda: out.update(r=[napari_get_reader(p) for p in paths]), daemon=True)
    worker.start()
    worker.join(60)
    if worker.is_alive():  # blocked on the FIFO: release it, then fail
        os.close(os.open(fifo, os.O_WRONLY | os.O_NONBLOCK))
        pytest.fail("the reader blocked on a FIFO")
    assert out["r"] == [None] * len(names)


def test_the_detect_widget_says_what_is_wrong_with_a_group_text(viewer):
    from oapcal.napari_plugin._widgets import DetectWidget

    viewer.add_image(np.zeros((40, 50), np.uint8), name="img")
    w = DetectWidget(viewer)
    viewer.window.add_dock_widget(w, name="Detect")
    for text, why in (("4-99999999999999999999", "-2 to 9"), ("9-3", "reversed")):
        w.groups.value = text
        w.run()
        assert not w.busy and w.last_error is not None and why in w.last_error, w.last_error
        assert "OverflowError" not in w.last_error


def test_the_detect_widget_says_what_is_wrong_with_an_anchor_text(viewer):
    from oapcal.napari_plugin._widgets import DetectWidget

    viewer.add_image(np.zeros((40, 50), np.uint8), name="img")
    w = DetectWidget(viewer)
    viewer.window.add_dock_widget(w, name="Detect")
    for text, why in (("G4E9", "not an element name"), ("G4E2 G4E2@3,4", "named twice")):
        w.anchor.value = text
        w.run()
        assert not w.busy and w.last_error is not None and why in w.last_error, w.last_error
