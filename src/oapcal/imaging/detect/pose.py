"""Pose search: which triplet of the target is which triplet of the image.

A pose is a similarity with an optional mirror, ``camera = s L um + t`` (``L`` a rotation,
times ``diag(1, -1)`` when mirrored; ``s`` px per um), from object um to camera px.  Every
pair (image triplet, reference triplet) and each of the 4 ways to lay one onto the other
(two directions along the bars, with and without a mirror) gives a hypothesis: the scale
from the bar widths, the rotation from the bars' direction, the shift from the centres.
Each hypothesis predicts where every triplet of the whole target is and how wide its bars
are; it scores the number of image triplets found there (same width, same direction), less
a penalty for resolvable triplets it predicts inside the image that are not there.  The
best hypotheses are refined (similarity refitted to their matches, matched again).

The answer is only accepted when it is clearly better than every *different* pose, in
particular the ones this target is prone to (``docs/detection.md``): the one-element slip
(scale ``2 ** (1 / 6)`` and one element along the column) and the two-group slip (scale 4,
the nested layer).  Otherwise the search refuses with the scores of both.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

import numpy as np

from oapcal.imaging.detect.bars import Triplets
from oapcal.imaging.detect.warp import PolyWarp, normalisation, poly_exponents

#: Penalty per resolvable reference triplet predicted inside the image but not found.
MISSING_PENALTY = 0.3
#: Predicted triplets with bars narrower than this (px) are neither expected nor penalised.
MIN_EXPECTED_BAR_PX = 2.2
#: The image resolves no triplet much finer than its finest one found: a pose expects only
#: triplets predicted at least this fraction of that width (one and a half element steps,
#: ``2 ** (-1.5/6)``: the next finer element is still expected, the one after it not).
#: Why: a strongly blurred image (the LAB-UMK micrograph rendered through the relay: group 5's
#: bars modulated by about 20 % between bar and gap, which no local threshold separates)
#: shows group 4 alone, and counting group 5 as expected refused every pose, even a named one,
#: as "finds only 4 of the 20 triplets it expects".
RESOLVED_FRACTION = 2.0 ** (-1.5 / 6.0)
#: Missing triplets are penalised only from this predicted bar width (px).
MIN_PENALISED_BAR_PX = 4.0
#: Bar widths found / predicted within this factor match (local scale changes of a
#: strongly distorted image reach 20-30 %).
WIDTH_TOL = 1.4
#: Bar directions found / predicted within this angle (deg) match.  Why 14, not 12: through
#: the aligned relay with the target turned by 285 degrees and mirrored, the relay's image
#: is anamorphic (local scales 1.3 apart) and turns by -67 to -82 degrees over groups 4-5,
#: so the right pose's V triplets lay 12-13.5 degrees off its H triplets' direction and the
#: pose stalled at 7 of 20 (refused, where the default layout with 14 degrees and the local
#: directions of :func:`_smooth_prediction` matches 15 of 18).
ANGLE_TOL_DEG = 14.0
#: The best pose must find at least this fraction of the named groups' triplets that it
#: expects in the image (resolvable, inside); below, its evidence is too thin to trust.
MIN_FOUND_FRACTION = 0.5
#: ... with anchors (the identity named by the user, and checked against the bars), this
#: fraction: the evidence then only has to place the target, not to name it.
MIN_FOUND_FRACTION_ANCHORED = 0.25
#: The best pose is refused when more image triplets than it matched are wider than its
#: widest match by more than :data:`WIDTH_TOL` and matched by nothing
#: (:func:`unexplained_wider`): the widest bars in view are the surest, and a pose that
#: leaves them unexplained has taken a finer part of the target for a coarser one.  Measured:
#: right poses leave 0-0.5 as many (LAB-UMK mirrored and turned: 5 for 11 matched, binned 4
#: for 8; the FPM frame 2-4 for 42-43, group 3 cut by the image's edge); a wrong pose through
#: a 143 px field (group 5's column taken for group 4's at 8.7 um/px instead of 4.8) 9 for 6,
#: and it was kept with 36 wrong ids.
MAX_UNEXPLAINED_WIDER = 1.0
#: Matched triplets from which the pose's correction is quadratic (else affine).  Why 8,
#: not 12: under a setup-1-like field (~40 px) the rows of triplets bend by 5-10 px between
#: neighbours, which an affine correction leaves, so the pose stalled at 8 of 20 triplets
#: and was refused without a given scale; 8 matches are 16 equations for the 12
#: coefficients, and the correction is trusted only near the matches.
QUADRATIC_MATCHES = 5
#: Matched triplets from which the pose's prediction follows a smooth correction (affine).
MIN_SMOOTH_MATCHES = 3
#: The largest local stretch (either way) the smooth correction may add to the pose at a
#: matched triplet (:func:`_plausible_stretch`).  Through the relay the local scales against
#: the best similarity span 0.7-1.26 (the LAB-UMK render, group 4); against the refitted
#: affine pose less; a stretch of 2 is beyond any of the renders.
CORRECTION_STRETCH = 2.0
#: ... and the largest local turn (deg): twice the bars' direction tolerance (ANGLE_TOL_DEG).
CORRECTION_TURN_DEG = 28.0
#: Turns (deg) added to every seed when the seeds' own angles find no pose in any layout
#: (``search_pose(turned_seeds=True)``, :func:`_turned_seeds`): under a strongly distorted
#: field a triplet's bars are turned against the whole target's pose by up to 8-12 degrees
#: (measured through the aligned relay with the target turned 45 degrees: every seed 7-11
#: degrees off, so no seed's prediction reached the other triplets and the pose was refused).
SEED_TURNS_DEG = (-7.0, 7.0)
#: A different pose scoring more than this fraction of the best makes the answer ambiguous.
AMBIGUITY_RATIO = 0.9
#: ... or within this many triplets of it.
AMBIGUITY_MARGIN = 2.0
#: With ``um_per_px`` given, hypotheses within this factor of its scale are searched.
SCALE_PRIOR_RANGE = 1.3
#: Half of one element step of the target, ``2 ** (1 / 12)`` (6 %): ``um_per_px`` nearer
#: than this to one hypothesis' scale than to any other identifies the element when the
#: view alone cannot (and detection refuses a registration whose scale is farther off).
HALF_ELEMENT = 2.0 ** (1.0 / 12.0)


@dataclass(frozen=True)
class RefTriplets:
    """The target's triplets: centre (um), bar width (um), long-axis direction (0 for H
    bars along x, pi/2 for V), group, element, orientation letter and the bar indices."""

    centre: np.ndarray
    width: np.ndarray
    angle: np.ndarray
    group: np.ndarray
    element: np.ndarray
    orient: np.ndarray
    bars: list

    @classmethod
    def from_target(cls, target) -> RefTriplets:
        trip = target.triplets()
        rect = target.bars
        centre = np.array(
            [[(rect[b, 0] + rect[b, 2]).mean() / 2, (rect[b, 1] + rect[b, 3]).mean() / 2] for b in trip]
        )
        return cls(
            centre=centre.reshape(-1, 2),
            width=np.array([target.bar_width[b[0]] for b in trip], float),
            angle=np.array([0.0 if target.bar_orientation[b[0]] == "H" else np.pi / 2 for b in trip]),
            group=np.array([target.bar_group[b[0]] for b in trip], int),
            element=np.array([target.bar_element[b[0]] for b in trip], int),
            orient=np.array([target.bar_orientation[b[0]] for b in trip]),
            bars=list(trip),
        )

    def key(self, j: int) -> str:
        return f"G{self.group[j]}E{self.element[j]}{self.orient[j]}"


@dataclass
class Pose:
    """``camera = s * L @ um + t``; ``matches`` (image triplet, reference triplet) pairs."""

    s: float
    lin: np.ndarray  # L (2, 2), orthogonal
    t: np.ndarray
    score: float = 0.0
    matches: list = field(default_factory=list)
    n_missing: int = 0
    n_expected: int = 0  # triplets of the named groups it expects resolvable in the image

    @property
    def mirrored(self) -> bool:
        return bool(np.linalg.det(self.lin) < 0)

    @property
    def angle_deg(self) -> float:
        return float(np.degrees(np.arctan2(self.lin[1, 0], self.lin[0, 0])))

    def apply(self, um: np.ndarray) -> np.ndarray:
        return self.s * np.asarray(um, float) @ self.lin.T + self.t

    def matrix(self) -> np.ndarray:
        """The 2x2 linear part ``s L`` (px per um)."""
        return self.s * self.lin

    def summary(self, um_per_px_given: float | None = None) -> dict:
        return {
            "um_per_px": 1.0 / self.s,
            "rotation_deg": self.angle_deg,
            "mirrored": self.mirrored,
            "shift_px": [float(v) for v in self.t],
            "score": float(self.score),
            "matched_triplets": len(self.matches),
            "missing_triplets": int(self.n_missing),
        }


def _rot(phi: np.ndarray) -> np.ndarray:
    c, s = np.cos(phi), np.sin(phi)
    return np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)


def _angle_diff(a, b):
    """Difference of two undirected angles (mod pi), in [0, pi/2]."""
    return np.abs((np.asarray(a) - np.asarray(b) + np.pi / 2) % np.pi - np.pi / 2)


@dataclass(frozen=True)
class _Scene:
    """What every pose of one search is scored against: the reference triplets, the image's
    triplets with their k-d tree of centres, the image shape (rows, cols) and the
    reference triplets of the named groups (``listed``, None: all)."""

    ref: RefTriplets
    img: Triplets
    tree: object
    shape: tuple[int, int]
    listed: np.ndarray | None = None

    @functools.cached_property  # once per search: every scoring of a chunk of hypotheses reads it
    def finest_expected_px(self) -> float:
        """The narrowest predicted bar width (px) a pose expects to find: the fixed floor
        (:data:`MIN_EXPECTED_BAR_PX`) or, when the image's finest triplet found is coarser,
        a little more than one element step below it (:data:`RESOLVED_FRACTION`)."""
        finest = float(np.min(self.img.width)) if len(self.img) else 0.0
        return max(MIN_EXPECTED_BAR_PX, RESOLVED_FRACTION * finest)


def _score(
    pose_s, pose_lin, pose_t, scene: _Scene, *, anchor=None, loose=1.0, pred=None, width_tol=1.25, local=None
):
    """Score hypotheses given as arrays ``s`` (H,), ``lin`` (H, 2, 2), ``t`` (H, 2).

    ``pred`` (H, n, 2) replaces the similarity's predicted centres (a smoother map fitted
    to the matches) and ``local`` (H, n, 2, 2) its linear part at each reference triplet
    (that map's derivative: the bars' predicted direction and width); ``anchor`` (H, 2)
    widens the position tolerance with the distance from it (a single triplet predicts its
    neighbours better than far triplets).
    Returns ``score`` (H,), ``n_missing`` (H,), the matched image index per
    (hypothesis, reference triplet) (-1: none) and the mask of the named groups' triplets
    it expects to find (H, n: resolvable, inside)."""
    ref, listed = scene.ref, scene.listed
    h, w = scene.shape
    amat = pose_lin * pose_s[:, None, None]  # px per um, (H, 2, 2); may be non-orthogonal
    pred, wpred, apred = _predicted(amat, pose_t, ref, pred, local)
    half = 3.6 * wpred  # half the diagonal of a 5w x 5w triplet, and a little
    inside = (pred[..., 0] > half) & (pred[..., 0] < w - 1 - half)
    inside &= (pred[..., 1] > half) & (pred[..., 1] < h - 1 - half)
    expected = inside & (wpred >= scene.finest_expected_px)
    ok, match = _matched(pred, wpred, apred, scene, anchor, loose, width_tol)
    weight = np.ones(len(ref.width)) if listed is None else np.where(listed, 1.0, 0.25)
    missing = _missing(ok, inside, expected, wpred, ref, listed)
    score = _match_score(match, weight)
    score -= MISSING_PENALTY * missing
    expected_named = expected if listed is None else expected & listed[None, :]
    return score, missing, match, expected_named


def _n_expected(expected: np.ndarray, match: np.ndarray, ref: RefTriplets) -> int:
    """The number of triplets one pose expects (``expected`` (n,) from :func:`_score`) that
    its evidence is judged against: without a group none of whose triplets it matched when
    that group is wholly finer than every triplet it matched.  Why: a blurred image loses
    its finest group first; through the relay the LAB-UMK micrograph shows group 4's bars
    and group 5's only at about 20 % modulation (no triplet), so the right pose, matching
    7 of group 4's 12, counted 6 of group 5 as expected and was refused at 7 of 18.  A
    coarser group missing is not excused (the pose two groups off would be)."""
    matched = match >= 0
    keep = expected.copy()
    if matched.any():
        finest = float(ref.width[matched].min())
        for g in np.unique(ref.group[expected]):
            in_g = ref.group == g
            if not (matched & in_g).any() and float(ref.width[in_g].max()) < finest:
                keep &= ~in_g
    return int(keep.sum())


def apply_maps(amat: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Every 2 x 2 map of ``amat`` (H, 2, 2) applied to every point of ``xy`` (n, 2): (H, n, 2),
    ``np.einsum("hij,nj->hni", amat, xy)`` bit for bit (the same two products and one sum
    per entry) at a fifth of its time: the pose search applies thousands of hypotheses to
    the reference triplets (tests/imaging/test_detect_pose.py compares the two)."""
    x = amat[:, None, 0, 0] * xy[None, :, 0] + amat[:, None, 0, 1] * xy[None, :, 1]
    y = amat[:, None, 1, 0] * xy[None, :, 0] + amat[:, None, 1, 1] * xy[None, :, 1]
    return np.stack([x, y], -1)


