"""The calibration report: one self-contained HTML page that shows how good a correction is.

Compute, then render.  :func:`compute_report` gathers, for a calibration and whatever else
is given, a :class:`ReportContent`:

* the residuals in the paper's Table-1 form (max / mean / RMS / total, px and um);
* with landmark pairs, the residual vectors after correction;
* the uncertainty map of the correction (:mod:`oapcal.uncertainty`), with the
  extrapolated region flagged;
* with an image of a bar target, the image corrected, the edge straightness and
  aspect-ratio checks before and after (:mod:`oapcal.imaging.checks`), and the edge
  spread functions of the corrected image (:mod:`oapcal.imaging.esf`);
* model-selection and robustness results (the :class:`~oapcal.select.Selection` and
  :class:`~oapcal.subsampling.Robustness` of the library, or of their files read with
  :func:`oapcal.io.results.load_selection` / :func:`~oapcal.io.results.load_robustness`),
  to be tabulated.

:func:`render_report` draws the figures (the distortion field among them) and writes the
page; :func:`build_report` does both.  :func:`write_report` writes the page atomically.
Progress goes to an optional callback ``progress(done, total, label)``.  Nothing else in
oapcal imports this package.
"""

from __future__ import annotations

import datetime as _dt
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from oapcal.records import ImageSize
from oapcal.report import html as H

if TYPE_CHECKING:
    from oapcal.families import FamilySelection
    from oapcal.select import Selection
    from oapcal.subsampling import Robustness

#: ``progress(done, total, label)``: ``done`` steps of ``total`` finished, ``label`` the next.
Progress = Callable[[int, int, str], None]


@dataclass
class ReportData:
    """The numbers of a report (``oapcal report --json``): ``residuals`` (Table 1),
    ``uncertainty`` (the map's summary), ``checks`` (``before`` / ``after`` summaries of the
    target checks) and ``esf`` (the edge spread functions), the last two with an image;
    ``model`` the calibration's model (``family``, ``free``, and for the relay
    ``as_fitted``, its parameters in physical words)."""

    residuals: dict
    uncertainty: dict
    checks: dict = field(default_factory=dict)
    esf: dict | None = None
    model: dict = field(default_factory=dict)


@dataclass(frozen=True)
class ImageAnalysis:
    """A bar-target image and its correction: ``image`` the distorted image, ``corrected``
    the corrected one (NaN where an output pixel samples outside the image), ``before`` /
    ``after`` the :class:`~oapcal.imaging.checks.TargetCheck` of each, ``esf`` the
    :class:`~oapcal.imaging.esf.EsfSummary` of the corrected image."""

    image: np.ndarray
    corrected: np.ndarray
    before: object
    after: object
    esf: object
    expected_ratios: tuple[float, ...]


@dataclass(frozen=True)
class ReportContent:
    """Everything :func:`render_report` shows, computed by :func:`compute_report`.

    ``shape`` ``(rows, cols)`` the output frame; ``residuals`` the Table-1 dict, from the
    landmarks when given (``vectors`` their :class:`~oapcal.imaging.checks.ResidualVectors`)
    else the calibration's; ``uncertainty`` the
    :class:`~oapcal.uncertainty.UncertaintyMap`; ``image`` the :class:`ImageAnalysis` or
    None; ``selection`` / ``robustness`` the :class:`~oapcal.select.Selection` (or a
    cross-family :class:`~oapcal.families.FamilySelection`) and
    :class:`~oapcal.subsampling.Robustness` or None, ``selection_source`` /
    ``robustness_source`` where they came from (a file name), shown under their tables.
    """

    calibration: object
    shape: tuple[int, int]
    residuals: dict
    vectors: object | None
    uncertainty: object
    image: ImageAnalysis | None = None
    selection: Selection | FamilySelection | None = None
    robustness: Robustness | None = None
    selection_source: str | None = None
    robustness_source: str | None = None

    @property
    def data(self) -> ReportData:
        """The numbers of the report."""
        data = ReportData(residuals=self.residuals, uncertainty=self.uncertainty.summary(),
                          model=model_summary(self.calibration))  # fmt: skip
        if self.image is not None:
            data.checks = {"before": self.image.before.summary(), "after": self.image.after.summary()}
            data.esf = self.image.esf.to_dict()
        return data


