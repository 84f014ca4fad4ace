"""The report in a real browser: headless Chromium (Debian's ``chromium`` package, installed
by ``scripts/ensure-chromium.sh``) must render it with no console errors and every image
loaded, and print it to PDF.

How: a copy of the page gets a probe script at the top of <head> that records error events
(script errors and resources that fail to load, caught in the capture phase) and
``console.error`` calls, and on ``load`` writes them, with the number of images whose
``naturalWidth`` is 0, into an attribute of <html>; ``--dump-dom`` prints the DOM after the
load event.  Chromium's own log (``--enable-logging=stderr``) must hold no CONSOLE line.
A negative control (a broken image, a console error, a thrown error) shows the probe works.
"""

import html
import json
import re
import shutil
import subprocess
from pathlib import Path

import cv2
import numpy as np
import pytest

from paths import REPO

CHROMIUM = Path("/usr/bin/chromium")
pytestmark = pytest.mark.skipif(
    not CHROMIUM.exists(),
    reason="/usr/bin/chromium is missing: run scripts/ensure-chromium.sh (as root) to install it",
)
FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync",
         "--hide-scrollbars"]  # fmt: skip

PROBE = """<script>
window.__errors = [];
window.addEventListener("error", function (e) {
  window.__errors.push(e.message || ("failed to load " + (e.target && (e.target.src || e.target.href))));
}, true);
var __ce = console.error;
console.error = function () { window.__errors.push(Array.prototype.join.call(arguments, " ")); };
window.addEventListener("load", function () {
  var imgs = Array.prototype.slice.call(document.images);
  var broken = imgs.filter(function (i) { return !i.complete || i.naturalWidth === 0; }).length;
  document.documentElement.setAttribute("data-probe",
    JSON.stringify({images: imgs.length, broken: broken, errors: window.__errors}));
});
</script>"""


def run_chromium(tmp_path, *args, timeout=90):
    profile = tmp_path / f"profile-{len(list(tmp_path.glob('profile-*')))}"
    cmd = [str(CHROMIUM), *FLAGS, f"--user-data-dir={profile}", *args]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, check=False)


def probe(tmp_path, page: Path) -> tuple[dict, list[str]]:
    text = page.read_text()
    probed = tmp_path / f"probed-{page.name}"
    probed.write_text(text.replace("<head>", "<head>" + PROBE, 1))
    proc = run_chromium(tmp_path, "--enable-logging=stderr", "--v=0", "--dump-dom", probed.as_uri())
    assert proc.returncode == 0, proc.stderr[-2000:]
    match = re.search(r'data-probe="([^"]*)"', proc.stdout)
    assert match, "the page's load event never ran: " + proc.stdout[:500]
    console = [line for line in proc.stderr.splitlines() if ":CONSOLE" in line]
    return json.loads(html.unescape(match.group(1))), console


def test_probe_catches_errors_and_broken_images(tmp_path):
    page = tmp_path / "bad.html"
    page.write_text('<!DOCTYPE html><html><head></head><body><img src="data:image/png;base64,AAAA">'
                    '<img src="missing.png"><script>console.error("boom"); undefinedFunction();</script>'
                    "</body></html>")  # fmt: skip
    result, console = probe(tmp_path, page)
    assert result["images"] == 2 and result["broken"] == 2
    assert any("boom" in e for e in result["errors"])
    assert any("undefinedFunction" in e for e in result["errors"])
    assert any("missing.png" in e for e in result["errors"])


@pytest.fixture(scope="module")
def demo_like_report(tmp_path_factory):
    from oapcal.calibration import calibrate
    from oapcal.imaging.bars import bar_target, demo_layout
    from oapcal.report import build_report, write_report
    from oapcal.synthetic import EXAMPLE_TRUTH, synthetic_pairs

    truth = EXAMPLE_TRUTH.copy()  # half-size example distortion centred on a 320 x 240 frame
    truth[[8, 9, 10, 11]] = [-160.0, -120.0, 160.0, 120.0]
    truth[0] *= 4
    d = tmp_path_factory.mktemp("browser")
    data = synthetic_pairs(truth, n_x=12, n_y=9, size=(320, 240), margin=20, noise_px=0.2, seed=5)
    cal = calibrate(data.xy_u, data.xy_d, "paper", um_per_px=4.8, image_size=(320, 240), name="browser test")
    image, _ = bar_target((240, 320), demo_layout((240, 320), bar=8), sigma=1.1, low=30, high=220,
                          params=truth, noise=1.0, seed=5)  # fmt: skip
    text, _ = build_report(cal, points=(data.xy_u, data.xy_d), image=np.round(image))
    write_report(d / "report.html", text)
    return d / "report.html"


def test_report_renders_without_errors_and_all_images_load(tmp_path, demo_like_report):
    result, console = probe(tmp_path, demo_like_report)
    assert result["errors"] == []
    assert result["images"] == 6 and result["broken"] == 0  # with the predicted error and trust region
    assert console == []  # nothing at all on the page's console


def test_screenshot_and_print(tmp_path, demo_like_report):
    shot = tmp_path / "report.png"
    proc = run_chromium(
        tmp_path, "--window-size=1280,2400", f"--screenshot={shot}", demo_like_report.as_uri()
    )
    assert proc.returncode == 0 and shot.exists(), proc.stderr[-2000:]
    image = cv2.imread(str(shot), cv2.IMREAD_GRAYSCALE)
    assert image.shape == (2400, 1280)
    assert image.std() > 20  # not a blank page: text, tables and figures
    keep = REPO / ".pytest_cache" / "report-screenshot.png"
    keep.parent.mkdir(exist_ok=True)
    shutil.copyfile(shot, keep)  # for a human to look at after the run
    pdf = tmp_path / "report.pdf"
    proc = run_chromium(
        tmp_path, "--no-pdf-header-footer", f"--print-to-pdf={pdf}", demo_like_report.as_uri()
    )
    assert proc.returncode == 0 and pdf.exists(), proc.stderr[-2000:]
    data = pdf.read_bytes()
    assert data[:5] == b"%PDF-"
    assert len(re.findall(rb"/Type\s*/Page[^s]", data)) >= 3  # A4 pages with the figures