def _predicted(amat, pose_t, ref: RefTriplets, pred, local=None):
    """Where each hypothesis (linear part ``amat`` (H, 2, 2), shift ``pose_t``) puts every
    reference triplet: centres (H, n, 2) (``pred`` when given), bar widths (H, n) and
    bar directions mod pi (H, n), in px (through each triplet's own linear map ``local``
    (H, n, 2, 2) when given)."""
    if pred is None:
        pred = apply_maps(amat, ref.centre) + pose_t[:, None, :]
    along = np.stack([np.cos(ref.angle), np.sin(ref.angle)], -1)
    normal = np.stack([-np.sin(ref.angle), np.cos(ref.angle)], -1)
    if local is None:
        dirs = apply_maps(amat, along)
        # bar width in px: the period across the bars, i.e. the map's scale along the normal
        # (an anisotropic image has other widths for H and V triplets)
        nrm = apply_maps(amat, normal)
    else:
        # each triplet's own linear map (H, n, 2, 2): the smooth correction's local turn and
        # stretch
        dirs = np.einsum("hnij,nj->hni", local, along)
        nrm = np.einsum("hnij,nj->hni", local, normal)
    cross = np.abs(dirs[..., 0] * nrm[..., 1] - dirs[..., 1] * nrm[..., 0])
    wpred = ref.width[None, :] * cross / np.maximum(np.hypot(dirs[..., 0], dirs[..., 1]), 1e-12)
    apred = np.arctan2(dirs[..., 1], dirs[..., 0]) % np.pi
    return pred, wpred, apred


