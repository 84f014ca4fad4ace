"""Automatic detection of USAF-1951 bar corners in a camera image: :func:`detect_usaf`.

The detector never looks for corners one by one and then guesses which is which; it
places the whole known target on the image, so every corner is matched by construction,
then refines and checks each bar triplet locally (``docs/detection.md``):

1. **Bar triplets** found bottom-up in any pose, scale and polarity (:mod:`.bars`).
2. **Pose search** (:mod:`.pose`): which image triplet is which triplet of the whole
   target (a similarity with optional mirror, continuous rotation, scale found or given),
   accepted only when clearly better than every different pose, with the one-element and
   two-group slips tested explicitly; every layout of ``oapcal.imaging.usaf.LAYOUTS``.
3. **Registration**: a polynomial warp through the matched triplets; the dense
   registration of the whole target (Levenberg-Marquardt on the pixels, coarse to fine) from it,
   or, with a given scale and no trusted pose, from a correlation search over the 8
   quarter-turn orientations (:mod:`.registration`).  Several registrations must agree.
4. **Refine each triplet** (:mod:`.triplet`) and **drop what is not certain**.
5. **Check the global alignment** with a smooth model (:mod:`.checks`).

Every internal fit is bounded (blur, shift, raster size, pixels per fit) and failures are
``status != 0`` results with the reason, never exceptions.  Coordinates follow
``docs/conventions.md``; reference px are the target at ``um_per_px`` (given or found)
with its bounding-box centre at the image centre (``oapcal.imaging.usaf``).
"""

from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass, field, replace

import numpy as np

from oapcal.errors import DataError
from oapcal.imaging.detect.bars import MIN_BAR_PX
from oapcal.imaging.detect.checks import check_consistency, cubic_residuals, grow_consistent, outvoted
from oapcal.imaging.detect.pose import HALF_ELEMENT
from oapcal.imaging.detect.records import (
    ConsistencySummary,
    DetectionDebug,
    DroppedCounts,
    PoseInfo,
    WorkEstimate,
    with_changes,
)
from oapcal.imaging.detect.registration import (
    MAX_FIT_PIXELS,
    FitOptions,
    FitStart,
    PixelData,
    Reference,
    camera_sigma,
    find_target,
    fit_pixels,
    initial_warp,
    region_pixels,
)
from oapcal.imaging.detect.triplet import TripletContext, refine_element, refine_triplet
from oapcal.imaging.detect.triplet import corner_indices as _corner_indices
from oapcal.imaging.detect.warp import PolyWarp
from oapcal.imaging.usaf import (
    ORIENTATIONS,
    nearest_orientation,
    orientation_matrix,
    parse_groups,
    usaf_target,
)
from oapcal.progress import Stages
from oapcal.records import ImageSize

#: (Gaussian blur of both images in px, polynomial degree) of the registration levels;
#: the last level (blur None) uses the image as it is and fits the blur.
LEVELS = ((6.0, 1), (3.0, 2), (1.5, 3), (None, 4))
#: Reason keys of dropped triplets, in the order they are checked.
DROP_REASONS = (
    "not_converged",
    "contrast",
    "moved",
    "ambiguous",
    "uncertain",
    "outside",
    "inconsistent",
    "unresolved",
)
#: The orientation is ambiguous when the second-best orientation's correlation reaches
#: this fraction of the best (measured on relay images: about 0.6).
ORIENTATION_RATIO = 0.9
#: The other corners of a triplet with corners off the smooth map are dropped when their
#: median residual from the cubic map exceeds this many times its robust rms, and this many
#: px (:func:`_whole_triplets`).  Measured: such corners of right triplets 0.07-0.22 px
#: (1.2-2.1 times the robust rms), of triplets off the truth by 0.6-1.5 px 0.48-1.04 px.
WHOLE_TRIPLET_SIGMAS = 2.0
WHOLE_TRIPLET_FLOOR_PX = 0.25
#: The registration is refused when fewer than this fraction of the corners it expects
#: inside the image pass the local checks (a wrong orientation keeps none).
MIN_KEPT_FRACTION = 0.25
#: Images up to this size are always also registered densely (with ``um_per_px`` given,
#: from the correlation search too), and the result with the most corners is kept when all
#: agree; on larger ones the dense registration runs only when the triplet path keeps less
#: than 90 % (the time limit).
DENSE_MAX_PIXELS = 1_000_000
#: Two registrations that put at most this fraction of their common corners between a
#: quarter and half a bar width apart (and none farther) lose those corners (:func:`_combine`);
#: more, or any farther apart, and the image is refused.
MAX_DISPUTED_FRACTION = 0.05
#: A kept corner must be this much farther inside than the 3 px of an expected one (its
#: detected position is uncertain by up to ``max_stderr_px``).
KEEP_MARGIN_EXTRA_PX = 0.5
#: Groups of the whole target (the pose search matches image triplets against all of them).
ALL_GROUPS = tuple(range(-2, 10))
#: Largest image detection accepts (pixels).
MAX_IMAGE_PIXELS = 2**24
#: Corners of bars narrower than this (camera px) are not expected to be found.
RESOLVED_BAR_PX = 2.0
#: With ``um_per_px`` given and fewer bar triplets than this found, the correlation search
#: at that scale places the target instead (heavily blurred or noisy images).
FALLBACK_MAX_TRIPLETS = 3


@dataclass(frozen=True)
class Detection:
    """Detected and matched corners of one image.

    ``ids``, ``xy_u`` (reference px), ``xy_d`` (detected camera px) and ``stderr_px``
    (1-sigma position uncertainty from the local fit) of every kept corner;
    ``n_expected`` reference corners that the registration puts fully inside the image;
    ``dropped`` the number of those dropped, by reason (:data:`DROP_REASONS`);
    ``status`` 0 when the target was found (else the message says why); ``polarity``,
    ``sigma_px`` (fitted blur of the image, camera px) and ``ncc`` (correlation of the
    registered model with the image; median over the triplets) describe the registration;
    ``um_per_px`` the scale of ``xy_u`` (given, or found by the pose search), ``pose`` the
    pose search's result (scale, rotation, mirror, scores of the best and rival poses).
    ``param`` names the parameters of :func:`detect_usaf` that the message of a failed
    detection suggests changing (``um_per_px``, ``groups``, ``orientation``), else ``()``;
    ``reason`` a code for a failure the caller acts on (``"registrations_disagree"``: two
    registrations put a corner id in different places), else ``""``.

    The pixel-size answer (:mod:`.pixel_size`): ``um_per_px_sigma`` the 1-sigma uncertainty
    of a found ``um_per_px`` (None when it was given), ``field_of_view_um`` the image's
    width and height in object um, ``pixel_size`` the measurement from the kept corners
    (``um_per_px``, its ``statistical``, ``anisotropy`` and ``estimator`` parts, ...);
    ``image_sha256`` the digest of the image file (set by the command; ``""`` for an array).

    ``dropped``, ``consistency``, ``pose``, ``work`` and ``debug`` are the typed records of
    :mod:`.records` (each read like the dict it was: ``det.pose["layout"]``, ``dict(det.work)``;
    ``{}`` until the stage that fills it has run); ``orientation_scores`` and ``predicted``
    are dicts keyed by orientation name and corner id.  The message of a detection is
    ``message``; :meth:`summary` (the JSON of ``oapcal detect``) also writes it under the
    key ``reason``, while the attribute ``reason`` is the failure code above.
    """

    ids: tuple[str, ...]
    xy_u: np.ndarray
    xy_d: np.ndarray
    stderr_px: np.ndarray
    n_expected: int
    dropped: DroppedCounts | dict = field(default_factory=dict)
    status: int = 0
    message: str = "ok"
    polarity: str = "bright"
    sigma_px: float = float("nan")
    ncc: float = float("nan")
    orientation: str = "none"
    orientation_scores: dict = field(default_factory=dict)
    consistency: ConsistencySummary | dict = field(default_factory=dict)
    predicted: dict = field(default_factory=dict, repr=False)
    um_per_px: float = float("nan")
    pose: PoseInfo | dict = field(default_factory=dict)
    triplets_found: int = 0
    work: WorkEstimate | dict = field(default_factory=dict)
    debug: DetectionDebug | dict = field(default_factory=dict, repr=False)
    param: tuple[str, ...] = ()
    reason: str = ""
    um_per_px_sigma: float | None = None
    field_of_view_um: tuple[float, float] | None = None
    pixel_size: dict | None = None
    image_sha256: str = ""

    @property
    def ok(self) -> bool:
        """Whether the target was found (``status == 0``; docs/conventions.md)."""
        return self.status == 0

    @property
    def coverage(self) -> float:
        """Kept corners / corners expected fully inside the image."""
        return len(self.ids) / self.n_expected if self.n_expected else 0.0

    def summary(self) -> dict:
        return {
            "status": self.status,
            "message": self.message,
            "found": len(self.ids),
            "expected": self.n_expected,
            "coverage": self.coverage,
            "dropped": dict(self.dropped),
            "polarity": self.polarity,
            "sigma_px": self.sigma_px,
            "ncc": self.ncc,
            "orientation": self.orientation,
            "orientation_matrix": orientation_matrix(self.orientation).tolist(),
            "orientation_scores": dict(self.orientation_scores),
            "consistency": dict(self.consistency),
            "reason": self.message,
            "um_per_px": self.um_per_px,
            "pose": dict(self.pose),
            "triplets_found": self.triplets_found,
            "work": dict(self.work),
            "um_per_px_sigma": self.um_per_px_sigma,
            "field_of_view_um": list(self.field_of_view_um) if self.field_of_view_um is not None else None,
            "pixel_size": dict(self.pixel_size) if self.pixel_size is not None else None,
            "image_sha256": self.image_sha256,
        }


