"""Target orientation, relay images (paraxial map -I) and the global consistency check."""

import csv

import numpy as np
import pytest

from oapcal.imaging.detect import check_consistency, detect_usaf, evaluate_detection
from oapcal.imaging.detect.checks import rms_limit
from oapcal.imaging.field import setup1_like_field
from oapcal.imaging.simulate import simulate_image
from oapcal.imaging.usaf import (
    ORIENTATIONS,
    nearest_orientation,
    orient_px,
    orientation_matrix,
    render_rectangles,
    usaf_target,
)
from oapcal.model import distort

# numpy's own array operations, the independent reference for each orientation of a
# square image (np.rot90 turns counter-clockwise as displayed).
NUMPY_OPS = {
    "none": lambda a: a,
    "rot90": np.rot90,
    "rot180": lambda a: np.rot90(a, 2),
    "rot270": lambda a: np.rot90(a, 3),
    "flip-x": np.fliplr,
    "flip-y": np.flipud,
    "transpose": lambda a: a.T,
    "anti-transpose": lambda a: np.rot90(a, 2).T,
}


def test_orientations_are_the_eight_symmetries_of_the_square():
    mats = {k: orientation_matrix(k) for k in ORIENTATIONS}
    keys = {m.tobytes() for m in mats.values()}
    assert len(keys) == 8
    for a in mats.values():
        assert (a.T @ a == np.eye(2)).all()
        for b in mats.values():
            assert (a @ b).tobytes() in keys  # closed under composition
    dets = sorted(round(np.linalg.det(m)) for m in mats.values())
    assert dets == [-1] * 4 + [1] * 4


@pytest.mark.parametrize("name", list(ORIENTATIONS))
def test_each_orientation_equals_numpy_on_a_rendered_target(name):
    t = usaf_target((4, 5))
    size = (240, 240)
    plain = render_rectangles(t.rectangles_px(9.6, size), size)
    turned = render_rectangles(t.rectangles_px(9.6, size, name), size)
    np.testing.assert_allclose(turned, NUMPY_OPS[name](plain), atol=1e-12)


def test_orientation_by_hand():
    # y points down: the target's right side (+x) goes up (-y) under rot90.
    assert orientation_matrix("rot90") @ [1, 0] == pytest.approx([0, -1])
    assert orient_px([[10.0, 20.0]], "flip-x", (640, 480)).tolist() == [[629.0, 20.0]]
    assert orient_px([[10.0, 20.0]], "flip-y", (640, 480)).tolist() == [[10.0, 459.0]]
    assert nearest_orientation([[-1.0, 1e-9], [0.0, -1.0]]) == "rot180"
    assert nearest_orientation([[0.0, 0.21], [0.2, 0.0]]) == "transpose"


def test_relay_truth_is_the_paraxial_image_and_turned_180():
    from oapcal.optics import relay_distortion

    field = relay_distortion(1)
    sim = simulate_image((5,), field, sigma_px=0, snr=None, oversample=1)
    t = usaf_target((5,))
    assert sim.orientation == "rot180" and sim.ids == t.corner_ids
    paraxial = field.paraxial_from_object_um(t.corners_um - t.centre_um)  # the relay's own map
    np.testing.assert_allclose(sim.xy_u, paraxial, atol=1e-6)
    # a 180-degree turn: the top-left corner of a bar is the bottom-right one in the image
    assert (sim.xy_u[0] > sim.xy_u[2]).all()


def _goal(sim, det):
    score = evaluate_detection(det, sim.ids, sim.xy_d, sim.visible)
    assert det.status == 0, det.message
    assert score["visible"] == 288
    assert score["coverage"] >= 0.95
    assert score["median_error_px"] <= 0.25
    assert score["mismatches"] == 0
    return score


@pytest.mark.slow  # setup 1 runs in the default suite (test_cli_relay_setup_1_simulate_detect_fit)
def test_relay_setup_2_meets_the_goal_and_fits_with_m_near_one():
    from oapcal.fitting import fit
    from oapcal.optics import relay_distortion

    sim = simulate_image((4, 5), relay_distortion(2), sigma_px=0.8, snr=50, seed=21)
    det = detect_usaf(sim.image, (4, 5), 4.8)
    _goal(sim, det)
    assert det.orientation == "rot180"
    k = [sim.ids.index(i) for i in det.ids]
    np.testing.assert_allclose(det.xy_u, sim.xy_u[k], atol=1e-9)  # the truth's convention
    result = fit(det.xy_u, det.xy_d, "paper", init="pixel")
    assert result.converged and result.value("m") == pytest.approx(1.0, abs=0.01)
    assert det.consistency["model"] == "full" and det.consistency["inconsistent"] == 0


