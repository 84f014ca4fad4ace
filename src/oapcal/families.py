"""Choosing across model families: Brown-Conrady subsets (Eq. 1), the same with the
target's rotation (``bc+rotation``) and physical-relay subsets ranked together, by AICc
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

from oapcal.calibration import check_model_region
from oapcal.errors import DataError, InputFileError
from oapcal.fitting import DEFAULT_INIT, initial_params_many
from oapcal.model import (
    BROWN_CONRADY,
    BROWN_CONRADY_POSE,
    RELAY,
    RELAY_POSE_NAMES,
    ROTATION_SUFFIX,
    all_masks,
    jacobian_params,
    names_from_mask,
)
from oapcal.optics.relay_model import RelayDesign, default_centre, identifiability, relay_mask, relay_params
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
FAMILY_NAMES = {"bc": "brown-conrady", "bc+rotation": "brown-conrady+rotation", "relay": "relay"}
Progress = Callable[[int, int], None]
#: The start of the reason of a model that ``oapcal fit`` would refuse to write.
REFUSED_PREFIX = "fit would refuse it"


@dataclass(frozen=True)
class Candidate:
    """One model of a cross-family selection: its ``family`` (``"brown-conrady"``,
    ``"brown-conrady+rotation"``, ``"relay"`` or ``"relay+microscope"``), ``spec`` (what
    ``--model`` takes to fit it again), ``free`` parameters, ``k`` (free count), ``aicc``
    and ``delta_aicc`` over all families, ``mean_error`` (px) of the corrected calibration
    points, ``cv_mean_error`` (px, the K-fold held-out error;
    None when not cross-validated), ``valid`` and ``reason``."""

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

    def to_dict(self) -> dict:
        return {
            "family": self.family, "spec": self.spec, "free": list(self.free), "k": self.k,
            "aicc": finite_or_none(self.aicc), "delta_aicc": finite_or_none(self.delta_aicc),
            "mean_error": finite_or_none(self.mean_error), "valid": self.valid, "reason": self.reason,
            "cv_mean_error": finite_or_none(self.cv_mean_error), "cv_failed": self.cv_failed,
        }  # fmt: skip


@dataclass(frozen=True)
class FamilySelection:
    """Candidates of every family, valid ones by AICc first; ``recommended`` the one with
    the smallest cross-validated error (None when none could be cross-validated)."""

    n_points: int
    cv_folds: int
    candidates: tuple[Candidate, ...]
    recommended: Candidate | None

    def best_of(self, family: str) -> Candidate | None:
        """The best candidate of one family by AICc (``family``: ``"brown-conrady"``,
        ``"brown-conrady+rotation"``, ``"relay"`` or ``"relay+microscope"``)."""
        return next((c for c in self.candidates if c.family == family and c.valid), None)

    def to_dict(self) -> dict:
        return {
            "n_points": self.n_points, "cv_folds": self.cv_folds,
            "recommended": None if self.recommended is None else self.recommended.spec,
            "candidates": [c.to_dict() for c in self.candidates],
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


class _Region:
    """What :func:`~oapcal.calibration.check_model_region` reads of a calibration: the
    model, the reference points' bounds and the image frame."""

    def __init__(self, params, bounds, image_size):
        self.params = params
        self.bounds = bounds
        self.image_size = image_size


def region_problem(params, xy_u, image_size=None) -> str:
    """Why ``oapcal fit`` would refuse to write the model ``params`` fitted to the reference
    points ``xy_u`` (its check :func:`~oapcal.calibration.check_model_region` over the
    points' bounds and the ``image_size`` frame), or ``""`` when it would write it."""
    xy_u = np.asarray(xy_u, float)
    bounds = (*xy_u.min(axis=0).tolist(), *xy_u.max(axis=0).tolist())
    if not np.isfinite(params).all():
        return "the fit gave non-finite parameters"
    try:
        check_model_region(_Region(np.asarray(params, float), bounds, image_size), source="the fitted model")
    except InputFileError as exc:
        return str(exc).removeprefix("the fitted model: ").split(";")[0]
    return ""


