"""Index a square lattice of landmark candidates from local neighbourhoods (``docs/detection.md``).

Dot grids and chessboards are square lattices seen through a smooth, unknown distortion.
No global model is fitted to find which candidate is which: the lattice is *grown* from a
seed, one node at a time, each node's position predicted from the nodes already indexed
around it (a local polynomial in the indices, so the local basis vectors follow the
distortion), and a candidate is accepted only when it is the one clear match of the
prediction:

1. **Seed**: a candidate whose eight neighbours make a clean, nearly square 3 x 3 block
   (two pairs of opposite vectors of about one pitch, within 14 degrees of perpendicular,
   the four diagonals where their sums predict, nothing else within 1.5 pitches).
2. **Growth**: the unindexed node with the most indexed neighbours is predicted next from
   the indexed nodes within two index steps (quadratic in the indices when they span three
   rows and columns, else bilinear or affine); the nearest candidate is accepted when it is
   within :data:`ACCEPT_FRACTION` of the local pitch, the second nearest farther than
   :data:`AMBIGUOUS_FRACTION`, and the candidate is not indexed yet.  A node without such a
   candidate stays empty (a missing or dirty dot), and the growth goes round it.
3. **Leave-one-out check**: every indexed node is predicted again from its neighbours
   without itself; nodes farther than :data:`LOO_FRACTION` of the local pitch are dropped.
4. **Second seed**: the lattice is grown again from a seed far from the first; both must
   give every shared candidate the same index up to one lattice symmetry and shift, else
   the indexing is refused.

Index axes follow the image: the column index grows along the lattice direction nearest
to +x, the row index along the one nearest to +y (so the indices keep the image's
handedness, and a mirrored target is indexed as seen).
"""

from __future__ import annotations

import heapq
from dataclasses import dataclass, field

import numpy as np

#: A candidate is accepted when it is within this fraction of the local pitch of the prediction ...
ACCEPT_FRACTION = 0.3
#: ... and the next candidate is farther than this fraction (otherwise the node stays empty).
AMBIGUOUS_FRACTION = 0.6
#: An indexed node farther than this fraction of the local pitch from its leave-one-out
#: prediction is dropped.
LOO_FRACTION = 0.2
#: The indexing is refused when more than this fraction of its nodes fail the leave-one-out check.
MAX_LOO_FAIL_FRACTION = 0.05
#: Fewer indexed nodes than this is no lattice.
MIN_NODES = 9
#: Local fits use indexed nodes within this many index steps (Chebyshev) of the node.
NEIGHBOURHOOD = 2
#: A seed block is nearly square: its basis vectors at least acos(0.25) = 76 deg apart, and
#: of lengths within 25 %.
SEED_MAX_COS, SEED_MAX_RATIO = 0.25, 1.25


@dataclass(frozen=True)
class Lattice:
    """The indexing of candidates: ``rc`` ``(M, 2)`` int (row, col) of each indexed node and
    ``point`` ``(M,)`` the index of its candidate; ``pitch_px`` the median local pitch;
    ``ok`` with ``message`` and ``reason`` (``no_seed``, ``too_few``, ``inconsistent``,
    ``seeds_disagree``); ``counts`` of the checks (``loo_dropped``, ``ambiguous``,
    ``conflicts``, ``shared_with_second_seed``); ``loo_px`` each node's distance (px) from
    its leave-one-out prediction (NaN where its neighbours do not determine one)."""

    rc: np.ndarray
    point: np.ndarray
    pitch_px: float
    ok: bool = True
    message: str = "ok"
    reason: str = ""
    counts: dict = field(default_factory=dict)
    loo_px: np.ndarray = field(default_factory=lambda: np.zeros(0))


def _design(rc: np.ndarray, kind: str) -> np.ndarray:
    """The local model of the positions in the indices (row, col): not the polynomial warp of
    :mod:`.warp`, since ``bilinear`` (1, r, c, rc) is no total-degree polynomial, and the
    coefficients 1 and 2 are read as the local basis vectors (d xy / d row, d xy / d col)."""
    r, c = rc[:, 0].astype(float), rc[:, 1].astype(float)
    one = np.ones_like(r)
    if kind == "quadratic":
        return np.stack([one, r, c, r * c, r * r, c * c], axis=1)
    if kind == "bilinear":
        return np.stack([one, r, c, r * c], axis=1)
    return np.stack([one, r, c], axis=1)


