"""The plugin's reader and writer, its manifest, and that ``import oapcal`` stays free of napari."""

import numpy as np
import pytest

import oapcal
from fresh_python import run_fresh
from oapcal.errors import DataError
from oapcal.synthetic import synthetic_pairs


@pytest.fixture
def pairs_csv(tmp_path):
    data = synthetic_pairs(seed=3)
    ids = [f"P{i:03d}" for i in range(len(data.xy_u))]
    path = tmp_path / "points.csv"
    oapcal.write_point_pairs(path, data.xy_u, data.xy_d, ids=ids)
    return path, data, ids


def test_point_pairs_open_as_two_points_layers_with_ids(pairs_csv):
    from oapcal.napari_plugin._io import napari_get_reader

    path, data, ids = pairs_csv
    reader = napari_get_reader(str(path))
    assert reader is not None
    (d_data, d_kw, d_kind), (r_data, r_kw, r_kind) = reader(str(path))
    assert (d_kind, r_kind) == ("points", "points")
    assert d_kw["name"] == "distorted" and r_kw["name"] == "reference"
    # napari is (row, col) = (y, x)
    np.testing.assert_array_equal(d_data[:, 1], data.xy_d[:, 0])
    np.testing.assert_array_equal(d_data[:, 0], data.xy_d[:, 1])
    np.testing.assert_array_equal(r_data[:, ::-1], data.xy_u)
    assert list(d_kw["features"]["id"]) == ids and list(r_kw["features"]["id"]) == ids


def test_calibration_opens_as_field_magnitude_and_hull(tmp_path):
    from oapcal.napari_plugin._io import napari_get_reader

    data = synthetic_pairs(seed=4)
    cal = oapcal.calibrate(data.xy_u, data.xy_d, "paper", image_size=(640, 480))
    path = tmp_path / "calib.json"
    oapcal.save_calibration(cal, path)
    layers = napari_get_reader(str(path))(str(path))
    kinds = {kind: (d, kw) for d, kw, kind in layers}
    assert set(kinds) == {"image", "vectors", "shapes"}
    magnitude, kw = kinds["image"]
    assert magnitude.shape == (480, 640)
    loaded = oapcal.load_calibration(path)
    for x, y in [(0, 0), (639, 479), (320, 17), (5, 400)]:
        expected = np.hypot(*(oapcal.distort(np.array([[x, y]], float), loaded.params)[0] - (x, y)))
        assert magnitude[y, x] == pytest.approx(expected, rel=1e-5, abs=1e-4)
    assert magnitude.max() > 5  # the synthetic relay distorts by tens of px
    vectors, _ = kinds["vectors"]
    start_xy = vectors[:, 0, ::-1]
    np.testing.assert_allclose(
        vectors[:, 1, ::-1], oapcal.distort(start_xy, loaded.params) - start_xy, atol=1e-9
    )
    (hull,), _ = kinds["shapes"]
    np.testing.assert_allclose(hull[:, ::-1], loaded.hull)
    assert kw["metadata"]["oapcal_calibration"].free == loaded.free


def test_a_large_calibration_frame_is_sampled(monkeypatch):
    from oapcal.napari_plugin import _layers

    data = synthetic_pairs(seed=4)
    cal = oapcal.calibrate(data.xy_u, data.xy_d, "paper", image_size=(640, 480))
    monkeypatch.setattr(_layers, "MAX_FIELD_PIXELS", 34_200)  # 307,200 px need a step of 3
    magnitude, kw, _ = _layers.calibration_layers(cal)[0]
    assert magnitude.shape == (160, 214) and kw["scale"] == (3, 3)
    x, y = 3 * 100, 3 * 50
    expected = np.hypot(*(oapcal.distort(np.array([[x, y]], float), cal.params)[0] - (x, y)))
    assert magnitude[50, 100] == pytest.approx(expected, rel=1e-5)


def test_a_broken_calibration_file_is_refused_with_oapcals_message(tmp_path):
    from oapcal.napari_plugin._io import napari_get_reader

    path = tmp_path / "broken.json"
    path.write_text('{"format": "oapcal-calibration", "version": 1, "free": ["k1"]}')
    reader = napari_get_reader(str(path))
    assert reader is not None
    with pytest.raises(oapcal.InputFileError, match="broken.json"):
        reader(str(path))


def test_other_files_are_left_to_other_readers(tmp_path):
    from oapcal.napari_plugin._io import napari_get_reader

    (tmp_path / "other.json").write_text('{"format": "something else"}')
    (tmp_path / "other.csv").write_text("x,y\n1,2\n")
    (tmp_path / "image.png").write_bytes(b"\x89PNG")
    for name in ("other.json", "other.csv", "image.png"):
        assert napari_get_reader(str(tmp_path / name)) is None, name
    assert napari_get_reader([str(tmp_path / "other.json"), str(tmp_path / "other.csv")]) is None


def test_writer_pairs_the_layers_by_id(tmp_path):
    from oapcal.napari_plugin._io import write_point_pairs
    from oapcal.napari_plugin._layers import points_layers

    data = synthetic_pairs(seed=5)
    ids = [f"C{i}" for i in range(len(data.xy_u))]
    dist, ref = points_layers(data.xy_u, data.xy_d, ids)
    # the user deleted the distorted point C3 and the reference layer is in another order
    keep = [k for k in range(len(ids)) if ids[k] != "C3"]
    dist = (dist[0][keep], {**dist[1], "features": {"id": np.array(ids, object)[keep]}}, "points")
    order = np.random.default_rng(0).permutation(len(ids))
    ref = (ref[0][order], {**ref[1], "features": {"id": np.array(ids, object)[order]}}, "points")
    out = tmp_path / "saved.csv"
    assert write_point_pairs(str(out), [ref, dist]) == [str(out)]
    back = oapcal.read_points(out)
    assert list(back.ids) == [ids[k] for k in keep]
    np.testing.assert_array_equal(back.xy_u, data.xy_u[keep])
    np.testing.assert_array_equal(back.xy_d, data.xy_d[keep])


def test_writer_needs_one_distorted_and_one_reference_layer(tmp_path):
    from oapcal.napari_plugin._io import write_point_pairs
    from oapcal.napari_plugin._layers import points_layers

    data = synthetic_pairs(seed=5)
    dist, _ref = points_layers(data.xy_u, data.xy_d)
    with pytest.raises(DataError, match="one of distorted and one of reference"):
        write_point_pairs(str(tmp_path / "x.csv"), [dist, dist])
    assert not (tmp_path / "x.csv").exists()


def test_the_manifest_is_found_by_napari():
    from npe2 import PluginManager

    pm = PluginManager.instance()
    pm.discover()
    manifest = pm.get_manifest("oapcal")
    widgets = {w.display_name for w in manifest.contributions.widgets}
    assert widgets == {"Detect", "Label by hand", "Fit & inspect", "Correct"}
    assert [w.layer_types for w in manifest.contributions.writers] == [["points{2}"]]
    assert manifest.contributions.readers[0].command == "oapcal.get_reader"
    assert [(s.key, s.command) for s in manifest.contributions.sample_data] == [("demo", "oapcal.demo_image")]
    for command in manifest.contributions.commands:
        module, _, attr = command.python_name.partition(":")
        assert callable(getattr(__import__(module, fromlist=[attr]), attr)), command.python_name


def test_import_oapcal_loads_neither_napari_nor_qt():
    gui = ("napari", "magicgui", "qtpy", "PyQt6", "PyQt5", "vispy")
    _, loaded = run_fresh("import oapcal; oapcal.calibrate")
    assert sorted(loaded & set(gui)) == []
