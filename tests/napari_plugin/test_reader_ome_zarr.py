"""The plugin's reader opens the OME-Zarr that ``oapcal correct`` writes: the corrected
frames lazily, scaled in um, with the provenance; in a real viewer without naming the plugin."""

import numpy as np
import pytest
import tifffile

from imaging_helpers import known_calibration, remap_reference
from oapcal.batch.stack import correct_stack
from oapcal.model import params_from_dict

pytest.importorskip("zarr", reason="zarr comes with the 'dask' extra")

SMALL = params_from_dict({"k1": 4e-6, "p1": -1e-4, "s3": 6e-4, "x_off": -128, "y_off": -128,
                          "c_x": 129, "c_y": 127, "m": 1.0})  # fmt: skip


@pytest.fixture
def ome_zarr(tmp_path):
    cal = known_calibration(params=SMALL, image_size=(256, 256))
    stack = np.random.default_rng(4).integers(0, 4000, (5, 256, 256), dtype=np.uint16)
    tifffile.imwrite(tmp_path / "s.tif", stack)
    report = correct_stack(cal, [tmp_path / "s.tif"], tmp_path / "out", output_format="ome-zarr")
    assert report.ok, report.results
    expected = np.stack([remap_reference(f, SMALL) for f in stack])
    return tmp_path / "out" / "s.ome.zarr", expected, cal


def test_reader_gives_the_corrected_frames_with_their_scale(ome_zarr):
    from oapcal.napari_plugin._io import napari_get_reader

    path, expected, cal = ome_zarr
    reader = napari_get_reader(str(path))
    assert reader is not None
    ((data, kwargs, kind),) = reader(str(path))
    assert kind == "image" and kwargs["name"] == "s"
    np.testing.assert_array_equal(np.asarray(data), expected)
    assert kwargs["scale"] == (1.0, cal.um_per_px, cal.um_per_px)
    assert kwargs["metadata"]["oapcal"]["source"] == "s.tif" and kwargs["metadata"]["unit"] == "micrometer"
    assert napari_get_reader(str(path.parent)) is None  # a directory that is not OME-Zarr: other readers


def test_viewer_opens_it_without_naming_the_plugin(ome_zarr, viewer):
    path, expected, _ = ome_zarr
    layers = viewer.open(str(path))
    assert len(layers) == 1
    np.testing.assert_array_equal(np.asarray(layers[0].data), expected)


def test_napari_ome_zarr_opens_it_too(ome_zarr, viewer):
    """The ecosystem's own reader (the napari-ome-zarr plugin, in the test extra) reads the
    same frames and the physical pixel size from the NGFF metadata."""
    pytest.importorskip("napari_ome_zarr", reason="napari-ome-zarr comes with the 'test' extra")
    path, expected, cal = ome_zarr
    layers = viewer.open(str(path), plugin="napari-ome-zarr")
    assert len(layers) == 1
    layer = layers[0]
    data = layer.data[0] if layer.multiscale else layer.data
    np.testing.assert_array_equal(np.asarray(data), expected)
    assert tuple(layer.scale[-2:]) == pytest.approx((cal.um_per_px, cal.um_per_px))