# ---------------------------------------------------------------------------- detection


def to_float_image(image: np.ndarray) -> np.ndarray | None:
    """``image`` (grey or colour) as floats scaled to its 0.5 and 99.9 percentiles (0 to 1),
    or None for an image without contrast; :class:`DataError` for an array that is not an
    image."""
    img = np.asarray(image)
    if img.ndim == 3:
        img = img[..., :3].mean(axis=-1)
    if img.ndim != 2:
        raise DataError(f"image has shape {img.shape}: expected a 2-D grey or colour image")
    if min(img.shape) < 2:
        raise DataError(f"image has shape {img.shape}: it has no pixels to detect a target in")
    img = img.astype(np.float64)
    lo, hi = np.percentile(img, [0.5, 99.9])
    if not hi > lo:  # a valid image without a target: a failed detection (exit 3), not bad input
        return None
    return (img - lo) / (hi - lo)


# (12 parameters: the public keywords of detection, a contract; the stages take them as one
# _Options record)
def detect_usaf(
    image: np.ndarray,
    groups=(4, 5),
    um_per_px: float | None = None,
    *,
    orientation: str = "auto",
    mirror: str = "auto",
    sigma_hint_px: float = 1.0,
    max_stderr_px: float = 0.3,
    ambiguity_ratio: float = 1.5,
    orientation_ratio: float = ORIENTATION_RATIO,
    consistency_model: str | None = "auto",
    progress=None,
    anchors=None,
) -> Detection:
    """Find, match and refine the bar corners of USAF ``groups`` in ``image`` (module docstring).

    ``um_per_px`` (optional) is the object-space size of a camera pixel, to within 30 %;
    the pose search then only considers scales in that range, and a value within 6 % (half
    an element step) identifies the element when the view alone cannot (one element in
    view).  Without it the scale is found and reported (``Detection.um_per_px``).  The
    reference points ``xy_u`` are the target at ``um_per_px`` (given or found), turned into
    the nearest of the 8 orientations (:data:`oapcal.imaging.usaf.ORIENTATIONS`) about the
    image centre (:meth:`~oapcal.imaging.usaf.UsafTarget.reference_px`), so a model fitted
    to the pairs has ``m`` close to +1.  ``orientation`` forces that orientation (the pose
    search keeps only rotations within 45 degrees of it); ``mirror`` ``"yes"``/``"no"``
    forces a mirrored / unmirrored image (``"auto"``: find it).

    ``consistency_model`` is the model (``"full"``, ``"paper"``, ...) fitted to the matched
    pairs to check the global alignment (:func:`check_consistency`); ``"auto"`` uses
    ``full`` from 40 corners, ``paper`` from 16, and skips the check below; ``None`` skips it.

    ``anchors`` (optional): elements the user can read, e.g. ``"G6E3"``, ``["G6E3", "G4E2"]``
    or ``"G6E3@512,300"`` with where the element is (camera px; :mod:`.anchor`): the pose
    search then lays a named triplet onto an image triplet and keeps only poses that honour
    every anchor, which decides the scale and the slips that the bars alone leave open.

    ``progress(done, total, description)`` (optional) hears of each stage and refined
    triplet (:mod:`oapcal.progress`).

    Returns a :class:`Detection`; a target that cannot be found, an ambiguous pose or an
    inconsistent alignment is a ``status != 0`` result with the reason, not an exception.
    """
    from threadpoolctl import threadpool_limits

    if um_per_px is not None and not (np.isfinite(um_per_px) and um_per_px > 0):
        raise DataError(f"um_per_px {um_per_px}: must be a positive number")
    if orientation != "auto":
        orientation_matrix(orientation)  # raises for an unknown name
    if mirror not in ("auto", "yes", "no"):
        raise DataError(f"mirror {mirror!r}: use auto, yes or no")
    groups = parse_groups(groups)
    from oapcal.imaging.detect.anchor import parse_anchors

    anchors = parse_anchors(anchors)
    outside = [a for a in anchors if a.group not in groups]
    if outside:
        raise DataError(
            f"anchor {outside[0].text()} names group {outside[0].group}, which is not among the groups "
            f"searched ({', '.join(map(str, groups))}): list it in groups",
            param="groups",
        )
    img = to_float_image(image)
    if img is None:
        return Detection((), np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0), 0, {}, 1,
                         "the target was not found: the image is uniform (no contrast at all)",
                         um_per_px=float(um_per_px) if um_per_px else float("nan"))  # fmt: skip
    h, w = img.shape
    if h * w > MAX_IMAGE_PIXELS:
        raise DataError(
            f"the image has {w} x {h} px; detection handles at most {MAX_IMAGE_PIXELS} px "
            f"(e.g. 4096 x 4096): crop it to the target or bin it"
        )
    # Detection does many small dense solves; a multithreaded BLAS only adds contention on
    # them (measured on 2 cores: 1.2-1.9 s with one BLAS thread, 12-14 s at random with two).
    with threadpool_limits(limits=1, user_api="blas"):
        opts = _Options(um_per_px, orientation, mirror, sigma_hint_px, max_stderr_px, ambiguity_ratio,
                        orientation_ratio, consistency_model, anchors)  # fmt: skip
        det = _detect(img, groups, opts, progress)
    det = _with_anchor_hint(det, anchors)
    return _with_pixel_size(det, groups, um_per_px is not None, (w, h))


def work_estimate(shape: tuple[int, int]) -> WorkEstimate:
    """Memory (MB) that detection needs at most for an image of ``shape`` (rows, cols):
    a few float copies of the image, the bounded reference raster with its blurred
    copies, and the bounded pixel fit (Jacobian of at most 34 columns)."""
    from oapcal.imaging.detect.registration import MAX_FIT_PIXELS, MAX_RASTER_CELLS, RASTER_CACHE

    h, w = shape
    image = 12 * h * w * 8
    raster = MAX_RASTER_CELLS * 4 * (1 + 3 * RASTER_CACHE + 2)
    fit = MAX_FIT_PIXELS * (34 + 12) * 8
    return WorkEstimate(int(h * w), round((image + min(raster, 48 * h * w * 4) + fit) / 2**20))


@dataclass(frozen=True)
class _Options:
    """The keywords of :func:`detect_usaf` that the stages of one detection read."""

    um_per_px: float | None
    orientation: str
    mirror: str
    sigma_hint_px: float
    max_stderr_px: float
    ambiguity_ratio: float
    orientation_ratio: float
    consistency_model: str | None
    anchors: tuple = ()
    layout: str | None = None  # None: every layout (_layouts); a name: only that one


@dataclass(frozen=True)
class _PoseFound:
    """The pose search's answer over every layout: the layout kept, its target, reference
    triplets and search result, and the image's triplets."""

    layout: str | None
    target: object
    ref: object
    result: object
    trips: object
    mirror_from_digits: dict | None = None


def _detect(img, groups, opts: _Options, progress) -> Detection:
    """The detection in the layout the pose search chose, and again in the other layouts
    when its corners follow another one clearly better, or when it kept too few of the
    resolved corners (:mod:`.layouts`)."""
    from oapcal.imaging.detect.layouts import layouts_to_retry, prefer
    from oapcal.imaging.usaf import layout

    det = _detect_in_layouts(img, groups, opts, progress)
    if opts.layout is not None:
        return det
    first = best = layout(det.pose.get("layout")).name
    retry, rms = layouts_to_retry(det, groups, first, _layouts())
    kept = det
    for name in retry:
        again = _detect_in_layouts(img, groups, replace(opts, layout=name), progress)
        if prefer(again, name, kept, best, groups):
            kept, best = again, name
    if kept is det:
        return det
    note = {"pose_layout": first, "rms_px": {k: round(v, 4) for k, v in rms.items()}}
    return _replace(kept, pose=with_changes(kept.pose, layout_from_corners=note))


