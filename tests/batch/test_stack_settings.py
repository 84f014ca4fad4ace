"""``correct_stack`` takes its options as a :class:`StackSettings` record or as the
keywords it always took; both give the same outputs."""

import dataclasses
import inspect

import numpy as np
import pytest
import tifffile

from imaging_helpers import known_calibration, remap_reference
from oapcal.batch.stack import StackSettings, correct_stack

#: The keywords of correct_stack before the record (its signature at ff4a879), with defaults.
OLD_KEYWORDS = {
    "interp": "linear", "border": 0, "workers": 1, "extent": "input", "um_per_px": None,
    "out_size": None, "cmap": None, "allow_size_mismatch": False, "max_pixels": 2**28,
    "overwrite": False, "calibration_name": None, "protect": (), "reserved": (), "progress": None,
    "output_format": None, "max_error_px": None, "predicted_errors": None,
}  # fmt: skip


def test_the_record_has_every_old_keyword_with_its_default():
    fields = {f.name: f.default for f in dataclasses.fields(StackSettings)}
    assert fields == OLD_KEYWORDS
    assert list(inspect.signature(correct_stack).parameters)[:4] == [
        "calibration",
        "inputs",
        "out_dir",
        "settings",
    ]


@pytest.fixture
def stack(tmp_path):
    frames = np.random.default_rng(3).integers(0, 255, (3, 480, 640), dtype=np.uint8)
    tifffile.imwrite(tmp_path / "s.tif", frames, photometric="minisblack")
    return tmp_path / "s.tif", frames


@pytest.mark.parametrize("options", [{"calibration_name": "k"}, {"interp": "nearest", "border": 7}])
def test_record_and_keywords_give_the_same_output(tmp_path, stack, options):
    path, frames = stack
    cal = known_calibration()
    by_keywords = correct_stack(cal, [path], tmp_path / "a", **options)
    by_record = correct_stack(cal, [path], tmp_path / "b", StackSettings(**options))
    assert [r.status for r in by_keywords.results] == [r.status for r in by_record.results] == ["corrected"]
    a, b = tifffile.imread(tmp_path / "a" / "s.tif"), tifffile.imread(tmp_path / "b" / "s.tif")
    np.testing.assert_array_equal(a, b)
    if "interp" not in options:  # linear, border 0: the reference remap
        np.testing.assert_array_equal(a[1], remap_reference(frames[1], cal.params))
    else:
        assert not np.array_equal(a[1], remap_reference(frames[1], cal.params))
    assert by_keywords.geometries == by_record.geometries


def test_keywords_replace_the_records_fields(tmp_path, stack):
    path, _ = stack
    cal = known_calibration()
    correct_stack(cal, [path], tmp_path / "o", StackSettings(interp="cubic"))
    again = correct_stack(cal, [path], tmp_path / "o", StackSettings(interp="cubic"))
    assert again.results[0].status == "skipped"  # complete, same settings
    redo = correct_stack(cal, [path], tmp_path / "o", StackSettings(interp="cubic"), overwrite=True)
    assert redo.results[0].status == "corrected"
    other = correct_stack(cal, [path], tmp_path / "o", StackSettings(interp="cubic"), interp="linear")
    assert other.results[0].status == "corrected"  # another interpolation: not the recorded output


def test_an_unknown_keyword_is_a_type_error(tmp_path, stack):
    path, _ = stack
    with pytest.raises(TypeError, match="interpolation"):
        correct_stack(known_calibration(), [path], tmp_path / "o", interpolation="cubic")
    assert not (tmp_path / "o").exists()
