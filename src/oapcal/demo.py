"""The end-to-end demonstration on built-in data (``oapcal demo``).

Generates the example point pairs from known parameters (:mod:`oapcal.synthetic`),
fits the paper's model, scores it as in the paper's Table 1, corrects the points and
writes everything into one directory.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np


@dataclass(frozen=True)
class DemoResult:
    out_dir: Path
    files: dict[str, Path]
    calibration: object
    max_abs_z: float


def run_demo(out_dir: str | Path, *, seed: int = 0, um_per_px: float = 4.8) -> DemoResult:
    """Run the demonstration, writing into ``out_dir`` (created if missing)."""
    from oapcal.calibrate import calibrate
    from oapcal.io.calibration import save_calibration
    from oapcal.io.points import write_point_pairs
    from oapcal.model import INDEX
    from oapcal.synthetic import synthetic_pairs

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    data = synthetic_pairs(seed=seed)
    files = {"points": out / "points.csv", "calibration": out / "calibration.json"}
    write_point_pairs(files["points"], data.xy_u, data.xy_d, ids=np.arange(len(data.xy_u)))
    cal = calibrate(
        data.xy_u, data.xy_d, "paper", um_per_px=um_per_px, image_size=(640, 480),
        name="demo", source=str(files["points"]),
    )  # fmt: skip
    save_calibration(cal, files["calibration"])
    z = [(cal.params[INDEX[n]] - data.params[INDEX[n]]) / cal.stderr[INDEX[n]] for n in cal.free]
    return DemoResult(out, files, cal, float(np.max(np.abs(z))))