def _matched(pred, wpred, apred, scene: _Scene, anchor, loose, width_tol):
    """The nearest image triplet to every predicted one, kept when near enough (the
    tolerance widened away from ``anchor``), as wide and as turned as predicted: the mask
    (H, n) and the matched image index (-1: none)."""
    img = scene.img
    h, w = scene.shape
    tol = 0.6 * wpred
    if anchor is not None:
        tol = tol + loose * 0.05 * np.hypot(*(pred - anchor[:, None, :]).transpose(2, 0, 1))
    # Only predictions that can match are looked up: wide enough, and within the largest
    # tolerance of the image (where every image triplet lies); the tree then stops its
    # search at that tolerance.  The same matches as looking every one up: a large image's
    # hypotheses put most of a whole target's triplets outside it or below the bar limit, and
    # looking them up took most of its pose search (62 M look-ups, 10 of 26 s).
    bound = min(float(np.nanmax(tol, initial=0.0)), float(max(h, w)))
    cand = wpred >= 0.7 * MIN_EXPECTED_BAR_PX
    cand &= (pred[..., 0] > -bound) & (pred[..., 0] < w - 1 + bound)
    cand &= (pred[..., 1] > -bound) & (pred[..., 1] < h - 1 + bound)
    hh, jj = np.nonzero(cand)
    ok = np.zeros(wpred.shape, bool)
    match = np.full(wpred.shape, -1, dtype=np.intp)
    if len(hh) == 0:
        return ok, match
    dist, k = scene.tree.query(pred[hh, jj], k=1, distance_upper_bound=bound)
    near = (k < len(img)) & (dist < tol[hh, jj])
    hh, jj, kk = hh[near], jj[near], k[near]
    good = (np.abs(np.log(img.width[kk] / wpred[hh, jj])) < np.log(width_tol)) & (
        _angle_diff(img.angle[kk], apred[hh, jj]) < np.deg2rad(ANGLE_TOL_DEG)
    )
    ok[hh[good], jj[good]] = True
    match[hh[good], jj[good]] = kk[good]
    return ok, match


def _missing(ok, inside, expected, wpred, ref: RefTriplets, listed) -> np.ndarray:
    """The number of resolvable triplets each hypothesis expects but does not find (H,)."""
    # only the named groups are penalised when missing: an image (or a simulation) may show
    # those alone
    pen = (expected & ~ok) & (wpred >= MIN_PENALISED_BAR_PX)
    if listed is not None:
        pen &= listed[None, :]
    missing = pen.sum(axis=1)
    if listed is not None:
        # a named group is in view: when none of its triplets is matched, its resolvable
        # triplets predicted outside the image count as missing too (this rules out the
        # pose two groups off, whose named groups would lie outside the image)
        out = ~inside & (wpred >= MIN_PENALISED_BAR_PX)
        for g in np.unique(ref.group[listed]):
            in_g = (ref.group == g)[None, :]
            none_matched = ~(ok & in_g).any(axis=1)
            missing = missing + none_matched * (out & in_g).sum(axis=1)
    return missing


def _match_score(match, weight) -> np.ndarray:
    """The summed weight of the reference triplets each hypothesis matched (H,): each image
    triplet counts once per hypothesis (two reference triplets cannot both be it), with the
    weight of the first reference triplet that matched it."""
    hh, jj = np.nonzero(match >= 0)
    if len(hh) == 0:
        return np.zeros(len(match))
    # (hypothesis, image triplet) pairs in row-major order: the first of each is the first
    # reference triplet of that row that matched it
    key = hh * (int(match.max()) + 1) + match[hh, jj]
    _, first = np.unique(key, return_index=True)
    return np.bincount(hh[first], weights=weight[jj[first]], minlength=len(match)).astype(float)