def _kinds(d: np.ndarray):
    """The local models (kind, number of coefficients), richest first, that neighbours at the
    relative indices ``d`` may determine: two points to spare beyond affine, 3 rows and
    columns for quadratic, 2 for bilinear."""
    n = len(d)
    rows, cols = len(np.unique(d[:, 0])), len(np.unique(d[:, 1]))
    for kind, k in (("quadratic", 6), ("bilinear", 4), ("affine", 3)):
        if n < k + (2 if kind != "affine" else 0):
            continue
        if kind == "quadratic" and (rows < 3 or cols < 3):
            continue
        if kind != "affine" and (rows < 2 or cols < 2):
            continue
        yield kind, k


def _local_solver(offsets: tuple):
    """The least-squares solver of :func:`local_fit` for neighbours at the relative indices
    ``offsets``: ``(design, pseudo-inverse, dof)`` of the richest model they determine, or
    None.  It depends only on which offsets are present, so it is computed once per pattern
    (:data:`_SOLVERS`)."""
    hit = _SOLVERS.get(offsets)
    if hit is not None or offsets in _SOLVERS:
        return hit
    d = np.array(offsets, float).reshape(-1, 2)
    n = len(d)
    out = None
    if n >= 3:
        for kind, k in _kinds(d):
            a = _design(d, kind)
            sv = np.linalg.svd(a, compute_uv=False)
            if sv[-1] < 1e-6 * sv[0]:
                continue
            out = (a, np.linalg.pinv(a), max(n - k, 1), n > k)
            break
    if len(_SOLVERS) < 100_000:
        _SOLVERS[offsets] = out
    return out


#: The solvers of :func:`_local_solver` by neighbour pattern.
_SOLVERS: dict = {}


def local_fit(rc_nb: np.ndarray, xy_nb: np.ndarray, at: np.ndarray):
    """Predict the position of node ``at`` (row, col) from indexed neighbours ``rc_nb`` with
    positions ``xy_nb``: ``(xy, pitch, rms)`` or None when they do not determine it.

    The model is the richest of quadratic / bilinear / affine in the indices (centred on
    ``at``) that the neighbours determine with two points to spare; ``pitch`` is the length of
    the shorter of the two local basis vectors (the fit's derivatives at ``at``), ``rms`` the
    fit's residual."""
    n = len(rc_nb)
    if n < 3:
        return None
    d = rc_nb - np.asarray(at)[None, :]
    for kind, k in _kinds(d):
        a = _design(d, kind)
        coef, _, rank, sv = np.linalg.lstsq(a, xy_nb, rcond=None)
        if rank < k or sv[-1] < 1e-6 * sv[0]:
            continue
        res = xy_nb - a @ coef
        dof = max(n - k, 1)
        rms = float(np.sqrt((res**2).sum() / dof)) if n > k else 0.0
        pitch = min(np.hypot(*coef[1]), np.hypot(*coef[2]))  # the shorter basis vector
        return coef[0], float(pitch), rms
    return None


