"""Video in and out (files written by cv2.VideoWriter, read back by cv2.VideoCapture), OME-TIFF
output (read back by tifffile's OME parser) and OME-Zarr output (read back by zarr, and by
ome-zarr's reader where installed), through ``oapcal correct``'s library form and command.

Expected frames are the library's ``correct_image`` of each input frame as OpenCV or tifffile
decodes the input: the file formats under test must carry them unchanged (lossless codecs)."""

import json
import tracemalloc
import xml.etree.ElementTree as ET

import cv2
import numpy as np
import pytest
import tifffile

from oapcal.batch.stack import correct_stack
from oapcal.calibration import calibrate
from oapcal.imaging.remap import correct_image, correction_map
from oapcal.io.calibration import load_calibration, save_calibration
from oapcal.synthetic import synthetic_pairs

W, H = 96, 72
UM = 2.5


@pytest.fixture(scope="module")
def cal(tmp_path_factory):
    data = synthetic_pairs(n_x=8, n_y=6, seed=1)
    # the synthetic grid spans a 640 x 480 camera; scale it onto these small frames
    s = np.array([W / 640, H / 480])
    c = calibrate(data.xy_u * s, data.xy_d * s, "paper", um_per_px=UM, image_size=(W, H))
    path = tmp_path_factory.mktemp("cal") / "calib.json"
    save_calibration(c, path)
    return load_calibration(path), path


def _frames(n, colour=True, seed=0):
    rng = np.random.default_rng(seed)
    shape = (H, W, 3) if colour else (H, W)
    # smooth content (a codec's best case is not needed: FFV1 is lossless), plus noise
    yy, xx = np.mgrid[0:H, 0:W]
    base = 127 + 100 * np.sin(xx / 7.0) * np.cos(yy / 5.0)
    out = []
    for i in range(n):
        f = base[..., None] if colour else base
        f = np.broadcast_to(f + 10 * i, shape) + rng.normal(0, 8, shape)
        out.append(np.clip(f, 0, 255).astype(np.uint8))
    return out


def _write_video(path, frames, fourcc, fps=12.0):
    colour = frames[0].ndim == 3
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*fourcc), fps, (W, H), colour)
    assert writer.isOpened(), f"OpenCV cannot write {fourcc} here"
    for f in frames:
        writer.write(f)
    writer.release()


def _read_video(path):
    cap = cv2.VideoCapture(str(path))
    fps = cap.get(cv2.CAP_PROP_FPS)
    frames = []
    while True:
        ok, f = cap.read()
        if not ok:
            break
        frames.append(f)
    cap.release()
    return frames, fps


def _expected(cal, frames):
    cmap = correction_map(cal, (H, W))
    return np.stack([correct_image(f, cmap) for f in frames])


@pytest.mark.parametrize("fourcc", ["FFV1", "MJPG"])
def test_avi_in_avi_out(cal, tmp_path, fourcc):
    cal, _ = cal
    frames = _frames(9)
    _write_video(tmp_path / "run.avi", frames, fourcc)
    decoded, _ = _read_video(tmp_path / "run.avi")  # what the camera file holds (MJPG is lossy)
    report = correct_stack(cal, [tmp_path / "run.avi"], tmp_path / "out")
    assert report.ok and report.frames == 9, report.results
    got, fps = _read_video(tmp_path / "out" / "run.avi")
    assert fps == 12.0 and len(got) == 9
    expected = _expected(cal, decoded)
    np.testing.assert_array_equal(np.stack(got), expected)  # the output is FFV1: lossless
    assert np.abs(expected.astype(int) - np.stack(decoded)).max() > 20  # the correction moved pixels
    # a rerun skips it (the resume record holds for videos too)
    again = correct_stack(cal, [tmp_path / "run.avi"], tmp_path / "out")
    assert [r.status for r in again.results] == ["skipped"]


def test_mp4_in_mp4_out_is_lossy_but_close(cal, tmp_path):
    cal, _ = cal
    frames = _frames(6)
    _write_video(tmp_path / "run.mp4", frames, "mp4v")
    decoded, _ = _read_video(tmp_path / "run.mp4")
    report = correct_stack(cal, [tmp_path / "run.mp4"], tmp_path / "out")
    assert report.ok and report.frames == len(decoded) == 6, report.results
    got, _ = _read_video(tmp_path / "out" / "run.mp4")
    diff = np.abs(np.stack(got).astype(float) - _expected(cal, decoded))
    assert len(got) == 6 and diff.mean() < 6, diff.mean()  # mp4v re-encodes: close, not equal