def _smooth_prediction(pose: Pose, ref: RefTriplets, img: Triplets, pairs):
    """Centres of all reference triplets predicted by the similarity plus a smooth
    correction fitted to the matched pairs, so that a distorted image (tens of px) is
    followed, and the linear map at each (n, 2, 2): the pose's times the correction's
    derivative there, so that the bars' direction and width follow the image's local turn
    and stretch too; None when too few matches.

    Each matched triplet gives four equations: its centre (two), and its bars' direction
    and bar width, which are the map's derivative there (:func:`_derivative_rows`); the
    correction is affine from :data:`MIN_SMOOTH_MATCHES` matches and quadratic from
    :data:`QUADRATIC_MATCHES`.  Why the derivatives: through a strongly distorted field
    (the LAB-UMK micrograph through the relay: local scales 0.7-1.26 and the axes sheared by
    up to 19 degrees across group 4) the few triplets first matched predicted their
    neighbours 8-16 px off from their centres alone, while their own bars already show the
    local turn and stretch."""
    warp = _correction(pose, ref, img, pairs)
    if warp is None:
        return None
    base = pose.apply(ref.centre)
    # only near the matched triplets is the correction trusted (it is a polynomial)
    corr = warp(base)
    far = np.hypot(*((base - warp.centre) / warp.scale).T) > 1.6
    corr[far] = 0.0
    jac = warp.jacobian(base)
    jac[far] = 0.0
    local = (np.eye(2)[None] + jac) @ pose.matrix()[None]
    return base + corr, local


def _correction(pose: Pose, ref: RefTriplets, img: Triplets, pairs) -> PolyWarp | None:
    """The smooth correction (camera px -> px added to the pose's prediction) fitted to the
    matched pairs' centres, bar directions and bar widths (:func:`_smooth_prediction`);
    None when too few matches or degenerate."""
    n = len(pairs)
    if n < MIN_SMOOTH_MATCHES:
        return None
    ii = np.array([p[0] for p in pairs])
    jj = np.array([p[1] for p in pairs])
    base = pose.apply(ref.centre)
    x = base[jj]
    resid = img.centre[ii] - x
    degree = 2 if n >= QUADRATIC_MATCHES else 1
    centre, scale = normalisation(x)
    nb = len(poly_exponents(degree))
    shell = PolyWarp(centre, scale, np.zeros((nb, 2)), degree)
    b0 = shell.basis(x)
    zero = np.zeros_like(b0)
    rows, rhs = _derivative_rows(shell, x, pose.matrix(), ref, img, ii, jj)
    design = np.vstack([np.hstack([b0, zero]), np.hstack([zero, b0]), rows])
    target = np.concatenate([resid[:, 0], resid[:, 1], rhs])
    coef, _, rank, _ = np.linalg.lstsq(design, target, rcond=None)
    if rank < 2 * nb or not np.isfinite(coef).all():
        return None
    warp = shell.with_coef(np.column_stack([coef[:nb], coef[nb:]]))
    return warp if _plausible_stretch(warp, x) else None


def _plausible_stretch(warp: PolyWarp, x: np.ndarray) -> bool:
    """Whether the correction's local map ``I + C`` at the matched points ``x`` keeps the
    orientation, stretches by :data:`CORRECTION_STRETCH` at most, either way, and turns by
    :data:`CORRECTION_TURN_DEG` at most.  Why: a bar's
    direction equation is homogeneous (``(I + C) v`` parallel to the bar found is also met
    by ``(I + C) v = 0``), so a wrong pose with 3-4 matches could collapse its bars' direction
    to fit them: on the LAB-UMK micrograph turned by 30 degrees such a pose (mirrored, 4
    triplets, a singular value of 0.0) scored within the ambiguity margin of the right one."""
    jac = np.eye(2)[None] + warp.jacobian(x)
    sv = np.linalg.svd(jac, compute_uv=False)
    lo, hi = 1.0 / CORRECTION_STRETCH, CORRECTION_STRETCH
    turn = np.degrees(np.abs(np.arctan2(jac[:, 1, 0] - jac[:, 0, 1], jac[:, 0, 0] + jac[:, 1, 1])))
    ok = (np.linalg.det(jac) > 0) & (sv >= lo).all(axis=1) & (sv <= hi).all(axis=1)
    return bool((ok & (turn <= CORRECTION_TURN_DEG)).all())


def _derivative_rows(shell: PolyWarp, x, mat, ref: RefTriplets, img: Triplets, ii, jj):
    """Two linear equations per matched triplet (image ``ii``, reference ``jj``, predicted at
    ``x`` by the pose's linear part ``mat``) on the correction's coefficients (x's, then
    y's, in ``shell``'s basis): the mapped bar direction parallel to the one found, and the
    mapped bar period across it equal to the one found.  The map there is ``(I + C) mat``
    with ``C`` the correction's derivative, linear in the coefficients.  Each equation is
    weighted to px at the triplet's outer bars: an angle error ``d`` (rad) moves a bar's
    end by ``2.5 w d``, a relative width error ``e`` the outer bars by ``2 w e``."""
    dbx, dby = shell.basis_jacobian(x)
    m = np.column_stack([np.cos(img.angle[ii]), np.sin(img.angle[ii])])  # found direction
    m_perp = np.column_stack([-m[:, 1], m[:, 0]])
    along = np.column_stack([np.cos(ref.angle[jj]), np.sin(ref.angle[jj])])
    normal = np.column_stack([-np.sin(ref.angle[jj]), np.cos(ref.angle[jj])])
    w_found = img.width[ii]
    rows, rhs = [], []
    # direction: cross((I + C) v, m) = 0 with v = mat @ along; (C v)_k = (v_x dbx + v_y dby) . c_k
    v = along @ mat.T
    r = v[:, :1] * dbx + v[:, 1:] * dby
    vlen = np.hypot(v[:, 0], v[:, 1])
    wt = 2.5 * w_found / vlen
    rows.append(wt[:, None] * np.hstack([m[:, 1:] * r, -m[:, :1] * r]))
    rhs.append(wt * (v[:, 1] * m[:, 0] - v[:, 0] * m[:, 1]))
    # period: m_perp . (I + C) u = +-w_found / w_ref with u = mat @ normal (the sign the pose gives)
    u = normal @ mat.T
    r = u[:, :1] * dbx + u[:, 1:] * dby
    now = (m_perp * u).sum(axis=1)
    want = np.sign(now) * w_found / ref.width[jj]
    wt = 2.0 * ref.width[jj]
    rows.append(wt[:, None] * np.hstack([m_perp[:, :1] * r, m_perp[:, 1:] * r]))
    rhs.append(wt * (want - now))
    return np.vstack(rows), np.concatenate(rhs)


