"""The calibration report: one self-contained HTML page that shows how good a correction is.

:func:`build_report` gathers, for a calibration and whatever else is given:

* the fit summary in the paper's Table-1 form (max / mean / RMS / total residual, px and
  um) and the parameter table with standard errors;
* with landmark pairs, the residual vectors after correction;
* the distortion field of the model and the uncertainty map of the correction
  (:mod:`oapcal.uncertainty`), with the extrapolated region flagged;
* with an image of a bar target, the image before and after correction with the edge
  straightness and aspect-ratio checks (:mod:`oapcal.imaging.checks`), and the edge
  spread functions of the corrected image (:mod:`oapcal.imaging.esf`);
* with model-selection and robustness results, their tables.

:func:`write_report` writes it atomically.  Nothing else in oapcal imports this package.
"""

from __future__ import annotations

import datetime as _dt
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from oapcal.report import html as H


@dataclass
class ReportData:
    """Everything computed for a report (kept for tests and for callers who want numbers)."""

    residuals: dict
    uncertainty: dict
    checks: dict = field(default_factory=dict)
    esf: dict | None = None


class _Steps:
    """A Rich progress bar on stderr over the report's steps (or nothing)."""

    def __init__(self, total: int, show: bool):
        self.total = total
        self.show = show
        self._progress = None
        self._task = None

    def __enter__(self):
        if self.show:
            import sys

            from rich.console import Console
            from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

            self._progress = Progress(
                TextColumn("{task.description:<34}"), BarColumn(), TimeElapsedColumn(),
                console=Console(file=sys.stderr), transient=True,
            )  # fmt: skip
            self._progress.__enter__()
            self._task = self._progress.add_task("report", total=self.total)
        return self

    def step(self, label: str) -> None:
        if self._progress is not None:
            self._progress.update(self._task, description=label, advance=1)

    def __exit__(self, *exc):
        if self._progress is not None:
            self._progress.__exit__(*exc)
        return False


def _normalized_points(calibration, xy_u, xy_d):
    """The points in the calibration's coordinates (its normalization applied again)."""
    from oapcal.normalize import normalize

    how = (calibration.fit or {}).get("normalize", "none") or "none"
    norm = normalize(how, xy_u, xy_d)
    return norm.xy_u, norm.xy_d


