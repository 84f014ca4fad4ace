"""The whole method end to end on built-in data (``oapcal demo``).

1. **trace** the OAP relay of setup 1 (:mod:`oapcal.optics`): a 17 x 17 grid of paraxial
   and real image points over a 1 mm x 1 mm field, as the paper's Figure 3a;
2. **select** the model on that grid by AICc over all 4,096 subsets, with the paper's grid
   normalization and zero start (:mod:`oapcal.select`);
3. **simulate** a camera image of USAF-1951 groups 4-5 through the traced relay (blur
   sigma 0.8 px, peak SNR 50, 640 x 480 px of 4.8 um), as the paper's Figure 3b;
4. **detect** the bar corners automatically and match them to the target;
5. **fit** the selected model to the detected pairs and score it as in the paper's
   Table 1, in px and um; compare the fitted model with the ray-traced truth;
6. test the fit's **robustness** by refitting on random 90 % subsets;
7. **correct** the image where the correction is trusted (predicted error at most
   :data:`oapcal.imaging.remap.DEFAULT_MAX_ERROR_PX`, as ``oapcal correct`` by default);
8. write the **report**.

Everything goes into one directory; :class:`DemoResult` lists the files and numbers.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

STEPS = ("trace", "select", "simulate", "detect", "fit", "robustness", "correct", "report")

PIXEL_UM = 4.8
IMAGE_SIZE = (640, 480)
GROUPS = (4, 5)


@dataclass(frozen=True)
class DemoResult:
    """What the demo made: ``files`` (label -> path) and the numbers it reports."""

    out_dir: Path
    files: dict[str, Path]
    calibration: object
    relay: dict
    selection: object
    detection: dict
    truth_error: dict
    robustness: object | None = None
    extra: dict = field(default_factory=dict)


def run_demo(
    out_dir: str | Path,
    *,
    seed: int = 0,
    trials: int = 1000,
    report: bool = True,
    step: Callable[[str], None] | None = None,
) -> DemoResult:
    """Run the demonstration (module docstring), writing into ``out_dir`` (created).

    ``trials`` is the number of robustness trials (0 skips that step); ``step`` is called
    with each step's name as it starts (for a progress display).  All or nothing: the files
    are made in a hidden directory inside ``out_dir`` and moved into it only when every step
    succeeded; on any error (or Ctrl-C) nothing is left, and ``out_dir`` is removed again if
    the demo created it.
    """
    import os
    import shutil
    import tempfile
    from dataclasses import replace

    from oapcal.errors import OutputError

    final = Path(out_dir)
    if final.exists() and not final.is_dir():
        raise OutputError(
            f"{out_dir}: exists and is not a directory; choose another out_dir", param="out_dir"
        )
    created = not final.exists()
    final.mkdir(parents=True, exist_ok=True)
    stage = Path(tempfile.mkdtemp(prefix=".oapcal-demo-", dir=final))
    try:
        result = _run_steps(stage, final, seed=seed, trials=trials, report=report, step=step)
        from oapcal.io.atomic import check_output_target

        for path in result.files.values():  # none moved unless all may be
            check_output_target(final / path.name)
        files = {}
        for label, path in result.files.items():
            os.replace(path, final / path.name)
            files[label] = final / path.name
        shutil.rmtree(stage)
    except BaseException:
        shutil.rmtree(stage, ignore_errors=True)
        if created:
            shutil.rmtree(final, ignore_errors=True)
        raise
    return replace(result, out_dir=final, files=files)


def _run_steps(out: Path, final: Path, *, seed, trials, report, step) -> DemoResult:
    """The steps of :func:`run_demo`, writing into ``out``; ``final`` is where the files
    will be (named in the calibration's ``source``)."""

    def start(name: str) -> None:
        if step is not None:
            step(name)

    files: dict[str, Path] = {}
    start("trace")
    sim, grid_u, grid_d = _trace(out, files)
    start("select")
    selection, chosen = _select(out, files, grid_u, grid_d)
    start("simulate")
    image = _simulate(out, files, seed)
    start("detect")
    detection, detection_summary = _detect(out, files, image)
    start("fit")
    cal, truth_error = _fit(out, final, files, detection, image, chosen)
    rob = None
    if trials > 0:
        start("robustness")
        rob = _robustness(out, files, detection, chosen, trials, seed)
    start("correct")
    trust = _correct(out, files, cal, image)
    if report:
        start("report")
        _report(out, files, cal, detection, image, rob)
    return DemoResult(
        out_dir=out,
        files=files,
        calibration=cal,
        relay=sim.summary,
        selection=selection,
        detection=detection_summary,
        truth_error=truth_error,
        robustness=rob,
        extra={"chosen": chosen, "trust": trust},
    )


def _trace(out: Path, files: dict):
    """1. the relay's grid distortion, in camera px with the field centre at the image
    centre: ``(simulation, grid_u, grid_d)`` (the grid as written and read back)."""
    from oapcal.io.grid import write_grid_csv
    from oapcal.io.points import read_points
    from oapcal.optics.summary import simulate_relay
    from oapcal.report.optics_plots import plot_grid

    sim = simulate_relay(1, n=17, field_mm=1.0, pixel_size_um=PIXEL_UM)
    files["relay grid"] = out / "grid.csv"
    write_grid_csv(sim.grid, files["relay grid"], "px", PIXEL_UM, IMAGE_SIZE)
    grid = read_points(files["relay grid"])
    files["relay grid plot"] = out / "grid.png"
    plot_grid(sim.grid, files["relay grid plot"], units="px", pixel_size_um=PIXEL_UM)
    return sim, grid.xy_u, grid.xy_d


def _select(out: Path, files: dict, grid_u, grid_d):
    """2. model selection on the grid, as the paper did on its simulated data:
    ``(selection, chosen)``, the model fitted in camera px."""
    from oapcal.io.results import save_selection
    from oapcal.select import select_models, with_frame_terms

    selection = select_models(grid_u, grid_d, normalization="grid")
    files["model selection"] = out / "selection.json"
    save_selection(selection, files["model selection"])
    # the selection on the centred grid decides the distortion terms; camera px need the
    # frame terms as well (select.with_frame_terms)
    return selection, with_frame_terms(selection)


def _simulate(out: Path, files: dict, seed: int):
    """3. a camera image of the target through the traced relay."""
    from oapcal.imaging.simulate import simulate_image
    from oapcal.io.images import write_image
    from oapcal.io.points import write_truth
    from oapcal.optics import relay_distortion

    relay_field = relay_distortion(1, pixel_size_um=PIXEL_UM, image_size=IMAGE_SIZE)
    image = simulate_image(GROUPS, relay_field, sigma_px=0.8, snr=50, seed=seed)
    files["simulated image"] = out / "distorted.png"
    write_image(files["simulated image"], image.image)
    files["ground truth"] = out / "truth.csv"
    write_truth(files["ground truth"], image)
    return image


def _detect(out: Path, files: dict, image):
    """4. automatic landmark detection: ``(detection, summary)``."""
    from oapcal.imaging.detect import detect_usaf, evaluate_detection
    from oapcal.io.jsonfile import write_json
    from oapcal.io.points import write_point_pairs

    detection = detect_usaf(image.image, GROUPS, um_per_px=PIXEL_UM)
    scores = evaluate_detection(detection, image.ids, image.xy_d, image.visible)
    files["detected points"] = out / "points.csv"
    write_point_pairs(files["detected points"], detection.xy_u, detection.xy_d, ids=detection.ids)
    detection_summary = {**detection.summary(), **scores}
    write_json(out / "detection.json", detection_summary)
    files["detection summary"] = out / "detection.json"
    return detection, detection_summary


def _fit(out: Path, final: Path, files: dict, detection, image, chosen):
    """5. the selected model fitted to the detected pairs (Table 1), and its error against
    the ray-traced truth: ``(calibration, truth_error)``."""
    from oapcal.calibration import calibrate
    from oapcal.io.calibration import save_calibration

    cal = calibrate(
        detection.xy_u, detection.xy_d, chosen, um_per_px=PIXEL_UM, image_size=IMAGE_SIZE,
        name="oapcal demo (setup 1)", source=str(final / "points.csv"),
    )  # fmt: skip
    files["calibration"] = out / "calibration.json"
    save_calibration(cal, files["calibration"])
    visible = np.asarray(image.visible, bool)
    err = np.hypot(*(cal.model(image.xy_u[visible]) - image.xy_d[visible]).T)
    return cal, {"n": int(err.size), "mean_px": float(err.mean()), "max_px": float(err.max())}


def _robustness(out: Path, files: dict, detection, chosen, trials: int, seed: int):
    """6. robustness of the chosen model against the full one."""
    from oapcal.io.results import save_robustness
    from oapcal.select import robustness

    rob = robustness(
        detection.xy_u,
        detection.xy_d,
        (",".join(chosen), "full"),
        trials=trials,
        seed=seed,
    )  # the shared default start (fitting.DEFAULT_INIT), as in `oapcal robustness`
    files["robustness"] = out / "robustness.json"
    save_robustness(rob, files["robustness"])
    return rob


def _correct(out: Path, files: dict, cal, image):
    """7. the corrected image, where the correction is trusted; returns the trust summary."""
    from oapcal.imaging.remap import DEFAULT_MAX_ERROR_PX, correct_image, correction_map, trust_summary
    from oapcal.io.images import write_image

    cmap = correction_map(cal, image.image.shape[:2], max_error_px=DEFAULT_MAX_ERROR_PX)
    corrected = correct_image(image.image, cmap, "cubic")
    trust = trust_summary(cal, cmap.geometry, DEFAULT_MAX_ERROR_PX, cmap.predicted_error)
    files["corrected image"] = out / "corrected.png"
    write_image(files["corrected image"], corrected)
    return trust


def _report(out: Path, files: dict, cal, detection, image, rob) -> None:
    """8. the report."""
    from oapcal.io.results import load_robustness, load_selection
    from oapcal.report import build_report, write_report

    html_text, _ = build_report(
        cal, points=(detection.xy_u, detection.xy_d), image=image.image.astype(float),
        image_name="distorted.png", selection=load_selection(files["model selection"]),
        robustness=load_robustness(files["robustness"]) if rob is not None else None,
        selection_source=files["model selection"], robustness_source=files.get("robustness"),
        title="oapcal demo: setup 1",
    )  # fmt: skip
    files["report"] = out / "report.html"
    write_report(files["report"], html_text)