def _detect_in_layouts(img, groups, opts: _Options, progress) -> Detection:
    h, w = img.shape
    um_per_px = opts.um_per_px
    work = work_estimate((h, w))
    empty = Detection((), np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0), 0, {}, 1, "",
                      um_per_px=float(um_per_px) if um_per_px else float("nan"), work=work)  # fmt: skip
    n_trip = len(usaf_target(groups).triplets())
    with Stages(progress, 3 + n_trip, "detecting corners") as bar:
        found = _search_pose(img, groups, opts, bar)
        pres, trips = found.result, found.trips
        debug = DetectionDebug(trips, found.ref, pres.pose, pres.runner_up)
        pose_info = with_changes(
            _pose_summary(pres, found.layout), mirror_from_digits=found.mirror_from_digits
        )
        seen = {"debug": debug, "triplets_found": len(trips), "work": work}
        empty = _replace(empty, pose=pose_info, debug=debug, triplets_found=len(trips))
        if pres.status != 0 and (um_per_px is None or opts.anchors):
            # (with anchors, the correlation search below could not honour them)
            return _replace(empty, message=pres.message, param=pres.param)
        det_p = start = None
        if pres.status == 0:
            bar.stage("refining triplets")
            # The pose's own scale, not the given one, from here on: a strongly distorted
            # image (a misaligned relay, a tilted camera) has a best-similarity scale some
            # % off the paraxial one, and every check below that compares a registration's
            # scale with the one it started from would refuse the pose at the given scale
            # (measured: +7 to +11 % through misaligned relays; 156 of 264 corners dropped).
            # The ids were decided by the pose search, slips tested; the reference points
            # are put at the given scale at the end (_at_scale).
            det_p, start = _detect_from_pose(img, found, opts, _replace(empty), bar)
        # The dense registration of the whole target: from the pose when there is one,
        # else (um_per_px given, the triplets did not place the target) from a correlation
        # search at that scale.
        small = h * w <= DENSE_MAX_PIXELS and um_per_px is not None
        # Not only with the scale given: the triplet path refines each triplet alone and,
        # measured on the paper-like simulation (~40 px field, groups 4-5), leaves group 4's
        # corners up to 0.54 px off (median 0.05-0.10 px) where the dense registration
        # leaves 0.10 px at most; it was returned whenever it kept 90 % without a scale.
        if det_p is not None and det_p.status == 0 and det_p.coverage >= 0.9 and h * w > DENSE_MAX_PIXELS:
            # a large image: the dense registration only when the triplets fell short
            return _at_scale(
                _replace(det_p, pose=with_changes(det_p.pose, method="triplets")), um_per_px, (w, h)
            )
        bar.stage("dense registration")
        if start is not None:
            det_d = _detect_dense(img, found.target, det_p.um_per_px, start.orientation, opts, bar, start)
        else:
            det_d = _detect_dense(img, usaf_target(groups), float(um_per_px), opts.orientation, opts, bar)
        det_d = _replace(det_d, pose=pose_info, **seen)
        if det_p is None:
            return _replace(det_d, pose=with_changes(pose_info, method="correlation"))
        det_p, det_d = _at_scale(det_p, um_per_px, (w, h)), _at_scale(det_d, um_per_px, (w, h))
        det = _combine([det_p, det_d], opts.consistency_model)
        if um_per_px is not None and det.reason != "registrations_disagree" and (small or det.status != 0):
            # the pose from few triplets may be poor (a blurred, noisy or strongly
            # distorted image): the correlation search at the given scale, as without a pose
            bar.stage("correlation search")
            # (the layout of a weak pose is not trusted either: the default one)
            det_c = _detect_dense(img, usaf_target(groups), float(um_per_px), opts.orientation, opts, bar)
            det_c = _replace(det_c, pose=with_changes(pose_info, method="correlation"), **seen)
            det = _combine([det_p, det_d, det_c], opts.consistency_model)
    return det


def _search_pose(img, groups, opts: _Options, bar) -> _PoseFound:
    """Bar triplets, then the pose search in every layout; the default layout is kept unless
    another one explains clearly more (2 triplets)."""
    from oapcal.imaging.detect.bars import find_triplets

    bar.stage("finding bar triplets")
    trips = find_triplets(img)
    bar.advance()
    bar.stage("pose search")
    tried = _try_layouts(trips, img.shape, groups, opts)
    top = max(tried, key=lambda r: r[0])[4]
    if not opts.anchors and not any(r[1] for r in tried) and top.pose is not None:
        # the seeds' own angles found no pose in any layout, the best one too little: every
        # seed also turned by a few degrees (pose.SEED_TURNS_DEG; a strongly distorted field
        # turns a triplet's bars against the target's pose).  Also when the best was
        # ambiguous (kept only if the turned seeds find a pose): with a scale given, the
        # search narrowed to it can leave two poses of 10 triplets each where the turned
        # seeds find 16 (a real micrograph through the relay, turned 135 degrees, mirrored)
        if top.kind in ("not_found", "ambiguous"):
            turned = _try_layouts(trips, img.shape, groups, opts, turned_seeds=True)
            if top.kind == "not_found" or any(r[1] for r in turned):
                tried = turned
    elif not opts.anchors and opts.layout is None and not tried[0][1] and any(r[1] for r in tried):
        # another layout found a pose but the default one did not: its seeds turned too
        # before another maker's layout is believed (through the aligned relay turned by
        # 225 degrees the default layout's seeds stall at 10 triplets, turned they match 18,
        # where the whole-target layout's 17 then fail the registration)
        turned = _try_layouts(trips, img.shape, groups, opts, turned_seeds=True)
        if turned[0][1]:
            tried = turned
    default = tried[0]
    tried.sort(key=lambda r: (-r[0], not r[1]))
    if tried[0] is not default and tried[0][0] - default[0] < 2.0 and default[1]:
        tried.insert(0, default)
    _, _, layout, ref, pres = tried[0]
    digits = None
    if pres.kind == "ambiguous" and pres.param == ("mirror",) and opts.mirror == "auto":
        pres, digits = _mirror_from_digits(img, trips, layout, ref, pres, groups, opts)
    bar.advance()
    return _PoseFound(layout, usaf_target(groups, layout_name=layout), ref, pres, trips, digits)


def _mirror_from_digits(img, trips, layout, ref, pres, groups, opts: _Options):
    """The pose search again with the mirror that the printed numbers show, when the bars
    left only the mirror open (:mod:`.digits`): ``(result, evidence)``; the refusal as it
    was, and no evidence, when the numbers do not decide it."""
    from oapcal.imaging.detect.digits import mirror_from_digits

    pose = pres.pose
    centres = ref.centre[[j for _, j in pose.matches]]
    polarity = 1.0 if _pose_polarity(img, trips, pose) > 0 else -1.0
    ev = mirror_from_digits(img, _full_target(layout), pose.s, pose.lin, pose.t, centres, polarity)
    if ev.mirrored is None:
        return pres, None
    res = _pose_search(trips, ref, img.shape, groups, opts, ev.mirrored)
    if res.status != 0:
        return pres, None
    evidence = {"mirrored": ev.mirrored, "ncc_unmirrored": round(ev.ncc_unmirrored, 4),
                "ncc_mirrored": round(ev.ncc_mirrored, 4), "numbers": ev.n_numbers}  # fmt: skip
    return res, evidence


def _pose_search(trips, ref, shape, groups, opts: _Options, mirror: bool | None, turned_seeds: bool = False):
    """:func:`~.pose.search_pose` of ``trips`` against ``ref`` with the options' scale,
    orientation and anchors, and ``mirror`` (None: either)."""
    from oapcal.imaging.detect.pose import search_pose

    return search_pose(
        trips, ref, shape, um_per_px=opts.um_per_px, listed=np.isin(ref.group, groups),
        orientation=None if opts.orientation == "auto" else opts.orientation, mirror=mirror,
        anchors=opts.anchors, turned_seeds=turned_seeds,
    )  # fmt: skip


