"""The report of a relay calibration and of Eq. (1) with the target's rotation."""

import html
import json
import re

import cv2
import numpy as np
import pytest

from oapcal.imaging.bars import bar_target, demo_layout
from oapcal.io.calibration import save_calibration
from oapcal.io.points import write_point_pairs
from oapcal.model import PARAM_NAMES, RELAY_MISALIGNMENT_NAMES, RELAY_POSE_NAMES, distort, undistort
from relay_helpers import TRUE_MISALIGNMENT, relay_calibration, write_relay_calibration


def _table(text: str, caption: str) -> list[list[str]]:
    """The body cells of the table with ``caption`` in a report page."""
    head = "<table><caption>" + re.escape(html.escape(caption, quote=True))
    m = re.search(head + r"</caption>(.*?)</table>", text, re.S)
    assert m, f"no table {caption!r}"
    body = m.group(1).split("<tbody>", 1)[1]
    return [[html.unescape(c) for c in re.findall(r"<td[^>]*>(.*?)</td>", row)]
            for row in re.findall(r"<tr[^>]*>(.*?)</tr>", body, re.S)]  # fmt: skip


def _report(d, *extra):
    """``oapcal report`` of the relay calibration with the calibration's points (exact
    images of the fitted relay, on a 20 px grid in the calibrated box) and ``extra``
    arguments: (page text, --json numbers)."""
    import contextlib
    import io

    from oapcal.cli import main

    cal = relay_calibration()
    calib = write_relay_calibration(d / "relay.json")
    gx, gy = np.meshgrid(np.arange(180.0, 470, 20), np.arange(140.0, 350, 20))
    xy_u = np.stack([gx.ravel(), gy.ravel()], -1)
    write_point_pairs(d / "points.csv", xy_u, distort(xy_u, cal.params))
    stdout = io.StringIO()
    with contextlib.redirect_stdout(stdout):
        code = main(["report", str(calib), "--points", str(d / "points.csv"), "--out", str(d / "report.html"),
                     "--json", *(str(a) for a in extra)])  # fmt: skip
    assert code == 0
    return (d / "report.html").read_text(), json.loads(stdout.getvalue())


@pytest.fixture(scope="module")
def relay_report(tmp_path_factory):
    return _report(tmp_path_factory.mktemp("relay_report"))


def test_relay_report_shows_the_family_and_its_parameters(relay_report):
    text, numbers = relay_report
    cal = relay_calibration()
    assert "relay (the physical relay" in text
    rows = _table(text, "Parameters of the physical relay (pose of the target, misalignment of the relay)")
    # every parameter of the relay but its design's constants, in the family's order
    assert [r[0] for r in rows] == list(RELAY_POSE_NAMES + RELAY_MISALIGNMENT_NAMES)
    by_name = {r[0]: r for r in rows}
    for name in cal.free:
        assert by_name[name][-1] == "free"
    assert by_name["m1_tilt_x"][-1] == "fixed (design)" and by_name["camera_tilt_y"][4] == "deg"
    # the fitted misalignment is the one the points were traced with (within 3 standard errors)
    for name, truth in TRUE_MISALIGNMENT.items():
        value, err = float(by_name[name][1]), float(by_name[name][2])
        assert abs(value - truth) < 3 * err + 1e-3 * abs(truth), name
    # the relay as fitted, in physical words, and the design it started from
    assert "The relay as fitted" in text
    assert re.search(r"<li>camera_tilt_y: image plane rotated about its y axis \(rows\): 0\.5\d* \+/- ", text)
    design = dict((r[0], r[1]) for r in _table(text, "The nominal relay the fit started from"))
    assert design["setup"] == "1" and design["pixel_size_um"] == "4.8" and design["centre"] == "319.5, 239.5"
    assert numbers["model"]["family"] == "relay" and numbers["model"]["free"] == list(cal.free)
    from oapcal.optics.relay_model import describe

    assert numbers["model"]["as_fitted"] == describe(cal)
    assert [line.split(":")[0] for line in numbers["model"]["as_fitted"]] == list(cal.free)


