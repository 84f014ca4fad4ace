"""The calibration file of a self-calibration keeps what it found (``selfcal``), and the
HTML report shows it: frames, matches, the gauge, residuals, the misalignment (relay)."""

import dataclasses
import html
import json

import numpy as np
import pytest

from oapcal.io.calibration import load_calibration, save_calibration
from oapcal.report import build_report
from oapcal.selfcal import self_calibrate


@pytest.fixture(scope="module")
def radial(distorted):
    return self_calibrate(distorted, "radial")


def test_the_record_holds_what_the_solve_found(radial, distorted):
    rec = radial.calibration.selfcal
    assert rec["frames"] == 9 and rec["moves"] == "unknown"
    assert rec["pairs"] == len(distorted.pairs) and rec["matches"] == len(distorted)
    assert rec["inliers"] == int(radial.inlier.sum()) == radial.calibration.residuals.n_points
    assert rec["gauge"] == list(radial.gauge)
    assert rec["gauge_left"] == pytest.approx(radial.gauge_left)
    np.testing.assert_allclose(rec["translations_px"], radial.translations)
    table = rec["pair_table"]
    assert [(q["a"], q["b"]) for q in table] == [(p.a, p.b) for p in distorted.pairs]
    assert sum(q["matches"] for q in table) == len(distorted)
    assert sum(q["inliers"] for q in table) == rec["inliers"]
    # a pair's RMS from the per-match residuals, directly
    q = table[0]
    sel = (distorted.frame_a == q["a"]) & (distorted.frame_b == q["b"]) & radial.inlier
    assert q["rms_px"] == pytest.approx(np.sqrt(np.mean(np.sum(radial.residuals[sel] ** 2, axis=1))))


def test_the_file_keeps_it_and_the_report_shows_it(radial, tmp_path):
    path = tmp_path / "calib.json"
    save_calibration(radial.calibration, path)
    assert json.loads(path.read_text())["selfcal"]["frames"] == 9
    cal = load_calibration(path)
    assert cal.selfcal == json.loads(json.dumps(radial.calibration.selfcal))
    page, _ = build_report(cal)
    assert '<section id="selfcal"><h2>Self-calibration</h2>' in page
    text = html.unescape(page)
    rec = cal.selfcal
    assert "Solved from 9 frames" in text
    assert f"{rec['inliers']} of {rec['matches']} matches in {rec['pairs']} overlapping pairs" in text
    for line in rec["gauge"]:
        assert line in text
    assert "The misalignment found" not in text  # Eq. (1): its parameters are the section above
    assert 'alt="frame moves and pairs"' in page
    worst = max(rec["pair_table"], key=lambda q: q["rms_px"])
    assert f"<td>{worst['a']} - {worst['b']}</td>" in page


def test_a_calibration_without_the_record_has_no_section(radial, tmp_path):
    """A landmark fit's record (``selfcal`` None) writes no key and gets no section."""
    cal = dataclasses.replace(radial.calibration, selfcal=None)
    path = tmp_path / "fit.json"
    save_calibration(cal, path)
    assert "selfcal" not in json.loads(path.read_text())
    page, _ = build_report(load_calibration(path))
    assert 'id="selfcal"' not in page and "Fitted parameters" in page


def test_report_command_on_a_selfcal_file(run_cli, radial, tmp_path):
    path = tmp_path / "calib.json"
    save_calibration(radial.calibration, path)
    out = tmp_path / "report.html"
    code, stdout, err = run_cli("report", path, "--out", out)
    assert code == 0, err
    assert '<section id="selfcal">' in out.read_text()
    code, stdout, err = run_cli("report", path, "--out", tmp_path / "again.html", "--json")
    assert code == 0, err
    numbers = json.loads(stdout)
    assert numbers["selfcal"] == json.loads(json.dumps(radial.calibration.selfcal))
    assert numbers["selfcal"]["frames"] == 9 and numbers["selfcal"]["pair_table"]


def test_report_json_has_no_selfcal_for_a_landmark_fit(run_cli, radial, tmp_path):
    path = tmp_path / "fit.json"
    save_calibration(dataclasses.replace(radial.calibration, selfcal=None), path)
    code, stdout, err = run_cli("report", path, "--out", tmp_path / "r.html", "--json")
    assert code == 0, err
    assert json.loads(stdout)["selfcal"] is None


@pytest.mark.slow  # renders 9 frames through a misaligned relay (~20 s)
def test_the_report_shows_the_relay_misalignment_found():
    from selfcal_scenes import texture
    from test_selfcal_relay import DESIGN, TRUTH_MIS, _frames

    from oapcal.optics.relay_model import describe, relay_params
    from oapcal.selfcal import find_matches

    moves = np.array([(i * 40.0, j * 30.0) for j in (-1, 0, 1) for i in (-1, 0, 1)])
    frames = _frames(relay_params(DESIGN, TRUTH_MIS), moves, texture(3))
    result = self_calibrate(find_matches(frames, prior=relay_params(DESIGN)), "relay", design=DESIGN)
    page, _ = build_report(result.calibration)
    text = html.unescape(page[page.index('<section id="selfcal">') :])
    assert "The misalignment found" in text
    lines = describe(result.calibration)
    assert any(line.startswith("camera_defocus") for line in lines)
    for line in lines:
        assert line in text