def model_summary(calibration) -> dict:
    """The calibration's model: ``family`` (its name), ``free`` (the fitted parameters) and,
    for the relay, ``as_fitted`` (:func:`oapcal.optics.relay_model.describe`)."""
    out = {"family": calibration.family.name, "free": list(calibration.free)}
    if calibration.relay_design is not None:
        from oapcal.optics.relay_model import describe

        out["as_fitted"] = describe(calibration)
    return out


class _Steps:
    """Calls ``progress(done, total, label)`` as each step starts (nothing without one)."""

    def __init__(self, progress: Progress | None, total: int):
        self.progress = progress
        self.done = 0
        self.total = total

    def __call__(self, label: str) -> None:
        if self.progress is not None:
            self.progress(self.done, self.total, label)
        self.done += 1


def _normalized_points(calibration, xy_u, xy_d):
    """The points in the calibration's coordinates (its normalization applied again)."""
    from oapcal.normalize import normalize

    how = calibration.fit.normalize or "none"
    norm = normalize(how, xy_u, xy_d)
    return norm.xy_u, norm.xy_d


def output_shape(calibration, image: np.ndarray | None = None) -> tuple[int, int]:
    """``(rows, cols)`` of the report's output frame: the image's, else the calibration's
    image size, else the reference points' bounds plus the same margin, else 480 x 640."""
    cal = calibration
    if image is not None:
        return tuple(image.shape[:2])
    if cal.image_size:
        return ImageSize(*(int(v) for v in cal.image_size)).shape
    if cal.bounds is not None:
        return (
            int(np.ceil(cal.bounds[3] + cal.bounds[1])) + 1,
            int(np.ceil(cal.bounds[2] + cal.bounds[0])) + 1,
        )
    return (480, 640)


def _compute_steps(with_points: bool, with_image: bool) -> int:
    return with_points + 1 + 3 * with_image


def _render_steps(with_points: bool, with_image: bool) -> int:
    return with_points + 2 + 2 * with_image


def _within(progress: Progress | None, start: int, total: int) -> Progress | None:
    """The progress of one phase reported as part of the whole."""
    if progress is None:
        return None
    return lambda done, _total, label: progress(start + done, total, label)