class _Grower:
    """One growth of the lattice from a seed (module docstring, steps 1-2)."""

    def __init__(self, xy, tree, pitch, parity=None):
        self.xy = xy
        self.tree = tree
        self.pitch = pitch
        self.parity = parity  # per candidate +1/-1 (chessboard corner type) or None
        self.node_of_point: dict[int, tuple[int, int]] = {}
        self.point_of_node: dict[tuple[int, int], int] = {}
        self.failed: dict[tuple[int, int], int] = {}
        self.counts = {"ambiguous": 0, "conflicts": 0, "no_candidate": 0, "parity": 0}
        self.parity0 = None

    def assign(self, node, p):
        self.point_of_node[node] = p
        self.node_of_point[p] = node

    def neighbours(self, node, radius=NEIGHBOURHOOD, exclude_self=True):
        r0, c0 = node
        out = []
        for dr in range(-radius, radius + 1):
            for dc in range(-radius, radius + 1):
                if exclude_self and dr == 0 and dc == 0:
                    continue
                p = self.point_of_node.get((r0 + dr, c0 + dc))
                if p is not None:
                    out.append(((r0 + dr, c0 + dc), p))
        return out

    def predict(self, node, exclude_self=True):
        nb = self.neighbours(node, exclude_self=exclude_self)
        if len(nb) < 6:
            nb = self.neighbours(node, NEIGHBOURHOOD + 1, exclude_self=exclude_self)
        if len(nb) < 3:
            return None
        r0, c0 = node
        offsets = tuple(v for (r, c), _ in nb for v in (r - r0, c - c0))
        solver = _local_solver(offsets)
        if solver is None:
            return None
        a, pinv, dof, redundant = solver
        xy = self.xy[[p for _, p in nb]]
        coef = pinv @ xy
        rms = float(np.sqrt(((xy - a @ coef) ** 2).sum() / dof)) if redundant else 0.0
        pitch = min(np.hypot(*coef[1]), np.hypot(*coef[2]))  # the shorter basis vector
        return coef[0], float(pitch), rms

    def square_at(self, node) -> bool:
        """Whether the local basis at ``node`` (fitted to its indexed neighbours) is nearly
        square (:data:`SEED_MAX_COS`, :data:`SEED_MAX_RATIO`)."""
        nb = self.neighbours(node, exclude_self=False)
        r0, c0 = node
        solver = _local_solver(tuple(v for (r, c), _ in nb for v in (r - r0, c - c0)))
        if solver is None:
            return False
        coef = solver[1] @ self.xy[[p for _, p in nb]]
        a, b = coef[1], coef[2]
        la, lb = np.hypot(*a), np.hypot(*b)
        return abs(a @ b) / (la * lb) < SEED_MAX_COS and 1 / SEED_MAX_RATIO < la / lb < SEED_MAX_RATIO

    def expected_parity(self, node):
        return self.parity0 * (1 if (node[0] + node[1]) % 2 == 0 else -1)

    def try_node(self, node) -> bool:
        pred = self.predict(node)
        if pred is None:
            return False
        xy, pitch, rms = pred
        if not (np.isfinite(xy).all() and 0.3 * self.pitch < pitch < 3.0 * self.pitch) or rms > 0.15 * pitch:
            return False
        dist, idx = self.tree.query(xy, k=2)
        if not dist[0] < ACCEPT_FRACTION * pitch:
            self.counts["no_candidate"] += 1
            return False
        if dist[1] < AMBIGUOUS_FRACTION * pitch:
            self.counts["ambiguous"] += 1
            return False
        p = int(idx[0])
        if p in self.node_of_point:
            self.counts["conflicts"] += 1
            return False
        if self.parity is not None and self.parity[p] != self.expected_parity(node):
            self.counts["parity"] += 1
            return False
        self.assign(node, p)
        return True

    def support(self, node):
        r0, c0 = node
        return sum(
            (r0 + dr, c0 + dc) in self.point_of_node for dr in (-1, 0, 1) for dc in (-1, 0, 1) if dr or dc
        )

    def near_assigned(self, node, radius=2):
        r0, c0 = node
        return any(
            (r0 + dr, c0 + dc) in self.point_of_node
            for dr in range(-radius, radius + 1)
            for dc in range(-radius, radius + 1)
        )

    def grow(self, max_nodes):
        """Grow until no node can be added.  A node is queued when it has indexed
        8-neighbours, or when it lies next to a node that stayed empty and within two steps
        of an indexed one (to bridge a missing dot); each node is tried again only when its
        support grew, so the growth ends."""
        heap = []

        def consider(nb):
            if nb in self.point_of_node:
                return
            s = self.support(nb)
            if self.failed.get(nb, -1) >= s:
                return
            if s == 0 and not self.near_assigned(nb):
                return
            heapq.heappush(heap, (-s, nb))

        def around(node):
            r0, c0 = node
            for dr in (-1, 0, 1):
                for dc in (-1, 0, 1):
                    if dr or dc:
                        consider((r0 + dr, c0 + dc))

        for node in list(self.point_of_node):
            around(node)
        while heap and len(self.point_of_node) < max_nodes:
            negs, node = heapq.heappop(heap)
            if node in self.point_of_node:
                continue
            s = self.support(node)
            if s != -negs or self.failed.get(node, -1) >= s:
                continue  # stale entry
            if self.try_node(node):
                self.failed.pop(node, None)
            else:
                self.failed[node] = s
            around(node)