@pytest.mark.slow  # setup 1 through the relay stays in the default suite
def test_a_turned_camera_image_is_found_with_matching_ids():
    # np.rot90 of the image turns the target counter-clockwise: orientation rot90. A pixel
    # (x, y) of the 640 x 480 image goes to (y, 639 - x) in the 480 x 640 result.
    sim = simulate_image((4, 5), setup1_like_field(), sigma_px=0.8, snr=50, oversample=2, seed=5)
    turned = np.rot90(sim.image).copy()

    def move(xy):
        return np.column_stack([xy[:, 1], 639.0 - xy[:, 0]])

    det = detect_usaf(turned, (4, 5), 4.8)
    assert det.status == 0 and det.orientation == "rot90"
    score = evaluate_detection(det, sim.ids, move(sim.xy_d), sim.visible)
    assert score["coverage"] >= 0.95 and score["mismatches"] == 0 and score["median_error_px"] < 0.1
    k = [sim.ids.index(i) for i in det.ids]
    np.testing.assert_allclose(det.xy_u, move(sim.xy_u[k]), atol=1e-9)
    # the pairs share the camera's axes: the linear part of an affine fit is near +I
    design = np.column_stack([det.xy_u, np.ones(len(det.xy_u))])
    coef = np.linalg.lstsq(design, det.xy_d, rcond=None)[0]
    np.testing.assert_allclose(coef[:2].T, np.eye(2), atol=0.1)


def test_a_symmetric_image_has_an_ambiguous_orientation():
    sim = simulate_image((4, 5), setup1_like_field(), sigma_px=0.8, snr=None, oversample=1)
    symmetric = np.maximum(sim.image, np.rot90(sim.image, 2))
    det = detect_usaf(symmetric, (4, 5), 4.8)
    assert det.status != 0 and "ambiguous" in det.message and len(det.ids) == 0
    assert det.orientation_scores["none"] == pytest.approx(det.orientation_scores["rot180"], abs=1e-3)


def _smooth_pairs(seed=0):
    rng = np.random.default_rng(seed)
    t = usaf_target((4, 5))
    xy_u = t.reference_px(4.8, (640, 480))
    xy_d = distort(xy_u, setup1_like_field().params) + rng.normal(0, 0.02, xy_u.shape)
    return xy_u, xy_d, t.corner_width_um / 4.8


def test_consistency_check_drops_exactly_the_pairs_shifted_by_a_bar():
    xy_u, xy_d, width = _smooth_pairs()
    bad = np.random.default_rng(1).choice(len(xy_u), 12, replace=False)
    xy_d = xy_d.copy()
    xy_d[bad, 1] += width[bad]  # matched to the neighbouring bar edge
    check = check_consistency(xy_u, xy_d, width)
    assert check.status == 0 and check.model == "full"
    np.testing.assert_array_equal(np.flatnonzero(~check.consistent), np.sort(bad))
    assert check.rms_px < 0.05


def test_consistency_check_refuses_a_wrong_alignment():
    xy_u, xy_d, width = _smooth_pairs()
    xy_d = xy_d.copy()
    xy_d[:100] += 2 * width[:100, None]  # a third of the target one bar period off
    check = check_consistency(xy_u, xy_d, width)
    assert check.status == 1 and "inconsistent" in check.message and not check.consistent.any()


def test_consistency_check_refuses_pairs_that_fit_no_smooth_model_well():
    """Noise of a fifth of the bars' median width (rms; bars 10 times as wide, so that no
    pair is off by half its own width): over the limit, which on this many pairs is 0.15
    of that width (``checks.rms_limit``)."""
    xy_u, xy_d, width = _smooth_pairs()
    wide = 10 * width
    sd = 0.2 * float(np.median(wide)) / np.sqrt(2)
    noisy = xy_d + np.random.default_rng(2).normal(0, sd, xy_d.shape)
    check = check_consistency(xy_u, noisy, wide)
    assert check.status == 1 and "doubtful" in check.message
    # nor does a cubic map: noise is not a smooth distortion
    assert check.cubic_rms_px > rms_limit(wide) > 0.75 and "cubic map" in check.message


def test_consistency_check_needs_enough_pairs():
    xy_u, xy_d, width = _smooth_pairs()
    assert check_consistency(xy_u[:20], xy_d[:20], width[:20]).model == "paper"
    few = check_consistency(xy_u[:10], xy_d[:10], width[:10])
    assert few.model is None and few.consistent.all()
    assert check_consistency(xy_u, xy_d, width, None).model is None


