"""``oapcal correct`` with an Eq. (1) calibration loads neither Numba (the compiled kernels)
nor scipy.ndimage: the fold-over check, the map and the trust region go through the NumPy
closed form (oapcal.eq1_closed_form) and the NumPy bilinear interpolation, the command's
fixed cost (docs/benchmarks.md, issue 23).  A relay calibration still uses the kernels."""

import os
import subprocess
import sys

import numpy as np
import pytest
import tifffile

from oapcal.calibration import calibrate
from oapcal.io.calibration import save_calibration
from oapcal.synthetic import synthetic_pairs
from paths import SRC

#: Runs the command as ``python -m oapcal`` does, then says which heavy modules it loaded.
RUN = """
import runpy, sys
sys.argv = ["oapcal", *sys.argv[1:]]
try:
    runpy.run_module("oapcal", run_name="__main__")
except SystemExit as exc:
    code = exc.code
print("LOADED", [m for m in ("numba", "scipy.ndimage") if m in sys.modules], "EXIT", code)
"""


@pytest.mark.parametrize("model", ["paper", "paper+rotation"])
def test_correct_loads_no_compiled_core(tmp_path, model):
    data = synthetic_pairs(seed=0)
    cal = calibrate(data.xy_u, data.xy_d, model, image_size=(640, 480), rotation="none")
    save_calibration(cal, tmp_path / "cal.json")
    frames = np.random.default_rng(0).integers(0, 255, (2, 480, 640), dtype=np.uint8)
    tifffile.imwrite(tmp_path / "stack.tif", frames, photometric="minisblack")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(SRC.parent), os.environ.get("PYTHONPATH", "")])}
    argv = ["correct", str(tmp_path / "cal.json"), str(tmp_path / "stack.tif"), "--quiet",
            "--out-dir", str(tmp_path / "out")]  # fmt: skip
    out = subprocess.run([sys.executable, "-c", RUN, *argv], capture_output=True, text=True, env=env)
    assert "LOADED [] EXIT 0" in out.stdout, out.stdout + out.stderr
    corrected = tifffile.imread(tmp_path / "out" / "stack.tif")
    assert corrected.shape == frames.shape and corrected.any()
