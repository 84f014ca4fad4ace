"""Choosing across model families (oapcal.families, oapcal select --families)."""

import json

import numpy as np
import pytest
from click.testing import CliRunner

import reference_model
from oapcal.cli import cli
from oapcal.errors import DataError
from oapcal.families import relay_subset_masks, select_families
from oapcal.model import RELAY, distort
from oapcal.optics.relay_model import RelayDesign, relay_mask, relay_params


def _relay_points(seed=2, noise=0.05, n=200, d1=15.0):
    rng = np.random.default_rng(seed)
    design = RelayDesign(setup=1, centre=(320.0, 240.0))
    truth = relay_params(design, {"m2_tilt_x": 0.03, "m2_tilt_y": -0.02, "camera_tilt_y": 0.4, "d1": d1},
                         {"rotation": 0.3, "scale": 1.01})  # fmt: skip
    xy_u = np.column_stack([rng.uniform(216, 424, n), rng.uniform(136, 344, n)])
    return design, xy_u, distort(xy_u, truth) + rng.normal(0, noise, (n, 2))


def test_relay_subsets_cover_every_block_combination_with_the_pose():
    subsets = relay_subset_masks()
    assert len(subsets) == 64 and len({s for s, _ in subsets}) == 64
    assert all(m[:4].all() for _, m in subsets)  # the pose is always fitted


def test_relay_family_alone_recovers_the_true_subset_and_is_recommended():
    design, xy_u, xy_d = _relay_points(n=60, noise=0.02, d1=40.0)
    sel = select_families(xy_u, xy_d, design, ("relay",), cv=2, cv_top=2)
    best = sel.best_of("relay")
    # the truth lies in relay:tilt2,d1,camera; the best model by AICc contains it (the second
    # mirror's decentre acts almost like its tilt and may stand in for it)
    assert {"d1", "camera_tilt_x", "camera_tilt_y"} <= set(best.free)
    assert {"m2_tilt_x", "m2_tilt_y"} <= set(best.free) or {"m2_decentre_x", "m2_decentre_y"} <= set(
        best.free
    )
    assert sel.recommended is not None and sel.recommended.family == "relay"
    # every candidate's spec is what --model takes to fit it again
    for c in sel.candidates:
        assert {n for n, m in zip(RELAY.param_names, relay_mask(c.spec)) if m} == set(c.free)
    # held-out error at the noise level (0.02 px per axis: mean distance ~0.025)
    assert sel.recommended.cv_mean_error < 0.04


def test_models_that_cannot_be_scored_rank_last_with_their_reason():
    from oapcal.families import _score

    design, xy_u, xy_d = _relay_points(n=40, noise=0.02)
    p0 = relay_params(design)
    ok = [("relay:d1", relay_mask("relay:d1")), ("relay:camera", relay_mask("relay:camera"))]
    invalid = [("relay:all", relay_mask("all"), "not identifiable: m1_clock")]
    out = _score("relay", xy_u, xy_d, ok, np.repeat(p0[None], 2, 0), invalid, 0, 0, 0, None)
    assert [c.valid for c in out] == [True, True, False]
    assert out[-1].spec == "relay:all" and out[-1].reason == "not identifiable: m1_clock"
    assert out[0].aicc <= out[1].aicc


def test_unknown_family_and_too_few_folds_are_refused():
    design, xy_u, xy_d = _relay_points(n=30)
    with pytest.raises(DataError, match="unknown model family 'spline'"):
        select_families(xy_u, xy_d, design, "bc,spline")
    with pytest.raises(DataError, match="2 or more folds"):
        select_families(xy_u, xy_d, design, ("relay",), cv=1)


@pytest.mark.slow
def test_select_families_command_ranks_all_three_and_recommends_the_relay(tmp_path):
    design, xy_u, xy_d = _relay_points(noise=0.1, n=289)
    path = tmp_path / "points.csv"
    rows = ["x_u,y_u,x_d,y_d"] + [f"{a},{b},{c},{d}" for (a, b), (c, d) in zip(xy_u, xy_d)]
    path.write_text("\n".join(rows) + "\n")
    out = tmp_path / "fam.json"
    args = [
        "select",
        str(path),
        "--families",
        "bc,bc+rotation,relay",
        "--relay-centre",
        "320,240",
        "--top",
        "2",
    ]
    result = CliRunner().invoke(cli, [*args, "--json", str(out)])
    assert result.exit_code == 0, result.output
    data = json.loads(out.read_text())
    assert data["format"] == "oapcal-family-selection"
    assert data["recommended"].startswith("relay:")
    families = {c["family"] for c in data["candidates"] if c["valid"]}
    assert families == {"brown-conrady", "brown-conrady+rotation", "relay"}
    best = {f: min(c["cv_mean_error"] for c in data["candidates"] if c["family"] == f and c["cv_mean_error"])
            for f in families}  # fmt: skip
    # the turned target raises Eq. (1)'s floor; its rotation term removes part of it; the relay none
    assert best["relay"] < best["brown-conrady+rotation"] < best["brown-conrady"]
    assert "Recommended by held-out error: --model relay:" in result.output


