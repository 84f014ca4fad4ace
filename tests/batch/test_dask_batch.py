"""The library form of ``oapcal correct --dask``: a planned batch of stacks corrected on one
scheduler, per-stack failures as results naming the file, the note said once."""

import numpy as np
import pytest
import tifffile

pytest.importorskip("distributed", reason="Dask comes with the 'dask' extra")
import zarr  # noqa: E402

from imaging_helpers import known_calibration, remap_reference  # noqa: E402
from oapcal.batch.distributed import DaskSettings, correct_stacks_dask  # noqa: E402
from oapcal.batch.stack import plan_batch  # noqa: E402
from oapcal.errors import OutputError  # noqa: E402
from oapcal.model import params_from_dict  # noqa: E402

SMALL = params_from_dict({"k1": 4e-6, "p1": -1e-4, "s3": 6e-4, "x_off": -64, "y_off": -64,
                          "c_x": 65, "c_y": 63, "m": 1.0})  # fmt: skip


def test_a_batch_of_stacks_reports_each_and_notes_once(tmp_path):
    rng = np.random.default_rng(4)
    stacks = {name: rng.integers(0, 4000, (n, 128, 128), dtype=np.uint16) for name, n in (("a", 3), ("b", 4))}
    for name, stack in stacks.items():
        tifffile.imwrite(tmp_path / f"{name}.tif", stack, photometric="minisblack")
    tifffile.imwrite(tmp_path / "small.tif", np.zeros((2, 64, 64), np.uint16), photometric="minisblack")
    cal = known_calibration(params=SMALL, image_size=(128, 128))
    inputs = [tmp_path / "a.tif", tmp_path / "missing.tif", tmp_path / "small.tif", tmp_path / "b.tif"]
    plan = plan_batch(inputs, tmp_path / "o", dask_format="zarr")
    assert [p.name for p in plan.files] == ["a.tif", "small.tif", "b.tif"]
    assert [p.name for p in plan.outputs] == ["a.zarr", "small.zarr", "b.zarr"]
    report = correct_stacks_dask(cal, plan, tmp_path / "o", None, DaskSettings(chunk_frames=2))
    # the plan's failure first, then the stacks in order
    assert [(r.input.rsplit("/", 1)[-1], r.status, r.reason) for r in report.results] == [
        ("missing.tif", "failed", "not_found"), ("a.tif", "corrected", ""),
        ("small.tif", "failed", "refused"), ("b.tif", "corrected", ""),
    ]  # fmt: skip
    small = report.results[2]
    assert small.message.startswith(f"{tmp_path / 'small.tif'}: frames are 64x64 px but the calibration")
    assert small.param == "allow_size_mismatch" and small.output is None
    assert report.summary() == "2 corrected (7 frames), 0 skipped (complete output exists), 2 failed"
    assert len(report.notes) == 1 and report.notes[0].startswith("streamed in this process")
    for name, stack in stacks.items():
        z = zarr.open_array(str(tmp_path / "o" / f"{name}.zarr"), mode="r")
        for i in range(len(stack)):
            np.testing.assert_array_equal(z[i], remap_reference(stack[i], SMALL))
    again = correct_stacks_dask(cal, plan, tmp_path / "o", None, DaskSettings(chunk_frames=2))
    assert [r.status for r in again.results] == ["failed", "skipped", "failed", "skipped"]
    assert again.notes == ()  # nothing ran


def test_the_plan_refuses_two_inputs_with_one_output(tmp_path):
    for d in ("x", "y"):
        (tmp_path / d).mkdir()
        tifffile.imwrite(tmp_path / d / "s.tif", np.zeros((1, 8, 8), np.uint8))
    with pytest.raises(OutputError, match="would be written to the same output"):
        plan_batch([tmp_path / "x" / "s.tif", tmp_path / "y" / "s.tif"], tmp_path / "o", dask_format="tiff")