# keyword options of the public report API (one per input the report can show)
def compute_report(
    calibration,
    *,
    points=None,
    image: np.ndarray | None = None,
    selection: Selection | FamilySelection | None = None,
    robustness: Robustness | None = None,
    selection_source: str | None = None,
    robustness_source: str | None = None,
    expected_ratios=(5.0, 1.0),
    progress: Progress | None = None,
) -> ReportContent:
    """The report's content (arguments as :func:`build_report`); draws nothing."""
    from oapcal.imaging.checks import ResidualVectors
    from oapcal.model import as_model
    from oapcal.stats import residual_stats
    from oapcal.uncertainty import uncertainty_map

    cal = calibration
    step = _Steps(progress, _compute_steps(points is not None, image is not None))
    shape = output_shape(cal, image)
    vectors = None
    if points is not None:
        step("correcting the landmarks")
        xy_u, xy_d = _normalized_points(cal, *points)
        xy_c = as_model(cal).inverse(np.asarray(xy_d, float)).xy
        vectors = ResidualVectors(np.asarray(xy_u, float), xy_c, xy_c - np.asarray(xy_u, float))
        residuals = residual_stats(vectors.xy_c, xy_u, cal.um_per_px).to_dict()
    else:
        residuals = cal.residuals.to_dict()
    step("uncertainty map")
    # a family without analytic parameter columns (the relay) differentiates numerically:
    # sample it more coarsely (the map is smooth)
    across = 320 if cal.family.analytic_jacobian else 160
    umap = uncertainty_map(cal, shape, step=max(1, max(shape) // across))
    analysis = None
    if image is not None:
        analysis = analyse_image(cal, image, shape, tuple(expected_ratios), step)
    return ReportContent(
        cal, shape, residuals, vectors, umap, analysis, selection, robustness,
        None if selection_source is None else str(selection_source),
        None if robustness_source is None else str(robustness_source),
    )  # fmt: skip


def analyse_image(calibration, image: np.ndarray, shape, expected_ratios, step=None) -> ImageAnalysis:
    """Correct a bar-target image with the calibration (cubic) and check it before and
    after (straightness, aspect ratios) and its edge spread functions after.

    Output pixels that sample outside the observed image are not data: only pixels at
    least 2 px inside (cubic interpolation reaches 2 px) are analysed, the rest filled with
    the background so they make no edges.  ``step(label)`` is called as each part starts.
    """
    from scipy.ndimage import binary_erosion

    from oapcal.imaging.checks import check_target
    from oapcal.imaging.esf import analyse_edges, find_edge_rois
    from oapcal.imaging.remap import correct_image, correction_map

    step = step or (lambda label: None)
    step("correcting the image")
    maps = correction_map(calibration, shape)
    corrected = correct_image(image.astype(np.float32), maps, "cubic").astype(float)
    inside = correct_image(np.ones(image.shape[:2], np.float32), maps, "nearest") > 0.5
    valid = binary_erosion(inside, iterations=2)
    analysed = np.where(valid, corrected, np.median(corrected[valid]) if valid.any() else 0.0)
    step("straightness and aspect checks")
    before = check_target(image, expected_ratios)
    after = check_target(analysed, expected_ratios, valid=valid)
    step("edge spread functions")
    rois, labels = find_edge_rois(analysed, valid=valid)
    esf = analyse_edges(analysed, rois, labels=labels, um_per_px=calibration.um_per_px)
    return ImageAnalysis(
        image, np.where(inside, corrected, np.nan), before, after, esf, tuple(expected_ratios)
    )


def render_report(
    content: ReportContent,
    *,
    image_name: str | None = None,
    title: str | None = None,
    progress: Progress | None = None,
) -> str:
    """The report's HTML page for ``content``: its figures drawn and embedded, its tables."""
    from oapcal.report import plots

    step = _Steps(progress, _render_steps(content.vectors is not None, content.image is not None))
    cal = content.calibration
    from_points = content.vectors is not None
    sections = [
        H.section("Summary", _summary_html(cal, content.residuals, from_points)),
        H.section("Fitted parameters", _params_html(cal)),
    ]
    if getattr(cal, "selfcal", None):
        sections.append(H.section("Self-calibration", _selfcal_html(cal, plots), "selfcal"))
    sections += _figure_sections(content, step, image_name, plots)
    sections += _results_sections(content)
    name = cal.name or (Path(cal.source).name if cal.source else "calibration")
    page_title = title or f"oapcal calibration report: {name}"
    return H.document(page_title, sections, _page_meta(cal))


def _figure_sections(content: ReportContent, step, image_name: str | None, plots) -> list:
    """The sections drawn as figures: residual vectors (from points), distortion field,
    uncertainty, and with an image the image before and after correction and its edge
    spread functions; each announced to ``step``."""
    cal, shape, um = content.calibration, content.shape, content.calibration.um_per_px
    sections = []
    if content.vectors is not None:
        step("residual vectors")
        png = plots.figure_png(plots.residual_vectors_figure(content.vectors, um, shape))
        caption = ("Each arrow goes from a reference point to where its observed point lands after "
                   "correction, magnified as stated; colour is the residual length.")  # fmt: skip
        sections.append(H.section("Residual vectors", H.png_figure(png, "residual vectors", caption)))
    step("distortion field")
    png = plots.figure_png(plots.distortion_field_figure(cal, shape, cal.hull, um))
    caption = (
        "Where each output pixel is sampled from in the observed image, relative to itself "
        "(the model's distortion)."
    )
    sections.append(H.section("Distortion field", H.png_figure(png, "distortion field", caption)))
    step("uncertainty map")
    umap = content.uncertainty
    sections.append(
        H.section(
            "Uncertainty of the correction", _uncertainty_html(umap, umap.summary(), plots, _fold_of(cal))
        )
    )
    if content.image is not None:
        a = content.image
        step("image before and after correction")
        body = _checks_html(a.image, a.corrected, a.before, a.after, image_name, a.expected_ratios, um, plots)
        sections.append(H.section("Image before and after correction", body, "image"))
        step("edge spread functions")
        sections.append(H.section("Edge spread functions", _esf_html(a.esf, plots), "esf"))
    return sections


def _results_sections(content: ReportContent) -> list:
    """The model selection and robustness sections, for the results given."""
    cal = content.calibration
    sections = []
    if content.selection is not None:
        if hasattr(content.selection, "candidates"):  # a cross-family selection
            body = _family_selection_html(content.selection, cal, content.selection_source)
        else:
            body = _selection_html(content.selection, cal, content.selection_source)
        sections.append(H.section("Model selection", body))
    if content.robustness is not None:
        sections.append(
            H.section("Robustness", _robustness_html(content.robustness, content.robustness_source))
        )
    return sections


def _page_meta(cal) -> str:
    """The page's footnote: where the calibration came from, when the report was made and
    the coordinate convention."""
    now = _dt.datetime.now(_dt.UTC).strftime("%Y-%m-%d %H:%M UTC")
    return (
        f"Calibration created {cal.created_utc} with oapcal {cal.oapcal_version}"
        + (f" from {cal.source}" if cal.source else "")
        + f"; report made {now}. Coordinates: px, origin at the centre of the top-left pixel, "
        "x = column, y = row (down)."
    )


# keyword options of the public report API (one per input the report can show)
def build_report(
    calibration,
    *,
    points=None,
    image: np.ndarray | None = None,
    image_name: str | None = None,
    selection: Selection | FamilySelection | None = None,
    robustness: Robustness | None = None,
    selection_source: str | None = None,
    robustness_source: str | None = None,
    expected_ratios=(5.0, 1.0),
    title: str | None = None,
    progress: Progress | None = None,
) -> tuple[str, ReportData]:
    """The report's HTML and the numbers in it: :func:`compute_report`, then
    :func:`render_report`.

    ``points`` is ``(xy_u, xy_d)`` (``(N, 2)`` each, as given to the fit; the calibration's
    normalization is applied again); ``image`` a grey distorted image of a bar target;
    ``selection`` / ``robustness`` a :class:`~oapcal.select.Selection` (or the
    :class:`~oapcal.families.FamilySelection` of ``select_families``: the families compared)
    and a :class:`~oapcal.subsampling.Robustness` (of the library, or loaded from their files by
    :mod:`oapcal.io.results`), ``selection_source`` / ``robustness_source`` the files they
    came from; ``image_name`` and ``title`` label the page.  ``progress(done, total, label)``
    is called as each step of both phases starts.
    """
    parts = (points is not None, image is not None)
    n_compute = _compute_steps(*parts)
    total = n_compute + _render_steps(*parts)
    content = compute_report(
        calibration, points=points, image=image, selection=selection, robustness=robustness,
        selection_source=selection_source, robustness_source=robustness_source,
        expected_ratios=expected_ratios, progress=_within(progress, 0, total),
    )  # fmt: skip
    page = render_report(
        content, image_name=image_name, title=title, progress=_within(progress, n_compute, total)
    )
    return page, content.data


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
    criteria = (f.aic, f.aicc_forward, f.bic)
    status = "" if f.converged else "NOT converged: "
    stats = [
        ["model family", _family_text(cal)],
        ["model (free parameters)", ", ".join(cal.free)],
        ["fit", f"{status}{f.message} ({'?' if f.n_iter is None else f.n_iter} iterations)"],
        ["points / residuals", f"{f.n_points} / {f.n_residuals}"],
        ["RSS of the fit (forward residuals: model(reference) - distorted)", H.fmt(f.rss, 6)],
        [
            "AIC / AICc forward / BIC of the fit (forward residuals)",
            " / ".join(H.fmt(v, 6) for v in criteria),
        ],
        ["AICc corrected (after correction, as model selection scores it)", H.fmt(f.aicc_corrected, 6)],
        ["normalization", f.normalize],
        ["scale", f"{um:.4g} um per px" if um else "unknown"],
    ]
    return out + H.table(["quantity", "value"], stats, "Fit")


#: What each model family is, in the report's words.
FAMILY_WORDS = {
    "brown-conrady": "Eq. (1), the Brown-Conrady model",
    "brown-conrady+rotation": "Eq. (1) after an in-plane rotation of the target (deg)",
    "relay": "the physical relay: the target's pose and the relay's misalignment, traced through its design",
    "relay+microscope": "the physical relay with a microscope behind it: the target's pose, the relay's "
    "misalignment and the microscope's magnification and radial term, traced through its design",
}

#: Units and meanings of the relay's pose parameters (its misalignments':
#: :data:`oapcal.optics.misalign.PARAMETERS`).
_POSE_WORDS = {
    "scale": ("", "target scale"),
    "rotation": ("deg", "target turned (counter-clockwise)"),
    "shift_x": ("px", "target shifted in x"),
    "shift_y": ("px", "target shifted in y"),
}


def _family_text(cal) -> str:
    family = cal.family
    return f"{family.name} ({FAMILY_WORDS.get(family.name, family.name)})"


def _params_html(cal) -> str:
    """The fitted parameters of the calibration's family (its design constants left out)."""
    family = cal.family
    relay = not family.zero_when_fixed
    if relay:
        from oapcal.optics.misalign import PARAMETERS

        words = {**_POSE_WORDS, **PARAMETERS}
    else:
        words = {"rotation": ("deg", "target turned (counter-clockwise)")}
    fixed_text = "fixed (design)" if relay else "fixed at 0"
    rows, classes = [], []
    for i, name in enumerate(family.param_names):
        if name in family.never_free:
            continue
        unit, meaning = words.get(name, ("", ""))
        extra = [unit, meaning] if relay else []
        value = float(cal.params[i])
        if name in cal.free:
            err = float(cal.stderr[i])
            rel = abs(err / value) if value else float("nan")
            rows.append([name, value, err, rel, *extra, "free"])
            classes.append("")
        else:
            rows.append([name, value, None, None, *extra, fixed_text])
            classes.append("dim")
    headers = ["parameter", "value", "std. error", "relative error"] + (["unit", "meaning"] if relay else [])
    if relay:
        caption = "Parameters of the physical relay (pose of the target, misalignment of the relay)"
        note = (
            "Standard errors from the fit's covariance s^2 (J^T J)^-1 with s^2 = RSS / (n - k); "
            "fixed parameters are held at the design's values (no misalignment, the target's identity "
            "pose). The design's constants (path length, focal lengths, pixel size, centre) are not "
            "fitted: see the relay's design below."
        )
    else:
        caption = "Parameters of Eq. (1) (px units of the reference points)"
        if family.name != "brown-conrady":
            caption = (
                "Parameters of Eq. (1) and the target's rotation (px units of the reference points; deg)"
            )
        note = (
            "Standard errors from the fit's covariance s^2 (J^T J)^-1 with s^2 = RSS / (n - k); "
            "fixed parameters are held at 0."
        )
    out = H.table([*headers, ""], rows, caption, classes)
    out += H.paragraph(note)
    if relay:
        out += _relay_html(cal)
    return out


def _relay_html(cal) -> str:
    """The relay as fitted in physical words, and the design it was fitted from."""
    from oapcal.optics.relay_model import describe

    lines = describe(cal)
    out = "<p><strong>The relay as fitted</strong></p><ul>"
    out += "".join(f"<li>{H.esc(line)}</li>" for line in lines) + "</ul>"
    design = cal.relay_design or {}
    if design:
        rows = [[k, "-" if v is None else (", ".join(H.fmt(c) for c in v) if isinstance(v, list) else v)]
                for k, v in design.items()]  # fmt: skip
        out += H.table(["design", "value"], rows, "The nominal relay the fit started from")
    return out


#: Pairs listed one by one in the self-calibration section (beyond: those of largest RMS).
SELFCAL_PAIR_ROWS = 40


def _selfcal_html(cal, plots) -> str:
    """What a self-calibration found (the file's ``selfcal`` record): the frames and
    matches, the gauge, the misalignment for the relay, the frames' moves and the pairs."""
    from oapcal.report.selfcal_plots import moves_figure

    rec = cal.selfcal
    r = cal.residuals
    out = H.paragraph(
        f"Solved from {rec['frames']} frames of one moved, textured scene (oapcal selfcal), not from a "
        f"target: {rec['inliers']} of {rec['matches']} matches in {rec['pairs']} overlapping pairs agree "
        f"with one model and one move per frame (the rest are dropped as outliers); moves "
        f"{rec['moves']}. The residuals of the summary (Table 1) are those of the inlier matches, "
        "e = u(d_a) - t_a - (u(d_b) - t_b), u the correction and t a frame's move."
    )
    stage = rec.get("stage_rotation_deg")
    centre = rec.get("um_per_px_centre")
    rows = [
        ["frames", rec["frames"]],
        ["overlapping pairs", rec["pairs"]],
        ["matches (inliers)", f"{rec['matches']} ({rec['inliers']})"],
        ["moves", rec["moves"]],
        ["match residuals: RMS / mean / max [px]", " / ".join(map(H.fmt, (r.rms_px, r.mean_px, r.max_px)))],
        ["stage turned against the camera [deg]", "-" if stage is None else f"{stage:+.4f}"],
        ["object um per px at the image centre (x, y)",
         "-" if centre is None else " / ".join(H.fmt(v, 5) for v in centre)],
    ]  # fmt: skip
    out += H.table(["quantity", "value"], rows, "Self-calibration")
    out += "<p><strong>The gauge</strong>: what fixes each affine part of the correction</p><ul>"
    out += "".join(f"<li>{H.esc(line)}</li>" for line in rec.get("gauge", [])) + "</ul>"
    left = rec.get("gauge_left") or {}
    if left:
        out += H.table(["part", *left], [["left after the model's best absorption", *left.values()]],
                       "The fraction of each affine part the model cannot absorb (0: a free gauge, "
                       "1: fixed by the model's form)")  # fmt: skip
    if cal.relay_design is not None:
        from oapcal.optics.relay_model import describe

        out += "<p><strong>The misalignment found</strong> (in place, from the frames)</p><ul>"
        out += "".join(f"<li>{H.esc(line)}</li>" for line in describe(cal)) + "</ul>"
    png = plots.figure_png(moves_figure(rec, cal.image_size))
    caption = ("Each frame's move (px of the corrected image) and each overlapping pair as a line, "
               "coloured by the RMS residual of its inlier matches; dashed: the frame's size.")  # fmt: skip
    out += H.png_figure(png, "frame moves and pairs", caption)
    pairs = sorted(rec.get("pair_table", []), key=lambda q: -(q["rms_px"] or 0.0))
    shown = pairs if len(pairs) <= SELFCAL_PAIR_ROWS else pairs[:SELFCAL_PAIR_ROWS]
    rows = [[f"{q['a']} - {q['b']}", q["matches"], q["inliers"], q["rms_px"], *q["shift_px"], q["overlap"]]
            for q in shown]  # fmt: skip
    what = "" if len(shown) == len(pairs) else f" (the {len(shown)} of largest RMS of {len(pairs)})"
    out += H.table(["frames", "matches", "inliers", "RMS [px]", "shift x [px]", "shift y [px]", "overlap"],
                   rows, f"The overlapping pairs{what}, largest RMS first")  # fmt: skip
    return out


def _fold_of(cal) -> str:
    """The sentence of a calibration whose model folds over beyond its landmarks' bounds in its
    frame (:func:`oapcal.calibration.folds_beyond_bounds`), or ``""``."""
    from oapcal.calibration import fold_note, folds_beyond_bounds

    fold = folds_beyond_bounds(cal) if cal.bounds is not None else None
    return "" if fold is None else f"Note: {fold_note(fold)}."


def _uncertainty_html(umap, s: dict, plots, fold: str = "") -> str:
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
        + _trust_html(umap, s, plots)
        + (H.paragraph(fold) if fold else "")
    )


def _sides_kept(em) -> str:
    """How the error model combined its sides' refits: the worst (Eq. 1) or their mean (the relay)."""
    return "the mean over the" if em.method == "leave-side-out-mean" else "the worst of"


def _trust_html(umap, s: dict, plots) -> str:
    """The predicted error (covariance, model floor, extrapolation) and the trust region."""
    from oapcal.imaging.remap import DEFAULT_MAX_ERROR_PX
    from oapcal.uncertainty import TRUST_LEVELS_PX

    if umap.predicted_px is None:
        return ""
    png = plots.figure_png(plots.predicted_error_figure(umap, DEFAULT_MAX_ERROR_PX))
    rows = [
        [f"{region} the hull", s.get(f"{region}_predicted_median_px"), s.get(f"{region}_predicted_max_px")]
        for region in ("inside", "outside")
    ]
    shares = [
        [f"{limit:g} px", f"{100 * s[f'trusted_fraction_{limit:g}px']:.1f} %"] for limit in TRUST_LEVELS_PX
    ]
    em = umap.error_model
    if em is None:
        how = (
            "This calibration has no error model (a file written before oapcal measured one): the "
            "predicted error is the covariance alone, optimistic beyond the hull. Refit to measure it."
        )
    else:
        how = (
            "Predicted error = the covariance above, inflated where the model extrapolates, with the "
            f"model floor added, both measured on the landmarks: floor {em.floor_px:.3g} px (the part "
            f"of the residuals neighbouring landmarks share; uncorrelated noise {em.noise_px:.3g} px), "
            f"extrapolation factor {em.extrapolation:.3g} ({_sides_kept(em)} {em.sides_used} refits that "
            "each left one side of the landmarks out and predicted it), growing as "
            f"(1 + d/R)^{em.growth_exponent:g} beyond {em.probed_distance:.2f} hull radii. "
            "'oapcal correct' writes only the trust region, where the predicted error is at most "
            f"{DEFAULT_MAX_ERROR_PX:g} px by default (outlined in red; docs/correct.md)."
        )
    return (
        H.png_figure(
            png,
            "predicted error and trust region",
            "Predicted 1-sigma error of the correction and the trust region.",
        )  # fmt: skip
        + H.table(["region", "predicted median [px]", "predicted max [px]"], rows, "Predicted 1-sigma error")
        + H.table(["max predicted error", "share of the frame trusted"], shares, "The trust region")
        + H.paragraph(how)
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


def _shown(value):
    """A number of a result as the tables show it: None when it is not finite."""
    return None if value is None or not math.isfinite(value) else float(value)


def _selection_html(sel: Selection, cal, source: str | None = None) -> str:
    def by_aicc(m):
        aicc = _shown(m.aicc)
        return (not m.valid, np.inf if aicc is None else aicc)

    models = sorted(sel.models, key=by_aicc)
    shown = models[:15]
    rows, classes = [], []
    for i, m in enumerate(shown):
        numbers = [_shown(v) for v in (m.aicc, m.delta_aicc, m.weight, m.rss)]
        rows.append([i + 1, ", ".join(m.free), int(m.k), *numbers, bool(m.valid), m.reason])
        classes.append("best" if tuple(m.free) == tuple(cal.free) else ("dim" if not m.valid else ""))
    caption = f"Models by AICc ({len(shown)} of {len(models)} shown; {sel.n_points} points)"
    header = ["rank", "free parameters", "k", "AICc corrected", "delta AICc", "weight", "RSS (corrected)",
              "valid", "reason"]  # fmt: skip
    out = H.table(header, rows, caption, classes)
    return out + H.paragraph(
        f"From {source or 'the selection file'}. The highlighted row is this calibration's model. "
        "The selection scores the corrected points (the distorted points through each model's "
        "inverse, against the reference), so its AICc and RSS differ from the fit's, which come "
        "from the forward residuals."
    )


#: Models of each family shown in a cross-family selection's table.
FAMILY_TOP = 5


def _family_selection_html(sel: FamilySelection, cal, source: str | None = None) -> str:
    """A cross-family selection (:func:`oapcal.families.select_families`): the best models
    of each family by AICc (by the spec that fits them again) side by side with their
    held-out error, the recommendation, this calibration's model highlighted."""
    ours = (cal.family.name, frozenset(cal.free))
    families = list(dict.fromkeys(c.family for c in sel.candidates))
    shown = []
    for family in families:
        valid = [c for c in sel.candidates if c.family == family and c.valid]
        shown += valid[:FAMILY_TOP]
        if sel.recommended is not None and sel.recommended in valid[FAMILY_TOP:]:
            shown.append(sel.recommended)
    rows, classes = [], []
    for c in shown:
        mine = (c.family, frozenset(c.free)) == ours
        notes = [
            text for flag, text in ((c is sel.recommended, "recommended"), (mine, "this calibration")) if flag
        ]
        numbers = [_shown(v) for v in (c.aicc, c.delta_aicc, c.mean_error)]
        cv = None if c.cv_mean_error is None else _shown(c.cv_mean_error)
        rows.append([c.family, c.spec, int(c.k) + 1, *numbers, cv, ", ".join(notes)])
        classes.append("best" if mine else "")
    n_bad = sum(not c.valid for c in sel.candidates)
    caption = (f"Best {FAMILY_TOP} models of each family by AICc ({len(sel.candidates)} models, "
               f"{sel.n_points} points)")  # fmt: skip
    out = H.table(["family", "model", "K", "AICc corrected", "delta AICc", "mean error [px]",
                   f"{sel.cv_folds}-fold held-out error [px]", ""], rows, caption, classes)  # fmt: skip
    if sel.recommended is not None:
        r = sel.recommended
        if getattr(r, "predicted_error", None) is not None:  # the choice over the region to be corrected
            verdict = (f"Recommended by the predicted error over the region to be corrected: {r.spec} "
                       f"({r.family}, {H.fmt(_shown(r.predicted_error))} px: the held-out error "
                       f"{H.fmt(_shown(r.cv_mean_error))} px with the uncertainty propagated over the "
                       f"region, {H.fmt(_shown(r.region_sigma))} px).")  # fmt: skip
        else:  # read from a selection file (its reader keeps the choice, not the predicted errors)
            verdict = (f"Recommended in the selection file: {r.spec} ({r.family}, held-out error "
                       f"{H.fmt(_shown(r.cv_mean_error))} px).")  # fmt: skip
    else:
        verdict = "No model could be cross-validated, so none is recommended."
    text = (
        f"{verdict} AICc ranks models of all families on the same corrected points (K counts the "
        "free parameters and the noise); the held-out error is the mean corrected-point error on "
        f"the folds left out of {sel.cv_folds}-fold cross-validation, computed for the best models "
        "by AICc."
        + (f" {n_bad} models could not be scored (not identifiable, or the fit or its inverse failed)."
           if n_bad else "")
        + f" From {source or 'the selection'}. The highlighted row is this calibration's model."
    )  # fmt: skip
    return out + H.paragraph(text)


def _robustness_html(rob: Robustness, source: str | None = None) -> str:
    rows, cells = [], []
    for m in rob.models:
        trials, nc = int(m.trials), int(m.not_converged)
        share = 100.0 * nc / trials if trials else float("nan")
        reasons = ", ".join(f"{k}: {v}" for k, v in m.by_reason.items()) or "-"
        stds = ", ".join(f"{k} {H.fmt(_shown(v), 2)}" for k, v in m.param_std.items()) or "-"
        rows.append([m.name or ", ".join(m.free), trials, nc, f"{share:.1f} %", reasons,
                     _shown(m.heldout_mean_error), stds])  # fmt: skip
        cells.append(["", "", "bad" if nc else "", "bad" if nc else "", "", "", ""])
    out = H.table(["model", "trials", "not converged", "share", "by reason", "held-out mean error [px]",
                   "parameter std over trials"], rows, "Refits on random subsets of the points",
                  cell_classes=cells)  # fmt: skip
    return out + H.paragraph(f"From {source or 'the robustness file'}.")


# ------------------------------------------------------------------------- the demo