def _try_layouts(trips, shape, groups, opts: _Options, turned_seeds: bool = False) -> list:
    """The pose search in every layout: rows ``(score, found, layout, reference triplets,
    result)``."""
    tried = []
    mirror = None if opts.mirror == "auto" else opts.mirror == "yes"
    for layout in [opts.layout] if opts.layout is not None else _layouts():
        ref = _reference_triplets(layout)
        res = _pose_search(trips, ref, shape, groups, opts, mirror, turned_seeds)
        score = res.pose.score if res.pose is not None else -np.inf
        tried.append((score, res.status == 0, layout, ref, res))
    return tried


def _with_pixel_size(det: Detection, groups, given: bool, size) -> Detection:
    """``det`` with the pixel-size answer (:func:`~.pixel_size.pixel_size_answer`) measured
    from its kept corners."""
    from oapcal.imaging.detect.pixel_size import measure_pixel_size, pixel_size_answer

    measured = None
    if det.ok and len(det.ids):
        target = usaf_target(groups, layout_name=det.pose.get("layout"))
        index = {cid: k for k, cid in enumerate(target.corner_ids)}
        um = target.corners_um[[index[i] for i in det.ids]]
        mirrored = float(np.linalg.det(orientation_matrix(det.orientation))) < 0
        elements = [i[: max(i.find("H"), i.find("V"))] for i in det.ids]
        measured = measure_pixel_size(um, det.xy_d, mirrored, elements)
    ans = pixel_size_answer(measured, det.um_per_px, given, size)
    fov = tuple(ans["field_of_view_um"]) if ans["field_of_view_um"] is not None else None
    return _replace(
        det, um_per_px_sigma=ans["um_per_px_sigma"], field_of_view_um=fov, pixel_size=ans["pixel_size"]
    )


#: Refusals about the target's identity or pose, which an anchor may decide (the others,
#: e.g. a scale no target fits or an image without bars, it cannot).
ANCHOR_DECIDES = (
    "ambiguous", "scale differs", "disagree", "not found reliably", "explains only",
    "left the pose's matched triplets", "finds only",
)  # fmt: skip


def _with_anchor_hint(det: Detection, anchors) -> Detection:
    """A refusal that does not yet say which anchor would decide it gets the generic advice
    (the pose search's own refusals name the triplet to read)."""
    decided_elsewhere = bool(anchors) and bool({"mirror", "orientation"} & set(det.param))
    if det.status == 0 or "anchors" in det.message or decided_elsewhere:
        return det
    if not any(words in det.message for words in ANCHOR_DECIDES):
        return det
    trips = det.debug.get("image_triplets")
    where = ""
    if trips is not None and len(trips):
        i = int(np.argmax(trips.width))
        where = f" (the widest bar triplet found is at ({trips.centre[i][0]:.0f}, {trips.centre[i][1]:.0f}))"
    if anchors:
        hint = f"; the anchors given ({', '.join(a.text() for a in anchors)}) did not decide it{where}"
    else:
        hint = (
            f"; name one element you can read, with where it is, in anchors, e.g. 'G4E2@x,y' for group 4, "
            f"element 2 at camera px x,y{where}"
        )
    return _replace(det, message=det.message + hint, param=tuple(dict.fromkeys((*det.param, "anchors"))))


def _at_scale(det: Detection, um_per_px, size) -> Detection:
    """``det`` with its reference points at ``um_per_px`` (None: unchanged): the target's
    reference px are linear in ``1 / um_per_px`` about the image centre of ``size``
    (w, h) (:meth:`~oapcal.imaging.usaf.UsafTarget.to_reference_px`)."""
    if um_per_px is None or not np.isfinite(det.um_per_px):
        return det
    c = (np.asarray(size, float) - 1.0) / 2.0
    xy_u = c + (det.xy_u - c) * (det.um_per_px / float(um_per_px))
    return _replace(det, xy_u=xy_u, um_per_px=float(um_per_px))


def _combine(dets: list, consistency_model="auto") -> Detection:
    """The detection with the most corners (the lowest consistency rms among equals), when
    all successful ones agree: a corner id
    found by two must be at the same place (within a quarter of its bar width) in both,
    else the detection is refused (one of them would give wrong ids), unless the triplet
    path (``dets[0]``, as :func:`_detect` passes it) put the disputed corners on another
    element's bars (:func:`~.checks.outvoted`): it is left out (``pose.outvoted``) and the
    rest compared again.  The corners that only the
    others kept are added to it (:func:`_with_corners_of`)."""
    ok = [d for d in dets if d.status == 0]
    if not ok:
        reason = "; ".join(dict.fromkeys(d.message for d in dets))
        return _replace(dets[0], message=reason, param=tuple(dict.fromkeys(p for d in dets for p in d.param)))
    width = _corner_width_um()
    losers = []
    while True:
        verdict = _agreement(ok, width)
        if not isinstance(verdict, tuple):
            disputed = verdict
            break
        d1, d2, msg, vote = verdict
        loser = d2 if vote == 2 else d1 if vote == 1 else None
        # Only the triplet path (dets[0]) is outvoted: it names each triplet from the pose,
        # so it can slip one triplet; a dense registration names every corner through one
        # smooth warp of the whole target, whose global consistency check a local slip
        # fails.  (A dense registration that slipped a whole group, against a triplet path
        # that kept one element of it, would look the same to the corners: it is refused.)
        if loser is None or loser is not dets[0]:
            empty = np.zeros((0, 2))
            return _replace(d1, status=1, message=msg, reason="registrations_disagree", ids=(),
                            xy_u=empty, xy_d=empty.copy(), stderr_px=np.zeros(0))  # fmt: skip
        losers.append(f"triplets: {msg.split(';')[0]}")
        ok = [d for d in ok if d is not loser]
    first = [d is dets[0] for d in ok]
    ok = [_without(d, disputed) for d in ok] if disputed else ok

    # the most corners; among equals the smoothest (lowest consistency rms)
    def rank(k):
        rms = ok[k].consistency.get("rms_px")
        return (len(ok[k].ids), -(rms if rms is not None and np.isfinite(rms) else np.inf))

    pick = max(range(len(ok)), key=rank)
    best = _with_corners_of(ok[pick], ok, consistency_model)
    if losers:
        best = _replace(best, pose=with_changes(best.pose, outvoted=losers))
    if first[pick]:
        return _replace(best, pose=with_changes(best.pose, method="triplets"))
    if best.pose.get("method") != "correlation":
        return _replace(best, pose=with_changes(best.pose, method="dense"))
    return best


def _agreement(ok: list, width: dict):
    """The corner ids the successful registrations ``ok`` dispute (a set, possibly empty:
    :func:`_combine`), or ``(d1, d2, message, vote)`` for the first pair that disagrees
    beyond that, ``vote`` the :func:`~.checks.outvoted` verdict (2: ``d2`` misplaced the
    disputed corners, 1: ``d1``, 0: the corners cannot tell)."""
    disputed: set = set()
    for n, d1 in enumerate(ok):
        for d2 in ok[n + 1 :]:
            common = sorted(set(d1.ids) & set(d2.ids))
            if not common:
                continue
            i1 = {k: n for n, k in enumerate(d1.ids)}
            i2 = {k: n for n, k in enumerate(d2.ids)}
            a = d1.xy_d[[i1[k] for k in common]]
            b = d2.xy_d[[i2[k] for k in common]]
            lim = 0.25 * np.array([width[k] for k in common]) / d1.um_per_px
            dist = np.hypot(*(a - b).T)
            bad = dist > lim
            # Within half a bar width a corner cannot be another corner (the nearest one is a
            # bar width away): the refinements differ, not the ids.  A few such corners are
            # dropped from every registration (neither place is trusted) instead of refusing
            # the image (measured: a target partly outside the image, 2 of 72 corners 0.26
            # and 0.35 bar widths apart, every other corner within 0.25).
            if bad.any() and ((dist > 2 * lim).any() or bad.sum() > MAX_DISPUTED_FRACTION * len(common)):
                example = common[int(np.argmax(dist / lim))]
                msg = (
                    f"two registrations disagree on {int(bad.sum())} of {len(common)} corners "
                    f"(e.g. {example}); nothing was kept"
                )
                vote = outvoted([k for k, f in zip(common, bad) if f], d1.ids, d1.xy_d, d2.ids, d2.xy_d)
                return d1, d2, msg, vote
            disputed.update(k for k, flag in zip(common, bad) if flag)
    return disputed


def _without(det: Detection, ids: set) -> Detection:
    """``det`` without the corners ``ids``."""
    keep = np.array([k not in ids for k in det.ids], bool)
    if keep.all():
        return det
    return _replace(det, ids=tuple(k for k, f in zip(det.ids, keep) if f), xy_u=det.xy_u[keep],
                    xy_d=det.xy_d[keep], stderr_px=det.stderr_px[keep])  # fmt: skip


