"""Detection of dot grids and chessboards: :func:`detect_grid` (``docs/detection.md``).

1. **Scale**: the lattice period in px from the image's power spectrum
   gradient (:func:`~oapcal.imaging.detect.lattice.lattice_period`), or from ``um_per_px``
   when given.
2. **Candidates**: dots (:mod:`.dots`: background-subtracted, windowed-moment centres) or
   chessboard corners (:mod:`.saddles`: verified X-junctions, ``cv2.cornerSubPix``).
3. **Indexing** from local neighbourhoods, grown from two seeds that must agree
   (:mod:`.lattice`); dots unlike their neighbours (dust on a dot, a damaged dot: area or
   shape off) are dropped.
4. **Ids and reference points**: ``R{row}C{col}`` with the column index along the grid
   direction nearest the image's +x and the row index nearest +y, counted from the first
   row and column found; when ``rows`` and ``cols`` are given and the whole grid is found,
   ``R0C0`` is the grid's own corner (top-left as seen).  The reference points ``x_u, y_u``
   are the ideal grid at ``um_per_px`` (given, else the one found), its axes along the
   image's, placed so that the image centre has the same grid coordinates in both.
5. **Pixel size**: the object-space um per px at the image centre (the grid's derivative
   there, from a cubic polynomial image px -> grid um through all nodes), its standard
   error (the fit's, and the difference to a quartic fit, in quadrature), the field of view.

A failure (no periodic pattern, no seed, an inconsistent or ambiguous grid, a grid larger
than ``rows x cols``) is a result with ``ok`` False and the reason, never a wrong index.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from oapcal.errors import DataError
from oapcal.imaging.detect.lattice import index_lattice, lattice_periods
from oapcal.imaging.detect.warp import PolyWarp
from oapcal.records import ImageSize

#: Kinds of grid target.
GRID_TARGETS = ("dots", "chessboard")
#: A dot is dropped when its area differs from its neighbours' median by more than this factor ...
DOT_AREA_FACTOR = 1.6
#: ... or its ellipticity (1 - minor/major) by more than this.
DOT_ELLIPTICITY_TOL = 0.15
#: A landmark is dropped when its distance from the leave-one-out prediction of its
#: neighbours exceeds this factor times the typical (1.4826 x median) one, and this many px.
POSITION_OUTLIER_FACTOR, POSITION_OUTLIER_MIN_PX = 6.0, 0.15
#: A dot is dropped when the background changes across its window by more than this
#: fraction of its amplitude (a steep vignette edge: the background estimate does not
#: follow it there, and the centre moves by up to half a pitch; on the real X-ray image).
MAX_SHADING = 0.25
#: Fewer indexed landmarks than this is refused.
MIN_LANDMARKS = 16
#: Polynomial degree of the image -> grid map of the pixel size (and the check degree).
SCALE_DEGREE = 3


@dataclass(frozen=True)
class GridDetection:
    """Detected and indexed landmarks of a dot grid or chessboard.

    ``ids`` (``R{row}C{col}``), ``rc`` ``(N, 2)`` the indices, ``xy_u`` reference px,
    ``xy_d`` camera px, ``stderr_px`` ``(N, 2)`` (NaN where not estimated); ``n_expected``
    nodes of the found index range whose position lies in view; ``ids_absolute`` whether
    ``R0C0`` is the grid's own corner; ``um_per_px`` the scale of ``xy_u``;
    ``found_um_per_px``, ``um_per_px_sigma`` the pixel size measured at the image centre and
    its standard error, ``field_of_view_um`` ``(width, height)``; ``pitch_px`` the median
    local pitch; ``polarity``; ``counts`` (candidates, drops by reason, lattice checks);
    ``ok``, ``message``, ``param`` (parameters a failure suggests changing), ``reason``.
    """

    target: str
    ids: tuple[str, ...]
    rc: np.ndarray
    xy_u: np.ndarray
    xy_d: np.ndarray
    stderr_px: np.ndarray
    n_expected: int = 0
    ids_absolute: bool = False
    um_per_px: float = float("nan")
    found_um_per_px: float = float("nan")
    um_per_px_sigma: float = float("nan")
    um_per_px_at: tuple = ()
    field_of_view_um: tuple = ()
    um_per_px_given: bool = False
    pitch_px: float = float("nan")
    polarity: str = ""
    counts: dict = field(default_factory=dict)
    ok: bool = True
    message: str = "ok"
    param: tuple[str, ...] = ()
    reason: str = ""

    @property
    def status(self) -> int:
        return 0 if self.ok else 1

    @property
    def coverage(self) -> float:
        return len(self.ids) / self.n_expected if self.n_expected else 0.0

    def summary(self) -> dict:
        from oapcal.records import finite_or_none

        n_r = int(self.rc[:, 0].max()) + 1 if len(self.rc) else 0
        n_c = int(self.rc[:, 1].max()) + 1 if len(self.rc) else 0
        return {
            "status": self.status,
            "message": self.message,
            "reason": self.reason,
            "target": self.target,
            "found": len(self.ids),
            "expected": self.n_expected,
            "coverage": self.coverage,
            "grid_rows": n_r,
            "grid_cols": n_c,
            "ids_absolute": self.ids_absolute,
            "pitch_px": finite_or_none(self.pitch_px),
            "polarity": self.polarity,
            "um_per_px": finite_or_none(self.um_per_px),
            "um_per_px_sigma": None if self.um_per_px_given else finite_or_none(self.um_per_px_sigma),
            "field_of_view_um": [finite_or_none(v) for v in self.field_of_view_um] or None,
            "pixel_size": {
                "um_per_px": finite_or_none(self.found_um_per_px),
                "um_per_px_sigma": finite_or_none(self.um_per_px_sigma),
                "at_px": [float(v) for v in self.um_per_px_at],
                "given": self.um_per_px_given,
            }
            if self.ok
            else None,
            "counts": dict(self.counts),
        }


def _fail(
    target, message, reason, param=(), counts=None, polarity="", pitch_px=float("nan")
) -> GridDetection:
    e = np.zeros((0, 2))
    return GridDetection(target, (), np.zeros((0, 2), int), e, e.copy(), e.copy(), ok=False, message=message,
                         reason=reason, param=tuple(param), counts=dict(counts or {}), polarity=polarity,
                         pitch_px=pitch_px)  # fmt: skip


def _check_args(target, pitch_um, dot_um, rows, cols, um_per_px, polarity):
    if target not in GRID_TARGETS:
        raise DataError(f"target {target!r}: use one of {', '.join(GRID_TARGETS)}", param="target")
    if not (isinstance(pitch_um, (int, float)) and np.isfinite(pitch_um) and pitch_um > 0):
        raise DataError(
            f"pitch_um {pitch_um!r}: give the grid's pitch (or square) in um, > 0", param="pitch_um"
        )
    if dot_um is not None and not (np.isfinite(dot_um) and 0 < dot_um < pitch_um):
        raise DataError(
            f"dot_um {dot_um!r}: must be > 0 and smaller than the pitch {pitch_um} um", param="dot_um"
        )
    for name, v in (("rows", rows), ("cols", cols)):
        if v is not None and (int(v) != v or v < 2):
            raise DataError(f"{name} {v!r}: must be a whole number >= 2", param=name)
    if (rows is None) != (cols is None):
        raise DataError("give both rows and cols, or neither", param=("rows", "cols"))
    if um_per_px is not None and not (np.isfinite(um_per_px) and 1e-4 <= um_per_px <= 1e4):
        raise DataError(f"um_per_px {um_per_px!r}: must be between 1e-4 and 1e4", param="um_per_px")
    if polarity not in ("auto", "dark", "bright"):
        raise DataError(f"polarity {polarity!r}: use auto, dark or bright", param="polarity")


def detect_grid(
    image: np.ndarray,
    target: str = "dots",
    *,
    pitch_um: float,
    dot_um: float | None = None,
    rows: int | None = None,
    cols: int | None = None,
    um_per_px: float | None = None,
    polarity: str = "auto",
) -> GridDetection:
    """Find and index the dots or chessboard corners of ``image`` (module docstring).

    ``pitch_um`` is the dot pitch or the chessboard's square; ``dot_um`` the dot diameter
    (optional); ``rows`` x ``cols`` the target's dots or squares (optional: a check, and
    absolute ids when the whole grid is in view); ``um_per_px`` the camera's object-space
    pixel size to within 30 % (optional: the scale of ``xy_u`` and of the search);
    ``polarity`` of the dots (``dark`` on bright, ``bright`` on dark, or ``auto``)."""
    from oapcal.imaging.detect.core import to_float_image

    _check_args(target, pitch_um, dot_um, rows, cols, um_per_px, polarity)
    img = to_float_image(image)
    if img is None:
        return _fail(target, "the image is uniform: there is no grid in it", "uniform")
    h, w = img.shape
    centre = np.array([(w - 1) / 2.0, (h - 1) / 2.0])
    periods = lattice_periods(img)
    found_period = periods[0] if periods else float("nan")
    args = _GridArgs(target, pitch_um, dot_um, rows, cols, um_per_px, polarity, centre)
    if um_per_px is not None:
        # the given scale sets the search; the grid found must then measure it (below): the
        # image's own period can be a turned grid's outline, so it does not overrule it
        return _detect_at(img, args, pitch_um / um_per_px, found_period)
    # the spectrum's strongest peak first; when no grid is indexed at it, the next ones (the
    # outline of a turned grid can outshine its lattice: through the relay turned 30 degrees)
    det = None
    for period in periods or [float("nan")]:
        det = _detect_at(img, args, period, found_period)
        if det.ok or det.reason not in ("no_seed", "too_few", "no_period"):
            break
    return det


@dataclass(frozen=True)
class _GridArgs:
    """The keywords of :func:`detect_grid` (checked) and the image centre."""

    target: str
    pitch_um: float
    dot_um: float | None
    rows: int | None
    cols: int | None
    um_per_px: float | None
    polarity: str
    centre: np.ndarray


def _detect_at(img, args: _GridArgs, period, found_period):
    """:func:`detect_grid` at one lattice period (px)."""
    h, w = img.shape
    target, um_per_px = args.target, args.um_per_px
    if not (np.isfinite(period) and 3.0 <= period <= min(h, w) / 3.0):
        msg = "no periodic pattern of 3 px or more, with 3 periods across the image, was found"
        return _fail(target, msg, "no_period", ("um_per_px",))
    cand, xy, se, pol, parity = _candidates(img, args, period)
    counts: dict = {"candidates": len(xy)}
    lat = index_lattice(xy, centre=args.centre, parity=parity, pitch_px=period)
    counts.update(lat.counts)
    if not lat.ok:
        return _fail(target, f"the grid could not be indexed: {lat.message}", lat.reason, counts=counts,
                     polarity=pol, pitch_px=period)  # fmt: skip
    rc, pts = lat.rc, lat.point
    keep = _clean_dots(rc, cand, pts, counts) if target == "dots" else np.ones(len(rc), bool)
    off = _position_outliers(rc, xy[pts])
    counts["position_dropped"] = int((off & keep).sum())
    keep &= ~off
    rc, pts = rc[keep], pts[keep]
    if len(rc) < MIN_LANDMARKS:
        msg = f"only {len(rc)} grid landmarks were indexed, fewer than {MIN_LANDMARKS}"
        return _fail(target, msg, "too_few",
                     counts=counts, polarity=pol, pitch_px=lat.pitch_px)  # fmt: skip
    rc = rc - rc.min(axis=0)
    order = np.lexsort((rc[:, 1], rc[:, 0]))
    rc, pts = rc[order], pts[order]
    xy_d = xy[pts]
    ids_absolute = _ids_absolute(rc, args)
    if isinstance(ids_absolute, str):
        return _fail(target, ids_absolute, "larger_than_target", ("rows", "cols"), counts, pol, lat.pitch_px)
    scale = _pixel_size(xy_d, rc, args.pitch_um, args.centre)
    if um_per_px is not None and not 0.7 < scale["um_per_px"] / um_per_px < 1.43:
        msg = (f"the grid found measures {scale['um_per_px']:.4g} um/px, but um_per_px is {um_per_px:g} "
               f"(image period {found_period:.2f} px): check the pitch and the pixel size")  # fmt: skip
        return _fail(target, msg, "scale_mismatch", ("um_per_px", "pitch_um"), counts, pol, lat.pitch_px)
    ref_um_per_px = float(um_per_px) if um_per_px is not None else scale["um_per_px"]
    grid_centre = scale["grid_at_centre"]  # (row, col) of the image centre
    xy_u = args.centre + (rc[:, ::-1] - grid_centre[::-1]) * (args.pitch_um / ref_um_per_px)
    ids = tuple(f"R{r}C{c}" for r, c in rc)
    dot_um, pitch_um = args.dot_um, args.pitch_um
    margin = 2.0 + (
        0.5 * dot_um / pitch_um * lat.pitch_px if (target == "dots" and dot_um) else 0.25 * lat.pitch_px
    )
    n_expected = _expected(scale["forward"], rc, (w, h), margin, ids_absolute)
    fov = (w * ref_um_per_px, h * ref_um_per_px)
    return GridDetection(
        target=target, ids=ids, rc=rc, xy_u=xy_u, xy_d=xy_d, stderr_px=se[pts], n_expected=n_expected,
        ids_absolute=ids_absolute, um_per_px=ref_um_per_px, found_um_per_px=scale["um_per_px"],
        um_per_px_sigma=scale["sigma"], um_per_px_at=tuple(scale["at"]), field_of_view_um=fov,
        um_per_px_given=um_per_px is not None,
        pitch_px=lat.pitch_px, polarity=pol, counts=counts,
    )  # fmt: skip


def _candidates(img, args: _GridArgs, period):
    """The landmark candidates at ``period``: ``(candidates, xy, stderr, polarity, parity)``
    (dots: their centroids; chessboards: the saddle points, with their parity)."""
    if args.target == "dots":
        from oapcal.imaging.detect.dots import find_dots

        dot_px = args.dot_um / args.pitch_um * period if args.dot_um else None
        cand = find_dots(img, period, dot_px=dot_px, polarity=args.polarity)
        return cand, cand.xy, cand.stderr_px, cand.polarity, None
    from oapcal.imaging.detect.saddles import find_saddles

    cand = find_saddles(img, period)
    return cand, cand.xy, np.full((len(cand.xy), 2), np.nan), "", cand.parity


def _clean_dots(rc, cand, pts, counts) -> np.ndarray:
    """The indexed dots to keep: like their neighbours (not dirty), converged and not
    shaded; the dropped ones counted in ``counts``."""
    similar = _similar_to_neighbours(rc, cand.area[pts], cand.ellipticity[pts])
    keep = similar & cand.converged[pts]
    counts["dirty_dropped"] = int((~similar).sum())
    counts["unconverged_dropped"] = int((similar & ~cand.converged[pts]).sum())
    shaded = ~(cand.shading[pts] <= MAX_SHADING)
    counts["shaded_dropped"] = int((keep & shaded).sum())
    return keep & ~shaded


def _position_outliers(rc, xy) -> np.ndarray:
    """Landmarks off their neighbours' smooth course by far more than the others (dust on a
    dot that pulls its centre, a damaged corner), compared within nodes of the same number
    of neighbours (an edge node's prediction is an extrapolation, less certain than an
    inner one's)."""
    where = {tuple(n): i for i, n in enumerate(rc)}
    loo = _loo_residuals(rc, xy, where)
    finite = np.isfinite(loo)
    support = np.array(
        [sum((r + a, c + b) in where for a in (-1, 0, 1) for b in (-1, 0, 1)) - 1 for r, c in rc]
    )
    group = np.digitize(support, [5, 8])  # <= 4, 5-7, 8 neighbours
    median = {gi: float(np.median(loo[finite & (group == gi)])) for gi in range(3)
              if (finite & (group == gi)).sum() >= 8}  # fmt: skip
    off = np.zeros(len(rc), bool)
    for gi, med in median.items():
        off |= (
            finite
            & (group == gi)
            & (loo > max(POSITION_OUTLIER_MIN_PX, POSITION_OUTLIER_FACTOR * (1.4826 * med)))
        )
    if off.any():
        # once the suspects are out of their neighbours' fits, a clean node next to a dirty
        # one is predicted well again (its first prediction leaned on the dirty one)
        suspects = set(np.flatnonzero(off).tolist())
        again = _loo_residuals(rc, xy, where, exclude=suspects, only=suspects)
        limit = {
            gi: max(POSITION_OUTLIER_MIN_PX, POSITION_OUTLIER_FACTOR * 1.4826 * med)
            for gi, med in median.items()
        }
        for i in suspects:
            if np.isfinite(again[i]) and again[i] <= limit.get(group[i], np.inf):
                off[i] = False
    return off


def _ids_absolute(rc, args: _GridArgs):
    """Whether the ids count from the target's own corner (the whole grid of ``rows`` x
    ``cols`` in view), or the refusal's message when the grid found is larger."""
    if args.rows is None:
        return False
    rows, cols = args.rows, args.cols
    shape = (rows, cols) if args.target == "dots" else (rows - 1, cols - 1)
    found = tuple(int(v) + 1 for v in rc.max(axis=0))
    fits = (found[0] <= shape[0] and found[1] <= shape[1]) or (found[0] <= shape[1] and found[1] <= shape[0])
    if not fits:
        return (
            f"the grid found spans {found[0]} x {found[1]} landmarks, more than the target's "
            f"{shape[0]} x {shape[1]}: check rows and cols"
        )
    return found in (shape, shape[::-1])


def _loo_residuals(rc, xy, where, exclude=(), only=None) -> np.ndarray:
    """Each node's distance (px) from the prediction of its indexed neighbours within two
    steps (three when they are few), without the nodes in ``exclude``
    (:func:`~oapcal.imaging.detect.lattice.local_fit`);
    NaN where they do not determine one, and for nodes not in ``only`` (when given)."""
    from oapcal.imaging.detect.lattice import local_fit

    out = np.full(len(rc), np.nan)
    for i, (r, c) in enumerate(rc):
        if only is not None and i not in only:
            continue
        for radius in (2, 3):
            span = range(-radius, radius + 1)
            near = [where.get((r + a, c + b)) for a in span for b in span if a or b]
            nb = [j for j in near if j is not None and j not in exclude]
            if len(nb) >= 6:
                break
        pred = local_fit(rc[nb], xy[nb], np.array([r, c])) if len(nb) >= 3 else None
        if pred is not None:
            out[i] = float(np.hypot(*(xy[i] - pred[0])))
    return out


def _similar_to_neighbours(rc, area, ell) -> np.ndarray:
    """Dots whose area and ellipticity agree with the median of their lattice neighbours
    (within two index steps): dust on a dot or a damaged dot does not."""
    where = {tuple(n): i for i, n in enumerate(rc)}
    keep = np.ones(len(rc), bool)
    for i, (r, c) in enumerate(rc):
        nb = [where[(r + a, c + b)] for a in range(-2, 3) for b in range(-2, 3)
              if (a or b) and (r + a, c + b) in where]  # fmt: skip
        if len(nb) < 4:
            continue
        ma, me = np.median(area[nb]), np.median(ell[nb])
        if (
            not (ma / DOT_AREA_FACTOR <= area[i] <= ma * DOT_AREA_FACTOR)
            or abs(ell[i] - me) > DOT_ELLIPTICITY_TOL
        ):
            keep[i] = False
    return keep


def _scale_fit(xy_d, grid_um, at, degree, norm):
    """um per px at ``at`` from a polynomial image px -> grid um of ``degree``: ``(s, sigma,
    the polynomial)``."""
    c0, sc = norm
    warp = PolyWarp.fit(xy_d, grid_um, degree, c0, sc)
    a = warp.basis(xy_d)
    res = grid_um - a @ warp.coef
    dof = max(len(xy_d) - a.shape[1], 1)
    var = (res**2).sum(axis=0) / dof  # per output coordinate
    cov = np.linalg.pinv(a.T @ a)
    at = np.asarray(at, float)[None, :]
    jac = warp.jacobian(at)[0]
    det = abs(np.linalg.det(jac))
    s = float(np.sqrt(det))
    # linear propagation: ds/dJ = s/2 J^-T; J_kj = g_j . coef_k, coef_k ~ N(., var_k cov)
    ds = 0.5 * s * np.linalg.inv(jac).T
    g = np.concatenate(warp.basis_jacobian(at))  # (2, terms): d terms / dx, dy at ``at``
    var_s = 0.0
    for k in range(2):
        ck = var[k] * cov
        vec = ds[k] @ g  # d s / d coef_k
        var_s += float(vec @ ck @ vec)
    return s, float(np.sqrt(max(var_s, 0.0))), warp


def _pixel_size(xy_d, rc, pitch_um, centre) -> dict:
    """The pixel size at the image centre (module docstring, step 5), the grid coordinates
    of the image centre and the forward map grid -> px (for the expected landmarks)."""
    import cv2

    grid_um = rc[:, ::-1].astype(float) * pitch_um  # (x = col, y = row) um
    hull = cv2.convexHull(xy_d.astype(np.float32))
    inside = cv2.pointPolygonTest(hull, (float(centre[0]), float(centre[1])), False) >= 0
    at = centre if inside else xy_d.mean(axis=0)
    norm = (xy_d.mean(axis=0), max(float(np.ptp(xy_d, axis=0).max()) / 2, 1.0))
    deg = SCALE_DEGREE if len(xy_d) >= 30 else 1
    s, sig, scale_map = _scale_fit(xy_d, grid_um, at, deg, norm)
    if len(xy_d) >= 45:
        s4, _, _ = _scale_fit(xy_d, grid_um, at, deg + 1, norm)
        sig = float(np.hypot(sig, s4 - s))
    g_at_centre = scale_map(np.asarray(centre, float)[None, :])[0] / pitch_um  # (col, row)
    # the forward map grid (row, col) -> px, cubic, for the landmarks expected in view
    forward = PolyWarp.fit(rc, xy_d, min(3, deg))
    return {"um_per_px": s, "sigma": sig, "at": at, "grid_at_centre": g_at_centre[::-1], "forward": forward}


def _expected(forward, rc, size, margin, absolute) -> int:
    """Nodes of the found index range (all of it) whose predicted position lies ``margin``
    px inside the image."""
    r_max, c_max = rc.max(axis=0)
    rr, cc = np.meshgrid(np.arange(r_max + 1), np.arange(c_max + 1), indexing="ij")
    q = np.stack([rr.ravel(), cc.ravel()], axis=1)
    p = forward(q)
    inside = ImageSize(*size).contains(p, margin)
    found = {tuple(n) for n in rc}
    return int(inside.sum() + sum(1 for n in found if not inside[n[0] * (c_max + 1) + n[1]]))


def score_grid(det: GridDetection, truth_rc, truth_xy, in_view, *, match_fraction: float = 0.3) -> dict:
    """Score a detection against the truth of a rendered target (``truth_rc`` the target's
    indices, ``truth_xy`` camera px, ``in_view`` per landmark).

    A grid has no mark that fixes its origin or which way is up, so the detection's
    indices are compared with the truth's through the one lattice symmetry and shift that
    most detected landmarks agree on (the landmark nearest each detection within
    ``match_fraction`` of the pitch); a *wrong index* is a detection whose nearest true
    landmark has another index under that map, or that is near no true landmark.  Centre
    errors are measured for the rightly indexed ones."""
    from scipy.spatial import cKDTree

    truth_rc = np.asarray(truth_rc, int)
    truth_xy = np.asarray(truth_xy, float)
    in_view = np.asarray(in_view, bool)
    n_view = int(in_view.sum())
    out = {"in_view": n_view, "found": 0, "found_in_view": 0, "wrong": 0, "found_fraction": 0.0,
           "median_error_px": None, "rms_error_px": None, "max_error_px": None}  # fmt: skip
    if not det.ok or len(det.ids) == 0:
        return out
    ok_t = np.isfinite(truth_xy).all(axis=1)
    tree = cKDTree(truth_xy[ok_t])
    t_rc = truth_rc[ok_t]
    dist, idx = tree.query(det.xy_d)
    near = dist < match_fraction * det.pitch_px
    best, best_map = -1, None
    for m in (np.eye(2), np.array([[0, 1], [-1, 0]]), -np.eye(2), np.array([[0, -1], [1, 0]])):
        for f in (np.eye(2), np.diag([1, -1])):
            mat = (m @ f).astype(int)
            mapped = det.rc @ mat.T
            off = t_rc[idx[near]] - mapped[near]
            if len(off) == 0:
                continue
            vals, cnt = np.unique(off, axis=0, return_counts=True)
            k = int(np.argmax(cnt))
            if cnt[k] > best:
                best, best_map = int(cnt[k]), (mat, vals[k])
    mat, shift = best_map
    pred_rc = det.rc @ mat.T + shift
    right = near & (t_rc[idx] == pred_rc).all(axis=1)
    err = dist[right]
    view_ids = {tuple(v) for v in t_rc[in_view[ok_t]]}
    found_view = sum(1 for v in t_rc[idx[right]] if tuple(v) in view_ids)
    out.update(
        found=len(det.ids), found_in_view=int(found_view), wrong=int((~right).sum()),
        found_fraction=found_view / n_view if n_view else 0.0,
        median_error_px=float(np.median(err)) if len(err) else None,
        rms_error_px=float(np.sqrt(np.mean(err**2))) if len(err) else None,
        max_error_px=float(err.max()) if len(err) else None,
    )  # fmt: skip
    return out


@dataclass(frozen=True)
class GridSpec:
    """A named grid target of the spec file ``grid_targets.json`` (package data)."""

    name: str
    kind: str
    pitch_um: float
    dot_um: float | None
    rows: int | None
    cols: int | None
    source: str
    verified: bool


def grid_specs() -> dict:
    """The named grid targets: name -> :class:`GridSpec`."""
    import json
    from importlib import resources

    data = json.loads(
        resources.files("oapcal.imaging.detect").joinpath("grid_targets.json").read_text("utf-8")
    )
    return {
        name: GridSpec(
            name,
            v["kind"],
            float(v["pitch_um"]),
            v.get("dot_um"),
            v.get("rows"),
            v.get("cols"),
            v["source"],
            bool(v["verified"]),
        )  # fmt: skip
        for name, v in data["targets"].items()
    }


def grid_spec(name: str) -> GridSpec:
    """The named grid target; an unknown name is a :class:`~oapcal.errors.DataError` listing the names."""
    specs = grid_specs()
    if name not in specs:
        raise DataError(
            f"unknown grid target {name!r}: use one of {', '.join(sorted(specs))}", param="target_spec"
        )
    return specs[name]


__all__ = [
    "GRID_TARGETS",
    "GridDetection",
    "GridSpec",
    "detect_grid",
    "grid_spec",
    "grid_specs",
    "score_grid",
]