def test_relay_report_numbers(relay_report):
    text, numbers = relay_report
    # the points are exact images of the fitted relay: corrected, they land on their references
    assert numbers["residuals"]["n_points"] == 165 and numbers["residuals"]["max_px"] < 1e-6
    for heading in ("Residual vectors", "Distortion field", "Uncertainty of the correction"):
        assert f"<h2>{heading}</h2>" in text
    u = numbers["uncertainty"]
    assert 0 < u["inside_median_px"] < u["outside_max_px"]


@pytest.mark.slow
def test_relay_report_with_an_image_of_a_bar_target(tmp_path):
    """A bar target imaged through the fitted relay comes out straight (the image is made
    with the inverse on a 8 px grid, interpolated: tracing every pixel takes long)."""
    cal = relay_calibration()
    target, _ = bar_target((480, 640), demo_layout((480, 640), bar=12), sigma=1.1, low=30, high=220)
    gx, gy = np.meshgrid(np.arange(0.0, 648, 8), np.arange(0.0, 488, 8))
    inv = undistort(np.stack([gx, gy], -1).reshape(-1, 2), cal.params).xy.reshape(gx.shape + (2,))
    fine = [cv2.resize(inv[..., k].astype(np.float32), None, fx=8, fy=8, interpolation=cv2.INTER_CUBIC)
            for k in (0, 1)]  # fmt: skip
    # resize aligns pixel centres: coarse sample i sits at fine (i + 0.5) * 8 - 0.5; shift back
    shift = np.float32([[1, 0, -3.5], [0, 1, -3.5]])
    mx, my = (cv2.warpAffine(f, shift, (640, 480), flags=cv2.INTER_LINEAR) for f in fine)
    image = cv2.remap(target.astype(np.float32), mx, my, cv2.INTER_LINEAR, borderValue=30)
    image += np.random.default_rng(2).normal(0, 1.0, image.shape)
    cv2.imwrite(str(tmp_path / "target.png"), np.clip(np.round(image), 0, 255).astype(np.uint8))
    text, numbers = _report(tmp_path, "--image", tmp_path / "target.png")
    before, after = numbers["checks"]["before"], numbers["checks"]["after"]
    assert after["n_edges"] >= 50
    assert after["straightness_max_px"] < 0.25 * before["straightness_max_px"]
    for heading in ("Image before and after correction", "Edge spread functions"):
        assert f"<h2>{heading}</h2>" in text


def test_relay_uncertainty_equals_an_independent_propagation():
    """The map's sigma at one pixel against the covariance propagated with Jacobians taken
    here by central differences of distort()."""
    from oapcal.uncertainty import uncertainty_map

    cal = relay_calibration()
    umap = uncertainty_map(cal, (480, 640), step=80)
    names = cal.family.param_names
    idx = [names.index(n) for n in cal.free]
    u = np.array([[umap.x[3], umap.y[2]]])
    h = 1e-3
    jp = np.empty((2, len(idx)))
    for j, i in enumerate(idx):
        dp = np.zeros(len(names))
        dp[i] = h * max(abs(cal.params[i]), 1.0)
        jp[:, j] = (distort(u, cal.params + dp) - distort(u, cal.params - dp))[0] / (2 * dp[i])
    ju = np.empty((2, 2))
    for k in range(2):
        du = np.zeros((1, 2))
        du[0, k] = 1e-2
        ju[:, k] = (distort(u + du, cal.params) - distort(u - du, cal.params))[0] / 2e-2
    a = np.linalg.solve(ju, jp)
    s = a @ cal.covariance @ a.T
    assert umap.sigma_px[2, 3] == pytest.approx(np.sqrt(s[0, 0] + s[1, 1]), rel=1e-3)