def _with_corners_of(best: Detection, dets: list, consistency_model) -> Detection:
    """``best`` with the corners that only the other successful registrations ``dets`` kept.

    Each corner passed its own registration's local and global checks, and the registrations
    agree where they overlap (:func:`_combine`); the union must still follow one smooth
    model (:func:`check_consistency` on all of it, no pair flagged), else ``best`` alone.
    Only registrations whose reference points are ``best``'s (the same scale, layout and
    orientation) add corners.  Why: the paths lose different elements (measured on the real
    ``labumk_negative.tif``: the triplets keep 276 corners, the dense registration 312 with
    group 6 but not G5E2V; together 324); ``dropped`` stays ``best``'s."""
    index = {k: n for n, k in enumerate(best.ids)}
    extra = []
    for d in dets:
        if d is best or not d.ok:
            continue
        own = {k: n for n, k in enumerate(d.ids)}
        common = [k for k in d.ids if k in index]
        if not common:
            continue
        same_ref = np.allclose(
            best.xy_u[[index[k] for k in common]], d.xy_u[[own[k] for k in common]], atol=1e-6
        )
        seen = {k for k, _, _ in extra}
        if same_ref:
            extra += [(k, d, own[k]) for k in d.ids if k not in index and k not in seen]
    if not extra:
        return best
    ids = best.ids + tuple(k for k, _, _ in extra)
    xy_u = np.vstack([best.xy_u, [d.xy_u[n] for _, d, n in extra]])
    xy_d = np.vstack([best.xy_d, [d.xy_d[n] for _, d, n in extra]])
    stderr = np.concatenate([best.stderr_px, [d.stderr_px[n] for _, d, n in extra]])
    width_um = _corner_width_um()
    check = check_consistency(
        xy_u, xy_d, np.array([width_um[k] for k in ids]) / best.um_per_px, consistency_model
    )
    if check.status != 0 or not check.consistent.all():
        return best
    predicted = dict(best.predicted)
    for d in dets:
        if d.ok:
            predicted.update({k: v for k, v in d.predicted.items() if k not in predicted})
    resolved = {k for k in predicted if width_um[k] / best.um_per_px >= RESOLVED_BAR_PX}
    return _replace(best, ids=ids, xy_u=xy_u, xy_d=xy_d, stderr_px=stderr, predicted=predicted,
                    n_expected=max(best.n_expected, len(resolved | set(ids))),
                    consistency=ConsistencySummary(**check.summary()))  # fmt: skip


@dataclass(frozen=True)
class _DenseStart:
    """Where a dense registration starts: the orientation, the warp camera -> reference px,
    the model's bars and masked boxes, the polarity (+1 bright bars) and, from a pose, its
    matched triplets (:func:`_pose_anchors`); ``score_table`` the correlation scores of the
    orientations (from the correlation search)."""

    orientation: str
    warp: PolyWarp
    rects: np.ndarray
    masks: np.ndarray | None
    polarity: float
    anchors: list | None = None
    score_table: dict = field(default_factory=dict)
    max_degree: int = LEVELS[-1][1]


@dataclass(frozen=True)
class _Kept:
    """The refined triplets' kept corners (indices, positions, standard errors, sorted by
    index), the dropped corners by reason and the ``info`` of every refined triplet."""

    idx: np.ndarray
    xy: np.ndarray
    se: np.ndarray
    dropped: dict
    infos: list
    #: (bar indices, reason, corners expected inside) of every triplet dropped
    failed: list = field(default_factory=list)


def _detect_from_pose(img, found: _PoseFound, opts: _Options, empty, bar):
    """Corners from the pose: a warp through the matched triplet centres, then each triplet
    refined.  Returns the detection and the start for the dense registration."""
    h, w = img.shape
    target, pose, trips = found.target, found.result.pose, found.trips
    u_ref = 1.0 / pose.s
    orient = nearest_orientation(pose.lin) if opts.orientation == "auto" else opts.orientation
    polarity = _pose_polarity(img, trips, pose)
    empty = _replace(
        empty, um_per_px=u_ref, orientation=orient, polarity="bright" if polarity > 0 else "dark"
    )
    corners_u = target.reference_px(u_ref, (w, h), orient)
    rects, masks = _view_boxes(target, found.layout, pose, u_ref, (w, h), orient)
    # Initial warp camera -> reference px from the matched triplet centres.
    ii = np.array([i for i, _ in pose.matches])
    jj = np.array([j for _, j in pose.matches])
    u_img = target.to_reference_px(found.ref.centre[jj], u_ref, (w, h), orient)
    warp = _warp_from_points(trips.centre[ii], u_img, pose, target, u_ref, orient, (w, h))
    pred = warp.inverse(corners_u)
    m = 3.0
    # only corners of bars that are resolved count as expected
    inside = ImageSize(w, h).contains(pred, m) & (target.corner_width_um * pose.s >= RESOLVED_BAR_PX)
    scale_ref = pose.s * u_ref  # reference px per camera px
    sigma = float(np.hypot(opts.sigma_hint_px, np.sqrt(1 / 12))) * scale_ref
    swap_axes = orientation_matrix(orient)[0, 0] == 0
    ctx = TripletContext(img, warp, rects, masks, target, corners_u, pred, None, polarity, sigma, u_ref,
                         opts.max_stderr_px, opts.ambiguity_ratio, swap_axes)  # fmt: skip
    bar.stage("refining triplets")
    kept = _refine_triplets(target, inside, w, h, m, functools.partial(refine_triplet, ctx), bar)
    nccs = [info["ncc"] for info in kept.infos]
    sigmas = [info["sigma"] for info in kept.infos]
    bar.stage("consistency check")
    check = check_consistency(corners_u[kept.idx], kept.xy, target.corner_width_um[kept.idx] / u_ref,
                              opts.consistency_model, groups=_triplet_keys(kept.idx, target))  # fmt: skip
    bar.advance()
    sigma_ref = float(np.median(sigmas)) if sigmas else float("nan")
    common = dict(
        n_expected=int(inside.sum()),
        sigma_px=float(np.sqrt(max((sigma_ref / scale_ref) ** 2 - 1 / 12, 0.0))) if sigmas else float("nan"),
        ncc=float(np.median(nccs)) if nccs else float("nan"),
        consistency=ConsistencySummary(**check.summary()),
        predicted={target.corner_ids[i]: pred[i] for i in np.flatnonzero(inside)},
    )
    elements = {(int(found.ref.group[j]), int(found.ref.element[j])) for _, j in pose.matches}
    start = _DenseStart(orient, warp, rects, masks, polarity, _pose_anchors(target, found.ref, pose, trips),
                        max_degree=dense_degree_limit(len(elements)))  # fmt: skip
    return _finish(empty, target, corners_u, kept, check, common), start


def _view_boxes(target, layout, pose, u_ref, size, orient):
    """:func:`_model_boxes` of every bar of the whole target that is near the part of the
    target (um) that the image shows (so a neighbouring group is not mistaken for
    background)."""
    w, h = size
    corners_px = np.array([[0, 0], [w - 1, 0], [0, h - 1], [w - 1, h - 1]], float)
    view_um = (corners_px - pose.t) @ np.linalg.inv(pose.matrix()).T
    pad_um = 0.1 * float(np.ptp(view_um, axis=0).max())
    near_um = (*(view_um.min(axis=0) - pad_um), *(view_um.max(axis=0) + pad_um))
    return _model_boxes(target, _full_target(layout), u_ref, size, orient, near_um)


def _finish(empty, target, corners_u, kept: _Kept, check, common) -> Detection:
    """The consistency verdict and the kept-fraction limit; the final :class:`Detection`."""
    n_expected = common["n_expected"]
    dropped = dict(kept.dropped)
    if check.status != 0:
        dropped["inconsistent"] = len(kept.idx)
        return _replace(empty, dropped=DroppedCounts.from_counts(dropped), message=check.message, **common)
    keep = _whole_triplets(check.consistent, kept.idx, target, corners_u[kept.idx], kept.xy)
    dropped["inconsistent"] = int((~keep).sum())
    keep_idx = kept.idx[keep]
    if n_expected == 0 or len(keep_idx) < MIN_KEPT_FRACTION * n_expected:
        msg = (
            f"the registration is unreliable: only {len(keep_idx)} of {n_expected} expected corners "
            f"passed the checks; nothing was kept"
        )
        return _replace(empty, dropped=DroppedCounts.from_counts(dropped), message=msg, **common)
    return _replace(
        empty,
        ids=tuple(target.corner_ids[i] for i in keep_idx),
        xy_u=corners_u[keep_idx],
        xy_d=kept.xy[keep],
        stderr_px=kept.se[keep],
        dropped=DroppedCounts.from_counts(dropped),
        status=0,
        message="ok",
        **common,
    )


