"""Make the pictures of docs/usaf.md and docs/detection.md (simulated, detected, corrected)
for the ray-traced relay of setup 1 (the image is turned by 180 degrees).

Run: PYTHONPATH=src .venv/bin/python scripts/make_usaf_pictures.py
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from oapcal.fitting import fit
from oapcal.imaging.detect import detect_usaf, evaluate_detection
from oapcal.imaging.remap import correct_image, correction_map
from oapcal.imaging.simulate import simulate_image
from oapcal.optics import relay_distortion
from oapcal.report.detect_plots import plot_image

OUT = Path(__file__).resolve().parents[1] / "docs" / "img"


def main():
    OUT.mkdir(parents=True, exist_ok=True)
    sim = simulate_image((4, 5), relay_distortion(1), sigma_px=0.8, snr=50, seed=0)
    det = detect_usaf(sim.image, (4, 5), sim.um_per_px)
    score = evaluate_detection(det, sim.ids, sim.xy_d, sim.visible)
    crop = np.array([190, 120, 450, 360])
    plot_image(
        sim.image, OUT / "usaf_simulated.png", crop=crop,
        title="Simulated: groups 4-5 through the traced relay (setup 1), sigma 0.8 px, SNR 50",
        points={"paraxial (undistorted) corners, turned 180 degrees": sim.xy_u},
    )  # fmt: skip
    plot_image(
        sim.image, OUT / "usaf_detected.png", crop=crop,
        title=f"Detected ({det.orientation}): {score['found']}/{score['visible']} corners, median "
        f"error {score['median_error_px']:.3f} px, {score['mismatches']} mismatches",
        points={"detected": det.xy_d},
    )  # fmt: skip
    result = fit(det.xy_u, det.xy_d, "paper", init="pixel")
    corrected = correct_image(sim.image, correction_map(result.params, sim.image.shape), "cubic")
    plot_image(
        corrected, OUT / "usaf_corrected.png", crop=crop,
        title="Corrected with the paper model fitted to the detected corners",
        points={"reference corners": det.xy_u},
    )  # fmt: skip
    for p in sorted(OUT.glob("usaf_*.png")):
        print(p.name, p.stat().st_size // 1024, "kB")


if __name__ == "__main__":
    main()