def _refine(pose: Pose, scene: _Scene, n_iter=5) -> Pose:
    """Match, refit the similarity (and a smooth correction of it) to the matches, repeat.
    The position tolerance grows with the distance from the matched triplets' centroid
    (distortion), less at every round."""
    ref, img = scene.ref, scene.img
    pairs_prev = None
    pred = local = None
    anchor = img.centre.mean(axis=0)
    for it in range(n_iter + 1):
        loose = 0.8 * 0.6**it
        sc, miss, match, expected = _score(
            np.array([pose.s]), pose.lin[None], pose.t[None], scene,
            pred=None if pred is None else pred[None], anchor=anchor[None], loose=loose, width_tol=WIDTH_TOL,
            local=None if local is None else local[None],
        )  # fmt: skip
        pairs = [(int(i), j) for j, i in enumerate(match[0]) if i >= 0]
        n_exp = _n_expected(expected[0], match[0], ref)
        new = Pose(pose.s, pose.lin, pose.t, float(sc[0]), pairs, int(miss[0]), n_exp)
        if len(pairs) < 2 or it == n_iter:
            return new
        pairs_prev = pairs
        ii = np.array([p[0] for p in pairs])
        jj = np.array([p[1] for p in pairs])
        anchor = img.centre[ii].mean(axis=0)
        s, lin, t = _fit_similarity(ref.centre[jj], img.centre[ii], pose.mirrored)
        if not (np.isfinite(s) and s > 0):
            return new
        if len(pairs) >= 4:
            s, lin, t = _fit_affine(ref.centre[jj], img.centre[ii], s, lin, t, pose.mirrored)
        pose = Pose(s, lin, t, new.score, pairs, new.n_missing)
        smooth = _smooth_prediction(pose, ref, img, pairs)
        pred, local = (None, None) if smooth is None else smooth
    del pairs_prev
    return new


def _fit_similarity(src: np.ndarray, dst: np.ndarray, mirrored: bool):
    """Least-squares ``dst = s L src + t`` with ``L`` a rotation (times a mirror)."""
    m = np.diag([1.0, -1.0]) if mirrored else np.eye(2)
    a = src @ m.T
    ma, md = a.mean(0), dst.mean(0)
    a0, d0 = a - ma, dst - md
    cov = d0.T @ a0
    u, sv, vt = np.linalg.svd(cov)
    r = u @ vt
    if np.linalg.det(r) < 0:
        u[:, -1] *= -1
        r = u @ vt
    s = float(np.trace(r.T @ cov) / max((a0**2).sum(), 1e-12))
    lin = r @ m
    t = md - s * ma @ r.T
    return s, lin, t


def _fit_affine(src, dst, s, lin, t, mirrored):
    """Least-squares affine ``dst = A src + t`` written as ``s * lin`` with
    ``s = sqrt|det A|``; the similarity ``(s, lin, t)`` is kept when the affine is
    degenerate, flips the mirror or is far from a similarity (over 35 % anisotropy)."""
    design = np.column_stack([src, np.ones(len(src))])
    coef, _, rank, _ = np.linalg.lstsq(design, dst, rcond=None)
    if rank < 3:
        return s, lin, t
    a = coef[:2].T
    det = float(np.linalg.det(a))
    sv = np.linalg.svd(a, compute_uv=False)
    if det == 0 or (det < 0) != mirrored or sv[0] / sv[1] > 1.35:
        return s, lin, t
    sa = float(np.sqrt(abs(det)))
    return sa, a / sa, coef[2]


def _same_pose(a: Pose, b: Pose) -> bool:
    """Two poses are the same: same mirror, about the same rotation, and the same reference
    triplets for the image triplets they share (a mirrored or half-turned pose can match
    the same triplets but gives other corner ids)."""
    if a.mirrored != b.mirrored:
        return False
    if abs((a.angle_deg - b.angle_deg + 180.0) % 360.0 - 180.0) > 45.0:
        return False
    da = dict(a.matches)
    shared = [(i, j) for i, j in b.matches if i in da]
    if not shared:
        return abs(np.log(a.s / b.s)) < 0.04 and a.mirrored == b.mirrored
    same = sum(da[i] == j for i, j in shared)
    return same >= 0.5 * len(shared)


@dataclass
class PoseResult:
    pose: Pose | None
    runner_up: Pose | None
    status: int
    message: str
    slip_scores: dict
    n_image_triplets: int
    candidates: list = field(default_factory=list)
    kind: str = "ok"  # "ok", "not_found" or "ambiguous"
    param: tuple[str, ...] = ()  # the parameters the message suggests changing


