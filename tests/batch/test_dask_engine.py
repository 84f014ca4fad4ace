"""Where ``--dask`` runs on one machine: streamed in this process by default (no local
cluster, a note says so), a LocalCluster when asked for (workers > 1, or engine="dask"),
Dask's scheduler as given otherwise; the output is the same every way."""

import tracemalloc

import numpy as np
import pytest
import tifffile

pytest.importorskip("distributed", reason="Dask comes with the 'dask' extra")
import distributed  # noqa: E402
import zarr  # noqa: E402

from imaging_helpers import known_calibration, remap_reference  # noqa: E402
from oapcal.batch.distributed import DaskSettings, correct_stack_dask, dask_note, streams_locally  # noqa: E402
from oapcal.errors import InputFileError  # noqa: E402
from oapcal.model import params_from_dict  # noqa: E402

SMALL = params_from_dict({"k1": 4e-6, "p1": -1e-4, "s3": 6e-4, "x_off": -128, "y_off": -128,
                          "c_x": 129, "c_y": 127, "m": 1.0})  # fmt: skip


@pytest.fixture
def clusters(monkeypatch):
    """Count the LocalClusters started (the real class still does the work)."""
    started = []
    real = distributed.LocalCluster

    def counting(*args, **kwargs):
        started.append(kwargs.get("n_workers"))
        return real(*args, **kwargs)

    monkeypatch.setattr(distributed, "LocalCluster", counting)
    return started


def _stack(tmp_path, n=12):
    stack = np.random.default_rng(2).integers(0, 4000, (n, 256, 256), dtype=np.uint16)
    tifffile.imwrite(tmp_path / "s.tif", stack)
    return stack


def _check(out, stack):
    z = zarr.open_array(str(out / "s.zarr"), mode="r")
    for i in range(len(stack)):
        np.testing.assert_array_equal(z[i], remap_reference(stack[i], SMALL))


def test_default_streams_in_this_process_with_a_note(tmp_path, clusters):
    cal = known_calibration(params=SMALL, image_size=(256, 256))
    stack = _stack(tmp_path)
    result = correct_stack_dask(
        cal, tmp_path / "s.tif", tmp_path / "o", settings=DaskSettings(chunk_frames=5)
    )
    assert clusters == [] and result.frames == 12 and result.chunks == 3
    assert result.note.startswith("streamed in this process")
    _check(tmp_path / "o", stack)


@pytest.mark.slow  # starts two local clusters; the engine's choice is tested in the default suite
def test_a_local_cluster_when_asked_for(tmp_path, clusters):
    cal = known_calibration(params=SMALL, image_size=(256, 256))
    stack = _stack(tmp_path)
    for out, settings in (("one", DaskSettings(chunk_frames=5, engine="dask")),
                          ("two", DaskSettings(chunk_frames=5, workers=2))):  # fmt: skip
        result = correct_stack_dask(cal, tmp_path / "s.tif", tmp_path / out, settings=settings)
        assert "slower than correcting without Dask" in result.note
        _check(tmp_path / out, stack)
    assert clusters == [1, 2]


def test_streaming_engine_memory_is_one_chunk(tmp_path):
    cal = known_calibration(params=SMALL, image_size=(256, 256))
    stack = _stack(tmp_path, 160)  # 21 MB, 40 chunks of 4 frames
    tifffile.imwrite(tmp_path / "warm.tif", stack[:8])
    for fmt in ("zarr", "tiff"):
        settings = DaskSettings(chunk_frames=4, output_format=fmt)
        correct_stack_dask(cal, tmp_path / "warm.tif", tmp_path / "warm", settings=settings)
        tracemalloc.start()
        result = correct_stack_dask(cal, tmp_path / "s.tif", tmp_path / "out", settings=settings)
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        assert result.frames == 160 and result.note.startswith("streamed")
        assert peak < stack.nbytes / 4, f"{fmt}: peak {peak / 1e6:.1f} MB for {stack.nbytes / 1e6:.1f} MB"
    _check(tmp_path / "out", stack)
    np.testing.assert_array_equal(
        tifffile.imread(tmp_path / "out" / "s.tif")[-1], remap_reference(stack[-1], SMALL)
    )


def test_engine_choice_and_notes():
    assert streams_locally(None, 1) and not streams_locally(None, 1, "dask")
    assert not streams_locally("threads", None) and not streams_locally("tcp://127.0.0.1:8786", None)
    assert "slower than correcting without Dask" in dask_note("threads", None)
    assert dask_note("tcp://127.0.0.1:8786", 4) == ""
    with pytest.raises(InputFileError, match="engine 'fast'"):
        streams_locally(None, None, "fast")


def test_zarr_outputs_are_blosc_lz4_with_bit_shuffle(tmp_path):
    """Every zarr oapcal writes (the streamed one, the Dask one, OME-Zarr) uses the fast
    Blosc LZ4 compression (io.ome.zarr_compressors), not zarr's slower default (Zstd)."""
    import json

    import numcodecs

    cal = known_calibration(params=SMALL, image_size=(256, 256))
    stack = _stack(tmp_path, 6)
    ways = {
        "streamed": DaskSettings(chunk_frames=3),
        "threads": DaskSettings(chunk_frames=3, scheduler="threads"),
        "ome": DaskSettings(chunk_frames=3, output_format="ome-zarr"),
    }
    for out, settings in ways.items():
        correct_stack_dask(cal, tmp_path / "s.tif", tmp_path / out, settings=settings)
    for out in ("streamed", "threads"):
        z = zarr.open_array(str(tmp_path / out / "s.zarr"), mode="r")
        (codec,) = z.compressors
        assert isinstance(codec, zarr.codecs.BloscCodec)
        assert codec.cname.value == "lz4" and codec.shuffle.value == "bitshuffle"
        _check(tmp_path / out, stack)
    meta = json.loads((tmp_path / "ome" / "s.ome.zarr" / "0" / ".zarray").read_text())
    assert meta["compressor"]["id"] == "blosc" and meta["compressor"]["cname"] == "lz4"
    assert meta["compressor"]["shuffle"] == numcodecs.Blosc.BITSHUFFLE