def _whole_triplets(consistent: np.ndarray, idx: np.ndarray, target, xy_u, xy_d) -> np.ndarray:
    """``consistent`` with the other corners of a triplet that has corners off the smooth map
    flagged too, when their median residual from the cubic map of the consistent pairs
    (``checks.cubic_residuals``) exceeds :data:`WHOLE_TRIPLET_SIGMAS` times its robust rms
    and :data:`WHOLE_TRIPLET_FLOOR_PX` (``idx`` the corners' indices in ``target``, 4 per
    bar; ``xy_u``, ``xy_d`` the pairs).

    Why: a triplet's corners come from one local fit; when some of them are off the map the
    fit may be off, and the others then carry the same error below the check's limit:
    through a misaligned relay, 3 of the 12 corners of the LAB-UMK render's G5E2H (seed 0)
    were flagged and the other 9 kept, 1.5 px off the truth with standard errors of 0.05 px.
    Where only the flagged corners are off (bars cut by the image's edge, Eq. (1)'s misfit at
    the field's edge) the others stay: dropping every triplet with two corners flagged cost
    the real LAB-UMK image turned by 30 degrees 12 corners of G6E5H and G6E6H within 0.08 px
    of the unturned image's, and one flagged corner each cost the detection sweep's 80 px
    row 44 corners within 0.37 px of the truth."""
    key = _triplet_keys(idx, target)
    suspect = np.isin(key, key[~consistent]) & consistent
    if not suspect.any() or consistent.sum() < 2 * 10:
        return consistent
    r = cubic_residuals(np.asarray(xy_u, float), np.asarray(xy_d, float), consistent)
    s = 1.2 * float(np.median(r[consistent]))
    keep = consistent.copy()
    for label in np.unique(key[suspect]):
        members = suspect & (key == label)
        if float(np.median(r[members])) > max(WHOLE_TRIPLET_SIGMAS * s, WHOLE_TRIPLET_FLOOR_PX):
            keep[members] = False
    return keep


def _triplet_keys(idx, target) -> np.ndarray:
    """The triplet of each corner (indices ``idx`` in ``target``, 4 per bar), as a label."""
    bar = np.asarray(idx, int) // 4
    return np.array([f"{g} {e} {o}" for g, e, o in zip(
        target.bar_group[bar], target.bar_element[bar], target.bar_orientation[bar])])  # fmt: skip


def _model_boxes(target, source, u_ref, size, orient, near_um=None):
    """Bars and reference squares of ``source`` (a target, um) as reference-px rectangles of
    the model image, and its printed numbers (grown by a little) as boxes to leave out of
    every fit; ``near_um`` (x0, y0, x1, y1) keeps only those near the view."""

    def px(boxes):
        boxes = np.asarray(boxes, float).reshape(-1, 4)
        if near_um is not None:
            x0, y0, x1, y1 = near_um
            k = (boxes[:, 2] >= x0) & (boxes[:, 0] <= x1) & (boxes[:, 3] >= y0) & (boxes[:, 1] <= y1)
            boxes = boxes[k]
        a = target.to_reference_px(boxes[:, :2], u_ref, size, orient)
        b = target.to_reference_px(boxes[:, 2:], u_ref, size, orient)
        return np.concatenate([np.minimum(a, b), np.maximum(a, b)], axis=1)

    rects = np.concatenate([px(source.bars), px(getattr(source, "squares", np.zeros((0, 4))))])
    masks = px(getattr(source, "labels", np.zeros((0, 4))))
    if len(masks):
        grow = 0.15 * (masks[:, 2:] - masks[:, :2]).max(axis=1, keepdims=True) + 1.0
        masks = np.concatenate([masks[:, :2] - grow, masks[:, 2:] + grow], axis=1)
    return rects, masks


def _refine_triplets(target, inside, w, h, m, refine, bar, triplets=None) -> _Kept:
    """Refine every triplet (of ``triplets``, default the target's) with a corner expected
    ``inside`` the image (margin ``m``): ``refine(bars, idx)`` returns ``(reason, xy, se,
    info)`` for its corner indices ``idx``."""
    keep_idx, keep_xy, keep_se, infos, failed = [], [], [], [], []
    dropped = dict.fromkeys(DROP_REASONS, 0)
    for bars in target.triplets() if triplets is None else triplets:
        idx = _corner_indices(bars)
        n_in = int(inside[idx].sum())
        if n_in == 0:
            bar.advance()
            continue
        reason, xy, se, info = refine(bars, idx)
        bar.advance()
        if reason is not None:
            dropped[reason] += n_in
            failed.append((tuple(int(b) for b in bars), reason, n_in))
            continue
        infos.append(info)
        ok = ImageSize(w, h).contains(xy, m + KEEP_MARGIN_EXTRA_PX)
        dropped["outside"] += int((inside[idx] & ~ok).sum())
        for k, i in enumerate(idx):
            if ok[k] and inside[i]:
                keep_idx.append(i)
                keep_xy.append(xy[k])
                keep_se.append(se[k])
    order = np.argsort(keep_idx)
    return _Kept(
        np.asarray(keep_idx, int)[order],
        np.asarray(keep_xy, float).reshape(-1, 2)[order],
        np.asarray(keep_se, float)[order],
        dropped,
        infos,
        failed,
    )


def _refine_twice(ctx: TripletContext, target, inside, w, h, m, bar) -> tuple[_Kept, _Kept]:
    """Every triplet refined (:func:`_refine_triplets`); then each element with a triplet
    dropped as moved or for its contrast is registered as a whole (:func:`refine_element`:
    both triplets' pixels, an affine correction that may move it by up to two bar widths) and
    those triplets are refined again from that element's prediction.

    Why: a triplet's refinement may move its corners by at most half a bar width from the
    registration's prediction (a larger move may be a slip onto the next bar), and the
    registration of a strongly blurred image through a strongly distorted field can be off
    by more than that where the bars are finest: the LAB-UMK micrograph through a misaligned
    relay (seed 2) had group 5's corners predicted 1.1-4.3 px off the truth (half its bar
    widths: 0.9-1.6 px), and no smooth correction of the registration from the refined
    group-4 corners predicts them better (a cubic through group 4's true corners leaves
    2.5 px median there).  One element's two triplets, turned a quarter turn to each other,
    pin its place where one triplet cannot (measured there: G5E2-E6 within 0.07-0.36 px
    median of the truth, moved by 0.65-1.3 bar widths).  The second refinement holds every
    check of the first against the element's prediction; the consistency check then judges
    all kept corners together.  Returns the first pass and the union of both (the first
    pass itself when nothing was refined again)."""
    first = _refine_triplets(target, inside, w, h, m, functools.partial(refine_triplet, ctx), bar)
    # only bars the bar finder looks for (MIN_BAR_PX) and wider than the registration's blur:
    # registered on their own, G7E2-E5 of the real LAB-UMK image (bars 0.7-1.0 px) came
    # 1.0-1.5 bar widths off the prediction of the benchmark's anchors, which counts them as
    # wrong ids, and bars under a blur of 5 px (the detection sweep) 1-2 px off their truth
    resolved = target.bar_width / ctx.um_per_px >= max(MIN_BAR_PX, ctx.sigma)
    retry = [
        bars for bars, reason, _ in first.failed if reason in ("moved", "contrast") and resolved[bars[0]]
    ]
    if not retry:
        return first, first
    members: dict = {}
    for bars in target.triplets():
        members.setdefault(_element_key(target, bars), []).extend(int(b) for b in bars)
    contexts: dict = {}

    def refine_again(bars, idx):
        key = _element_key(target, bars)
        if key not in contexts:
            all_bars = np.array(members[key])
            contexts[key] = refine_element(ctx, all_bars, _corner_indices(all_bars))
        again = contexts[key]
        return ("moved", None, None, None) if again is None else refine_triplet(again, bars, idx)

    second = _refine_triplets(target, inside, w, h, m, refine_again, bar, [np.array(b) for b in retry])
    dropped = dict(first.dropped)
    for bars, reason, n in first.failed:
        if bars in retry:
            dropped[reason] -= n
    for reason, n in second.dropped.items():
        dropped[reason] += n
    idx = np.concatenate([first.idx, second.idx])
    order = np.argsort(idx)
    both = _Kept(
        idx[order],
        np.concatenate([first.xy, second.xy])[order],
        np.concatenate([first.se, second.se])[order],
        dropped,
        first.infos + second.infos,
        [f for f in first.failed if f[0] not in retry] + second.failed,
    )
    return first, both