def _score(family: str, xy_u, xy_d, subsets, p0, invalid, cv: int, cv_top: int, seed: int, progress,
           image_size=None):  # fmt: skip
    """Score the models ``subsets`` (``[(spec, mask)]``) of one family from the starts ``p0``
    ``(B, P)``; ``invalid`` lists ``(spec, mask, reason)`` ranked last.  The valid ones are
    checked in AICc order over the output region (:func:`region_problem`) until ``cv_top``
    pass, and those are cross-validated."""
    rows = [(spec, mask, np.nan, np.nan, False, reason) for spec, mask, reason in invalid]
    fitted = {}
    if subsets:
        masks = np.array([m for _, m in subsets])
        scores = score_models(xy_u, xy_d, masks, p0, progress=progress)
        codes, reasons = invalid_reasons(scores, masks.sum(axis=1), len(xy_u))
        for i, (spec, mask) in enumerate(subsets):
            if codes[i]:
                rows.append((spec, mask, np.nan, np.nan, False, reasons[i]))
            else:
                fitted[spec] = scores["params"][i]
                rows.append((spec, mask, float(scores["aicc"][i]), float(scores["mean_error"][i]), True, ""))
    rows.sort(key=lambda r: (not r[4], r[2] if np.isfinite(r[2]) else np.inf))
    top = []
    for i, row in enumerate(rows):
        if len(top) >= max(0, cv_top) or not row[4]:
            break
        problem = region_problem(fitted[row[0]], xy_u, image_size)
        if problem:
            rows[i] = (row[0], row[1], np.nan, np.nan, False, f"{REFUSED_PREFIX}: {problem}")
        else:
            top.append(row)
    rows.sort(key=lambda r: (not r[4], r[2] if np.isfinite(r[2]) else np.inf))
    cv_err = {}
    if top and cv:
        index = {spec: i for i, (spec, _) in enumerate(subsets)}
        masks_top = np.array([r[1] for r in top])
        starts = np.array([p0[index[r[0]]] for r in top])
        errs, failed = cross_validate(xy_u, xy_d, masks_top, folds=cv, init=starts, seed=seed)
        cv_err = {r[0]: (float(e), int(f)) for r, e, f in zip(top, errs, failed)}
    out = []
    for spec, mask, aicc, err, valid, reason in rows:
        free = names_from_mask(mask)
        e, f = cv_err.get(spec, (None, 0))
        out.append(Candidate(family, spec, free, len(free), aicc, np.nan, err, valid, reason, e, f))
    return out


def _relay_candidates(xy_u, xy_d, design: RelayDesign, cv, cv_top, seed, progress, image_size=None):
    p0 = relay_params(design)
    jac = jacobian_params(xy_u, p0)  # once for the 64 (128) subsets
    ok, invalid = [], []
    for spec, mask in relay_subset_masks(design.family):
        ident = identifiability(xy_u, p0, mask, jac)
        if ident.ok:
            ok.append((spec, mask))
        else:
            groups = "; ".join(" ~ ".join(g) for g in ident.degenerate)
            invalid.append((spec, mask, f"not identifiable: {groups}"))
    starts = np.repeat(p0[None], len(ok), 0)
    return _score(design.family.name, xy_u, xy_d, ok, starts, invalid, cv, cv_top, seed, progress, image_size)


def _bc_candidates(xy_u, xy_d, init, cv, cv_top, seed, progress, image_size=None):
    """Every Eq. (1) subset (all 4,096), fitted from ``init`` on the points as given."""
    masks = all_masks()
    p0 = initial_params_many(init, xy_u, xy_d, masks)
    subsets = [(",".join(names_from_mask(m)), m) for m in masks]
    return _score(BROWN_CONRADY.name, xy_u, xy_d, subsets, p0, [], cv, cv_top, seed, progress, image_size)


def _rotation_candidates(xy_u, xy_d, init, cv, cv_top, seed, progress, image_size=None):
    """Every Eq. (1) subset with the target's rotation free as well."""
    masks = all_masks()
    masks = np.pad(masks, ((0, 0), (0, 1)), constant_values=True)
    p0 = initial_params_many(init, xy_u, xy_d, masks)
    subsets = [(",".join(names_from_mask(m)[:-1]) + ROTATION_SUFFIX, m) for m in masks]
    return _score(BROWN_CONRADY_POSE.name, xy_u, xy_d, subsets, p0, [], cv, cv_top, seed, progress,
                  image_size)  # fmt: skip


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
) -> FamilySelection:
    """Rank Brown-Conrady subsets (all 4,096, fitted from ``init``) and relay subsets (from
    ``design``) together (module docstring).  ``cv`` folds for the ``cv_top`` best of each
    family by AICc that ``oapcal fit`` would write (finite and not folding over on the
    points' bounds and the ``image_size`` frame); ``progress(done, total)`` over the fits."""
    families = parse_families(",".join(families) if not isinstance(families, str) else families)
    xy_u = np.asarray(xy_u, float)
    xy_d = np.asarray(xy_d, float)
    if int(cv) < 2:
        raise DataError(f"choosing across families needs cross-validation with 2 or more folds, got {cv}",
                        param="cv")  # fmt: skip
    candidates: list[Candidate] = []
    if "bc" in families:
        candidates.extend(_bc_candidates(xy_u, xy_d, init, cv, cv_top, seed, progress, image_size))
    if "relay" in families:
        design = default_centre(design, xy_u, image_size)
        candidates.extend(_relay_candidates(xy_u, xy_d, design, cv, cv_top, seed, progress, image_size))
    if "bc+rotation" in families:
        candidates.extend(_rotation_candidates(xy_u, xy_d, init, cv, cv_top, seed, progress, image_size))
    valid_aicc = [c.aicc for c in candidates if c.valid and np.isfinite(c.aicc)]
    best = min(valid_aicc) if valid_aicc else np.nan
    candidates = [
        Candidate(**{**c.__dict__, "delta_aicc": c.aicc - best if c.valid else np.nan}) for c in candidates
    ]
    candidates.sort(key=lambda c: (not c.valid, c.aicc if np.isfinite(c.aicc) else np.inf))
    scored = [c for c in candidates if c.cv_mean_error is not None and np.isfinite(c.cv_mean_error)]
    recommended = min(scored, key=lambda c: c.cv_mean_error) if scored else None
    return FamilySelection(len(xy_u), int(cv), tuple(candidates), recommended)