def _seed_basis(xy, tree, pitch, p, parity=None):
    """The local basis ``(a, b)`` at candidate ``p`` when its neighbourhood is a clean 3 x 3
    block (module docstring, step 1), else None; with the 8 neighbours' candidates."""
    dist, idx = tree.query(xy[p], k=min(len(xy), 13))
    if len(dist) < 9 or not np.isfinite(dist[4]):
        return None
    local = float(np.median(dist[1:5]))  # the local pitch (the field may compress or stretch it)
    if not 0.5 * pitch < local < 2.0 * pitch:
        return None
    pitch = local
    near = [(d, int(i)) for d, i in zip(dist[1:], idx[1:]) if np.isfinite(d) and d < 1.6 * pitch]
    if len(near) < 8 or len(near) > 8:
        return None
    vec = {i: xy[i] - xy[p] for _, i in near}
    axis = [i for d, i in near if 0.6 * pitch < d < 1.25 * pitch]
    pairs = []
    for k, i in enumerate(axis):
        for j in axis[k + 1 :]:
            if np.hypot(*(vec[i] + vec[j])) < 0.25 * pitch:
                pairs.append((i, j))
    if len(pairs) != 2:
        return None
    a = 0.5 * (vec[pairs[0][0]] - vec[pairs[0][1]])
    b = 0.5 * (vec[pairs[1][0]] - vec[pairs[1][1]])
    la, lb = np.hypot(*a), np.hypot(*b)
    cos = abs(a @ b) / (la * lb)
    # a nearly square block only: where the field shears the grid strongly, a diagonal may be
    # as short as an axis and the local block alone cannot tell them apart
    if cos > SEED_MAX_COS or not 1 / SEED_MAX_RATIO < la / lb < SEED_MAX_RATIO:
        return None
    # the diagonals where the sums predict
    used = {i for pr in pairs for i in pr}
    diag = set()
    for sa in (1, -1):
        for sb in (1, -1):
            target = xy[p] + sa * a + sb * b
            d, i = tree.query(target)
            if d > 0.25 * min(la, lb):
                return None
            diag.add(int(i))
    if len(diag) != 4 or diag & used:
        return None
    if parity is not None:
        # the four axis neighbours have the other corner type, the diagonals the same
        if any(parity[i] == parity[p] for i in used) or any(parity[i] != parity[p] for i in diag):
            return None
    return a, b


def _orient(a, b):
    """Column axis: the one of +-a, +-b nearest +x; row axis: the other, pointing to +y ..."""
    cands = [a, -a, b, -b]
    col = max(cands, key=lambda v: v[0] / np.hypot(*v))
    rest = [v for v in cands if not (np.allclose(v, col) or np.allclose(v, -col))]
    # ... and making (col, row) right-handed in image coordinates (y down): det > 0
    row = rest[0] if (col[0] * rest[0][1] - col[1] * rest[0][0]) > 0 else rest[1]
    return col, row


def _grow_from(xy, tree, pitch, p, basis, parity, max_nodes):
    g = _Grower(xy, tree, pitch, parity)
    col, row = _orient(*basis)
    if parity is not None:
        g.parity0 = parity[p]
    g.assign((0, 0), p)
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            if dr or dc:
                d, i = tree.query(xy[p] + dc * col + dr * row)
                g.assign((dr, dc), int(i))
    g.grow(max_nodes)
    return g


