"""The report and the esf/report/demo commands, through the CLI runner."""

import base64
import json
import re

import cv2
import numpy as np
import pytest

from oapcal.calibration import calibrate
from oapcal.imaging.bars import bar_target, demo_layout
from oapcal.io.calibration import save_calibration
from oapcal.io.points import write_point_pairs
from oapcal.io.results import save_robustness, save_selection
from oapcal.model import bits_from_mask, names_from_mask, parse_model
from oapcal.select import ModelRobustness, ModelScore, Robustness, Selection
from oapcal.synthetic import EXAMPLE_TRUTH, synthetic_pairs

# A half-size version of the example distortion, centred on a 320 x 240 frame.
TRUTH = EXAMPLE_TRUTH.copy()
TRUTH[[8, 9, 10, 11]] = [-160.0, -120.0, 160.0, 120.0]
TRUTH[0] *= 4


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    d = tmp_path_factory.mktemp("report")
    data = synthetic_pairs(TRUTH, n_x=12, n_y=9, size=(320, 240), margin=20, noise_px=0.2, seed=4)
    write_point_pairs(d / "points.csv", data.xy_u, data.xy_d)
    cal = calibrate(data.xy_u, data.xy_d, "paper", um_per_px=4.8, image_size=(320, 240), name="test")
    save_calibration(cal, d / "calib.json")
    image, _ = bar_target((240, 320), demo_layout((240, 320), bar=8), sigma=1.1, low=30, high=220,
                          params=TRUTH, noise=1.0, seed=4)  # fmt: skip
    cv2.imwrite(str(d / "target.png"), np.clip(np.round(image), 0, 255).astype(np.uint8))

    # the selection and robustness files as 'oapcal select --json' / 'oapcal robustness --json' write them
    def score(spec, aicc, delta, weight, rss, reason="", code=""):
        free = names_from_mask(parse_model(spec))
        return ModelScore(bits=int(bits_from_mask(parse_model(spec))), free=free, k=len(free), aicc=aicc,
                          delta_aicc=delta, weight=weight, rss=rss, mean_error=0.1, valid=not reason,
                          reason=reason, fit_status=0 if reason else 1, reason_code=code)  # fmt: skip

    nan = float("nan")
    selection = Selection(len(data.xy_u), "experiment", "zero", (
        score(",".join(cal.free), -10.0, 0.0, 0.9, 1.0),
        score("k1,c_x,c_y,m", 50.0, 60.0, 0.0, 9.0),
        score("full", nan, nan, nan, nan, "fit did not converge (iteration cap)", "not_converged"),
    ))  # fmt: skip
    save_selection(selection, d / "sel.json")

    def trials(name, spec, not_converged, by_reason, param_std, heldout):
        return ModelRobustness(name, names_from_mask(parse_model(spec)), 100, not_converged, by_reason,
                               param_std, heldout, 0, 0.2, np.zeros(0, np.int64))  # fmt: skip

    robustness = Robustness(len(data.xy_u), 86, 0.8, 0, "pixel", "experiment", 3.0, (
        trials(",".join(cal.free), ",".join(cal.free), 0, {}, {"k1": 1e-7}, 0.31),
        trials("full", "full", 41, {"iteration_cap": 41}, {}, 0.5),
    ))  # fmt: skip
    save_robustness(robustness, d / "rob.json")
    return d, cal


@pytest.fixture(scope="module")
def report(inputs):
    """The report made once by the CLI with every input: (path, the --json numbers)."""
    import contextlib
    import io

    from oapcal.cli import main

    d, _ = inputs
    out = d / "report.html"
    stdout = io.StringIO()
    with contextlib.redirect_stdout(stdout):
        code = main(["report", str(d / "calib.json"), "--points", str(d / "points.csv"), "--image",
                     str(d / "target.png"), "--selection", str(d / "sel.json"), "--robustness",
                     str(d / "rob.json"), "--out", str(out), "--json"])  # fmt: skip
    assert code == 0
    return out, json.loads(stdout.getvalue())


def test_report_is_self_contained_and_has_every_section(report, inputs):
    report_html, _ = report
    _, cal = inputs
    text = report_html.read_text()
    assert "<script" not in text and "http://" not in text and "https://" not in text
    images = re.findall(r'<img src="data:image/png;base64,([^"]+)"', text)
    assert (
        len(images) == 6
    )  # residuals, field, uncertainty, predicted error + trust region, before/after, ESF
    for b64 in images:
        png = base64.b64decode(b64)
        assert png[:8] == b"\x89PNG\r\n\x1a\n"
        assert cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR).shape[1] > 400
    for heading in ("Summary", "Fitted parameters", "Residual vectors", "Distortion field",
                    "Uncertainty of the correction", "Image before and after correction",
                    "Edge spread functions", "Model selection", "Robustness"):  # fmt: skip
        assert f"<h2>{heading}</h2>" in text
    # Table 1 from the points equals the calibration's own residuals (same points, same model).
    assert f"<td>{cal.residuals.mean_px:.4g}</td>" in text
    assert f"<td>{cal.residuals.mean_um:.4g}</td>" in text
    assert 'class="best"' in text and "did not converge" in text and "41.0 %" in text
    d, _ = inputs
    assert f"From {d / 'sel.json'}." in text and f"From {d / 'rob.json'}." in text
    assert "@media print" in text


