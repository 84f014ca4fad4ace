"""Choosing across model families: Brown-Conrady subsets (Eq. 1), the same with the
target's rotation (``bc+rotation``) or the perspective terms (``bc+tilt``,
``bc+rotation+tilt``) and physical-relay subsets ranked together, by AICc
and by K-fold cross-validated held-out error (``oapcal select --families bc,relay``; ``docs/models.md``).

Both families are scored the same way as :func:`oapcal.select.select_models` scores Eq. (1):
every model is fitted to the points as given (no normalization: the relay fits the
target's pose itself, in px), the distorted points are corrected through its inverse and
compared with the reference points; AICc of those corrected residuals uses ``K = k + 1``.
The same data in the same units make the AICc values comparable across families.  The
recommendation is the model with the smallest cross-validated held-out error among the
``cv_top`` best of each family by AICc (AICc ranks within the assumptions of each model;
held-out error measures what a user needs, the error of correcting new points).

Relay subsets: the target's pose (scale, rotation, shift) always, plus every combination
of the blocks in :data:`RELAY_BLOCKS` (64 subsets; the first mirror's tilts are left out:
with the stop at that mirror they act like the target's shift; with a microscope in the
design, family ``relay+microscope``, also :data:`MICROSCOPE_BLOCKS`: 128); subsets the
points cannot identify (:func:`oapcal.optics.relay_model.identifiability`) are ranked last
with the reason.

Only a model that ``oapcal fit`` would write can be recommended: before cross-validation
each family's models are checked in AICc order with the check ``fit`` applies before
writing (:func:`oapcal.calibration.check_model_region`: finite and not folding over on the
reference points' bounds and, with ``image_size``, the image frame, the output region of
``correct``) until ``cv_top`` pass; those that fail are ranked with the invalid ones, with
the check's reason.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from oapcal.calibration import ModelRegion, check_model_region
from oapcal.errors import DataError, InputFileError
from oapcal.fitting import DEFAULT_INIT, initial_params_many
from oapcal.model import (
    BROWN_CONRADY,
    BROWN_CONRADY_POSE,
    BROWN_CONRADY_TILT,
    N_PARAMS,
    RELAY,
    RELAY_POSE_NAMES,
    ROTATION_SUFFIX,
    TILT_SUFFIX,
    Model,
    all_masks,
    as_model,
    family_named,
    jacobian_params,
)
from oapcal.optics.relay_model import (
    RelayDesign,
    default_centre,
    identifiability,
    map_fit,
    parse_priors,
    relay_mask,
    relay_params,
)
from oapcal.records import finite_or_none
from oapcal.select import cross_validate, invalid_reasons, score_models

#: The blocks of misalignment combined into relay subsets (each with the pose).
RELAY_BLOCKS: dict[str, tuple[str, ...]] = {
    "tilt2": ("m2_tilt_x", "m2_tilt_y"),
    "decentre2": ("m2_decentre_x", "m2_decentre_y"),
    "d1": ("d1",),
    "camera": ("camera_tilt_x", "camera_tilt_y"),
    "defocus": ("camera_defocus",),
    "object": ("object_tilt_x", "object_tilt_y"),
}
#: With a microscope behind the relay, also its radial term.
MICROSCOPE_BLOCKS: dict[str, tuple[str, ...]] = {"microscope": ("microscope_k1",)}
#: The ``--families`` keys; ``relay`` is the relay family of the design (``relay`` or,
#: with a microscope, ``relay+microscope``).
FAMILY_NAMES = {"bc": "brown-conrady", "bc+rotation": "brown-conrady+rotation", "relay": "relay",
                "bc+tilt": "brown-conrady+tilt", "bc+rotation+tilt": "brown-conrady+tilt"}  # fmt: skip
#: The Eq. (1) variants among them: key -> (family, the entries after Eq. (1)'s 13 that every
#: subset fits, the spec's suffix).  ``bc+tilt`` fits the perspective terms with the rotation
#: fixed at 0, ``bc+rotation+tilt`` both.
EQ1_VARIANTS = {
    "bc+rotation": (BROWN_CONRADY_POSE, (True,), ROTATION_SUFFIX),
    "bc+tilt": (BROWN_CONRADY_TILT, (False, True, True), TILT_SUFFIX),
    "bc+rotation+tilt": (BROWN_CONRADY_TILT, (True, True, True), ROTATION_SUFFIX + TILT_SUFFIX),
}
Progress = Callable[[int, int], None]
#: The relay subset of every misalignment value (with priors: always cross-validated).
FULL_RELAY_SPEC = "relay:all"
#: The start of the reason of a model that ``oapcal fit`` would refuse to write.
REFUSED_PREFIX = "fit would refuse it"
#: The start of the reason of a model that folds over in the image beyond the points: ``oapcal
#: fit`` writes it (with a note) and ``oapcal correct`` writes only its trust region, but it
#: cannot correct the whole image, so the selection does not recommend it.
FOLDS_PREFIX = "not recommended"


@dataclass(frozen=True)
class Candidate:
    """One model of a cross-family selection: its ``family`` (``"brown-conrady"``,
    ``"brown-conrady+rotation"``, ``"brown-conrady+tilt"``, ``"relay"`` or ``"relay+microscope"``),
    ``spec`` (what ``--model`` takes to fit it again), ``free`` parameters, ``k`` (free count), ``aicc``
    and ``delta_aicc`` over all families, ``mean_error`` (px) of the corrected calibration
    points, ``cv_mean_error`` (px, the K-fold held-out error;
    None when not cross-validated), ``valid`` and ``reason``; for the cross-validated ones
    ``region_sigma`` (px: the RMS over the region to be corrected of the 1-sigma position
    uncertainty propagated from the fit's covariance, :func:`oapcal.uncertainty.position_covariance`)
    and ``predicted_error = sqrt(cv_mean_error^2 + region_sigma^2)`` (px), and ``k_eff`` the
    effective number of parameters of a fit with priors."""

    family: str
    spec: str
    free: tuple[str, ...]
    k: int
    aicc: float
    delta_aicc: float
    mean_error: float
    valid: bool
    reason: str = ""
    cv_mean_error: float | None = None
    cv_failed: int = 0
    region_sigma: float | None = None
    predicted_error: float | None = None
    k_eff: float | None = None

    def to_dict(self) -> dict:
        return {
            "family": self.family, "spec": self.spec, "free": list(self.free), "k": self.k,
            "aicc": finite_or_none(self.aicc), "delta_aicc": finite_or_none(self.delta_aicc),
            "mean_error": finite_or_none(self.mean_error), "valid": self.valid, "reason": self.reason,
            "cv_mean_error": finite_or_none(self.cv_mean_error), "cv_failed": self.cv_failed,
            "region_sigma_px": finite_or_none(self.region_sigma),
            "predicted_error_px": finite_or_none(self.predicted_error), "k_eff": finite_or_none(self.k_eff),
        }  # fmt: skip


@dataclass(frozen=True)
class FamilySelection:
    """Candidates of every family, valid ones by AICc first; ``recommended`` the one with
    the smallest predicted error over the region to be corrected (:func:`select_families`;
    None when none could be cross-validated); ``heldout_best`` the one with the smallest
    cross-validated error alone; ``region`` the region ``(x0, y0, x1, y1)`` px (None: the
    landmarks' hull); ``notes`` what the choice saw (families indistinguishable on the
    landmarks but not beyond them); ``priors`` the relay's priors (a dict) or None."""

    n_points: int
    cv_folds: int
    candidates: tuple[Candidate, ...]
    recommended: Candidate | None
    heldout_best: Candidate | None = None
    region: tuple[float, float, float, float] | None = None
    notes: tuple[str, ...] = ()
    priors: dict | None = None

    def best_of(self, family: str) -> Candidate | None:
        """The best candidate of one family by AICc (``family``: ``"brown-conrady"``,
        ``"brown-conrady+rotation"``, ``"relay"`` or ``"relay+microscope"``)."""
        return next((c for c in self.candidates if c.family == family and c.valid), None)

    def to_dict(self) -> dict:
        return {
            "n_points": self.n_points, "cv_folds": self.cv_folds,
            "recommended": None if self.recommended is None else self.recommended.spec,
            "candidates": [c.to_dict() for c in self.candidates],
            "recommended_by": "predicted error over the region",
            "heldout_best": None if self.heldout_best is None else self.heldout_best.spec,
            "region": None if self.region is None else [float(v) for v in self.region],
            "notes": list(self.notes), "priors": self.priors,
        }  # fmt: skip


def relay_subset_masks(family=RELAY) -> list[tuple[str, np.ndarray]]:
    """``(spec, mask)`` of every relay subset of :data:`RELAY_BLOCKS` (with the pose); of
    ``family`` ``relay+microscope`` (a design with a microscope) with
    :data:`MICROSCOPE_BLOCKS` too."""
    out = []
    table = RELAY_BLOCKS if family is RELAY else {**RELAY_BLOCKS, **MICROSCOPE_BLOCKS}
    blocks = list(table)
    for r in range(len(blocks) + 1):
        for combo in itertools.combinations(blocks, r):
            names = RELAY_POSE_NAMES + tuple(n for b in combo for n in table[b])
            spec = "relay:" + (",".join(combo) if combo else "pose")
            out.append((spec, relay_mask(names, family)))
    return out


def parse_families(text: str) -> tuple[str, ...]:
    """``"bc,relay"`` -> the family keys, checked."""
    keys = tuple(t.strip() for t in str(text).split(",") if t.strip())
    bad = [k for k in keys if k not in FAMILY_NAMES]
    if bad or not keys:
        raise DataError(
            f"unknown model family {bad[0] if bad else text!r}: "
            f"use a comma list of {', '.join(FAMILY_NAMES)}",
            param="families",
        )
    return tuple(dict.fromkeys(keys))


def region_problem(params, xy_u, image_size=None, *, family=None, folds_beyond_bounds=False) -> str:
    """Why the model ``params`` (a :class:`~oapcal.model.Model`, or a vector of
    ``family``) fitted to the reference points ``xy_u`` cannot correct the whole
    ``image_size`` frame (:func:`~oapcal.calibration.check_model_region` over the points'
    bounds and the frame), or ``""`` when it can.  With ``folds_beyond_bounds`` a fold
    beyond the points' bounds is let pass, as ``oapcal fit`` writes such a model (with its
    error model, whose trust region ends before the fold): then ``""`` says fit writes it."""
    xy_u = np.asarray(xy_u, float)
    bounds = (*xy_u.min(axis=0).tolist(), *xy_u.max(axis=0).tolist())
    model = as_model(params, family)
    if not np.isfinite(model.params).all():
        return "the fit gave non-finite parameters"
    try:
        region = ModelRegion(model.params, model.family, bounds=bounds, image_size=image_size)
        check_model_region(region, source="the fitted model", folds_beyond_bounds=folds_beyond_bounds)
    except InputFileError as exc:
        return str(exc).removeprefix("the fitted model: ").split(";")[0]
    return ""


def region_sigma(xy_u, xy_d, mask, p0, region_points, prior=None, family=None,
                 fixed_prior=None) -> tuple[float, float | None]:  # fmt: skip
    """The RMS over ``region_points (M, 2)`` of the 1-sigma position uncertainty (px) of the
    model ``mask`` fitted to all points from ``p0`` (with ``prior``, the posterior one),
    propagated by :func:`oapcal.uncertainty.position_covariance`; inf where the map folds
    everywhere or the fit fails.  ``fixed_prior`` (name -> prior width, deg or mm): the
    values the model leaves at the design although their prior says they are uncertain;
    what of their prior variance the fitted values cannot absorb is propagated too and
    added (:func:`_fixed_variance`), so that a subset does not look surer for fixing what
    is not known.  Returns ``(sigma, k_eff)``."""
    from oapcal.fitting import fit_batch
    from oapcal.uncertainty import position_covariance

    fit = fit_batch(xy_u, xy_d, mask[None], np.asarray(p0)[None], family=family,
                    **({} if prior is None else {"prior": prior})).item(0)  # fmt: skip
    if not fit.converged or not np.isfinite(fit.covariance).all():
        return np.inf, fit.k_eff
    model = as_model(fit, family)
    with np.errstate(all="ignore"):
        cov = position_covariance(region_points, model, fit.covariance)
        var = cov[..., 0, 0] + cov[..., 1, 1]
        fixed = {
            n: w for n, w in (fixed_prior or {}).items() if n not in fit.free and np.isfinite(w) and w > 0
        }
        if fixed:
            var = var + _fixed_variance(xy_u, model, prior, fixed, region_points)
    var = var[np.isfinite(var)]
    return (float(np.sqrt(var.mean())) if var.size else np.inf), fit.k_eff


def _fixed_variance(xy_u, fit: Model, prior, fixed: dict, region_points) -> np.ndarray:
    """The position variance (px^2) at ``region_points`` that values held fixed at the design
    (``fixed``: name -> prior width) leave after the fit: linearized, an error ``dq`` of them
    moves the fitted values by ``dp = -G dq`` with ``G = (J_f^T J_f + W^2)^-1 J_f^T J_q`` at
    the landmarks (``W`` the prior rows' weights), and the corrected position by
    ``-J_u^-1 (J_q - J_f G) dq``.  Propagated by
    :func:`oapcal.uncertainty.position_covariance` with the joint covariance of ``(dp, dq)``,
    ``[[G S G^T, -G S], [-S G^T, S]]``, ``S = diag(width^2)``."""
    from oapcal.uncertainty import position_covariance

    names = fit.family.param_names
    f = [names.index(n) for n in fit.free]
    q = [names.index(n) for n in fixed]
    jac = fit.jacobian_params(xy_u).reshape(-1, len(names))
    jf, jq = jac[:, f], jac[:, q]
    w2 = np.zeros(len(f))
    if prior is not None:
        sigma = np.broadcast_to(prior[1], (1, len(names)))[0][f]
        with np.errstate(divide="ignore"):
            w2 = np.where(np.isfinite(sigma), 1.0 / sigma**2, 0.0)
    g = np.linalg.lstsq(jf.T @ jf + np.diag(w2), jf.T @ jq, rcond=None)[0]
    big_s = np.diag([w**2 for w in fixed.values()])
    joint = np.block([[g @ big_s @ g.T, -g @ big_s], [-big_s @ g.T, big_s]])
    cov = position_covariance(region_points, fit, joint, tuple(fit.free) + tuple(fixed))
    return cov[..., 0, 0] + cov[..., 1, 1]


# 14 parameters: select_families' settings handed on unchanged to each family's scoring
def _score(family: str, xy_u, xy_d, subsets, p0, invalid, cv: int, cv_top: int, seed: int, progress,
           image_size=None, prior=None, region_points=None, fixed_prior=None):  # fmt: skip
    """Score the models ``subsets`` (``[(spec, mask)]``) of one family from the starts ``p0``
    ``(B, P)``; ``invalid`` lists ``(spec, mask, reason)`` ranked last.  The valid ones are
    checked in AICc order over the output region (:func:`region_problem`) until ``cv_top``
    pass, and those are cross-validated.  ``prior``: ``(mean, sigma)`` ``(B, P)`` of the
    subsets' maximum a posteriori fits (relay priors), or None."""
    model_family = family_named(family)
    rows = [(spec, mask, np.nan, np.nan, False, reason) for spec, mask, reason in invalid]
    fitted = {}
    if subsets:
        masks = np.array([m for _, m in subsets])
        scores = score_models(xy_u, xy_d, masks, p0, progress=progress, prior=prior, family=model_family)
        codes, reasons = invalid_reasons(scores, masks.sum(axis=1), len(xy_u))
        for i, (spec, mask) in enumerate(subsets):
            if codes[i]:
                rows.append((spec, mask, np.nan, np.nan, False, reasons[i]))
            else:
                fitted[spec] = Model.from_mask(model_family, scores["params"][i], mask)
                rows.append((spec, mask, float(scores["aicc"][i]), float(scores["mean_error"][i]), True, ""))
    rows.sort(key=lambda r: (not r[4], r[2] if np.isfinite(r[2]) else np.inf))
    top = _admit_top(rows, fitted, xy_u, image_size, cv_top, always_full=prior is not None)
    rows.sort(key=lambda r: (not r[4], r[2] if np.isfinite(r[2]) else np.inf))
    cv_err = {}
    if top and cv:
        index = {spec: i for i, (spec, _) in enumerate(subsets)}
        masks_top = np.array([r[1] for r in top])
        starts = np.array([p0[index[r[0]]] for r in top])
        rows_top = [index[r[0]] for r in top]
        prior_top = None if prior is None else tuple(np.broadcast_to(a, masks.shape)[rows_top] for a in prior)
        errs, failed = cross_validate(
            xy_u, xy_d, masks_top, folds=cv, init=starts, seed=seed, prior=prior_top, family=model_family
        )
        cv_err = {r[0]: (float(e), int(f)) for r, e, f in zip(top, errs, failed)}
    sigma = {}
    if region_points is not None:
        for r in cv_err:
            i = index[r]
            one = None if prior is None else tuple(np.broadcast_to(a, masks.shape)[i : i + 1] for a in prior)
            sigma[r] = region_sigma(xy_u, xy_d, masks[i], p0[i], region_points, one, family=model_family,
                                    fixed_prior=fixed_prior)  # fmt: skip
    out = []
    for spec, mask, aicc, err, valid, reason in rows:
        free = _free_names(model_family, mask)
        e, f = cv_err.get(spec, (None, 0))
        sig, k_eff = sigma.get(spec, (None, None))
        pred = None if sig is None or e is None else float(np.hypot(e, sig))
        out.append(Candidate(family, spec, free, len(free), aicc, np.nan, err, valid, reason, e, f, sig, pred,
                             k_eff))  # fmt: skip
    return out


def _admit_top(rows: list, fitted: dict, xy_u, image_size, cv_top: int, always_full: bool) -> list:
    """The rows to cross-validate: the valid ones in AICc order that ``oapcal fit`` would
    write (:func:`region_problem`) until ``cv_top`` pass, and with ``always_full`` (relay
    priors: every value of the relay is constrained) the full relay model as well (the
    Bayesian model; a subset fixes what the priors say is uncertain).  A row that fails the
    check becomes invalid in ``rows``, with the check's reason."""
    top = []

    def admit(i, row):
        problem = region_problem(fitted[row[0]], xy_u, image_size)
        if problem:
            written = not region_problem(fitted[row[0]], xy_u, image_size, folds_beyond_bounds=True)
            prefix = FOLDS_PREFIX if written else REFUSED_PREFIX
            rows[i] = (row[0], row[1], np.nan, np.nan, False, f"{prefix}: {problem}")
        else:
            top.append(row)

    for i, row in enumerate(rows):
        if len(top) >= max(0, cv_top) or not row[4]:
            break
        admit(i, row)
    for i, row in enumerate(rows):
        if row[0] == FULL_RELAY_SPEC and always_full and row[4] and row not in top:
            admit(i, row)
    return top


# select_families' settings handed on unchanged (as to _score)
def _relay_candidates(xy_u, xy_d, design: RelayDesign, cv, cv_top, seed, progress, image_size=None,
                      priors=None, region_points=None):  # fmt: skip
    """The relay's subsets; with ``priors`` (:class:`~oapcal.optics.relay_model.RelayPriors`)
    each a maximum a posteriori fit, ``relay:all`` (every misalignment value) among them, and
    a value with a prior needs no identifiability from the points."""
    p0 = relay_params(design)
    jac = jacobian_params(xy_u, p0, family=design.family)  # once for the 64 (128) subsets
    subsets = relay_subset_masks(design.family)
    constrained = np.zeros(design.family.n_params, bool)
    if priors is not None:
        subsets.append((FULL_RELAY_SPEC, relay_mask("all", design.family)))
        sig = priors.sigma(design)
        constrained = np.array([np.isfinite(sig.get(n, np.inf)) for n in design.family.param_names])
    ok, invalid = [], []
    for spec, mask in subsets:
        ident = identifiability(xy_u, p0, mask & ~constrained, jac, family=design.family)
        if ident.ok:
            ok.append((spec, mask))
        else:
            groups = "; ".join(" ~ ".join(g) for g in ident.degenerate)
            invalid.append((spec, mask, f"not identifiable: {groups}"))
    starts = np.repeat(p0[None], len(ok), 0)
    prior = None
    if priors is not None and ok:
        # the noise that weighs each subset's priors, from its own all-points MAP fit
        _, noise = map_fit(xy_u, xy_d, design, np.array([m for _, m in ok]), priors, covariance=False)
        mean, unit = priors.arrays(design, 1.0)
        prior = (np.broadcast_to(mean, starts.shape), unit[None] / noise[:, None])
    fixed_prior = None if priors is None else priors.sigma(design)
    return _score(design.family.name, xy_u, xy_d, ok, starts, invalid, cv, cv_top, seed, progress, image_size,
                  prior, region_points, fixed_prior)  # fmt: skip


def _free_names(family, mask) -> tuple[str, ...]:
    return tuple(n for n, m in zip(family.param_names, mask) if m)


# select_families' settings handed on unchanged (as to _score)
def _bc_candidates(xy_u, xy_d, init, cv, cv_top, seed, progress, image_size=None, region_points=None):
    """Every Eq. (1) subset (all 4,096), fitted from ``init`` on the points as given."""
    masks = all_masks()
    p0 = initial_params_many(init, xy_u, xy_d, masks, family=BROWN_CONRADY)
    subsets = [(",".join(_free_names(BROWN_CONRADY, m)), m) for m in masks]
    return _score(BROWN_CONRADY.name, xy_u, xy_d, subsets, p0, [], cv, cv_top, seed, progress, image_size,
                  region_points=region_points)  # fmt: skip


# select_families' settings handed on unchanged (as to _score)
def _variant_candidates(key, xy_u, xy_d, init, cv, cv_top, seed, progress, image_size=None,
                        region_points=None):  # fmt: skip
    """Every Eq. (1) subset with the terms of the variant ``key`` of :data:`EQ1_VARIANTS`
    free as well (the target's rotation, the perspective terms)."""
    family, extra, suffix = EQ1_VARIANTS[key]
    masks = all_masks()
    masks = np.concatenate([masks, np.broadcast_to(np.array(extra), (len(masks), len(extra)))], axis=1)
    p0 = initial_params_many(init, xy_u, xy_d, masks, family=family)
    subsets = [(",".join(_free_names(BROWN_CONRADY, m[:N_PARAMS])) + suffix, m) for m in masks]
    return _score(family.name, xy_u, xy_d, subsets, p0, [], cv, cv_top, seed, progress, image_size,
                  region_points=region_points)  # fmt: skip


#: Points per side of the grid over the region on which the propagated uncertainty is
#: averaged (:func:`region_points`).
REGION_GRID = 21
#: Two families are indistinguishable on the landmarks when their held-out errors differ by
#: at most this fraction of the smaller.
INDISTINGUISHABLE = 0.10
#: ... and differ beyond them when their predicted errors over the region differ by more
#: than this factor.
DIFFER_BEYOND = 1.5
#: The physically constrained families (preferred when the landmarks cannot tell).
PHYSICAL = ("relay", "relay+microscope")


def region_points(xy_u, region=None) -> np.ndarray:
    """Points ``(M, 2)`` over the region to be corrected: a :data:`REGION_GRID` grid over
    the box ``region = (x0, y0, x1, y1)`` (px of the reference points), or over the
    reference points' bounds kept inside their convex hull when ``region`` is None."""
    from oapcal.uncertainty import inside_hull

    xy_u = np.asarray(xy_u, float)
    if region is None:
        lo, hi = xy_u.min(axis=0), xy_u.max(axis=0)
    else:
        x0, y0, x1, y1 = (float(v) for v in region)
        if not (np.isfinite([x0, y0, x1, y1]).all() and x1 > x0 and y1 > y0):
            raise DataError(f"region must be x0, y0, x1, y1 with x1 > x0 and y1 > y0, got {region}",
                            param="region")  # fmt: skip
        lo, hi = np.array([x0, y0]), np.array([x1, y1])
    g = [np.linspace(lo[j], hi[j], REGION_GRID) for j in (0, 1)]
    pts = np.stack(np.meshgrid(*g), -1).reshape(-1, 2)
    if region is None:
        from scipy.spatial import ConvexHull, QhullError

        try:
            hull = xy_u[ConvexHull(xy_u).vertices]
            inside = inside_hull(pts, hull)
            pts = pts[inside] if inside.any() else pts
        except QhullError:
            pass
    return pts


def _disagreement(a: Candidate, b: Candidate, params: dict, points) -> float:
    """The largest distance (px) between the distorted positions two fitted models give the
    region's points."""
    with np.errstate(all="ignore"):
        d = np.hypot(*(params[a.spec](points) - params[b.spec](points)).T)
    return float(np.nanmax(d)) if np.isfinite(d).any() else np.inf


def _recommend(candidates, params, points, region_words):
    """The recommendation (smallest predicted error; among the families indistinguishable
    from it on the landmarks a physically constrained one is preferred when its predicted
    error is at most :data:`DIFFER_BEYOND` x larger), and the notes."""
    scored = [c for c in candidates if c.predicted_error is not None and np.isfinite(c.predicted_error)]
    if not scored:
        return None, ()
    best = min(scored, key=lambda c: c.predicted_error)
    per_family = {}
    for c in sorted(scored, key=lambda c: c.predicted_error):
        per_family.setdefault(c.family, c)
    notes = []
    same = [
        c for c in per_family.values()
        if c is not best and abs(c.cv_mean_error - best.cv_mean_error)
        <= INDISTINGUISHABLE * min(c.cv_mean_error, best.cv_mean_error)
    ]  # fmt: skip
    for c in same:
        lo, hi = sorted((c.predicted_error, best.predicted_error))
        ratio = hi / max(lo, 1e-300)
        gap = _disagreement(best, c, params, points) if c.spec in params and best.spec in params else np.nan
        if ratio > DIFFER_BEYOND:
            notes.append(
                f"{best.family} ({best.spec}) and {c.family} ({c.spec}) are indistinguishable on the "
                f"landmarks (held-out {best.cv_mean_error:.3g} and {c.cv_mean_error:.3g} px) but differ "
                f"over {region_words}: predicted {best.predicted_error:.3g} and {c.predicted_error:.3g} px, "
                f"the two models {gap:.3g} px apart at most"
            )
    if best.family not in PHYSICAL:
        physical = [
            c
            for c in same
            if c.family in PHYSICAL and c.predicted_error <= DIFFER_BEYOND * best.predicted_error
        ]
        if physical:
            pick = physical[0]
            notes.append(
                f"preferred the physically constrained {pick.family} ({pick.spec}, predicted "
                f"{pick.predicted_error:.3g} px) to {best.family} ({best.predicted_error:.3g} px): the "
                "landmarks cannot tell them apart and the physics constrains it beyond them"
            )
            best = pick
    return best, tuple(notes)


# keyword options of the public choice across families (each an `oapcal select` option)
def select_families(
    xy_u,
    xy_d,
    design: RelayDesign,
    families=("bc", "relay"),
    *,
    cv: int = 5,
    cv_top: int = 5,
    init=DEFAULT_INIT,
    seed: int = 0,
    progress: Progress | None = None,
    image_size: tuple[int, int] | None = None,
    priors=None,
    region: tuple[float, float, float, float] | str | None = "auto",
) -> FamilySelection:
    """Rank Brown-Conrady subsets (all 4,096, fitted from ``init``) and relay subsets (from
    ``design``) together (module docstring).  ``cv`` folds for the ``cv_top`` best of each
    family by AICc that ``oapcal fit`` would write (finite and not folding over on the
    points' bounds and the ``image_size`` frame); ``progress(done, total)`` over the fits.

    The recommendation is by the **predicted error over the region to be corrected**:
    ``sqrt(cv^2 + sigma^2)`` with ``cv`` the held-out error and ``sigma`` the RMS over the
    region of the position uncertainty propagated from each model's covariance
    (:func:`region_sigma`).  ``region``: ``"auto"`` (default) the image frame
    ``(0, 0, w - 1, h - 1)`` with ``image_size``, else the landmarks' hull; ``"hull"``; or a
    box ``(x0, y0, x1, y1)`` px.  When families are indistinguishable on the landmarks
    (held-out errors within :data:`INDISTINGUISHABLE`) but not over the region, the notes say
    so, and a physically constrained family (the relay) is preferred among them unless its
    predicted error is over :data:`DIFFER_BEYOND` x the best.  ``priors`` (relay priors, as
    :func:`oapcal.optics.relay_model.parse_priors`) makes the relay's fits maximum a
    posteriori ones (``relay:all`` among them)."""
    families = parse_families(",".join(families) if not isinstance(families, str) else families)
    xy_u = np.asarray(xy_u, float)
    xy_d = np.asarray(xy_d, float)
    if int(cv) < 2:
        raise DataError(f"choosing across families needs cross-validation with 2 or more folds, got {cv}",
                        param="cv")  # fmt: skip
    priors = parse_priors(priors)
    region = _region_box(region, image_size)
    points = region_points(xy_u, region)
    candidates: list[Candidate] = []
    if "bc" in families:
        candidates.extend(_bc_candidates(xy_u, xy_d, init, cv, cv_top, seed, progress, image_size, points))
    if "relay" in families:
        design = default_centre(design, xy_u, image_size)
        candidates.extend(_relay_candidates(xy_u, xy_d, design, cv, cv_top, seed, progress, image_size,
                                            priors,
                                            points))  # fmt: skip
    for key in (k for k in EQ1_VARIANTS if k in families):
        candidates.extend(
            _variant_candidates(key, xy_u, xy_d, init, cv, cv_top, seed, progress, image_size, points)
        )
    valid_aicc = [c.aicc for c in candidates if c.valid and np.isfinite(c.aicc)]
    best = min(valid_aicc) if valid_aicc else np.nan
    candidates = [
        Candidate(**{**c.__dict__, "delta_aicc": c.aicc - best if c.valid else np.nan}) for c in candidates
    ]
    candidates.sort(key=lambda c: (not c.valid, c.aicc if np.isfinite(c.aicc) else np.inf))
    scored = [c for c in candidates if c.cv_mean_error is not None and np.isfinite(c.cv_mean_error)]
    heldout = min(scored, key=lambda c: c.cv_mean_error) if scored else None
    params = _fitted_params(xy_u, xy_d, scored, design, init, priors)
    words = "the landmarks' hull" if region is None else f"the region {tuple(round(v, 1) for v in region)}"
    recommended, notes = _recommend(candidates, params, points, words)
    if recommended is None:
        recommended = heldout
    record = None
    if priors is not None and "relay" in families:
        record = priors.to_dict(design)
    return FamilySelection(len(xy_u), int(cv), tuple(candidates), recommended, heldout, region, notes, record)


def _region_box(region, image_size):
    """``select_families``'s ``region`` as a box ``(x0, y0, x1, y1)``, or None for the hull."""
    if isinstance(region, str) and region == "auto":
        return None if image_size is None else (0.0, 0.0, float(image_size[0]) - 1, float(image_size[1]) - 1)
    if isinstance(region, str) and region == "hull":
        return None
    if isinstance(region, str):
        raise DataError(f"region must be 'auto', 'hull' or a box x0,y0,x1,y1, got {region!r}", param="region")
    return region


def _fitted_params(xy_u, xy_d, scored, design, init, priors) -> dict:
    """The models of the cross-validated candidates fitted to all points (for comparing
    two models' maps), by spec."""
    from oapcal.fitting import fit_batch, initial_params
    from oapcal.model import parse_any_model

    out = {}
    for c in scored:
        try:
            if c.family in PHYSICAL:
                mask = relay_mask(c.spec, design.family)
                if priors is not None:
                    fits, _ = map_fit(xy_u, xy_d, design, mask[None], priors, covariance=False, max_iter=200)
                else:
                    fits = fit_batch(xy_u, xy_d, mask[None], relay_params(design)[None], covariance=False,
                                     family=family_named(c.family))  # fmt: skip
            else:
                mask = parse_any_model(c.spec)
                fam = family_named(c.family)
                start = initial_params(init, xy_u, xy_d, mask, family=fam)
                fits = fit_batch(xy_u, xy_d, mask[None], start[None], covariance=False, family=fam)
            out[c.spec] = Model.from_mask(c.family, fits.params[0], mask)
        except Exception:  # noqa: BLE001 -- a model that cannot be refitted is not compared
            continue
    return out
