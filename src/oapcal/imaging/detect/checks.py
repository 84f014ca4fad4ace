"""Checks of a detection: the global consistency of the matched pairs with one smooth
distortion, and scoring against ground truth."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from oapcal.imaging.detect.warp import PolyWarp, poly_exponents

#: Consistency check (:func:`check_consistency`): residual limit ``max(SIGMAS * s, FLOOR)``
#: px, capped at half a bar width; refuse the alignment above MAX_FRACTION flagged pairs.
CONSISTENCY_FLOOR_PX = 0.5
CONSISTENCY_SIGMAS = 5.0
CONSISTENCY_MAX_FRACTION = 0.25
#: ... and above this rms residual (px) of the consistent pairs, from the model and from a
#: cubic polynomial map alike: an empirical limit between a right detection through the
#: relay at 94 px distortion (0.39 px, the model's own misfit) and a wrong alignment at
#: 161 px that was smooth enough to fit (0.93 px).
CONSISTENCY_MAX_RMS_PX = 0.75
#: ... or, on :data:`CUBIC_RMS_MIN_PAIRS` consistent pairs or more, this fraction of their
#: median bar width (px) when that is more (:func:`rms_limit`).  Why: a real target is not
#: where the drawn layout puts it by a part of its own size, so a right detection's residual
#: grows with the image's scale: the whole-target scan and the LAB-UMK micrograph leave
#: 0.07-0.09 bar widths (0.40 and 0.27 px at their own size; 1.4-2.0 px enlarged 4 and 6.4
#: times, refused by the px limit alone), a relay with 94 px of distortion 0.11; the wrong
#: but smooth alignment above 0.27 (0.93 px on bars about 3.5 px wide), a wrong pose kept on
#: 36 pairs of a 143 px field 0.22.  On the 640 x 480 renders (bars 2-7 px) the px limit is
#: the larger.
CONSISTENCY_MAX_RMS_WIDTHS = 0.15
#: The cubic map's rms (:func:`check_consistency`) is judged only on this many consistent
#: pairs or more, five per coefficient of its 20: on fewer it fits a wrong alignment too (the
#: single high-magnification element binned 2x with ``G7E1``: 24 pairs, ``paper`` 0.92 px,
#: the cubic under the limit, 6 of the 24 ids wrong).
CUBIC_RMS_MIN_PAIRS = 100
#: A pair off the model is tested against the cubic map of the kept pairs only within this
#: many of its bar widths from one of them (:func:`grow_consistent`).
RESCUE_STEP_WIDTHS = 3.0


@dataclass(frozen=True)
class Consistency:
    """The global consistency check of matched pairs (:func:`check_consistency`).

    ``consistent`` (bool per pair); ``model`` the fitted model (None: not checked);
    ``rms_px`` the rms residual of the consistent pairs, ``threshold_px`` the residual
    limit (per pair); ``status`` 0, or 1 when the alignment is refused (``message``);
    ``rescued`` the pairs off the model kept after all because a cubic map fits them
    (:func:`check_consistency`); ``cubic_rms_px`` the rms residual of the consistent pairs
    from a cubic map, computed only when the model's exceeds the limit (None otherwise).
    """

    consistent: np.ndarray
    model: str | None
    rms_px: float
    max_px: float
    n_inconsistent: int
    status: int = 0
    message: str = "ok"
    rescued: int = 0
    cubic_rms_px: float | None = None

    def summary(self) -> dict:
        return {
            "model": self.model,
            "rms_px": self.rms_px,
            "max_px": self.max_px,
            "inconsistent": self.n_inconsistent,
            "status": self.status,
            "message": self.message,
            "rescued": self.rescued,
            "cubic_rms_px": self.cubic_rms_px,
        }


def check_consistency(
    xy_u: np.ndarray,
    xy_d: np.ndarray,
    width_px: np.ndarray,
    model: str | None = "auto",
    *,
    floor_px: float = CONSISTENCY_FLOOR_PX,
    n_sigma: float = CONSISTENCY_SIGMAS,
    max_fraction: float = CONSISTENCY_MAX_FRACTION,
    max_rms_px: float = CONSISTENCY_MAX_RMS_PX,
    groups=None,
) -> Consistency:
    """Check that matched pairs follow one smooth distortion: fit ``model``
    (:func:`oapcal.fitting.fit`, the pixel start) to the pairs and flag every pair whose
    residual exceeds ``min(max(n_sigma * s, floor_px), width_px / 2)``, with ``s`` a
    robust rms of the residuals (1.2 x their median); refit without the flagged pairs
    until nothing changes (at most 8 times).

    A pair off by a whole bar (a mismatch) is at least ``width_px`` from its true position
    and cannot follow the smooth model; a correct pair is within the model's own error.
    The alignment is refused (``status`` 1) when the fit does not converge, when more than
    ``max_fraction`` of the pairs are flagged (then the model is fitted to wrong pairs
    as much as to right ones and nothing can be trusted), or when the rms residual of
    the rest exceeds :func:`rms_limit` (``max_rms_px``, or a fraction of the bars' width on
    many pairs) both from the model and from the cubic polynomial map
    fitted to the same pairs, when there are :data:`CUBIC_RMS_MIN_PAIRS` of them (a wrong
    alignment can be smooth, but rarely as smooth as a real distortion; the limit is
    empirical, see :data:`CONSISTENCY_MAX_RMS_PX`).  Why the cubic too: a real target in
    a real image is not where the drawn layout puts it, and through a misaligned relay
    behind a tilted camera Eq. (1) misfits its field's edge (the rescue below): the LAB-UMK
    micrograph, itself 0.8-0.9 px rms off the layout, through the misaligned relay of seed
    3 left 0.89 px from ``full`` on 245 right corners, 0.31 px from the cubic.

    A flagged pair is kept after all (``rescued``) when it follows the cubic polynomial
    map fitted to the unflagged pairs within the same kind of limit, grown outwards from
    them a few bar widths at a time (:func:`grow_consistent`): Eq. (1) has no perspective term, so
    through a misaligned relay behind a tilted camera (keystone) its own misfit exceeds half
    a narrow bar's width where a cubic map still fits every right pair to a few hundredths
    of a px.  The refusals above are decided on the model's flags alone, before the
    rescue; ``rms_px`` and ``max_px`` are the model's.  ``groups`` (a label per pair, e.g.
    its triplet): the rescue tests a group's pairs together (:func:`grow_consistent`).

    ``model="auto"``: ``full`` from 40 pairs, ``paper`` from 16, no check below
    (``model`` None in the result); ``None``: no check.  When the model's fit does not
    converge (an image with almost no distortion leaves the distortion centre undetermined)
    a cubic polynomial map is the smooth model (``model`` ``"cubic"`` in the result).
    """
    n = len(xy_u)
    everything = np.ones(n, bool)
    if model == "auto":
        model = "full" if n >= 40 else "paper" if n >= 16 else None
    if model is None:
        return Consistency(everything, None, float("nan"), float("nan"), 0)
    width_px = np.asarray(width_px, float)
    # The model's pixel start assumes pairs near the identity: take out the mean shift
    # first (a target off the image centre is shifted by tens of px; residuals do not change).
    xy_u = np.asarray(xy_u, float) + np.median(np.asarray(xy_d, float) - np.asarray(xy_u, float), axis=0)
    xy_d = np.asarray(xy_d, float)
    flagged = _flag_off_model(xy_u, xy_d, width_px, model, floor_px, n_sigma)
    if isinstance(flagged, str):
        return Consistency(~everything, model, float("nan"), float("nan"), n, 1, flagged)
    keep, r, model = flagged
    n_bad = int((~keep).sum())
    rms = float(np.sqrt(np.mean(r[keep] ** 2))) if keep.any() else float("nan")
    worst = float(r[keep].max()) if keep.any() else float("nan")
    if n_bad > max_fraction * n:
        return Consistency(
            ~everything, model, rms, worst, n, 1,
            f"the global alignment is inconsistent: {n_bad} of {n} matched corners are off the "
            f"smooth {model} model (rms residual of the rest {rms:.2f} px); nothing was kept",
        )  # fmt: skip
    cubic_rms = None
    limit = rms_limit(width_px[keep], max_rms_px)
    if not rms <= limit and model != "cubic" and keep.sum() >= CUBIC_RMS_MIN_PAIRS:
        cubic_rms = float(np.sqrt(np.mean(cubic_residuals(xy_u, xy_d, keep)[keep] ** 2)))
    if not (rms <= limit or (cubic_rms is not None and cubic_rms <= limit)):
        cubic = "" if cubic_rms is None else f" and a cubic map with {cubic_rms:.2f} px"
        return Consistency(
            ~everything, model, rms, worst, n, 1,
            f"the global alignment is doubtful: the {model} model fits the matched corners with an rms "
            f"residual of {rms:.2f} px{cubic} (limit {limit:.3g} px); nothing was kept",
            cubic_rms_px=cubic_rms,
        )  # fmt: skip
    rescued = grow_consistent(xy_u, xy_d, width_px, keep, floor_px, n_sigma, groups)
    keep = keep | rescued
    return Consistency(
        keep, model, rms, worst, int((~keep).sum()), rescued=int(rescued.sum()), cubic_rms_px=cubic_rms
    )


def rms_limit(width_px: np.ndarray, max_rms_px: float = CONSISTENCY_MAX_RMS_PX) -> float:
    """The rms residual (px) above which :func:`check_consistency` refuses an alignment whose
    consistent pairs have bar widths ``width_px``: ``max_rms_px``, or
    :data:`CONSISTENCY_MAX_RMS_WIDTHS` of their median width when that is more and there are
    :data:`CUBIC_RMS_MIN_PAIRS` of them (on fewer, a wrong alignment of a few wide triplets
    fits a smooth map too: the single element binned 2x with ``G7E1``, 24 pairs on bars 17
    px wide, 6 ids wrong, 0.92 px)."""
    width_px = np.asarray(width_px, float)
    if len(width_px) < CUBIC_RMS_MIN_PAIRS:
        return float(max_rms_px)
    return float(max(max_rms_px, CONSISTENCY_MAX_RMS_WIDTHS * np.median(width_px)))


def _flag_off_model(xy_u, xy_d, width_px, model, floor_px, n_sigma):
    """The pairs that follow ``model`` (:func:`check_consistency`'s iteration): ``(keep,
    residuals px, model name)``, the name ``"cubic"`` when the model's fit did not converge
    and a cubic map took its place; or the message when neither could be fitted."""
    from oapcal.fitting import fit

    n = len(xy_u)
    keep = np.ones(n, bool)
    cubic = False
    for _ in range(8):
        result = None if cubic else fit(xy_u[keep], xy_d[keep], model, init="pixel")
        if result is not None and result.converged:
            r = np.hypot(*(result.model(xy_u) - xy_d).T)
        elif keep.sum() >= 2 * len(poly_exponents(3)):
            # An image with almost no distortion leaves Eq. (1)'s centre undetermined and
            # its fit may not converge: a cubic polynomial map (linear least squares) is
            # the smooth model then.
            model, cubic = "cubic", True
            r = cubic_residuals(xy_u, xy_d, keep)
        else:
            return (
                f"the global alignment could not be checked: the {model} model did not converge "
                f"on the matched corners ({result.message if result is not None else 'too few pairs left'})"
            )
        new = r <= _residual_limit(r, keep, width_px, floor_px, n_sigma)
        if (new == keep).all() or new.sum() < 0.5 * n:
            keep = new
            break
        keep = new
    return keep, r, model


def _residual_limit(r, keep, width_px, floor_px, n_sigma):
    """The residual limit per pair: ``min(max(n_sigma * s, floor_px), width_px / 2)``,
    ``s`` = 1.2 x the median residual of the ``keep`` pairs (a robust rms)."""
    s = 1.2 * float(np.median(r[keep]))
    return np.minimum(max(n_sigma * s, floor_px), 0.5 * width_px)


def cubic_residuals(xy_u, xy_d, keep):
    """Residuals (px) of every pair from the cubic polynomial map fitted to the ``keep`` pairs."""
    return np.hypot(*(PolyWarp.fit(xy_u[keep], xy_d[keep], 3)(xy_u) - xy_d).T)


def grow_consistent(
    xy_u, xy_d, width_px, keep, floor_px=CONSISTENCY_FLOOR_PX, n_sigma=CONSISTENCY_SIGMAS, groups=None
):
    """The flagged pairs (``~keep``) that the cubic map of the pairs already kept predicts
    within :func:`_residual_limit`, grown outwards from the kept pairs: each round fits the
    cubic to the pairs kept so far and tests only the flagged pairs at most
    :data:`RESCUE_STEP_WIDTHS` bar widths from one of them, so the map is never extrapolated
    further than that (measured through a misaligned relay: 0.03-0.08 px off at up to 9 bar
    widths beyond the kept pairs).  A pair matched one bar off is a bar width from its own
    place, twice the largest limit, and is never rescued, nor used by a later round; a right
    pair that only Eq. (1)'s misfit put over the limit is.  Needs twice the cubic's 10 terms
    of unflagged pairs.  ``groups`` (a label per pair, e.g. its triplet): a group's pairs
    are tested together, as soon as one of them is within the step (a triplet's far end is
    five bar widths from its near end)."""
    from scipy.spatial import cKDTree

    ok = keep.copy()
    if keep.all() or keep.sum() < 2 * len(poly_exponents(3)):
        return ~keep & ok
    while not ok.all():
        r = cubic_residuals(xy_u, xy_d, ok)
        dist, _ = cKDTree(xy_u[ok]).query(xy_u)
        near = dist <= RESCUE_STEP_WIDTHS * width_px
        if groups is not None:
            near = np.isin(groups, groups[near])
        new = ~ok & near & (r <= _residual_limit(r, ok, width_px, floor_px, n_sigma))
        if not new.any():
            break
        ok |= new
    return ~keep & ok


def outvoted(disputed, ids_a, xy_a, ids_b, xy_b) -> int:
    """Which of two registrations slipped on the corners they dispute: ``1`` when ``a``,
    ``2`` when ``b``, ``0`` when the corners cannot tell.

    ``disputed`` the corner ids the two place apart; ``ids_*`` and ``xy_*`` ``(N, 2)`` each
    registration's corners (camera px).  A registration slipped when it put the disputed
    corners on another element's bars: each of its disputed corners lies nearer to the
    other registration's corner of the same bar and corner index in one other element or
    triplet (``G5E4V1C2`` on the other's ``G5E5V1C2``) than half-way to where the other
    puts the id itself, for every disputed corner and with one such element for all.
    Exactly one of the two may have slipped.  Measured: the triplet path matched the
    vertical triplet of G5E4 of a real micrograph rendered through a misaligned relay,
    turned 45 degrees and mirrored, on the bars that the dense registration names G5E5V
    (0.3-2.4 px from them, 16-19 px from its own G5E4V, which is within 0.12 px of the
    truth like all of its 288 corners)."""

    def slipped(ids_x, xy_x, ids_y, xy_y) -> bool:
        from scipy.spatial import cKDTree

        ix = {k: n for n, k in enumerate(ids_x)}
        iy = {k: n for n, k in enumerate(ids_y)}
        tree = cKDTree(xy_y)
        onto = set()
        for k in disputed:
            p = xy_x[ix[k]]
            dist, j = tree.query(p)
            other = ids_y[j]
            own = float(np.hypot(*(p - xy_y[iy[k]])))
            # the same bar and corner (the id's last 4 characters, "V1C2") of another triplet
            if other == k or other[-4:] != k[-4:] or dist >= 0.5 * own:
                return False
            onto.add(other[:-4])
        return len(onto) == 1

    disputed = sorted(disputed)
    if not disputed:
        return 0
    a = slipped(ids_a, np.asarray(xy_a, float), ids_b, np.asarray(xy_b, float))
    b = slipped(ids_b, np.asarray(xy_b, float), ids_a, np.asarray(xy_a, float))
    return 1 if a and not b else 2 if b and not a else 0


# --------------------------------------------------------------------------- evaluation


def evaluate_detection(detection, ids, xy_d_true, visible) -> dict:
    """Compare a detection with ground truth (e.g. :class:`~oapcal.imaging.simulate.SimulatedImage`).

    Returns ``found`` (kept corners that are truly visible), ``visible`` (fully visible
    corners), ``coverage`` (found / visible), ``median_error_px``, ``max_error_px``,
    ``rms_error_px`` and ``mismatches``: kept corners farther from their true position than
    half the distance from that true position to the nearest other true corner (so nearer
    to another corner than to their own).
    """
    index = {i: k for k, i in enumerate(ids)}
    xy_true = np.asarray(xy_d_true, float)
    vis = np.asarray(visible, bool)
    k = np.array([index[i] for i in detection.ids], int)
    err = np.hypot(*(detection.xy_d - xy_true[k]).T) if len(k) else np.zeros(0)
    from scipy.spatial import cKDTree

    finite = np.isfinite(xy_true).all(axis=1)
    tree = cKDTree(xy_true[finite])
    nn = tree.query(xy_true[k], k=2)[0][:, 1] if len(k) else np.zeros(0)
    mismatches = int((err > 0.5 * nn).sum())
    found = int(vis[k].sum()) if len(k) else 0
    n_vis = int(vis.sum())
    return {
        "found": found,
        "visible": n_vis,
        "coverage": found / n_vis if n_vis else 0.0,
        "median_error_px": float(np.median(err)) if len(err) else float("nan"),
        "max_error_px": float(err.max()) if len(err) else float("nan"),
        "rms_error_px": float(np.sqrt(np.mean(err**2))) if len(err) else float("nan"),
        "mismatches": mismatches,
    }