def test_unknown_orientation_is_a_named_error():
    from oapcal.errors import DataError

    with pytest.raises(DataError, match="orientation 'rot45'"):
        detect_usaf(np.zeros((48, 64)), (5,), 4.8, orientation="rot45")


# ---------------------------------------------------------------------------- the CLI


def test_cli_orientation_choices_match_the_library():
    from oapcal.cli.detect import ORIENTATION_CHOICES

    assert list(ORIENTATION_CHOICES) == ["auto", *ORIENTATIONS]


def test_cli_relay_setup_1_simulate_detect_fit(run_cli, tmp_path):
    code, out, err = run_cli("simulate", "image", "--relay-setup", "1", "--groups", "4-5",
                             "--sigma-px", "0.8", "--snr", "50", "--seed", "3", "--out", tmp_path / "img.png",
                             "--truth", tmp_path / "truth.csv")  # fmt: skip
    assert code == 0, err
    assert "orientation rot180" in out
    code, out, err = run_cli("detect", tmp_path / "img.png", "--target", "usaf", "--groups", "4-5",
                             "--um-per-px", "4.8", "--out", tmp_path / "points.csv",
                             "--truth", tmp_path / "truth.csv", "--json")  # fmt: skip
    assert code == 0, err
    import json

    summary = json.loads(out)
    assert summary["orientation"] == "rot180" and summary["orientation_matrix"] == [[-1, 0], [0, -1]]
    t = summary["truth"]
    assert t["coverage"] >= 0.95 and t["median_error_px"] <= 0.25 and t["mismatches"] == 0
    with open(tmp_path / "truth.csv") as fh:
        truth = {r["id"]: r for r in csv.DictReader(fh)}
    with open(tmp_path / "points.csv") as fh:
        points = list(csv.DictReader(fh))
    for p in points:  # the truth's scale is the relay's paraxial one, 4.8 um/px to 1e-9
        assert float(p["x_u"]) == pytest.approx(float(truth[p["id"]]["x_u"]), abs=1e-6)
        assert float(p["y_u"]) == pytest.approx(float(truth[p["id"]]["y_u"]), abs=1e-6)
    code, out, err = run_cli("fit", tmp_path / "points.csv", "--model", "paper", "--json")
    assert code == 0, err
    assert json.loads(out)["params"]["m"] == pytest.approx(1.0, abs=0.01)


def test_cli_bad_orientation_exits_2(run_cli, tmp_path):
    code, _, err = run_cli("detect", tmp_path / "x.png", "--um-per-px", "4.8", "--out", tmp_path / "p.csv",
                           "--orientation", "rot45")  # fmt: skip
    assert code == 2 and "rot45" in err
    assert not (tmp_path / "p.csv").exists()


# ------------------------------------------------------------------------ slow: more seeds


@pytest.mark.slow
@pytest.mark.parametrize("setup", [1, 2])
@pytest.mark.parametrize("seed", range(5))
def test_relay_goal_over_seeds(setup, seed):
    from oapcal.optics import relay_distortion

    sim = simulate_image((4, 5), relay_distortion(setup), sigma_px=0.8, snr=50, seed=200 + seed)
    det = detect_usaf(sim.image, (4, 5), 4.8)
    _goal(sim, det)
    assert det.orientation == "rot180"


@pytest.mark.slow
@pytest.mark.parametrize("name", ["flip-x", "transpose", "rot270"])
def test_other_orientations(name):
    sim = simulate_image((4, 5), setup1_like_field(), sigma_px=0.8, snr=50, oversample=2, seed=8)
    image = NUMPY_OPS[name](sim.image).copy()
    det = detect_usaf(image, (4, 5), 4.8)
    assert det.status == 0 and det.orientation == name
    h, w = image.shape
    # where each true corner lands in the turned image: the same orientation about the centres
    c_old, c_new = np.array([319.5, 239.5]), (np.array([w, h], float) - 1) / 2
    moved = c_new + (sim.xy_d - c_old) @ orientation_matrix(name).T
    score = evaluate_detection(det, sim.ids, moved, sim.visible)
    assert score["coverage"] >= 0.95 and score["mismatches"] == 0


@pytest.mark.slow
def test_a_forced_wrong_orientation_is_refused(run_cli, tmp_path):
    code, _, err = run_cli("simulate", "image", "--relay-setup", "1", "--oversample", "2",
                           "--out", tmp_path / "img.png")  # fmt: skip
    assert code == 0, err
    code, _, err = run_cli("detect", tmp_path / "img.png", "--um-per-px", "4.8", "--out",
                           tmp_path / "p.csv", "--orientation", "none")  # fmt: skip
    assert code == 3 and "detection failed" in err
    assert not (tmp_path / "p.csv").exists()