# (11 parameters: the search's keywords, which core passes by name)
def search_pose(
    img: Triplets,
    ref: RefTriplets,
    shape: tuple[int, int],
    *,
    um_per_px: float | None = None,
    listed=None,
    max_image_triplets: int = 120,
    top: int = 40,
    orientation: str | None = None,
    mirror: bool | None = None,
    anchors=(),
    turned_seeds: bool = False,
) -> PoseResult:
    """Find the pose (module docstring).  ``listed`` marks the reference triplets of the
    groups the user named (weighted 1; others 0.25).  ``orientation`` (a key of
    :data:`~oapcal.imaging.usaf.ORIENTATIONS`) keeps only the poses nearest to it;
    ``mirror`` True/False only mirrored / unmirrored poses.  ``anchors``
    (:class:`~oapcal.imaging.detect.anchor.Anchor`, elements the user named) seed poses only
    from the named triplets and keep only poses that honour them (:mod:`.anchor`).
    ``turned_seeds``: every seed also turned by :data:`SEED_TURNS_DEG` (three times the
    hypotheses; the detection asks for it only when no layout's search found a pose).

    The steps: every pairing of an image triplet with a reference triplet proposes poses
    (:func:`_hypotheses`); each is scored (:func:`_score_hypotheses`); the best are
    refined and merged (:func:`_refined_poses`); the given scale may pick among the best
    (:func:`_at_given_scale`); the winner is judged against its rivals and its slipped
    copies (:func:`_judge`).
    """
    from scipy.spatial import cKDTree

    n_img = len(img)
    if n_img == 0:
        msg = "no bar triplet (three parallel bars side by side) was found in the image"
        return PoseResult(None, None, 1, msg, {}, 0, kind="not_found")
    hyps = _hypotheses(img, ref, um_per_px, orientation, mirror, max_image_triplets, anchors)
    if hyps is None:
        return _no_hypothesis_result(img, anchors, um_per_px)
    if turned_seeds:
        hyps = _turned_seeds(hyps)
    scene = _Scene(ref, img, cKDTree(img.centre), shape, listed)
    scores = _score_hypotheses(hyps, scene)
    refined = _refined_poses(hyps, scores, scene, top)
    if anchors:
        refined = _anchored_poses(
            refined, scene, um_per_px, orientation, mirror, max_image_triplets, top, anchors
        )
        if isinstance(refined, PoseResult):
            return refined
    best = _at_given_scale(refined, um_per_px)
    slips = _slip_scores(best, scene)
    if anchors:
        from oapcal.imaging.detect.anchor import honours

        # a slipped copy gives the named element another place: no rival when it breaks an anchor
        slips_judged = {k: p for k, p in slips.items() if honours(p, ref, anchors, img)}
    else:
        slips_judged = slips
    res = _judge(best, refined, slips_judged, um_per_px, scene, anchors)
    res.slip_scores = {k: v.score for k, v in slips.items()}
    return res


def _no_hypothesis_result(img: Triplets, anchors, um_per_px) -> PoseResult:
    """The refusal when no pairing of triplets proposes a pose that fits the options."""
    n_img = len(img)
    if anchors:
        msg = _anchor_unmatched_message(img, anchors, um_per_px)
        return PoseResult(None, None, 1, msg, {}, n_img, kind="not_found", param=("anchors",))
    if um_per_px is None:
        return PoseResult(None, None, 1, "no pose fits the options given", {}, n_img, kind="not_found")
    msg = _no_scale_message(img, um_per_px)
    return PoseResult(None, None, 1, msg, {}, n_img, kind="not_found", param=("um_per_px",))


def _anchored_poses(
    refined: list[Pose], scene: _Scene, um_per_px, orientation, mirror, max_image_triplets, top, anchors
) -> list[Pose] | PoseResult:
    """The poses seeded from the named triplets (``refined``) and the free search's that
    honour every anchor, best first; or the refusal when none does, or when the bars
    clearly say otherwise."""
    from oapcal.imaging.detect.anchor import honours

    ref, img, n_img = scene.ref, scene.img, len(scene.img)
    # the poses seeded from the named triplets, and the free search's poses (a named
    # triplet's own bar width may be some 20 % off under distortion, so its seeds alone
    # may miss the pose the other triplets find): those that honour every anchor
    free = _hypotheses(img, ref, um_per_px, orientation, mirror, max_image_triplets)
    free_refined = []
    if free is not None:
        free_scores = _score_hypotheses(free, scene)
        free_refined = _refined_poses(free, free_scores, scene, top)
    pool = []
    for p in sorted(refined + free_refined, key=lambda q: -q.score):
        if honours(p, ref, anchors, img) and not any(_same_pose(p, q) for q in pool):
            pool.append(p)
    refined = pool
    if not refined:
        msg = _anchor_unmatched_message(img, anchors, um_per_px)
        return PoseResult(None, None, 1, msg, {}, n_img, kind="not_found", param=("anchors",))
    # An anchor decides what the bars leave open; it never overrules what they say
    # clearly: the best pose without the anchors must not beat the best one with them.
    anchored = _at_given_scale(refined, um_per_px)
    free_best = _at_given_scale(free_refined, um_per_px) if free_refined else anchored
    margin = max(AMBIGUITY_MARGIN, (1.0 - AMBIGUITY_RATIO) * free_best.score)
    if not honours(free_best, ref, anchors, img) and free_best.score - anchored.score >= margin:
        msg = _anchor_contradicted_message(free_best, anchored, ref, img, anchors)
        # (the best pose is what the bars say: the layouts are compared on it)
        return PoseResult(free_best, anchored, 1, msg, {}, n_img, refined, "contradicted", ("anchors",))
    return refined


def _turned_seeds(hyps: _Hypotheses) -> _Hypotheses:
    """``hyps`` and every one of them also turned by each of :data:`SEED_TURNS_DEG` about
    its seed's image triplet (which stays where it is)."""
    turned = [hyps]
    for deg in SEED_TURNS_DEG:
        r = _rot(np.deg2rad(deg))
        lin = np.einsum("ij,hjk->hik", r, hyps.lin)
        t = hyps.anchor + (hyps.t - hyps.anchor) @ r.T
        turned.append(_Hypotheses(hyps.s, lin, t, hyps.anchor))
    return _Hypotheses(
        *(np.concatenate([getattr(h, f) for h in turned]) for f in ("s", "lin", "t", "anchor"))
    )


@dataclass(frozen=True)
class _Hypotheses:
    """Poses proposed by pairing triplets: scale ``s (H,)``, linear part ``lin (H, 2, 2)``,
    shift ``t (H, 2)`` and the image triplet's centre ``anchor (H, 2)`` of each."""

    s: np.ndarray
    lin: np.ndarray
    t: np.ndarray
    anchor: np.ndarray