def test_video_frames_stream(cal, tmp_path):
    """60 colour frames of 384 x 288 (19.9 MB decoded): the peak traced by Python's
    allocator stays a few frames' worth, never the stack."""
    cal, _ = cal
    big = calibrate(*(lambda d: (d.xy_u * 0.6, d.xy_d * 0.6))(synthetic_pairs(n_x=8, n_y=6, seed=1)), "paper")
    rng = np.random.default_rng(1)
    writer = cv2.VideoWriter(
        str(tmp_path / "long.avi"), cv2.VideoWriter_fourcc(*"FFV1"), 30, (384, 288), True
    )
    for _ in range(60):
        writer.write(rng.integers(0, 255, (288, 384, 3), dtype=np.uint8))
    writer.release()
    stack_bytes = 60 * 288 * 384 * 3
    tracemalloc.start()
    try:
        report = correct_stack(big, [tmp_path / "long.avi"], tmp_path / "out")
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert report.ok and report.frames == 60, report.results
    assert peak < stack_bytes / 6, (peak, stack_bytes)


def test_truncated_avi_is_refused(cal, tmp_path):
    cal, _ = cal
    _write_video(tmp_path / "cut.avi", _frames(20), "MJPG")
    data = (tmp_path / "cut.avi").read_bytes()
    (tmp_path / "cut.avi").write_bytes(data[: len(data) // 2])
    report = correct_stack(cal, [tmp_path / "cut.avi"], tmp_path / "out")
    (result,) = report.results
    assert result.status == "failed" and "truncated or corrupt" in result.message, result
    assert not (tmp_path / "out" / "cut.avi").exists()


def _ome_pixels(path):
    with tifffile.TiffFile(path) as tif:
        assert tif.is_ome
        root = ET.fromstring(tif.ome_metadata)
        data = tif.series[0].asarray()
        axes = tif.series[0].axes
    ns = {"ome": root.tag.split("}")[0].strip("{")}
    image = root.find("ome:Image", ns)
    return data, axes, image.find("ome:Pixels", ns).attrib, json.loads(image.find("ome:Description", ns).text)


def test_ome_tiff_output_from_a_tiff_stack(cal, tmp_path):
    cal, _ = cal
    stack = np.stack([f.astype(np.uint16) * 250 for f in _frames(5, colour=False)])
    tifffile.imwrite(tmp_path / "stack.tif", stack)
    report = correct_stack(cal, [tmp_path / "stack.tif"], tmp_path / "out", output_format="ome-tiff",
                           calibration_name="calib.json", um_per_px=1.25)  # fmt: skip
    assert report.ok, report.results
    data, axes, pixels, description = _ome_pixels(tmp_path / "out" / "stack.ome.tif")
    assert axes == "TYX" and data.dtype == np.uint16
    cmap = correction_map(cal, (H, W), um_per_px=1.25)
    np.testing.assert_array_equal(data, np.stack([correct_image(f, cmap) for f in stack]))
    assert (pixels["SizeT"], pixels["SizeX"], pixels["SizeY"]) == (
        "5",
        str(cmap.shape[1]),
        str(cmap.shape[0]),
    )
    assert float(pixels["PhysicalSizeX"]) == float(pixels["PhysicalSizeY"]) == 1.25
    assert pixels["PhysicalSizeXUnit"] == "\u00b5m"
    assert description["oapcal_calibration"] == "calib.json" and description["source"] == "stack.tif"
    assert description["calibration"]["model_family"] == "brown-conrady"
    assert description["calibration"]["free"] == list(cal.free)


def test_video_to_ome_tiff_keeps_the_colours(cal, tmp_path):
    cal, _ = cal
    frames = _frames(4)
    frames[0][:10, :10] = (255, 0, 0)  # BGR: blue in OpenCV's order
    _write_video(tmp_path / "run.avi", frames, "FFV1")
    report = correct_stack(cal, [tmp_path / "run.avi"], tmp_path / "out", output_format="ome-tiff")
    assert report.ok, report.results
    data, axes, pixels, _ = _ome_pixels(tmp_path / "out" / "run.ome.tif")
    assert axes == "TYXS" and pixels["SizeC"] == "3"
    np.testing.assert_array_equal(data[..., ::-1], _expected(cal, frames))  # stored RGB


def test_ome_tiff_input_keeps_its_format(cal, tmp_path, run_cli):
    _, path = cal
    stack = np.stack(_frames(3, colour=False))
    tifffile.imwrite(tmp_path / "cells.ome.tif", stack, ome=True, metadata={"axes": "TYX"})
    code, _, err = run_cli("correct", path, tmp_path / "cells.ome.tif", "--out-dir", tmp_path / "out")
    assert code == 0, err
    data, axes, pixels, description = _ome_pixels(tmp_path / "out" / "cells.ome.tif")
    assert axes == "TYX" and float(pixels["PhysicalSizeX"]) == UM
    assert description["oapcal_calibration"] == "calib.json"


def test_video_through_the_command(cal, tmp_path, run_cli):
    cal, path = cal
    frames = _frames(5)
    _write_video(tmp_path / "movie.avi", frames, "FFV1")
    code, out, err = run_cli("correct", path, tmp_path / "movie.avi", "--out-dir", tmp_path / "out")
    assert code == 0, err
    assert "1 corrected (5 frames)" in out
    got, _ = _read_video(tmp_path / "out" / "movie.avi")
    np.testing.assert_array_equal(np.stack(got), _expected(cal, frames))


def _check_ome_zarr(path, expected_tyxc, um):
    zarr = pytest.importorskip("zarr", reason="zarr comes with the 'dask' extra")
    group = zarr.open_group(str(path), mode="r")
    (ms,) = group.attrs["multiscales"]
    assert ms["version"] == "0.4"
    colour = expected_tyxc.ndim == 4
    assert [a["name"] for a in ms["axes"]] == (["t", "c", "y", "x"] if colour else ["t", "y", "x"])
    assert ms["axes"][-1] == {"name": "x", "type": "space", "unit": "micrometer"}
    (dataset,) = ms["datasets"]
    assert dataset["coordinateTransformations"] == [
        {"type": "scale", "scale": [1.0] * (3 + colour - 2) + [um, um]}
    ]
    stored = group[dataset["path"]][:]
    np.testing.assert_array_equal(np.moveaxis(stored, 1, -1) if colour else stored, expected_tyxc)
    assert ms["metadata"]["calibration"]["model_family"] == "brown-conrady"
    try:
        from ome_zarr.io import parse_url
        from ome_zarr.reader import Reader
    except ImportError:
        return "ome-zarr not installed"
    nodes = list(Reader(parse_url(str(path)))())
    assert nodes and np.array_equal(np.asarray(nodes[0].data[0]), stored)
    assert nodes[0].metadata["coordinateTransformations"][0] == dataset["coordinateTransformations"]
    return "ome-zarr read it"


def test_ome_zarr_output_streaming(cal, tmp_path):
    cal, _ = cal
    frames = _frames(4)
    _write_video(tmp_path / "run.avi", frames, "FFV1")
    report = correct_stack(cal, [tmp_path / "run.avi"], tmp_path / "out", output_format="ome-zarr")
    assert report.ok, report.results
    expected = _expected(cal, frames)[..., ::-1]  # stored RGB
    _check_ome_zarr(tmp_path / "out" / "run.ome.zarr", expected, UM)
    again = correct_stack(cal, [tmp_path / "run.avi"], tmp_path / "out", output_format="ome-zarr")
    assert [r.status for r in again.results] == ["skipped"]


def test_ome_zarr_output_and_input_with_dask(cal, tmp_path):
    pytest.importorskip("dask", reason="dask comes with the 'dask' extra")
    from oapcal.batch.distributed import DaskSettings, correct_stack_dask

    cal, _ = cal
    stack = np.stack([f.astype(np.uint16) * 200 for f in _frames(7, colour=False)])
    tifffile.imwrite(tmp_path / "s.tif", stack)
    settings = DaskSettings(output_format="ome-zarr", chunk_frames=3, scheduler="threads")
    result = correct_stack_dask(cal, tmp_path / "s.tif", tmp_path / "out", None, settings)
    assert result.frames == 7 and result.output.endswith("s.ome.zarr")
    expected = _expected(cal, stack)
    _check_ome_zarr(tmp_path / "out" / "s.ome.zarr", expected, UM)
    # an OME-Zarr is read as input (its multiscales' full-resolution array)
    to_tiff = DaskSettings(output_format="tiff", chunk_frames=4, scheduler="threads")
    back = correct_stack_dask(cal, tmp_path / "out" / "s.ome.zarr", tmp_path / "again", None, to_tiff)
    assert back.frames == 7
    again = tifffile.imread(tmp_path / "again" / "s.ome.tif")
    np.testing.assert_array_equal(again, _expected(cal, expected))