def _folding_case():
    """Eq. (1) with a negative k2 whose map folds over at 260 px from the centre, inside the
    640 x 480 frame but outside the points (within 170 px of the centre): the models with k2
    fit the points best and fold inside the image."""
    from oapcal.model import params_from_dict

    rf = 260.0
    truth = params_from_dict({"k1": 2e-7, "k2": -1 / (5 * rf**4), "x_off": -319.5, "y_off": -239.5,
                              "c_x": 319.5, "c_y": 239.5, "m": 1.0})  # fmt: skip
    rng = np.random.default_rng(4)
    xy_u = rng.uniform([200, 120], [440, 360], (150, 2))
    return truth, xy_u, reference_model.distort(xy_u, truth) + rng.normal(0, 0.05, xy_u.shape)


def _frame_min_det(params):
    """The smallest Jacobian determinant of an Eq. (1) model over the 640 x 480 frame, by
    the NumPy reference (tests/reference_model.py), not the compiled model."""
    gx, gy = np.meshgrid(np.linspace(0, 639, 81), np.linspace(0, 479, 61))
    xy = np.column_stack([gx.ravel(), gy.ravel()])
    if len(params) == 14:  # Eq. (1) after turning the points (determinant 1) by `rotation` deg
        t = np.radians(params[13])
        xy = xy @ np.array([[np.cos(t), -np.sin(t)], [np.sin(t), np.cos(t)]]).T
    return reference_model.jacobian_determinant(xy, np.asarray(params[:13])).min()


def test_a_recommendation_never_folds_over_the_output_region():
    from oapcal.calibration import calibrate

    truth, xy_u, xy_d = _folding_case()
    assert _frame_min_det(truth) < 0  # the truth itself folds inside the frame
    # without an image the output region is the points' bounds: a k2 model wins, folding in the frame
    free = select_families(xy_u, xy_d, RelayDesign(), ("bc",), cv=3, cv_top=3)
    assert "k2" in free.recommended.free
    assert _frame_min_det(calibrate(xy_u, xy_d, free.recommended.spec).params) < 0
    # with the image it is not recommended (it folds beyond the points: fit writes it with a note,
    # correct writes only its trust region), and the recommendation fits and corrects the whole image
    sel = select_families(xy_u, xy_d, RelayDesign(), ("bc",), cv=3, cv_top=3, image_size=(640, 480))
    refused = [c for c in sel.candidates if c.reason.startswith("not recommended")]
    assert refused and all("folds over" in c.reason and "640x480 px image" in c.reason for c in refused)
    assert free.recommended.spec in {c.spec for c in refused}
    kept = calibrate(xy_u, xy_d, free.recommended.spec, image_size=(640, 480))
    assert any("folds over beyond the reference points' bounds" in n for n in kept.notes)
    assert sel.recommended is not None and sel.recommended.valid
    cal = calibrate(xy_u, xy_d, sel.recommended.spec, image_size=(640, 480))
    assert cal.fit.converged and _frame_min_det(cal.params) > 0
    # the ranking keeps the disqualified models after the valid ones
    valid = [c.valid for c in sel.candidates]
    assert valid == sorted(valid, reverse=True)


def test_select_families_recommends_what_fit_writes(tmp_path, run_cli):
    _, xy_u, xy_d = _folding_case()
    points = tmp_path / "points.csv"
    rows = ["x_u,y_u,x_d,y_d"] + [f"{a},{b},{c},{d}" for (a, b), (c, d) in zip(xy_u, xy_d)]
    points.write_text("\n".join(rows) + "\n")
    out = tmp_path / "fam.json"
    code, _, err = run_cli("select", points, "--families", "bc", "--image-size", "640x480", "--cv", "3",
                           "--top", "3", "--json", out)  # fmt: skip
    assert code == 0, err
    spec = json.loads(out.read_text())["recommended"]
    calib = tmp_path / "calib.json"
    code, _, err = run_cli("fit", points, "--model", spec, "--image-size", "640x480", "--out", calib)
    assert code == 0, err
    assert calib.exists()


def test_the_rotation_family_is_checked_over_the_image_too():
    """issue 20: a bc+rotation subset that folds inside the image was recommended."""
    from oapcal.calibration import calibrate

    _, xy_u, xy_d = _folding_case()
    sel = select_families(xy_u, xy_d, RelayDesign(), ("bc+rotation",), cv=3, cv_top=2, image_size=(640, 480))
    assert any(c.reason.startswith("not recommended") for c in sel.candidates)
    assert sel.recommended is not None and sel.recommended.spec.endswith("+rotation")
    cal = calibrate(xy_u, xy_d, sel.recommended.spec, image_size=(640, 480))
    assert cal.fit.converged and _frame_min_det(cal.params) > 0
