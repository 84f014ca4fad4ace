"""The plugin's reader opens BigWarp and VIA landmark files and plain zarr arrays, and
napari opens oapcal's JSON files without being told the plugin (only oapcal reads ``*.json``)."""

import numpy as np
import pytest

import oapcal
from oapcal.io.landmarks import read_landmark_pairs
from oapcal.napari_plugin._io import napari_get_reader
from paths import REAL

LANDMARKS = REAL / "landmarks"
needs_landmarks = pytest.mark.skipif(
    not (LANDMARKS / "bigwarp" / "bigwarp_2d_blobs.csv").is_file(),
    reason="../shared/real/landmarks (the real landmark files) is not present",
)

BIGWARP = '"Pt-0","true","10.5","20.5","11.0","19.0"\n"Pt-1","true","100.5","20.5","99.0","22.0"\n' \
          '"Pt-2","false","5.0","5.0","6.0","6.0"\n"Pt-3","true","50.5","80.5","52.0","79.0"\n'  # fmt: skip


def _layers(path):
    reader = napari_get_reader(str(path))
    assert reader is not None, path
    return {kwargs["name"]: (data, kwargs) for data, kwargs, _ in reader(str(path))}


def test_bigwarp_csv_opens_as_distorted_and_reference_layers(tmp_path):
    path = tmp_path / "landmarks.csv"
    path.write_text(BIGWARP)
    layers = _layers(path)
    pairs = read_landmark_pairs(path, check_geometry=False)  # the library's reading of the file
    assert list(pairs.ids) == ["Pt-0", "Pt-1", "Pt-3"]  # the disabled row is left out
    d, r = layers["distorted"], layers["reference"]
    np.testing.assert_array_equal(d[0][:, ::-1], pairs.xy_d)  # napari rows, columns
    np.testing.assert_array_equal(r[0][:, ::-1], pairs.xy_u)
    assert list(d[1]["features"]["id"]) == ["Pt-0", "Pt-1", "Pt-3"]
    # BigWarp's moving image is the distorted one: its x column comes first
    assert d[0][0, 1] == pytest.approx(pairs.xy_d[0, 0]) and pairs.xy_d[0, 0] != pairs.xy_u[0, 0]


@needs_landmarks
def test_real_bigwarp_and_via_files_open():
    layers = _layers(LANDMARKS / "bigwarp" / "bigwarp_2d_blobs.csv")
    assert set(layers) == {"distorted", "reference"} and len(layers["distorted"][0]) == 5
    from oapcal.io.landmarks.via import point_images, read_via

    for name in ("via1_mixed_points.csv", "via1_mixed_points.json", "via2_export_points_map.csv"):
        path = LANDMARKS / "via" / name
        layers = _layers(path)
        images = point_images(path)
        assert list(layers) == [f"{path.stem}: {im}" for im in images]
        for im in images:
            marks = read_via(path, im)
            data = layers[f"{path.stem}: {im}"][0]
            np.testing.assert_array_equal(data[:, ::-1], [(m.x, m.y) for m in marks.landmarks])
    # 63 labelled images: the first 16 as layers
    assert len(_layers(LANDMARKS / "via" / "via2_export_points_crowd.json")) == 16
    # a napari points CSV is napari's own reader's
    assert napari_get_reader(str(LANDMARKS / "napari" / "napari_points_3d_cells.csv")) is None


def test_other_json_and_csv_are_left_to_other_readers(tmp_path):
    (tmp_path / "a.json").write_text('{"hello": 1}')
    (tmp_path / "b.csv").write_text("a,b\n1,2\n")
    assert napari_get_reader(str(tmp_path / "a.json")) is None
    assert napari_get_reader(str(tmp_path / "b.csv")) is None


def test_plain_zarr_array_opens_lazily(tmp_path):
    zarr = pytest.importorskip("zarr", reason="zarr comes with the 'dask' extra")
    frames = np.random.default_rng(2).integers(0, 4000, (3, 40, 50), dtype=np.uint16)
    z = zarr.create_array(
        str(tmp_path / "c.zarr"), shape=frames.shape, chunks=(1, 40, 50), dtype=frames.dtype
    )
    z[:] = frames
    ((data, kwargs),) = _layers(tmp_path / "c.zarr").values()
    assert kwargs["name"] == "c" and type(data).__module__.startswith("dask")
    np.testing.assert_array_equal(np.asarray(data), frames)
    assert napari_get_reader(str(tmp_path)) is None  # a folder that is not zarr


def test_napari_opens_oapcal_json_without_naming_the_plugin(viewer, demo, tmp_path):
    cal = oapcal.calibrate(demo["xy_u"], demo["xy_d"], "paper", image_size=(640, 480))
    oapcal.save_calibration(cal, tmp_path / "c.json")
    layers = viewer.open(str(tmp_path / "c.json"), plugin=None)  # napari chooses the reader
    assert [layer.name for layer in layers] == ["c: distortion (px)", "c: distortion field", "c: hull"]
    # File > Open and drag and drop go through the Qt viewer's open, which asks only when
    # several readers claim a file
    viewer.layers.clear()
    viewer.window._qt_viewer._qt_open([str(tmp_path / "c.json")], stack=False)
    assert "c: distortion field" in [layer.name for layer in viewer.layers]