def _loo(g: _Grower, residuals: dict | None = None) -> list:
    """Nodes farther from their leave-one-out prediction than :data:`LOO_FRACTION` pitch
    (and each node's distance from it in ``residuals``, when given)."""
    bad = []
    for node, p in g.point_of_node.items():
        pred = g.predict(node, exclude_self=True)
        if pred is None:
            continue
        xy, pitch, _ = pred
        d = float(np.hypot(*(g.xy[p] - xy)))
        if residuals is not None:
            residuals[node] = d
        if d > LOO_FRACTION * pitch:
            bad.append(node)
    return bad


def _find_seeds(xy, tree, pitch, order, parity, skip=(), limit=400):
    for p in order[:limit]:
        if p in skip:
            continue
        basis = _seed_basis(xy, tree, pitch, int(p), parity)
        if basis is not None:
            yield int(p), basis


def _agree(g1: _Grower, g2: _Grower):
    """Whether the two growths index their shared candidates alike up to one lattice
    symmetry and shift: ``(ok, shared)``."""
    shared = [p for p in g1.node_of_point if p in g2.node_of_point]
    if len(shared) < 4:
        return False, len(shared)
    a = np.array([g1.node_of_point[p] for p in shared])
    b = np.array([g2.node_of_point[p] for p in shared])
    best = 0
    for m in (np.eye(2), np.array([[0, 1], [-1, 0]]), -np.eye(2), np.array([[0, -1], [1, 0]])):
        for f in (np.eye(2), np.diag([1, -1])):
            t = (b @ (m @ f).T.astype(int)).astype(int)
            off = a - t
            vals, cnt = np.unique(off, axis=0, return_counts=True)
            best = max(best, int(cnt.max()))
    return best == len(shared), len(shared)


def index_lattice(
    xy: np.ndarray,
    *,
    centre=None,
    parity: np.ndarray | None = None,
    pitch_px: float | None = None,
) -> Lattice:
    """Index the candidates ``xy`` ``(N, 2)`` as a square lattice (module docstring).

    ``centre`` (px) is where the first seed is looked for (default: the candidates'
    median); ``parity`` (+1/-1 per candidate, optional) a type that must alternate between
    neighbouring nodes (a chessboard's two kinds of corner); ``pitch_px`` the expected
    pitch (default: the median nearest-neighbour distance)."""
    from scipy.spatial import cKDTree

    xy = np.asarray(xy, float)
    empty = Lattice(np.zeros((0, 2), int), np.zeros(0, int), float("nan"))
    if len(xy) < MIN_NODES:
        return _fail(empty, "too_few", f"only {len(xy)} candidates were found, fewer than {MIN_NODES}")
    tree = cKDTree(xy)
    if pitch_px is None:
        d, _ = tree.query(xy, k=2)
        pitch_px = float(np.median(d[:, 1]))
    centre = np.median(xy, axis=0) if centre is None else np.asarray(centre, float)
    order = np.argsort(np.hypot(*(xy - centre).T))
    first = next(_find_seeds(xy, tree, pitch_px, order, parity), None)
    if first is None:
        return _fail(empty, "no_seed", "no candidate has eight neighbours in a clean 3 x 3 block of the grid")
    g1, loo, counts, failure = _first_growth(xy, tree, pitch_px, parity, *first)
    failure = failure or _second_growth(xy, tree, pitch_px, parity, first[0], g1, counts)
    if failure:
        return _fail(empty, *failure, counts)
    return _lattice(g1, loo, counts, pitch_px)


def _first_growth(xy, tree, pitch_px, parity, p1, basis1):
    """Steps 2 and 3 from the first seed ``p1``: the growth ``g1`` without the nodes that
    fail the leave-one-out check, each node's distance from its prediction (``loo``), the
    ``counts``, and the failure ``(reason, message)`` (None when the growth stands)."""
    g1 = _grow_from(xy, tree, pitch_px, p1, basis1, parity, len(xy))
    loo: dict = {}
    bad = _loo(g1, loo)
    counts = dict(g1.counts)
    counts["loo_dropped"] = len(bad)
    n1 = len(g1.point_of_node)
    if n1 >= MIN_NODES and len(bad) > MAX_LOO_FAIL_FRACTION * n1:
        why = (
            f"{len(bad)} of {n1} grid nodes disagree with their neighbours (more than "
            f"{100 * MAX_LOO_FAIL_FRACTION:.0f} %): the candidates are not one regular grid"
        )
        return g1, loo, counts, ("inconsistent", why)
    for node in bad:
        g1.node_of_point.pop(g1.point_of_node.pop(node))
    if len(g1.point_of_node) < MIN_NODES:
        return g1, loo, counts, ("too_few", f"the grid grew to only {len(g1.point_of_node)} nodes")
    return g1, loo, counts, None