def _grown_from_first(first: _Kept, union: _Kept, check, corners_u, target, um_per_px):
    """``(union, its consistency)`` when the union of both refinements failed the global
    check and the first pass passed it (``check``): the first pass's consistent corners, and
    those of the second pass that a cubic map of them predicts, grown outwards a few bar
    widths at a time (:func:`~oapcal.imaging.detect.checks.grow_consistent`, as the check's
    rescue), a triplet's corners tested together; the rest of the second pass counts as
    inconsistent.

    Why: through a misaligned relay behind a tilted camera Eq. (1)'s misfit over the field
    grows with the finer group (the LAB-UMK render of seed 3: `full` rms 0.52 px on the
    first pass's 132 corners, 0.86 px with the second pass's right corners, over the 0.75
    allowed), so the union is refused although most of it is right, while a cubic map grown
    from the first pass adds 24 corners, none more than 0.5 px off the truth, and never
    the element registered 18 px off."""
    in_first = np.isin(union.idx, first.idx[check.consistent])
    width = target.corner_width_um[union.idx] / um_per_px
    groups = _triplet_keys(union.idx, target)
    grown = grow_consistent(corners_u[union.idx], union.xy, width, in_first, groups=groups)
    grown &= ~np.isin(union.idx, first.idx)  # the first pass's verdicts stand
    consistent = in_first | grown
    both = dataclasses.replace(
        check,
        consistent=consistent,
        n_inconsistent=int((~consistent).sum()),
        rescued=check.rescued + int(grown.sum()),
    )
    return union, both


def _element_key(target, bars) -> tuple[int, int]:
    """(group, element) of a triplet's bars."""
    return int(target.bar_group[bars[0]]), int(target.bar_element[bars[0]])


def _replace(det: Detection, **changes) -> Detection:
    from dataclasses import replace

    return replace(det, **changes)


def _pose_summary(pres, layout) -> PoseInfo:
    """The pose search's result ``pres`` as reported (:class:`~.records.PoseInfo`)."""
    return PoseInfo(
        "triplets",
        pres.status,
        pres.message,
        pres.pose.summary() if pres.pose is not None else None,
        pres.runner_up.summary() if pres.runner_up is not None else None,
        {k: float(v) for k, v in pres.slip_scores.items()},
        pres.n_image_triplets,
        layout,
    )


def _warp_from_points(x_img, u_img, pose, target, u_ref, orient, size) -> PolyWarp:
    """Polynomial warp camera -> reference px through the matched triplet centres: affine
    from the pose itself when fewer than 6 triplets match, quadratic from 6, cubic from 20."""
    w, h = size
    n = len(x_img)
    degree = 3 if n >= 20 else 2 if n >= 6 else 1
    centre = x_img.mean(axis=0) if n >= 6 else np.array([(w - 1) / 2, (h - 1) / 2])
    scale = float(max(np.ptp(x_img, axis=0).max() / 2, 8.0)) if n >= 6 else float(max(w, h)) / 2
    if degree == 1:
        # points of the pose's own affine map around the image
        grid = np.array([[0, 0], [w - 1, 0], [0, h - 1], [w - 1, h - 1], [(w - 1) / 2, (h - 1) / 2]], float)
        um = (grid - pose.t) @ np.linalg.inv(pose.matrix()).T
        x_img, u_img = grid, target.to_reference_px(um, u_ref, (w, h), orient)
    return PolyWarp.fit(x_img, u_img, degree, centre, scale)


@functools.lru_cache(maxsize=4)
def _full_target(layout: str | None = None):
    return usaf_target(ALL_GROUPS, layout_name=layout)


@functools.lru_cache(maxsize=1)
def _corner_width_um() -> dict:
    """Corner id -> its bar's width (um), over the whole target (every layout's is the same)."""
    tw = _full_target()
    return dict(zip(tw.corner_ids, tw.corner_width_um))


@functools.lru_cache(maxsize=4)
def _reference_triplets(layout: str | None = None):
    from oapcal.imaging.detect.pose import RefTriplets

    return RefTriplets.from_target(_full_target(layout))


def _layouts() -> list:
    """The target layouts to try (``oapcal.imaging.usaf.LAYOUTS``: makers draw the layers'
    spacing slightly differently)."""
    from oapcal.imaging import usaf

    return list(getattr(usaf, "LAYOUTS", {None: None}))


def _pose_polarity(img, trips, pose) -> float:
    """+1 bright bars, -1 dark: the majority of the pose's matched triplets; on a tie (the
    gaps between overexposed bright bars also make a dark triplet at the same place) the
    polarity that the image's background has not (the background covers more of the image
    than the bars: a median below the middle of the range is a dark background)."""
    total = float(np.sum(trips.polarity[[i for i, _ in pose.matches]]))
    if total != 0:
        return float(np.sign(total))
    return 1.0 if float(np.median(img)) < 0.5 else -1.0


def dense_degree_limit(n_elements: int) -> int:
    """The highest degree of the dense registration's warp when the pose matched the
    triplets of ``n_elements`` elements: affine for one element (its two triplets span a
    few bar lengths, where no distortion is resolved; a degree-4 warp there follows the bars'
    exposure instead: on ``highmag_g7e1.jpg`` it spread the outer corners by 10 px, a third
    of a bar width, and the registrations disagreed), else the finest level's."""
    return 1 if n_elements <= 1 else LEVELS[-1][1]


def _pose_anchors(target, ref, pose, trips) -> list:
    """The pose's matched triplets that belong to ``target``: (their corner indices in
    ``target``, the image triplet's centre, its bar width in px) each."""
    keys = {
        (int(target.bar_group[b[0]]), int(target.bar_element[b[0]]), str(target.bar_orientation[b[0]])): b
        for b in target.triplets()
    }
    out = []
    for i, j in pose.matches:
        b = keys.get((int(ref.group[j]), int(ref.element[j]), str(ref.orient[j])))
        if b is not None:
            idx = np.concatenate([4 * np.asarray(b) + c for c in range(4)])
            out.append((idx, np.asarray(trips.centre[i], float), float(trips.width[i])))
    return out


def _detect_dense(img, target, um_per_px, orientation, opts: _Options, bar, start=None) -> Detection:
    """The dense registration at a given scale (module docstring, docs/detection.md), from
    ``start`` (the pose's orientation, warp, bars and polarity) or from the correlation
    search in ``orientation`` (``"auto"``: the 8).  Refused when the registered scale differs
    from ``um_per_px`` by more than half an element step (a one-element slip would differ by
    12 %)."""
    h, w = img.shape
    empty = Detection((), np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0), 0, {}, 1, "", um_per_px=um_per_px)
    # bound: the rendered target must be comparable with the image
    extent = np.ptp(target.bars.reshape(-1, 2), axis=0) / um_per_px
    if extent.max() > 4 * max(w, h) or extent.min() < 8:
        msg = (
            f"the target was not found: at {um_per_px:g} um/px groups {target.groups[0]}-{target.groups[-1]} "
            f"would be {extent[0]:.0f} x {extent[1]:.0f} px in a {w} x {h} px image; check um_per_px"
        )
        return _replace(empty, message=msg, param=("um_per_px",))
    if start is None:
        start = _correlation_start(img, target, um_per_px, orientation, opts.orientation_ratio)
        if isinstance(start, Detection):
            return _replace(start, um_per_px=um_per_px)
        empty = _replace(empty, orientation=start.orientation, orientation_scores=start.score_table)
    return _dense_levels(img, target, um_per_px, start, opts, bar, empty)


def _correlation_start(img, target, um_per_px, orientation, orientation_ratio):
    """The start of a dense registration from the correlation search over the orientations
    (:func:`~.registration.find_target`), or a failed :class:`Detection`."""
    h, w = img.shape
    ref_centre = (np.asarray((w, h), float) - 1) / 2
    candidates = list(ORIENTATIONS) if orientation == "auto" else [orientation]
    scores = {}
    for name in candidates:
        # bars and reference squares (the squares are part of every real target)
        templ_rects, _ = _model_boxes(target, target, um_per_px, (w, h), name)
        found = find_target(img, templ_rects, ref_centre)
        scores[name] = (found[2], found) if found is not None else (-1.0, None)
    ranked = sorted(scores, key=lambda k: -scores[k][0])
    best = ranked[0]
    score_table = {k: round(float(scores[k][0]), 4) for k in ranked}
    found = scores[best][1]
    failed = Detection((), np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0), 0, {}, 1, "",
                       orientation=best, orientation_scores=score_table)  # fmt: skip
    if found is None or found[2] < 0.2:
        msg = (
            "the target was not found (no bar triplets, no correlation with the rendered groups); "
            "check groups and um_per_px"
        )
        return _replace(failed, message=msg, param=("groups", "um_per_px"))
    if len(ranked) > 1 and scores[ranked[1]][0] >= orientation_ratio * scores[best][0]:
        msg = (
            f"the target's orientation is ambiguous: {best} scores {scores[best][0]:.3f} and "
            f"{ranked[1]} {scores[ranked[1]][0]:.3f}; give the orientation"
        )
        return _replace(failed, message=msg, param=("orientation",))
    rects = target.rectangles_px(um_per_px, (w, h), best)
    s, shift, _, sign = found  # camera = s u + shift
    model_rects, masks = _model_boxes(target, target, um_per_px, (w, h), best)
    return _DenseStart(best, initial_warp(s, shift, rects), model_rects, masks, sign, score_table=score_table)


