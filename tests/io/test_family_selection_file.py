"""The family-selection file (``oapcal select --families ... --json``) round trip, and the
report reading it."""

import json
import math

import pytest

from oapcal.errors import InputFileError
from oapcal.families import Candidate, FamilySelection
from oapcal.io.results import load_any_selection, save_family_selection
from oapcal.select import Selection


def _selection():
    free = ("scale", "rotation", "shift_x", "shift_y", "d1")
    a = Candidate("relay", "relay:d1", free, 5, -100.0, 0.0, 0.05, True, "", 0.051, 0)
    b = Candidate("brown-conrady", "k1,m", ("k1", "m"), 2, -20.0, 80.0, 0.4, True, "", None, 0)
    c = Candidate(
        "relay", "relay:all", ("scale",), 1, math.nan, math.nan, math.nan, False, "not identifiable"
    )
    return FamilySelection(120, 5, (a, b, c), a)


def test_round_trip(tmp_path):
    sel = _selection()
    path = tmp_path / "fam.json"
    save_family_selection(sel, path)
    data = json.loads(path.read_text())
    assert data["format"] == "oapcal-family-selection" and data["version"] == 1
    assert data["recommended"] == "relay:d1" and data["candidates"][2]["aicc"] is None
    back = load_any_selection(path)
    assert isinstance(back, FamilySelection) and back.recommended.spec == "relay:d1"
    assert back.candidates[:2] == sel.candidates[:2]
    assert math.isnan(back.candidates[2].aicc) and back.candidates[2].reason == "not identifiable"


def test_a_plain_selection_file_still_loads_as_a_selection(tmp_path):
    from oapcal.io.results import save_selection
    from oapcal.select import select_models
    from oapcal.synthetic import synthetic_pairs

    data = synthetic_pairs(seed=0)
    path = tmp_path / "sel.json"
    save_selection(select_models(data.xy_u, data.xy_d, masks=[[True] * 13], init="pixel"), path)
    assert isinstance(load_any_selection(path), Selection)


@pytest.mark.parametrize(
    "mutate,pattern",
    [
        (lambda d: d.update(recommended="relay:nothing"), "field 'recommended' is 'relay:nothing'"),
        (lambda d: d["candidates"][0].update(family="spline"), r"field 'candidates.0.family'"),
        (lambda d: d.update(version=2), "field 'version' is 2"),
    ],
)
def test_bad_files_name_the_field(tmp_path, mutate, pattern):
    path = tmp_path / "fam.json"
    save_family_selection(_selection(), path)
    data = json.loads(path.read_text())
    mutate(data)
    path.write_text(json.dumps(data))
    with pytest.raises(InputFileError, match=pattern):
        load_any_selection(path)