def test_rotation_family_report_lists_the_rotation(run_cli, tmp_path):
    from oapcal.calibration import calibrate
    from oapcal.synthetic import synthetic_pairs

    data = synthetic_pairs(seed=3)
    c, s = np.cos(np.deg2rad(0.5)), np.sin(np.deg2rad(0.5))
    # the reference points turned by +0.5 deg: the model turns them back by -0.5 deg
    turned = data.xy_u @ np.array([[c, s], [-s, c]])
    cal = calibrate(turned, data.xy_d, "paper+rotation", image_size=(640, 480))
    save_calibration(cal, tmp_path / "rot.json")
    code, out, err = run_cli("report", tmp_path / "rot.json", "--out", tmp_path / "r.html", "--json")
    assert code == 0, err
    assert json.loads(out)["model"]["family"] == "brown-conrady+rotation"
    text = (tmp_path / "r.html").read_text()
    caption = "Parameters of Eq. (1) and the target's rotation (px units of the reference points; deg)"
    rows = _table(text, caption)
    assert [r[0] for r in rows] == list(PARAM_NAMES) + ["rotation"]
    rotation = {r[0]: r for r in rows}["rotation"]
    assert rotation[-1] == "free"
    assert float(rotation[1]) == pytest.approx(-0.5, abs=3 * float(rotation[2]) + 0.02)


def test_report_shows_a_cross_family_selection():
    """A FamilySelection (select --families) is shown as the families compared, with the
    recommendation and this calibration's model highlighted."""
    from oapcal.families import Candidate, FamilySelection
    from oapcal.model import PRESETS
    from oapcal.report import build_report

    cal = relay_calibration()

    def cand(family, spec, free, aicc, cv, valid=True, reason=""):
        return Candidate(family, spec, tuple(free), len(free), aicc, aicc + 3000.0, 0.2, valid, reason, cv)

    ours = cand("relay", "relay", cal.free, -3000.0, 0.0631)
    tilt = cand("relay", "relay:tilt2,camera", [*RELAY_POSE_NAMES, "m2_tilt_x", "m2_tilt_y", "camera_tilt_x",
                "camera_tilt_y"], -3001.0, 0.0628)  # fmt: skip
    paper = cand("brown-conrady", "paper", PRESETS["paper"], 1200.0, 0.2084)
    bad = cand("relay", "relay:object", [*RELAY_POSE_NAMES, "object_tilt_x"], float("nan"), None, False,
               "not identifiable")  # fmt: skip
    sel = FamilySelection(441, 5, (tilt, ours, paper, bad), tilt)
    page, _ = build_report(cal, selection=sel, selection_source="fam.json")
    rows = _table(page, "Best 5 models of each family by AICc (4 models, 441 points)")
    assert [r[1] for r in rows] == ["relay:tilt2,camera", "relay", "paper"]
    assert rows[0][-1] == "recommended" and rows[1][-1] == "this calibration" and rows[2][-1] == ""
    assert rows[1][2] == str(len(cal.free) + 1) and rows[2][6] == "0.2084"
    assert '<tr class="best"><td>relay</td><td>relay</td>' in page
    assert "Recommended in the selection file: relay:tilt2,camera (relay, held-out error 0.0628 px)." in page
    assert "1 models could not be scored" in page and "From fam.json." in page


def test_the_region_based_recommendation_is_named_so():
    from dataclasses import replace

    from oapcal.families import Candidate, FamilySelection
    from oapcal.model import PRESETS
    from oapcal.report import build_report

    cal = relay_calibration()
    ours = Candidate("relay", "relay", cal.free, len(cal.free), -3000.0, 0.0, 0.2, True, "", 0.0631)
    ours = replace(ours, region_sigma=0.05, predicted_error=0.0805)
    paper = Candidate("brown-conrady", "paper", PRESETS["paper"], 8, 1200.0, 4200.0, 0.2, True, "", 0.0601)
    paper = replace(paper, region_sigma=3.1, predicted_error=3.1006)
    sel = FamilySelection(441, 5, (ours, paper), ours)
    page, _ = build_report(cal, selection=sel, selection_source="f.json")
    assert (
        "Recommended by the predicted error over the region to be corrected: relay (relay, 0.0805 px: "
        "the held-out error 0.0631 px with the uncertainty propagated over the region, 0.05 px)."
    ) in page


def test_relay_report_says_its_error_model_averages_the_sides(relay_report):
    """The relay's extrapolation factor is the mean over its sides' refits (Eq. 1: the worst)."""
    text, _ = relay_report
    assert relay_calibration().error_model.method == "leave-side-out-mean"
    assert "(the mean over the 8 refits that each left one side" in html.unescape(text)