def _second_growth(xy, tree, pitch_px, parity, p1, g1, counts: dict):
    """Step 4: the lattice grown again from a second seed, far from the first (``p1``),
    must index the candidates it shares with ``g1`` alike; the failure ``(reason,
    message)``, or None.  Sets ``counts["shared_with_second_seed"]``."""
    # the second seed: far from the first, among the indexed candidates
    # the farthest block that the first growth finds nearly square (where the field shears the
    # grid strongly, a block's own shape cannot tell an axis from a diagonal)
    dist = {p: float(np.hypot(*(xy[p] - xy[p1]))) for p in g1.node_of_point}
    far = [p for p in sorted(dist, key=lambda p: -dist[p]) if g1.square_at(g1.node_of_point[p])]
    second = next(
        _find_seeds(xy, tree, pitch_px, np.array(far, int), parity, skip={p1}, limit=len(far)), None
    )
    if second is None:
        counts["shared_with_second_seed"] = 0
        return None
    g2 = _grow_from(xy, tree, pitch_px, second[0], second[1], parity, len(xy))
    for node in _loo(g2):
        g2.node_of_point.pop(g2.point_of_node.pop(node))
    ok, shared = _agree(g1, g2)
    counts["shared_with_second_seed"] = shared
    if not ok:
        return ("seeds_disagree", "two growths of the grid from different seeds index the dots differently")
    # keep only what both growths agree to index (a node reached by one alone stays)
    return None


def _lattice(g1, loo: dict, counts: dict, pitch_px: float) -> Lattice:
    """The :class:`Lattice` of the growth ``g1``: its nodes shifted to start at (0, 0),
    their candidates, the median local pitch (``pitch_px`` when no node predicts one) and
    each node's leave-one-out distance (``loo``)."""
    nodes = np.array(list(g1.point_of_node), int)
    points = np.array([g1.point_of_node[tuple(n)] for n in nodes], int)
    base = nodes.min(axis=0)
    nodes -= base
    pitches = []
    for node in list(g1.point_of_node)[:: max(1, len(g1.point_of_node) // 200)]:
        pred = g1.predict(node, exclude_self=False)
        if pred is not None:
            pitches.append(pred[1])
    loo_px = np.array([loo.get(tuple(n + base), np.nan) for n in nodes])
    return Lattice(
        nodes, points, float(np.median(pitches)) if pitches else pitch_px, counts=counts, loo_px=loo_px
    )


def _fail(empty: Lattice, reason: str, message: str, counts=None) -> Lattice:
    return Lattice(empty.rc, empty.point, empty.pitch_px, ok=False, message=message, reason=reason,
                   counts=dict(counts or {}))  # fmt: skip


def lattice_periods(img: np.ndarray, count: int = 3) -> list:
    """Up to ``count`` candidate periods (px) of the periodic pattern in ``img``'s gradient
    magnitude, strongest first, each more than 30 % from the others: the highest peaks of its
    power spectrum (Hann window) among those that stand 20 times above the median of their
    ring, with between 4 periods across the image's shorter side and a period of 2.5 px;
    empty for an image without one.  The gradient repeats at the dot pitch of
    a dot grid and at the square of a chessboard (edges every square along both axes), and a
    target's outline, which dominates the spectrum of the intensity (it once gave a
    chessboard's period as 57 px instead of 10), is a single edge in it."""
    power, fx, fy = _gradient_power(img)
    h, w = power.shape
    f = np.hypot(fx, fy)
    band = (f >= 4.0 / min(h, w)) & (f <= 1.0 / 2.5)
    if not band.any() or not power[band].max() > 0:
        return []
    power = _whitened(power, band, fx, fy)
    return _peak_periods(power, f, count)


def _gradient_power(img: np.ndarray):
    """The power spectrum of ``img``'s gradient magnitude (Hann window) and its
    frequencies ``fx`` (1, w), ``fy`` (h, 1), in cycles per px."""
    import cv2

    a = np.asarray(img, np.float32)
    # the gradient magnitude: a target's outline is one edge, its squares or dots many, so
    # its period dominates; a chessboard's edges repeat at one square along each axis
    g = cv2.GaussianBlur(a, (0, 0), 1.0)
    a = np.hypot(cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3), cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3))
    h, w = a.shape
    win = np.outer(np.hanning(h), np.hanning(w)).astype(np.float32)
    a = (a - a.mean()) * win
    spec = cv2.dft(a, flags=cv2.DFT_COMPLEX_OUTPUT)
    power = spec[..., 0] ** 2 + spec[..., 1] ** 2
    fy = np.fft.fftfreq(h)[:, None]
    fx = np.fft.fftfreq(w)[None, :]
    return power, fx, fy