def _hypotheses(
    img, ref, um_per_px, orientation, mirror, max_image_triplets, anchors=()
) -> _Hypotheses | None:
    """Every pose that maps a reference triplet onto one of the ``max_image_triplets``
    widest image triplets (both mirrors, both half turns), kept when it agrees with the
    given scale, orientation and mirror (and, with ``anchors``, lays a named triplet onto
    the image triplet); None when none does."""
    from oapcal.imaging.usaf import ORIENTATIONS

    names = list(ORIENTATIONS)
    mats = np.array([ORIENTATIONS[k] for k in names], float)
    order = np.argsort(-img.width)[:max_image_triplets]
    seed = None
    if anchors:
        from oapcal.imaging.detect.anchor import seed_mask

        seed = np.zeros((len(img), len(ref.width)), bool)
        for a in anchors:
            seed |= seed_mask(a, ref, img)
        # every image triplet that may be a named one, however narrow
        order = np.unique(np.concatenate([order, np.flatnonzero(seed.any(axis=1))]))
    hyps_s, hyps_lin, hyps_t, hyps_anchor = [], [], [], []
    for i in order:
        for mir in (1.0, -1.0):
            if mirror is not None and (mir < 0) != mirror:
                continue
            m = np.diag([1.0, mir])
            for k in (0.0, np.pi):
                phi = img.angle[i] - ref.angle + k
                lin = _rot(phi) @ m
                s = img.width[i] / ref.width
                t = img.centre[i] - s[:, None] * np.einsum("hij,hj->hi", lin, ref.centre)
                keep = np.ones(len(s), bool) if seed is None else seed[i].copy()
                if um_per_px is not None:
                    keep &= np.abs(np.log(s * um_per_px)) < np.log(SCALE_PRIOR_RANGE)
                if orientation is not None:
                    d = ((lin[:, None] - mats[None]) ** 2).sum(axis=(2, 3))
                    keep &= np.array(names)[np.argmin(d, axis=1)] == orientation
                if keep.any():
                    hyps_s.append(s[keep])
                    hyps_lin.append(lin[keep])
                    hyps_t.append(t[keep])
                    hyps_anchor.append(np.repeat(img.centre[i][None], keep.sum(), 0))
    if not hyps_s:
        return None
    return _Hypotheses(
        np.concatenate(hyps_s), np.concatenate(hyps_lin), np.concatenate(hyps_t), np.concatenate(hyps_anchor)
    )


def _score_hypotheses(hyps: _Hypotheses, scene: _Scene, chunk: int = 2000) -> np.ndarray:
    """The score of every hypothesis, ``chunk`` at a time."""
    scores = np.empty(len(hyps.s))
    for lo in range(0, len(hyps.s), chunk):
        sl = slice(lo, lo + chunk)
        scores[sl] = _score(
            hyps.s[sl], hyps.lin[sl], hyps.t[sl], scene, anchor=hyps.anchor[sl], width_tol=WIDTH_TOL,
        )[0]  # fmt: skip
    return scores


def _refined_poses(hyps: _Hypotheses, scores, scene: _Scene, top: int) -> list[Pose]:
    """The best ``4 top`` hypotheses refined, the same pose kept once (its best score),
    until ``top`` distinct poses; best first."""
    refined: list[Pose] = []
    for h in np.argsort(-scores)[: top * 4]:
        p = _refine(Pose(float(hyps.s[h]), hyps.lin[h], hyps.t[h]), scene)
        if any(_same_pose(p, q) and q.score >= p.score for q in refined):
            continue
        refined = [q for q in refined if not (_same_pose(p, q) and q.score < p.score)]
        refined.append(p)
        if len(refined) >= top:
            break
    refined.sort(key=lambda p: -p.score)
    return refined


def _at_given_scale(refined: list[Pose], um_per_px) -> Pose:
    """The best pose; with a given scale, among the poses about as good as the best the
    one at that scale (to within half an element step): it names the element when the
    view alone cannot."""
    best = refined[0]
    if um_per_px is not None:
        margin = max(AMBIGUITY_MARGIN, (1.0 - AMBIGUITY_RATIO) * best.score)
        near = [
            p
            for p in refined
            if p.score > best.score - margin and abs(np.log(p.s * um_per_px)) < np.log(HALF_ELEMENT)
        ]
        if near:
            best = max(near, key=lambda p: p.score)
    return best


def _judge(best: Pose, refined: list[Pose], slips: dict, um_per_px, scene: _Scene, anchors=()) -> PoseResult:
    """The result for ``best``: not found when it explains too little, ambiguous when
    another pose or a slipped copy scores about as well (and the given scale does not
    decide), else found.  Every refusal says which anchor would decide it
    (:func:`anchor_hint`)."""
    ref, img, listed, n_img = scene.ref, scene.img, scene.listed, len(scene.img)
    slip_scores = {k: v.score for k, v in slips.items()}
    runner = next((p for p in refined[1:] if not _same_pose(best, p)), None)
    n_named = sum(1 for _, j in best.matches if listed is None or listed[j])
    min_found = MIN_FOUND_FRACTION_ANCHORED if anchors else MIN_FOUND_FRACTION
    if n_named < min_found * best.n_expected and best.score >= 1.9:
        msg = (
            f"the target was not found reliably: the best pose finds only {n_named} of the "
            f"{best.n_expected} triplets of the named groups that it expects in the image"
        )
        msg += anchor_hint(best, None, ref, img, anchors)
        return PoseResult(best, runner, 1, msg, slip_scores, n_img, refined, "not_found", ("anchors",))
    if best.score < 1.9 or len(best.matches) < 2:
        msg = (f"the target was not found: the best pose explains only {len(best.matches)} of the "
               f"{n_img} bar triplets found (score {best.score:.1f})")  # fmt: skip
        msg += anchor_hint(best, None, ref, img, anchors)
        return PoseResult(best, runner, 1, msg, slip_scores, n_img, refined, "not_found", ("anchors",))
    wider = unexplained_wider(best, img)
    if len(wider) > MAX_UNEXPLAINED_WIDER * len(best.matches):
        msg = (
            f"the target was not found reliably: the best pose ({len(best.matches)} triplets, scale "
            f"{1 / best.s:.4g} um/px) leaves {len(wider)} wider bar triplets found unexplained"
        )
        msg += anchor_hint(best, None, ref, img, anchors)
        if um_per_px is None:
            msg += ", or give um_per_px"
        param = ("anchors", "um_per_px")
        return PoseResult(best, runner, 1, msg, slip_scores, n_img, refined, "not_found", param)
    others = [p for p in refined if p is not best and not _same_pose(best, p)]
    rivals = [("another pose", p) for p in others]
    rivals += [(f"the pose slipped by {k}", p) for k, p in slips.items()]
    for name, rival in rivals:
        # a pose matching a single triplet is no rival: any one triplet fits any other
        if rival is None or _same_pose(best, rival) or len(rival.matches) < 2:
            continue
        close = best.score - rival.score < max(AMBIGUITY_MARGIN, (1.0 - AMBIGUITY_RATIO) * best.score)
        if close and um_per_px is not None:
            # the given scale may decide between the two when it is within half an element
            # step of one and not of the other
            near_best = abs(np.log(best.s * um_per_px)) < np.log(HALF_ELEMENT)
            near_rival = abs(np.log(rival.s * um_per_px)) < np.log(HALF_ELEMENT)
            if near_best and not near_rival:
                continue
        if close:
            how = "rotation" if rival.mirrored == best.mirrored else "mirror"
            msg = (
                f"the target's identity is ambiguous: the best pose (scale {1 / best.s:.4g} um/px, "
                f"turned {best.angle_deg:.0f} degrees{', mirrored' if best.mirrored else ''}, "
                f"{len(best.matches)} triplets) scores {best.score:.1f} and {name} "
                f"(scale {1 / rival.s:.4g} um/px, turned {rival.angle_deg:.0f} degrees"
                f"{', mirrored' if rival.mirrored else ''}, {len(rival.matches)} triplets) {rival.score:.1f}"
            )
            hint = anchor_hint(best, rival, ref, img, anchors)
            param = ("anchors", "um_per_px", "groups")
            if hint:
                msg += hint
            else:
                # the same triplets carry the same ids in both: only the mirror (or turn) differs
                msg += f"; both give the triplets found the same ids, only the {how} differs: give the {how}"
                param = ("mirror",) if how == "mirror" else ("orientation",)
            if um_per_px is None and hint:
                msg += ", or um_per_px (to within 6 %)"
            return PoseResult(best, rival, 1, msg, slip_scores, n_img, refined, "ambiguous", param)
    return PoseResult(best, runner, 0, "ok", slip_scores, n_img, refined)