def _dense_levels(img, target, um_per_px, start: _DenseStart, opts: _Options, bar, empty) -> Detection:
    """The dense registration, coarse to fine, then every triplet refined.  A slip onto the
    neighbouring element is ruled out by ``start.anchors`` (the pose's matched triplets: the
    registration must keep each on its image triplet) when it starts from a pose, else by
    its scale (within half an element step of ``um_per_px``)."""
    h, w = img.shape
    best = start.orientation
    empty = _replace(empty, orientation=best, orientation_scores=start.score_table, um_per_px=um_per_px,
                     polarity="bright" if start.polarity > 0 else "dark")  # fmt: skip
    corners_u = target.reference_px(um_per_px, (w, h), best)
    own = target.rectangles_px(um_per_px, (w, h), best)
    ref = Reference(start.rects, window=(own[:, :2].min(axis=0) - 60, own[:, 2:].max(axis=0) + 60),
                    masks=start.masks)  # fmt: skip
    ref.lo = np.maximum(ref.lo, own[:, :2].min(axis=0) - 20)
    ref.hi = np.minimum(ref.hi, own[:, 2:].max(axis=0) + 20)
    sigma = float(np.hypot(opts.sigma_hint_px, np.sqrt(1 / 12)))
    a, b = (0.05, 0.9) if start.polarity > 0 else (0.95, -0.9)
    reg = _register_levels(img, ref, FitStart(start.warp.coef, a, b, sigma), start.warp, start.max_degree)
    if isinstance(reg, dict):
        return _replace(empty, **reg)
    warp, res, sigma = reg
    global_ncc = res.ncc
    pred = warp.inverse(corners_u)
    slip = _slip_message(corners_u, pred, start.anchors, um_per_px)
    if slip:
        return _replace(empty, message=slip, ncc=global_ncc)
    pred = warp.inverse(corners_u)
    m = 3.0
    inside = ImageSize(w, h).contains(pred, m)
    ctx = TripletContext(img, warp, start.rects, start.masks, target, corners_u, pred, res.a, res.b, sigma,
                         um_per_px, opts.max_stderr_px, opts.ambiguity_ratio,
                         orientation_matrix(best)[0, 0] == 0)  # fmt: skip

    def judged(k: _Kept):
        return check_consistency(corners_u[k.idx], k.xy, target.corner_width_um[k.idx] / um_per_px,
                                 opts.consistency_model, groups=_triplet_keys(k.idx, target))  # fmt: skip

    first, kept = _refine_twice(ctx, target, inside, w, h, m, bar)
    check = judged(kept)
    if check.status != 0 and kept is not first:
        # the elements registered one by one must not cost the registration its corners: the
        # union is kept only when it passes the global check (its outliers then dropped),
        # else the first pass alone is judged, and the second pass's corners that the first's
        # smooth map reaches are added (_grown_from_first)
        check = judged(first)
        kept, check = (
            (first, check)
            if check.status != 0
            else _grown_from_first(first, kept, check, corners_u, target, um_per_px)
        )
    # expected: the corners of resolved bars (as the triplet path counts them) and any
    # narrower ones kept, so that the coverage of both paths means the same
    expected = inside & (target.corner_width_um / um_per_px >= RESOLVED_BAR_PX)
    expected[kept.idx] = True
    common = dict(
        n_expected=int(expected.sum()),
        sigma_px=camera_sigma(warp, sigma),
        ncc=global_ncc,
        consistency=ConsistencySummary(**check.summary()),
        predicted={target.corner_ids[i]: pred[i] for i in np.flatnonzero(inside)},
    )
    return _finish(empty, target, corners_u, kept, check, common)


def _register_levels(img, ref: Reference, fit: FitStart, warp: PolyWarp, max_degree: int = LEVELS[-1][1]):
    """The registration's levels (:data:`LEVELS`, coarse to fine, each warp's degree at most
    ``max_degree``) from ``warp`` and the contrast and blur of ``fit``: ``(warp, last fit,
    fitted blur)``, or the fields of the failed :class:`Detection` (a dict)."""
    import cv2

    h, w = img.shape
    a, b, sigma = fit.a, fit.b, fit.sigma
    for blur, degree in LEVELS:
        warp = warp.with_degree(min(degree, max_degree))
        values_img = img if blur is None else cv2.GaussianBlur(img, (0, 0), blur)
        xs = region_pixels(
            warp, ref, (w, h), max_pixels=MAX_FIT_PIXELS if blur is None else MAX_FIT_PIXELS // 4
        )
        if len(xs) < 50:
            return {"message": "the registered target falls outside the image"}
        # in the order of their reference rows: the raster is then read row after row (a turned
        # image's pixels read a 12 M-cell raster at half the speed in camera order)
        u0 = warp(xs)
        xs = xs[np.lexsort((u0[:, 0], np.floor(u0[:, 1])))]
        model_sigma = sigma if blur is None else float(np.hypot(blur, sigma))
        # a blurred level's raster needs no finer cells than a fraction of its blur
        level_ref = ref if blur is None else ref.for_blur(model_sigma)
        data = PixelData(values_img[xs[:, 1].astype(int), xs[:, 0].astype(int)], np.zeros((len(xs), 2)),
                         warp.basis(xs), level_ref)  # fmt: skip
        options = FitOptions(fit_sigma=blur is None, sigma_max=max(8.0, 2 * model_sigma))
        res = fit_pixels(data, FitStart(warp.coef, a, b, model_sigma), options)
        warp = warp.with_coef(res.coef)
        a, b = res.a, res.b
        if res.ncc < 0.3:
            msg = f"registration failed (model-image correlation {res.ncc:.2f} at blur {blur} px)"
            return {"message": msg, "ncc": res.ncc}
        if blur is None:
            sigma = res.sigma
    if res.ncc < 0.5:
        msg = f"registration failed (model-image correlation {res.ncc:.2f} < 0.5)"
        return {"message": msg, "ncc": res.ncc}
    return warp, res, sigma


def _slip_message(corners_u, pred, anchors, um_per_px) -> str:
    """Why the registration may have slipped onto the neighbouring element (``""`` when it
    has not): from a pose, it left the pose's matched triplets; else its scale is more than
    half an element step off the given one (a slip is 12 % off; the scale of the similarity
    that fits the registered corners best)."""
    fin = np.isfinite(pred).all(axis=1)
    pu = corners_u[fin] - corners_u[fin].mean(axis=0)
    pc = pred[fin] - pred[fin].mean(axis=0)
    scale = float(np.sqrt((pu**2).sum() / max((pc**2).sum(), 1e-12))) if fin.sum() > 2 else 1.0
    if anchors:
        # From a pose: its ids were decided (and its slips tested) by the pose search, on
        # the image triplets it matched.  The registration keeps them when it puts every
        # matched triplet's centre on the image triplet (a slip moves them by a period or
        # more).  The scale is no test here: under a strongly distorted field the pose's
        # scale, fitted near its matches, differs from the whole target's by up to 13 %
        # (measured through a misaligned relay), more than half an element step.
        off = [np.hypot(*(pred[idx].mean(axis=0) - xc)) / wc for idx, xc, wc in anchors]
        off = np.asarray(off)[np.isfinite(off)]
        if len(off) == 0 or np.median(off) > 1.0:
            return (
                f"the dense registration left the pose's matched triplets (median "
                f"{np.median(off) if len(off) else float('nan'):.1f} bar widths off): possibly every "
                f"id one element off; nothing was kept"
            )
    elif abs(np.log(scale)) > np.log(HALF_ELEMENT):
        return (
            f"the registered target's scale differs from {um_per_px:g} um/px by "
            f"{100 * (1 / scale - 1):+.1f} % "
            f"(more than half an element step, 6 %): possibly every id one element off; nothing was kept"
        )
    return ""