def _whitened(power: np.ndarray, band: np.ndarray, fx, fy) -> np.ndarray:
    """The power at the sharp peaks (over 20 times their ring's median, in ``band``), zero
    elsewhere; the whitened power itself when there is no such peak."""
    h, w = power.shape
    # whitened: each frequency over the median power of its ring, so that the lattice's few
    # sharp peaks per ring stand out and the broad low-frequency content of the target's
    # outline, the illumination or the scene does not (it once took a chessboard's outline
    # for its period)
    ring = np.rint(np.hypot(fx * w, fy * h)).astype(int)
    med = np.zeros(ring.max() + 1)
    order = np.argsort(ring, axis=None)
    r_sorted = ring.ravel()[order]
    p_sorted = power.ravel()[order]
    edges = np.searchsorted(r_sorted, np.arange(ring.max() + 2))
    for i in range(ring.max() + 1):
        seg = p_sorted[edges[i] : edges[i + 1]]
        if len(seg):
            med[i] = np.median(seg)
    white = np.where(band, power / (med[ring] + 1e-12 * power.max()), 0.0)
    sharp = white > 20.0  # a peak well above its ring
    return np.where(sharp, power, 0.0) if sharp.any() else white


def _peak_periods(power: np.ndarray, f: np.ndarray, count: int) -> list:
    """The periods (px) of up to ``count`` highest peaks of ``power``, each refined along
    both axes and more than 30 % from those before it."""
    h, w = power.shape

    # parabolic refinement of a peak along each axis
    def refine(vals, i):
        y0, y1, y2 = vals
        den = y0 - 2 * y1 + y2
        return i + (0.5 * (y0 - y2) / den if den < 0 else 0.0)

    periods = []
    left = power.copy()
    while len(periods) < count:
        k = int(np.argmax(left))
        if not left.flat[k] > 0:
            break
        iy, ix = np.unravel_index(k, power.shape)
        pyx = refine([power[(iy - 1) % h, ix], power[iy, ix], power[(iy + 1) % h, ix]], iy)
        pxx = refine([power[iy, (ix - 1) % w], power[iy, ix], power[iy, (ix + 1) % w]], ix)
        fyv = (pyx if pyx < h / 2 else pyx - h) / h
        fxv = (pxx if pxx < w / 2 else pxx - w) / w
        period = 1.0 / float(np.hypot(fxv, fyv))
        periods.append(period)
        # the next candidate: a period more than 30 % away from those taken
        with np.errstate(divide="ignore"):
            pf = 1.0 / f
        left[(pf > period / 1.3) & (pf < period * 1.3)] = 0.0
    return periods


def lattice_period(img: np.ndarray) -> float:
    """The period of :func:`lattice_periods`' strongest peak (NaN for an image without one)."""
    periods = lattice_periods(img, 1)
    return periods[0] if periods else float("nan")


__all__ = ["Lattice", "index_lattice", "lattice_period", "lattice_periods", "local_fit"]
