"""Selection and robustness files: format, version, schema, and a round trip to the
typed results."""

import json
import math

import numpy as np
import pytest

from oapcal.errors import InputFileError
from oapcal.io.results import (
    load_robustness,
    load_selection,
    robustness_to_dict,
    save_robustness,
    save_selection,
    selection_to_dict,
)
from oapcal.model import parse_model
from oapcal.select import INVALID_REASONS, robustness, select_models
from oapcal.synthetic import synthetic_pairs


@pytest.fixture(scope="module")
def data():
    return synthetic_pairs(seed=2)


@pytest.fixture(scope="module")
def selection(data):
    # a valid model, one with too few residuals for 8 points, and the full model
    masks = np.stack([parse_model("paper"), parse_model("full"), parse_model("k1,c_x,c_y,m")])
    return select_models(data.xy_u, data.xy_d, masks=masks, init="pixel", cv=3)


def _same_float(a, b):
    return (a is None and b is None) or (math.isnan(a) and math.isnan(b)) or a == pytest.approx(b, rel=1e-12)


def test_selection_round_trip(tmp_path, selection):
    save_selection(selection, tmp_path / "s.json")
    data = json.loads((tmp_path / "s.json").read_text())
    assert data["format"] == "oapcal-selection" and data["version"] == 1
    back = load_selection(tmp_path / "s.json")
    assert (back.n_points, back.normalization, back.init, back.cv_folds) == (
        selection.n_points, selection.normalization, selection.init, 3,
    )  # fmt: skip
    assert len(back.models) == len(selection.models)
    for a, b in zip(back.models, selection.models, strict=True):
        assert (a.bits, a.free, a.k, a.valid, a.reason, a.reason_code, a.fit_status, a.cv_failed) == (
            b.bits, b.free, b.k, b.valid, b.reason, b.reason_code, b.fit_status, b.cv_failed,
        )  # fmt: skip
        for name in ("aicc", "delta_aicc", "weight", "rss", "mean_error", "cv_mean_error"):
            assert _same_float(getattr(a, name), getattr(b, name)), name
    assert back.best.free == selection.best.free


def test_reason_codes_are_codes(data):
    few = data.xy_u[:3], data.xy_d[:3]  # 6 residuals: a model with K = 5 (4 free + variance) fits
    masks = np.stack([parse_model("k1,c_x,c_y,m"), parse_model("c_x,c_y,m")])  # but AICc needs n - K - 1 > 0
    sel = select_models(*few, masks=masks, init="pixel")
    four = next(m for m in sel.models if m.free == ("k1", "c_x", "c_y", "m"))
    assert four.reason_code == "too_few_residuals" and not four.valid, four.reason
    assert four.reason.startswith("too few residuals")
    for m in sel.models:
        assert (m.reason_code == "") == m.valid
        assert m.reason_code in ("", *INVALID_REASONS)


def test_robustness_round_trip(tmp_path, data):
    rob = robustness(data.xy_u, data.xy_d, ["paper", "full"], trials=20, seed=1, init="pixel")
    save_robustness(rob, tmp_path / "r.json")
    assert json.loads((tmp_path / "r.json").read_text())["format"] == "oapcal-robustness"
    back = load_robustness(tmp_path / "r.json")
    assert robustness_to_dict(back) == robustness_to_dict(rob)
    assert [m.name for m in back.models] == [m.name for m in rob.models]


def test_version_0_files_still_load(tmp_path, selection):
    old = selection.to_dict()  # what 'oapcal select --json' wrote before the format had a name
    for m in old["models"]:
        del m["reason_code"]
    (tmp_path / "old.json").write_text(json.dumps(old))
    back = load_selection(tmp_path / "old.json")
    assert [m.reason_code for m in back.models] == [m.reason_code for m in selection.models]


@pytest.mark.parametrize(
    "change, message",
    [
        (lambda d: d.update(format="oapcal-robustness"), "expected 'oapcal-selection'"),
        (lambda d: d.update(version=7), "reads version 1"),
        (lambda d: d["models"][0].update(k="eight"), "models.0.k"),
        (lambda d: d["models"][0].update(free=["k9"]), "models.0.free"),
        (lambda d: d["models"][0].update(reason_code="bad_luck"), "models.0.reason_code"),
    ],
)
def test_bad_selection_files_name_the_field(tmp_path, selection, change, message):
    data = selection_to_dict(selection)
    data = json.loads(json.dumps(data))
    change(data)
    (tmp_path / "bad.json").write_text(json.dumps(data))
    with pytest.raises(InputFileError, match=message) as err:
        load_selection(tmp_path / "bad.json")
    assert str(tmp_path / "bad.json") in str(err.value)


def test_cli_select_json_loads_back(tmp_path, run_cli):
    from oapcal.io.points import write_point_pairs

    d = synthetic_pairs(seed=3)
    write_point_pairs(tmp_path / "p.csv", d.xy_u, d.xy_d)
    code, _, err = run_cli("select", tmp_path / "p.csv", "--init", "pixel", "--json", tmp_path / "s.json")
    assert code == 0, err
    sel = load_selection(tmp_path / "s.json")
    assert len(sel.models) == 4096 and sel.n_points == len(d.xy_u)