def unexplained_wider(pose: Pose, img: Triplets) -> list[int]:
    """The image triplets that ``pose`` matched to nothing and whose bars are wider than
    its widest match by more than :data:`WIDTH_TOL` (widest first)."""
    matched = {i for i, _ in pose.matches}
    if not matched:
        return []
    widest = max(float(img.width[i]) for i in matched)
    return [int(i) for i in np.argsort(-img.width) if i not in matched and img.width[i] > WIDTH_TOL * widest]


def anchor_hint(best: Pose, rival: Pose | None, ref, img, anchors=()) -> str:
    """The part of a refusal that says which anchor would decide it (``""`` when none
    would): the widest image triplet to which ``best`` and ``rival`` give different ids,
    with both readings; without a rival, the widest triplet found, to be read by eye."""
    if ref is None or img is None or len(img) == 0:
        return ""
    if rival is None:
        i = int(np.argmax(img.width))
        x, y = img.centre[i]
        if anchors:
            named = ", ".join(a.text() for a in anchors)
            return (
                f"; the anchors given ({named}) do not decide it: check them, or name another element "
                f"you can read in anchors (the widest bar triplet found is at ({x:.0f}, {y:.0f}))"
            )
        return (
            f"; name one element you can read, with where it is, in anchors, e.g. 'G4E2@{x:.0f},{y:.0f}' if "
            f"the numbers printed at the widest bar triplet found, ({x:.0f}, {y:.0f}), say group 4, element 2"
        )
    ids_b = {i: j for i, j in best.matches}
    ids_r = {i: j for i, j in rival.matches}
    differ = [i for i in ids_b if i not in ids_r or _elem(ref, ids_r[i]) != _elem(ref, ids_b[i])]
    # the same element, but its other triplet (a quarter turn): name the triplet, H or V
    triplet = not differ
    if triplet:
        differ = [i for i in ids_b if ids_r[i] != ids_b[i]]
    if not differ:
        return ""
    i = max(differ, key=lambda k: img.width[k])
    x, y = img.centre[i]

    def name(j):
        return f"G{ref.group[j]}E{ref.element[j]}" + (str(ref.orient[j]) if triplet else "")

    a = name(ids_b[i])
    other = name(ids_r[i]) if i in ids_r else "no element"
    return (
        f"; the bar triplet at ({x:.0f}, {y:.0f}) is {a} in the best pose and {other} in the other: "
        f"name the element you read there in anchors, e.g. '{a}@{x:.0f},{y:.0f}'"
    )


def _elem(ref, j) -> tuple[int, int]:
    return int(ref.group[j]), int(ref.element[j])


def _anchor_contradicted_message(free: Pose, anchored: Pose, ref, img, anchors) -> str:
    named = ", ".join(a.text() for a in anchors)
    hint = anchor_hint(free, anchored, ref, img)
    hint = hint.replace("name the element you read there", "check the element")
    return (
        f"the anchors given ({named}) contradict the bars: the best pose that honours them scores "
        f"{anchored.score:.1f} ({len(anchored.matches)} triplets), the best without them {free.score:.1f} "
        f"({len(free.matches)} triplets){hint}"
    )


def _anchor_unmatched_message(img: Triplets, anchors, um_per_px) -> str:
    named = ", ".join(a.text() for a in anchors)
    scale = f" at um_per_px {um_per_px:g}" if um_per_px is not None else ""
    return (
        f"no pose{scale} lays the element named in anchors ({named}) onto a bar triplet found in the image "
        f"({len(img)} triplets found): check the name (and position), or name another element"
    )


def _element_index(g, e):
    return 6 * np.asarray(g) + np.asarray(e) - 1


def _slip_scores(best: Pose, scene: _Scene) -> dict:
    """The best pose re-fitted with every matched reference triplet replaced by the same
    triplet (H or V) one element (``+1``/``-1``) or one layer (``+2g``/``-2g``) along."""
    ref, img = scene.ref, scene.img
    index = {
        (int(_element_index(ref.group[j], ref.element[j])), ref.orient[j]): j for j in range(len(ref.width))
    }
    out = {}
    for name, step in (("+1 element", 1), ("-1 element", -1), ("+2 groups", 12), ("-2 groups", -12)):
        src, dst = [], []
        for i, j in best.matches:
            k = index.get((int(_element_index(ref.group[j], ref.element[j])) + step, ref.orient[j]))
            if k is not None:
                src.append(ref.centre[k])
                dst.append(img.centre[i])
        if len(src) < 2:
            continue
        s, lin, t = _fit_similarity(np.array(src), np.array(dst), best.mirrored)
        if not (np.isfinite(s) and s > 0):
            continue
        out[name] = _refine(Pose(s, lin, t), scene)
    return out


def _no_scale_message(img: Triplets, um_per_px) -> str:
    w = np.sort(img.width)[::-1]
    return (
        f"no triplet of the target fits the bar triplets found at um_per_px {um_per_px:g} "
        f"(the widest bars found are {w[0]:.1f} px); check um_per_px or leave it out to find the scale"
    )
