"""The end-to-end benchmark on real content (``benchmarks/e2e_real.py``) on two seeded cases,
and its scoring helpers.

The slow tests run the benchmark's core (render, ``oapcal detect`` without and with
``--um-per-px``, ``oapcal fit`` per family, ``correct-points``, ``correct``) on the aligned
relay of setup 1 and the seeded misaligned relay ``misaligned s0`` and assert the issue's
goals that hold today; the goals that do not hold yet are strict xfails with the measured
reason, so that they fail (XPASS) once the work that meets them is merged.
"""

import importlib.util
import sys

import numpy as np
import pytest

from paths import REAL, REPO

needs_real = pytest.mark.skipif(
    not (REAL / "usaf" / "fpm_brightfield.png").is_file(),
    reason="../shared/real/usaf (the real images) is not present",
)


def _benchmark():
    spec = importlib.util.spec_from_file_location("e2e_real", REPO / "benchmarks" / "e2e_real.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules["e2e_real"] = module  # its dataclasses look their module up
    spec.loader.exec_module(module)
    return module


bench = _benchmark()


def test_similarity_recovers_a_mirrored_turned_scaled_shift_exactly():
    rng = np.random.default_rng(0)
    a = rng.uniform(-100, 100, (50, 2))
    t = np.radians(37.0)
    rot = np.array([[np.cos(t), -np.sin(t)], [np.sin(t), np.cos(t)]])
    for flip in (np.eye(2), np.diag([-1.0, 1.0])):
        mat = 4.8 * rot @ flip
        b = a @ mat.T + [12.0, -7.0]
        got, shift, rms = bench.similarity(a, b)
        np.testing.assert_allclose(got, mat, atol=1e-10)
        np.testing.assert_allclose(shift, [12.0, -7.0], atol=1e-9)
        assert rms < 1e-9


def test_a_swapped_id_is_wrong_and_a_right_one_is_right():
    from oapcal.imaging.render import Camera, Placement, Scene
    from oapcal.model import identity_params

    # source corners on a 10 px grid; the scene maps source px to camera px 1:1 (4.8 um both)
    corners = {f"G4E1H0C{k}": np.array([100.0 + 10 * k, 50.0]) for k in range(4)}
    src = bench.SourceTruth(np.zeros((200, 300)), 4.8, corners, None)
    scene = Scene(identity_params(), Placement(4.8, (150.0, 100.0)), Camera(size=(300, 200)))
    truth = {i: scene.camera_from_source(xy[None])[0] for i, xy in corners.items()}
    rows = [{"id": i, "x_d": truth[i][0] + 0.2, "y_d": truth[i][1]} for i in ("G4E1H0C0", "G4E1H0C1")]
    rows.append({"id": "G4E1H0C2", "x_d": truth["G4E1H0C3"][0], "y_d": truth["G4E1H0C3"][1]})  # swapped
    s = bench.score_detection(rows, None, src, scene, truth, set(corners))
    assert (s["wrong_ids"], s["right_visible"], s["visible"]) == (1, 2, 4)
    assert s["median_error_px"] == pytest.approx(0.2, abs=1e-6)


def test_the_landmarks_floor_puts_each_corner_at_its_source_position(tmp_path):
    from oapcal.imaging.render import Camera, Placement, Scene
    from oapcal.model import identity_params

    # 2 um per source px, the source's (150, 100) on the axis: object um = 2 (source - centre)
    corners = {
        "G4E1H0C0": np.array([160.0, 90.0]),  # object (20, -20)
        "G4E1H0C1": np.array([140.5, 101.0]),  # object (-19, 2)
        "G4E1H0C2": np.array([150.0, 110.0]),  # object (0, 20)
    }
    src = bench.SourceTruth(np.zeros((200, 300)), 2.0, corners, None)
    scene = Scene(identity_params(), Placement(2.0, (150.0, 100.0)), Camera(size=(300, 200)))

    # the detected reference frame: the object mirrored (x and y swapped), halved, moved by
    # (100, 50), so the source positions there are (90, 60), (101, 40.5), (110, 50)
    def rows_with(ref):
        rows = [
            {
                "id": cid,
                "x_d": f"{k + 0.5}",
                "y_d": f"{k + 1.5}",
                "x_u": f"{x}",
                "y_u": f"{y}",
                "width_um": "7",
            }
            for k, (cid, (x, y)) in enumerate(zip(corners, ref))
        ]
        rows.append({"id": "G4E2H0C0", "x_d": "5.5", "y_d": "6.5", "x_u": "0", "y_u": "0", "width_um": "7"})
        return rows  # the last id is not in the source: left out

    exact = [[90.0, 60.0], [101.0, 40.5], [110.0, 50.0]]
    out = bench.read_csv_rows(bench.landmark_floor_points(rows_with(exact), src, scene, tmp_path / "a.csv"))
    assert [r["id"] for r in out] == list(corners)
    got = np.array([[float(r[k]) for k in ("x_d", "y_d", "x_u", "y_u")] for r in out])
    np.testing.assert_allclose(got[:, :2], [[0.5, 1.5], [1.5, 2.5], [2.5, 3.5]])
    np.testing.assert_allclose(got[:, 2:], exact, atol=1e-6)
    assert [r["width_um"] for r in out] == ["7"] * 3

    # a drawn layout that is off by a shape change: the floor keeps the source's shape (its
    # distances stay in the ratios of the object's) and does not copy the layout's points
    drawn = [[90.0, 60.0], [101.0, 40.5], [112.0, 51.0]]
    out = bench.read_csv_rows(bench.landmark_floor_points(rows_with(drawn), src, scene, tmp_path / "b.csv"))
    got = np.array([[float(r["x_u"]), float(r["y_u"])] for r in out])
    obj = np.array([[20.0, -20.0], [-19.0, 2.0], [0.0, 20.0]])
    pair = [(0, 1), (0, 2), (1, 2)]
    ratio = [np.hypot(*(got[a] - got[b])) / np.hypot(*(obj[a] - obj[b])) for a, b in pair]
    np.testing.assert_allclose(ratio, ratio[0], rtol=1e-6)  # the CSV keeps 6 decimals
    assert np.abs(got - drawn).max() > 0.3


def test_the_renders_are_placed_by_the_source_corners_kept_with_the_benchmark(monkeypatch):
    """Every source has its corners kept in ``benchmarks/e2e_source_corners.json`` and
    ``source_truth`` takes them from there, without detecting (a detector change then leaves
    the renders as they are)."""
    kept = bench._kept_sources()
    assert set(kept) == set(bench.SOURCES)
    for entry in kept.values():
        assert len(entry["corners"]) >= 300 and entry["layout"]

    def no_detection(*_):
        raise AssertionError("detected")

    monkeypatch.setattr(bench, "_detect_source", no_detection)
    src = bench.source_truth("labumk_negative.tif")
    assert src.layout == kept["labumk_negative.tif"]["layout"]
    cid, xy = next(iter(kept["labumk_negative.tif"]["corners"].items()))
    np.testing.assert_array_equal(src.corners[cid], xy)


def test_refreshed_source_corners_round_trip_and_are_checked_against_the_detector(monkeypatch, tmp_path):
    """``--refresh-sources`` writes what the detector finds (one corner per line, floats as
    they are); ``source_check`` reports the detector under test against the kept corners."""
    found = {"G4E1H0C0": np.array([10.123456789012345, 20.5]), "G4E1H0C1": np.array([30.0, 40.25])}
    monkeypatch.setattr(bench, "SOURCE_CORNERS", tmp_path / "kept.json")
    monkeypatch.setattr(bench, "_detect_source", lambda name, img: (dict(found), "compact"))
    bench.write_source_corners(["labumk_negative.tif"])
    text = (tmp_path / "kept.json").read_text()
    assert f'"G4E1H0C0": [{float(found["G4E1H0C0"][0])!r}, 20.5]' in text
    src = bench.source_truth("labumk_negative.tif")
    assert src.layout == "compact" and src.corners.keys() == found.keys()
    np.testing.assert_array_equal(src.corners["G4E1H0C0"], found["G4E1H0C0"])
    moved = {"G4E1H0C0": found["G4E1H0C0"] + [0.3, 0.4], "G5E1H0C0": np.array([1.0, 1.0])}
    monkeypatch.setattr(bench, "_detect_source", lambda name, img: (moved, "spaced"))
    check = bench.source_check("labumk_negative.tif", src)
    assert check["common"] == 1 and check["only_kept"] == 1 and check["only_now"] == 1
    assert check["max_px"] == pytest.approx(0.5) and not check["same_layout"]
    assert "in another layout" in bench.format_source_check(check)


@pytest.fixture(scope="module")
def results(tmp_path_factory):
    src = bench.source_truth("fpm_brightfield.png")
    work = tmp_path_factory.mktemp("e2e")
    chosen = {c.name: c for c in bench.cases(True, 1)}
    return {name: bench.run_case(chosen[name], src, work) for name in ("aligned", "misaligned s0")}


def _fit(result, model):
    return [f for d in result["detections"] for f in d["fits"] if f["model"] == model]


pytestmark = [needs_real]
ALIGNED = "aligned"
MISALIGNED = "misaligned s0"


@pytest.mark.slow
@pytest.mark.parametrize("name", [ALIGNED, MISALIGNED])
def test_detection_gives_no_wrong_id_with_or_without_the_scale(results, name):
    dets = results[name]["detections"]
    assert [d["hint"] for d in dets] == [False, True]
    for d in dets:
        assert d["code"] == 0 and d["checked"] == d["found"] > 200
        assert d["wrong_ids"] == 0
        assert d["reference_rms_px"] < bench.MAX_REFERENCE_RMS_PX  # the layout and scale are right
        assert d["peak_mb"] < bench.MEMORY_GOAL_MB


@pytest.mark.slow
@pytest.mark.parametrize("name", [ALIGNED, MISALIGNED])  # 264/264 on both since the rescue
def test_detection_finds_95_percent_of_the_fully_visible_corners(results, name):
    for d in results[name]["detections"]:
        assert d["visible"] >= 240 and d["coverage"] >= bench.DETECTION_COVERAGE


@pytest.mark.slow
@pytest.mark.parametrize("name", [ALIGNED, MISALIGNED])
def test_relay_model_corrects_the_field_to_the_goal(results, name):
    fits = _fit(results[name], "relay")
    assert len(fits) == 2
    for f in fits:
        assert f["code"] == 0 and f["uncorrected_pct"] == 0
        assert f["mean_px"] <= bench.RELAY_GOAL_PX[0] and f["max_px"] <= bench.RELAY_GOAL_PX[1]
        # the corrected image is close to the truth rendering: within 1.5x the noise alone
        assert f["image_error_pct"] < 1.5 * results[name]["image_noise_pct"]


@pytest.mark.slow
@pytest.mark.parametrize(
    "name",
    [
        ALIGNED,
        pytest.param(
            MISALIGNED,
            marks=pytest.mark.xfail(
                strict=True,
                reason="measured: paper 0.30 mean / 2.29 max px on misaligned s0 (Table 1: 0.93 / 2.05)",
            ),
        ),
    ],
)
def test_paper_model_is_as_good_as_table_1(results, name):
    fits = _fit(results[name], "paper")
    assert len(fits) == 2
    for f in fits:
        assert f["code"] == 0
        assert f["mean_px"] <= bench.TABLE1_PX[0] and f["max_px"] <= bench.TABLE1_PX[1]


@pytest.mark.slow
def test_every_default_fit_converges(results):
    for result in results.values():
        for d in result["detections"]:
            for f in d["fits"]:
                assert f["code"] == 0, (result["case"]["name"], f["model"], f["message"])


@pytest.fixture(scope="module")
def behind_the_microscope(tmp_path_factory):
    src = bench.source_truth("fpm_brightfield.png")
    case = next(c for c in bench.cases(False, 1) if c.name == "aligned, 5x microscope")
    return bench.run_case(case, src, tmp_path_factory.mktemp("e2e_5x"), ("relay",), images=False)


def _meets_relay_goal(f):
    return f["mean_px"] <= bench.RELAY_GOAL_PX[0] and f["max_px"] <= bench.RELAY_GOAL_PX[1]


@pytest.mark.slow
def test_behind_the_microscope_the_sources_corners_bring_the_relay_family_to_the_mean_goal(
    behind_the_microscope,
):
    # the same detected points with each corner's object point taken from the source image:
    # the mean error over the field falls from 0.27 px (the drawn layout) to 0.06 px
    for d in behind_the_microscope["detections"]:
        assert d["code"] == 0 and d["wrong_ids"] == 0
        (layout,) = [f for f in d["fits"] if f["model"] == "relay"]
        floor = d["floor"]
        assert floor["code"] == 0 and layout["code"] == 0
        assert floor["mean_px"] <= bench.RELAY_GOAL_PX[0], floor
        assert floor["mean_px"] <= layout["mean_px"] / 3, (floor, layout)


@pytest.mark.slow
@pytest.mark.xfail(
    strict=True,
    reason="measured: 0.36-0.41 px max on the source's corners (0.055-0.059 mean); with the exact "
    "camera positions as well 0.010 / 0.080 px, so the rest is the corners' position error "
    "behind the microscope (docs/benchmarks.md, the landmarks' floor)",
)
def test_behind_the_microscope_the_relay_family_meets_the_goal_on_the_sources_corners(
    behind_the_microscope,
):
    for d in behind_the_microscope["detections"]:
        assert d["floor"]["code"] == 0 and _meets_relay_goal(d["floor"]), d["floor"]


@pytest.mark.slow
@pytest.mark.xfail(
    strict=True,
    reason="measured: 0.27 mean / 0.86 max px on the drawn layout's coordinates; the source's groups "
    "6-7 deviate from it by 0.29 camera px rms (docs/benchmarks.md, the landmarks' floor)",
)
def test_behind_the_microscope_the_relay_family_meets_the_goal_on_the_layout(behind_the_microscope):
    for d in behind_the_microscope["detections"]:
        f = next(f for f in d["fits"] if f["model"] == "relay")
        assert f["code"] == 0 and _meets_relay_goal(f), f


def test_fully_visible_elements_are_whole_inside_and_resolved():
    from oapcal.imaging.render import Camera, Placement, Scene
    from oapcal.imaging.usaf import usaf_target
    from oapcal.model import identity_params

    target = usaf_target((4, 5))
    corners = dict(zip(target.corner_ids, target.corners_um / 1.0))  # a source at 1 um/px
    src = bench.SourceTruth(np.zeros((10, 10)), 1.0, corners, None)
    case = bench.Case("synthetic", groups="4-5")
    centre = target.corners_um.mean(axis=0)
    centred = Scene(identity_params(), Placement(1.0, tuple(centre)), Camera())
    truth, visible = bench.corner_truth(case, src, centred)
    # every element but G5E6, whose bars are 8.77 um = 1.83 px < 2 px at 4.8 um/px
    assert len(visible) == 11 * 24 and not any(c.startswith("G5E6") for c in visible)
    # moved by 1.4 mm (292 px) so that the target crosses the image's right edge: whole elements drop out
    shifted = Scene(identity_params(), Placement(1.0, tuple(centre + [-1400.0, 0.0])), Camera())
    truth, visible = bench.corner_truth(case, src, shifted)
    assert 0 < len(visible) < 11 * 24 and len(visible) % 24 == 0
    xy = np.array([truth[c] for c in visible])
    assert (xy >= 3).all() and (xy[:, 0] <= 636).all() and (xy[:, 1] <= 476).all()
    outside = [c for c in truth if c not in visible and not c.startswith("G5E6")]
    assert any(truth[c][0] > 636 for c in outside)


def _detections(name, tmp_path, models=()):
    """The two detections (without and with the scale) of the full run's case ``name``."""
    src = bench.source_truth("fpm_brightfield.png")
    case = next(c for c in bench.cases(False, 1) if c.name == name)
    return bench.run_case(case, src, tmp_path, models=models, images=False)["detections"]


def _assert_all_found(d, reference_px=None):
    """Exit 0, no wrong id, 95 % of the fully visible corners (and the reference points
    within ``reference_px`` of the truth)."""
    assert d["code"] == 0, d["message"]
    assert d["wrong_ids"] == 0 and d["coverage"] >= 0.95
    if reference_px is not None:
        assert d["reference_rms_px"] < reference_px


@pytest.mark.slow
@pytest.mark.parametrize(
    "name", ["aligned, turned 135, mirrored", "aligned, turned 225", "aligned, turned 15"]
)
def test_a_turned_target_is_detected_in_its_own_layout(tmp_path, name):
    """The full run's turned renders whose pose search chose another maker's layout (the
    similarity of ``whole-target`` explained more triplets): 158 and 124 of 264 corners,
    reference points 3.3 and 2.0 px rms off the truth, so every fit was 3-12 px off.  The
    corners found decide the layout (``oapcal.imaging.detect.layouts``) and the detection
    runs again in it.  Turned by 15 degrees, the corners kept in ``whole-target`` fit
    ``compact`` only to 0.503 of their own rms (8 wrong ids when the element registration on
    the registration's tangent first came): a milder ratio asks for the run again
    (``layouts.RETRY_RATIO``)."""
    for d in _detections(name, tmp_path):
        _assert_all_found(d, reference_px=0.2)


@pytest.mark.slow
def test_a_target_turned_a_quarter_turn_is_detected_without_the_scale(tmp_path):
    """The full run's aligned relay with the target turned by 90 degrees: without the scale
    the pose stalled at 9 of 20 triplets and was refused, because a blurred middle bar
    thresholded narrower than its neighbours and lost G4E1's V triplet (the triplet spacing's
    upper limit now comes from the wider bar, ``detect/bars.py``)."""
    for d in _detections("aligned, turned 90", tmp_path):
        _assert_all_found(d)


@pytest.mark.slow
def test_a_target_turned_285_degrees_and_mirrored_is_detected_without_the_scale(tmp_path):
    """The full run's aligned relay with the target turned by 285 degrees and mirrored: the
    relay's image turns by -67 to -82 degrees over groups 4-5, so one similarity predicted
    the V triplets' bars 12-13.5 degrees off and, without the scale, the pose stalled at 7 of
    20 triplets (refused).  The pose's correction now predicts each triplet's direction too
    (``detect/pose.py``, ``ANGLE_TOL_DEG``)."""
    for d in _detections("aligned, turned 285, mirrored", tmp_path):
        _assert_all_found(d, reference_px=0.2)


@pytest.mark.slow
def test_a_slipped_triplet_of_a_misaligned_relay_is_outvoted(tmp_path):
    """The full run's misaligned relay with the target turned by 45 degrees and mirrored was
    refused with and without the scale ("two registrations disagree on 12 of 84 corners"):
    the triplet path had put G5E4V on the bars of G5E5V.  The dense registration outvotes
    it (``checks.outvoted``): every corner kept, none wrong, and the relay model to the goal."""
    for d in _detections("misaligned s0, turned 45, mirrored", tmp_path, models=("relay",)):
        _assert_all_found(d, reference_px=0.2)
        (fit,) = d["fits"]
        assert fit["mean_px"] <= 0.08 and fit["max_px"] <= 0.3, fit


@pytest.mark.slow
def test_full_on_a_turned_target_is_written_though_it_folds_at_the_frame_corner(tmp_path):
    """The full run's aligned relay with the target turned by 30 degrees: ``full`` folds over
    at the frame's corner (landmarks over 8 % of it), beyond the landmarks' bounds; it was
    refused (nothing written), now it is written with a note and corrects the 1 mm field;
    the image comparison covers every pixel but the fold's."""
    src = bench.source_truth("fpm_brightfield.png")
    case = next(c for c in bench.cases(False, 1) if c.name == "aligned, turned 30")
    res = bench.run_case(case, src, tmp_path, models=("full",))
    for d in res["detections"]:
        assert d["code"] == 0 and d["wrong_ids"] == 0
        (f,) = d["fits"]
        assert f["code"] == 0 and f["converged"] and f["written"], f["message"]
        assert f["mean_px"] < 0.3 and f["max_px"] < 3.0  # measured 0.22 / 1.48-1.50 px
        assert f["image_region"] == "all but the fold"  # correct --extent input refuses the fold
        assert f["image_error_pct"] < 3 * res["image_noise_pct"]


@pytest.mark.slow
def test_a_blurred_micrograph_through_a_misaligned_relay_is_detected_with_its_finest_group(tmp_path):
    """The LAB-UMK micrograph through the misaligned relay of seed 2 was refused with and
    without the scale: the bar finder kept 8 triplets (uneven thresholded widths, bars
    squeezed along their length), and the registration's prediction of group 5 was 1-4 px
    off, so its triplets were dropped as moved.  Now the bars make 12 triplets and group 5's
    elements are registered one by one (``detect/bars.py``, ``core._refine_twice``): 95 % of
    the fully visible corners, no wrong id."""
    src = bench.source_truth("labumk_negative.tif")
    case = next(c for c in bench.cases(False, 5) if c.name == "labumk, misaligned s2")
    for d in bench.run_case(case, src, tmp_path, models=(), images=False)["detections"]:
        _assert_all_found(d, reference_px=1.0)


@pytest.mark.slow
def test_the_blurred_micrograph_through_misaligned_relay_0_keeps_every_visible_corner(tmp_path):
    """The LAB-UMK micrograph through the misaligned relay of seed 0: group 5's triplets
    refined on the registration came 0.4-0.95 px off the truth (its curvature at the edge of
    the target's view is wrong), G5E2 was dropped and 192 of 216 kept; an element is now
    registered on the registration's tangent when that fits its pixels better
    (``triplet.refine_element``): every fully visible corner, no wrong id."""
    src = bench.source_truth("labumk_negative.tif")
    case = next(c for c in bench.cases(False, 5) if c.name == "labumk, misaligned s0")
    for d in bench.run_case(case, src, tmp_path, models=(), images=False)["detections"]:
        assert d["code"] == 0, d["message"]
        assert d["wrong_ids"] == 0 and d["coverage"] == 1.0, d


@pytest.mark.slow
def test_a_refused_union_keeps_the_second_pass_corners_the_first_pass_reaches(tmp_path):
    """The LAB-UMK micrograph through the misaligned relay of seed 3: the union of both
    refinements (group 5's elements registered one by one) failed the global check (Eq. (1)
    `full` rms 0.89 px against 0.75: the field bends there) and its first pass alone was kept,
    132 of 216 corners.  Then the second pass's corners that a cubic map grown from the first
    pass reaches were added (``core._grown_from_first``: 168).  Now the union passes the
    check itself, a cubic map fitting it with 0.31 px rms (``checks.check_consistency``):
    215 of 216, the largest error 0.92 px.  Either way: no wrong id, more corners."""
    src = bench.source_truth("labumk_negative.tif")
    case = next(c for c in bench.cases(False, 5) if c.name == "labumk, misaligned s3")
    for d in bench.run_case(case, src, tmp_path, models=(), images=False)["detections"]:
        assert d["code"] == 0, d["message"]
        assert d["wrong_ids"] == 0 and d["found"] >= 200 and d["max_error_px"] < 1.0