def build_report(
    calibration,
    *,
    points=None,
    image: np.ndarray | None = None,
    image_name: str | None = None,
    selection: dict | None = None,
    robustness: dict | None = None,
    expected_ratios=(5.0, 1.0),
    title: str | None = None,
    show_progress: bool = False,
) -> tuple[str, ReportData]:
    """The report's HTML and the numbers in it.

    ``points`` is ``(xy_u, xy_d)`` (``(N, 2)`` each, as given to the fit; the calibration's
    normalization is applied again); ``image`` a grey distorted image of a bar target;
    ``selection`` / ``robustness`` dicts from :mod:`oapcal.report.inputs`.
    """
    from scipy.ndimage import binary_erosion

    from oapcal.imaging.checks import check_target, residual_vectors
    from oapcal.imaging.esf import analyse_edges, find_edge_rois
    from oapcal.imaging.remap import correct_image, correction_map
    from oapcal.report import plots
    from oapcal.stats import residual_stats
    from oapcal.uncertainty import uncertainty_map

    cal = calibration
    um = cal.um_per_px
    n_steps = 3 + (points is not None) + 3 * (image is not None)
    sections = []
    with _Steps(n_steps, show_progress) as steps:
        # ---- shape of the output frame
        if image is not None:
            shape = image.shape[:2]
        elif cal.image_size:
            shape = (int(cal.image_size[1]), int(cal.image_size[0]))
        elif cal.bounds is not None:  # the reference points' bounds plus the same margin
            shape = (
                int(np.ceil(cal.bounds[3] + cal.bounds[1])) + 1,
                int(np.ceil(cal.bounds[2] + cal.bounds[0])) + 1,
            )
        else:
            shape = (480, 640)

        # ---- residuals (Table 1)
        vectors = None
        if points is not None:
            steps.step("correcting the landmarks")
            xy_u, xy_d = _normalized_points(cal, *points)
            vectors = residual_vectors(cal.params, xy_u, xy_d)
            residuals = residual_stats(vectors.xy_c, xy_u, um).to_dict()
        else:
            residuals = dict(cal.residuals)
        sections.append(H.section("Summary", _summary_html(cal, residuals, points is not None)))
        sections.append(H.section("Fitted parameters", _params_html(cal)))
        if vectors is not None:
            png = plots.figure_png(plots.residual_vectors_figure(vectors, um, shape))
            sections.append(
                H.section(
                    "Residual vectors",
                    H.png_figure(
                        png,
                        "residual vectors",
                        "Each arrow goes from a reference point to where "
                        "its observed point lands after correction, magnified as stated; colour "
                        "is the residual length.",
                    ),  # fmt: skip
                )
            )

        # ---- distortion field and uncertainty
        steps.step("distortion field")
        png = plots.distortion_field_figure(cal.params, shape, cal.hull, um)
        field_html = H.png_figure(plots.figure_png(png), "distortion field",
                                  "Where each output pixel is sampled from in the observed image, "
                                  "relative to itself (the model's distortion).")  # fmt: skip
        sections.append(H.section("Distortion field", field_html))
        steps.step("uncertainty map")
        step = max(1, max(shape) // 320)
        umap = uncertainty_map(cal, shape, step=step)
        usum = umap.summary()
        sections.append(H.section("Uncertainty of the correction", _uncertainty_html(umap, usum, plots)))

        # ---- image checks and ESF
        data = ReportData(residuals=residuals, uncertainty=usum)
        if image is not None:
            steps.step("correcting the image")
            maps = correction_map(cal, shape)
            corrected = correct_image(image.astype(np.float32), maps, "cubic").astype(float)
            # Output pixels that sample outside the observed image are not data: analyse only
            # pixels at least 2 px inside (cubic interpolation reaches 2 px), fill the rest
            # with the background so they make no edges.
            inside = correct_image(np.ones(image.shape[:2], np.float32), maps, "nearest") > 0.5
            valid = binary_erosion(inside, iterations=2)
            analysed = np.where(valid, corrected, np.median(corrected[valid]) if valid.any() else 0.0)
            steps.step("straightness and aspect checks")
            before = check_target(image, expected_ratios)
            after = check_target(analysed, expected_ratios, valid=valid)
            data.checks = {"before": before.summary(), "after": after.summary()}
            steps.step("edge spread functions")
            rois, labels = find_edge_rois(analysed, valid=valid)
            corrected = np.where(inside, corrected, np.nan)
            esf = analyse_edges(analysed, rois, labels=labels, um_per_px=um)
            data.esf = esf.to_dict()
            sections.append(
                H.section(
                    "Image before and after correction",
                    _checks_html(image, corrected, before, after, image_name, expected_ratios, um, plots),
                    "image",
                )
            )
            sections.append(H.section("Edge spread functions", _esf_html(esf, plots), "esf"))
        if selection is not None:
            sections.append(H.section("Model selection", _selection_html(selection, cal)))
        if robustness is not None:
            sections.append(H.section("Robustness", _robustness_html(robustness)))
    name = cal.name or (Path(cal.source).name if cal.source else "calibration")
    page_title = title or f"oapcal calibration report: {name}"
    now = _dt.datetime.now(_dt.UTC).strftime("%Y-%m-%d %H:%M UTC")
    meta = (
        f"Calibration created {cal.created_utc} with oapcal {cal.oapcal_version}"
        + (f" from {cal.source}" if cal.source else "")
        + f"; report made {now}. Coordinates: px, origin at the centre of the top-left pixel, "
        "x = column, y = row (down)."
    )
    return H.document(page_title, sections, meta), data


def write_report(path, html_text: str) -> None:
    """Write the report atomically."""
    from oapcal.io.atomic import atomic_write

    with atomic_write(path) as fh:
        fh.write(html_text)


# ------------------------------------------------------------------------- sections


def _summary_html(cal, r: dict, from_points: bool) -> str:
    um = cal.um_per_px
    headers = ["setup", "max error [px]", "average error [px]", "RMS error [px]", "total [px]"]
    row = [cal.name or "calibration", r.get("max_px"), r.get("mean_px"), r.get("rms_px"), r.get("total_px")]
    if um:
        headers += ["average error [um]", "max error [um]"]
        row += [r.get("mean_um"), r.get("max_um")]
    headers += ["points", "not corrected"]
    row += [r.get("n_points"), r.get("n_failed", 0)]
    out = H.table(headers, [row], "Residual distortion after correction (the paper's Table 1)")
    src = "the landmark file given" if from_points else "the calibration file"
    out += H.paragraph(
        f"Residuals from {src}: each observed point is corrected through the inverse model and "
        "compared with its reference point; average = mean distance, total = sqrt(sum of squared "
        "distances)." + ("" if um else " No scale (um per px) is known, so no um columns.")
    )
    f = cal.fit
    status = "" if f.get("converged") else "NOT converged: "
    stats = [
        ["model (free parameters)", ", ".join(cal.free)],
        ["fit", f"{status}{f.get('message', '')} ({f.get('n_iter', '?')} iterations)"],
        ["points / residuals", f"{f.get('n_points')} / {f.get('n_residuals')}"],
        ["RSS", H.fmt(f.get("rss"), 6)],
        ["AIC / AICc / BIC", " / ".join(H.fmt(f.get(k), 6) for k in ("aic", "aicc", "bic"))],
        ["normalization", f.get("normalize", "none")],
        ["scale", f"{um:.4g} um per px" if um else "unknown"],
    ]
    return out + H.table(["quantity", "value"], stats, "Fit")


def _params_html(cal) -> str:
    from oapcal.model import PARAM_NAMES

    rows, classes = [], []
    for i, name in enumerate(PARAM_NAMES):
        if name in cal.free:
            value, err = float(cal.params[i]), float(cal.stderr[i])
            rel = abs(err / value) if value else float("nan")
            rows.append([name, value, err, rel, "free"])
            classes.append("")
        else:
            rows.append([name, 0.0, None, None, "fixed at 0"])
            classes.append("dim")
    out = H.table(["parameter", "value", "std. error", "relative error", ""], rows,
                  "Parameters of Eq. (1) (px units of the reference points)", classes)  # fmt: skip
    return out + H.paragraph(
        "Standard errors from the fit's covariance s^2 (J^T J)^-1 with s^2 = RSS / (n - k); "
        "fixed parameters are held at 0."
    )


def _uncertainty_html(umap, s: dict, plots) -> str:
    png = plots.figure_png(plots.uncertainty_figure(umap))
    um = umap.um_per_px
    headers = ["region", "share of the frame", "median [px]", "max [px]"] + (
        ["median [um]", "max [um]"] if um else []
    )
    rows = []
    for region in ("inside", "outside"):
        row = [f"{region} the hull", f"{100 * s[f'{region}_fraction']:.1f} %", s[f"{region}_median_px"],
               s[f"{region}_max_px"]]  # fmt: skip
        if um:
            row += [s[f"{region}_median_um"], s[f"{region}_max_um"]]
        rows.append(row)
    text = (
        "The fitted parameters' covariance propagated to the corrected position of every output "
        "pixel: sigma = sqrt(sigma_x^2 + sigma_y^2), to first order. Outside the convex hull of the "
        "calibration points (hatched) the model extrapolates and the map is a lower bound at best."
    )
    return (
        H.png_figure(png, "uncertainty map", "1-sigma positional uncertainty of the correction.")
        + H.table(headers, rows, "1-sigma positional uncertainty")
        + H.paragraph(text)
    )


def _checks_html(image, corrected, before, after, image_name, ratios, um, plots) -> str:
    png = plots.figure_png(plots.before_after_figure(image, corrected, before, after, um))
    b, a = before.summary(), after.summary()
    rows = [
        ["edges measured", b["n_edges"], a["n_edges"]],
        ["edge deviation from straight, RMS [px]", b["straightness_rms_px"], a["straightness_rms_px"]],
        ["edge deviation from straight, max [px]", b["straightness_max_px"], a["straightness_max_px"]],
        ["bars and squares measured", b["n_shapes"], a["n_shapes"]],
        ["aspect ratio error, mean [%]", b["aspect_error_mean_pct"], a["aspect_error_mean_pct"]],
        ["aspect ratio error, max [%]", b["aspect_error_max_pct"], a["aspect_error_max_pct"]],
    ]
    expected = ", ".join(f"{r:g}" for r in ratios) if len(ratios) else "none given"
    text = (
        f"Image {image_name or ''} corrected with the calibration (cubic interpolation). Edges: "
        "the half-way crossing located in every row or column of each side of each bar, a line "
        "fitted through them (coloured by its RMS deviation). Boxes: the bars and squares whose "
        f"aspect ratio (long / short side) is compared with the nearest expected ratio ({expected})."
    )
    return (
        H.png_figure(png, "image before and after correction")
        + H.table(["check", "before", "after"], rows, "Straightness and aspect ratio")
        + H.paragraph(text)
    )


def _esf_html(esf, plots) -> str:
    d = esf.to_dict()
    um = esf.um_per_px
    headers = ["edges fitted", "good fits", "sigma max [px]", "sigma mean [px]"]
    row = [d["n_edges"], d["n_ok"], d["sigma_max_px"], d["sigma_mean_px"]]
    if um:
        headers += ["sigma max [um]", "sigma mean [um]"]
        row += [d["sigma_max_um"], d["sigma_mean_um"]]
    out = H.table(headers, [row], "Gaussian PSF from edge spread functions of the corrected image")
    if esf.good:
        out += H.png_figure(plots.figure_png(plots.esf_figure(esf)), "edge spread function fits")
    bad = [e for e in esf.edges if not e.ok]
    if bad:
        reasons: dict[str, int] = {}
        for e in bad:
            key = e.message.split(":")[0]
            reasons[key] = reasons.get(key, 0) + 1
        out += H.paragraph(
            f"{len(bad)} edges left out: " + "; ".join(f"{v} x {k}" for k, v in sorted(reasons.items()))
        )
    out += H.paragraph(
        "Each edge's profile fitted with low + (high - low) Phi(d / sigma) over all pixels of its "
        "region, with a free slanted edge line; sigma is perpendicular to the edge and includes "
        "the pixels' own sampling blur."
    )
    return out


def _selection_html(sel: dict, cal) -> str:
    models = sorted(sel["models"], key=lambda m: (not m["valid"], np.inf if m["aicc"] is None else m["aicc"]))
    shown = models[:15]
    rows, classes = [], []
    for i, m in enumerate(shown):
        rows.append([i + 1, ", ".join(m["free"]), m.get("k"), m["aicc"], m.get("delta_aicc"), m.get("weight"),
                     m.get("rss"), m["valid"], m["reason"]])  # fmt: skip
        classes.append("best" if tuple(m["free"]) == tuple(cal.free) else ("dim" if not m["valid"] else ""))
    caption = f"Models by AICc ({len(shown)} of {len(models)} shown"
    caption += f"; {sel['n_points']} points)" if sel.get("n_points") is not None else ")"
    out = H.table(["rank", "free parameters", "k", "AICc", "delta AICc", "weight", "RSS", "valid", "reason"],
                  rows, caption, classes)  # fmt: skip
    return out + H.paragraph(
        f"From {sel.get('source', 'the selection file')}. The highlighted row is this calibration's model."
    )


def _robustness_html(rob: dict) -> str:
    rows, cells = [], []
    for m in rob["models"]:
        trials, nc = m["trials"], m["not_converged"]
        share = 100.0 * nc / trials if trials else float("nan")
        reasons = ", ".join(f"{k}: {v}" for k, v in m["by_reason"].items()) or "-"
        stds = ", ".join(f"{k} {H.fmt(v, 2)}" for k, v in m["param_std"].items()) or "-"
        rows.append([m["name"] or ", ".join(m["free"]), trials, nc, f"{share:.1f} %", reasons,
                     m["heldout_mean_error_px"], stds])  # fmt: skip
        cells.append(["", "", "bad" if nc else "", "bad" if nc else "", "", "", ""])
    out = H.table(["model", "trials", "not converged", "share", "by reason", "held-out mean error [px]",
                   "parameter std over trials"], rows, "Refits on random subsets of the points",
                  cell_classes=cells)  # fmt: skip
    return out + H.paragraph(f"From {rob.get('source', 'the robustness file')}.")


# ------------------------------------------------------------------------- the demo