def test_report_numbers_show_the_correction_works(report, inputs):
    _, numbers = report
    _, cal = inputs
    assert numbers["residuals"]["mean_px"] == pytest.approx(cal.residuals.mean_px)
    before, after = numbers["checks"]["before"], numbers["checks"]["after"]
    assert after["n_shapes"] >= 20 and after["n_edges"] >= 90
    assert after["straightness_max_px"] < 0.25 * before["straightness_max_px"]
    assert after["aspect_error_mean_pct"] < 1.0 < before["aspect_error_mean_pct"]
    assert numbers["esf"]["sigma_mean_px"] == pytest.approx(1.1, rel=0.1)  # rendered with sigma 1.1 px
    u = numbers["uncertainty"]
    assert 0 < u["inside_median_px"] < u["outside_max_px"]


def test_esf_command_json_and_plot(run_cli, tmp_path):
    image, rects = bar_target((120, 160), [(40.5, 30.5, 70.5, 90.5)], sigma=1.5, low=20, high=200, noise=1.0)
    cv2.imwrite(str(tmp_path / "edge.png"), np.round(image).astype(np.uint8))
    code, out, err = run_cli("esf", tmp_path / "edge.png", "--auto", "--json", "--um-per-px", "2.5",
                             "--plot", tmp_path / "esf.png")  # fmt: skip
    assert code == 0, err
    result = json.loads(out)
    assert result["n_edges"] == 4 and result["n_ok"] == 4
    assert result["sigma_mean_px"] == pytest.approx(1.5, rel=0.05)
    assert result["sigma_max_um"] == pytest.approx(2.5 * result["sigma_max_px"])
    assert (tmp_path / "esf.png").read_bytes()[:4] == b"\x89PNG"
    rois = tmp_path / "rois.csv"
    rois.write_text("label,x0,y0,x1,y1\nleft,33,45,47,75\n")
    code, out, _ = run_cli("esf", tmp_path / "edge.png", "--rois", rois)
    assert code == 0 and "left" in out and "sigma max 1.5" in out


@pytest.mark.parametrize(
    "args,pattern",
    [
        (["esf", "{tmp}/nope.png"], "no such image file"),
        (["esf", "{tmp}/edge.png", "--rois", "{tmp}/bad.csv"], "line 2, column 'y1': 'ten' is not a number"),
        (
            ["esf", "{tmp}/edge.png", "--rois", "{tmp}/out.csv"],
            "is not a rectangle inside the 60 x 40 px image",
        ),
        (["esf", "{tmp}/flat.png"], "no straight edges found"),
        (["report", "{tmp}/calib.json", "--out", "{tmp}/calib.json"], "would overwrite the input"),
        (
            ["report", "{tmp}/calib.json", "--selection", "{tmp}/bad.csv", "--out", "{tmp}/r.html"],
            "malformed JSON",
        ),
        (
            ["report", "{tmp}/calib.json", "--robustness", "{tmp}/rob.json", "--out", "{tmp}/r.html"],
            "field 'models.paper': 'not_converged' is a required property",
        ),
        (
            ["report", "{tmp}/calib.json", "--image", "{tmp}/bad.csv", "--out", "{tmp}/r.html"],
            "unsupported file type",
        ),
    ],
)
def test_user_errors_exit_2_one_line_nothing_written(run_cli, tmp_path, inputs, args, pattern):
    d, cal = inputs
    save_calibration(cal, tmp_path / "calib.json")
    cv2.imwrite(str(tmp_path / "edge.png"), np.zeros((40, 60), np.uint8))
    cv2.imwrite(str(tmp_path / "flat.png"), np.full((40, 60), 9, np.uint8))
    (tmp_path / "bad.csv").write_text("x0,y0,x1,y1\n1,2,3,ten\n")
    (tmp_path / "out.csv").write_text("x0,y0,x1,y1\n50,2,70,30\n")
    rob = json.loads((d / "rob.json").read_text())
    rob["models"] = {
        "paper": {k: v for k, v in next(iter(rob["models"].values())).items() if k != "not_converged"}
    }
    (tmp_path / "rob.json").write_text(json.dumps(rob))
    before = sorted(p.name for p in tmp_path.iterdir())
    code, _, err = run_cli(*(a.format(tmp=tmp_path) for a in args))
    assert code == 2, err
    assert err.count("\n") == 1 and pattern in err and "Traceback" not in err
    assert sorted(p.name for p in tmp_path.iterdir()) == before


@pytest.mark.slow  # the report's sections are tested in the default suite
def test_report_is_computed_then_rendered_with_progress_through_a_callback(inputs):
    from oapcal.io.points import read_points
    from oapcal.report import build_report, compute_report, render_report

    d, cal = inputs
    pairs = read_points(d / "points.csv")
    calls = []
    page, data = build_report(cal, points=(pairs.xy_u, pairs.xy_d), progress=lambda *a: calls.append(a))
    # one call as each step starts, counted over both phases against one total
    assert [c[0] for c in calls] == list(range(len(calls))) and {c[1] for c in calls} == {len(calls)}
    assert [c[2] for c in calls] == ["correcting the landmarks", "uncertainty map", "residual vectors",
                                     "distortion field", "uncertainty map"]  # fmt: skip
    content = compute_report(cal, points=(pairs.xy_u, pairs.xy_d))
    assert content.shape == (240, 320) and content.image is None
    assert content.data == data and data.residuals["n_points"] == len(pairs)
    again = render_report(content)
    assert 'id="residual-vectors"' in again and 'id="image"' not in again
    without_time = re.compile(r"report made [0-9: -]+UTC")
    assert without_time.sub("", again) == without_time.sub("", page)


def test_the_report_package_leaves_the_terminal_to_the_cli():
    from pathlib import Path

    import oapcal.report

    for path in Path(oapcal.report.__file__).parent.glob("*.py"):
        text = path.read_text(encoding="utf-8")
        assert "from rich" not in text and "import rich" not in text, path.name
        assert "matplotlib.pyplot" not in text and "matplotlib.use(" not in text, path.name
