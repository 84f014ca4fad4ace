"""Correspondences between frames of one static, textured scene moved by a stage
(``docs/selfcal.md``): which frames overlap, and many sub-pixel matches in each
overlapping pair, each with a weight from its local texture.

1. Every frame is made grey (float32) and checked for texture (:func:`texture_ratio`:
   the spread of the smoothed image against the pixel noise; a flat or noise-only frame
   is refused, :class:`SelfcalRefused` with reason ``"texture"``).
2. The pairwise shifts come from phase correlation of the whole frames
   (``cv2.phaseCorrelate`` with a Hanning window, on frames reduced to at most
   :data:`PHASE_MAX_SIDE` px); a pair overlaps when the shift leaves at least
   ``min_overlap`` of the frame in common and the correlation peak is clear
   (``min_response``).  Each frame keeps its ``max_pairs_per_frame`` clearest peaks, so
   50 frames cost at most ``50 * max_pairs_per_frame / 2`` pairs.
3. In an overlapping pair ``(a, b)`` the dense flow of ``cv2.DISOpticalFlow`` (on ``b``
   shifted back by the phase-correlation shift, at most :data:`FLOW_MAX_SIDE` px) gives
   each point's position in ``b`` to a pixel or so; candidates on a grid of cells over the
   overlap, the best-textured point of each cell (``cv2.cornerMinEigenVal``), are refined
   with pyramidal Lucas-Kanade (``cv2.calcOpticalFlowPyrLK`` at full resolution, started
   from the flow) and kept when the backward match returns within ``max_fb_px``.  The
   weight of a match is the smallest eigenvalue of its window's structure tensor (LK's
   own), relative to the median over all matches: the inverse variance of an LK match
   scales with it.

Memory: the frames as 8-bit grey, one pair's flow at a time.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from oapcal.errors import DataError
from oapcal.records import ImageSize

#: Phase correlation runs on frames reduced (``cv2.INTER_AREA``) to at most this side.
PHASE_MAX_SIDE = 512
#: The dense flow runs on frames reduced to at most this side.
FLOW_MAX_SIDE = 1024
#: Reduced px of the frames around the overlap that the dense flow also sees.
FLOW_PAD = 16
#: Lucas-Kanade window (px, full resolution) and pyramid levels.
LK_WINDOW = 21
LK_LEVELS = 2
#: A frame whose smoothed spread is below this multiple of its pixel noise has no texture.
MIN_TEXTURE_RATIO = 1.0
#: A pair with fewer good matches than this is not used.
MIN_PAIR_MATCHES = 12


class SelfcalRefused(DataError):
    """Self-calibration refused for a property of the frames (``reason``: ``"texture"``,
    ``"overlap"``, ``"moving"`` or ``"frames"``); the message says which frame or pair and
    what to do."""

    def __init__(self, message: str, reason: str, param=None):
        super().__init__(message, param=param)
        self.reason = reason


@dataclass(frozen=True)
class Pair:
    """An overlapping pair: frames ``a < b``, the phase-correlation ``shift`` (px: where
    ``a``'s content lies in ``b``, ``b ~ a`` moved by ``shift``), its ``response``, the
    ``overlap`` fraction of the frame, and ``n_matches`` kept."""

    a: int
    b: int
    shift: tuple[float, float]
    response: float
    overlap: float
    n_matches: int = 0


@dataclass(frozen=True)
class Matches:
    """Matches between frames: for match ``i`` the point ``xy_a[i]`` of frame
    ``frame_a[i]`` shows the same scene point as ``xy_b[i]`` of frame ``frame_b[i]``
    (camera px, ``docs/conventions.md``); ``weight`` (relative inverse variance, median 1);
    ``pairs`` the overlapping pairs; ``n_frames``; ``image_size`` ``(w, h)``."""

    frame_a: np.ndarray
    frame_b: np.ndarray
    xy_a: np.ndarray
    xy_b: np.ndarray
    weight: np.ndarray
    pairs: tuple[Pair, ...]
    n_frames: int
    image_size: tuple[int, int]

    def __len__(self) -> int:
        return len(self.frame_a)


def grey(frame) -> np.ndarray:
    """A frame ``(h, w)`` or ``(h, w, channels)`` as float32 grey (the channels' mean)."""
    f = np.asarray(frame)
    if f.ndim == 3:
        f = f[..., :3].astype(np.float32).mean(axis=-1)
    if f.ndim != 2 or min(f.shape) < 8:
        raise DataError(
            f"a frame has shape {np.shape(frame)}: expected a 2-D image of at least 8 x 8 px", param="frames"
        )
    f = f.astype(np.float32)
    if not np.isfinite(f).all():
        raise DataError("a frame holds non-finite values", param="frames")
    return f


def _reduce(img: np.ndarray, max_side: int) -> tuple[np.ndarray, float]:
    import cv2

    h, w = img.shape
    factor = max(1.0, max(h, w) / float(max_side))
    if factor == 1.0:
        return img, 1.0
    size = (max(8, round(w / factor)), max(8, round(h / factor)))
    return cv2.resize(img, size, interpolation=cv2.INTER_AREA), w / size[0]


def texture_ratio(g: np.ndarray) -> float:
    """The spread of the frame smoothed by a Gaussian of 2 px against its pixel noise (1.48
    times the median absolute difference from a 1 px smoothing): ~0.2 for noise alone, far
    above 1 for a textured scene; 0 for a constant frame."""
    import cv2

    small, _ = _reduce(g, 1024)
    smooth = cv2.GaussianBlur(small, (0, 0), 2.0)
    noise = 1.4826 * float(np.median(np.abs(small - cv2.GaussianBlur(small, (0, 0), 1.0))))
    signal = float(smooth[8:-8, 8:-8].std())
    floor = 1e-6 * max(float(np.abs(small).max()), 1e-30)
    return signal / max(noise, floor) if signal > floor else 0.0


def _to_uint8(g: np.ndarray, lo: float, hi: float) -> np.ndarray:
    return np.clip((g - lo) * (255.0 / max(hi - lo, 1e-30)), 0, 255).astype(np.uint8)


def pair_shifts(small: list[np.ndarray], scale: float, window) -> tuple[np.ndarray, np.ndarray]:
    """Phase-correlation shifts ``(F, F, 2)`` (full-resolution px) and responses ``(F, F)``
    for every pair ``a < b`` of reduced frames, each with the Hanning ``window``; the frames
    are left unchanged."""
    import cv2

    # the window applied here, once per frame: cv2.phaseCorrelate given a window multiplies
    # its *inputs* by it in place (OpenCV 5.0), so frame f of F was windowed F - 1 times over
    # the loop and the last pairs correlated little more than the frames' centres (50 frames
    # of 2048 x 2048: 408 of 455 candidate shifts wrong, the lower rows refused).  Without a
    # window the call leaves its inputs alone and gives the same shifts.
    windowed = [np.asarray(s, np.float32) * window for s in small]
    n = len(small)
    shifts = np.zeros((n, n, 2))
    response = np.zeros((n, n))
    for a in range(n):
        for b in range(a + 1, n):
            (dx, dy), r = cv2.phaseCorrelate(windowed[a], windowed[b])
            shifts[a, b] = (dx * scale, dy * scale)
            response[a, b] = r
    return shifts, response


def find_matches(
    frames,
    *,
    max_per_pair: int = 150,
    min_overlap: float = 0.2,
    min_response: float = 0.04,
    max_pairs_per_frame: int = 8,
    max_fb_px: float = 0.05,
    prior=None,
    progress=None,
) -> Matches:
    """The overlapping pairs and matches of ``frames`` (a sequence of 2-D arrays of one
    size, or an array ``(F, h, w)``): module docstring.

    ``prior`` (a :class:`~oapcal.model.Model` or a parameter vector, e.g. the relay's
    design): the frames are first corrected with it
    (:func:`oapcal.imaging.remap.correction_map`) and matched there, where moved frames
    differ by little more than a translation; the matches are then taken back to the
    frames' own pixels through the prior's forward map (exact).  Without it the frames
    are matched as they are (fine for distortion that changes little over a move).

    Raises :class:`SelfcalRefused` (reason ``"texture"``, ``"overlap"`` or ``"frames"``)
    when the frames cannot give matches, naming the frame."""
    from oapcal.progress import Stages

    frames = list(frames)
    if len(frames) < 2:
        raise SelfcalRefused(
            f"{len(frames)} frame given: self-calibration needs at least 3 frames of the moved scene",
            "frames",
            param="frames",
        )
    frames8 = _frames8(frames)
    del frames
    h, w = frames8[0].shape
    n = len(frames8)
    valid = np.ones((h, w), bool)
    if prior is not None:
        from oapcal.model import as_model

        prior = as_model(prior)
        frames8, valid = _precorrect(frames8, prior)
    with Stages(progress, total=n * (n - 1) // 2 + 1, description="phase correlation") as stages:
        shifts, response = _phase_shifts(frames8, valid)
        stages.advance(description="matching pairs")
        candidates = _candidates(shifts, response, (w, h), min_overlap, min_response)
        matcher = _PairMatcher(frames8, valid, shifts, response, (max_per_pair, max_fb_px), stages)
        _match_until_connected(matcher, candidates, n, max_pairs_per_frame)
    _check_connected(matcher.pairs, n, min_overlap)
    return matcher.matches(prior, n, (w, h))


def _phase_shifts(frames8, valid):
    """:func:`pair_shifts` of the frames faded out where the (pre-)correction has no data,
    reduced to at most :data:`PHASE_MAX_SIDE` px, with a Hanning window."""
    import cv2

    soft = cv2.GaussianBlur(cv2.erode(valid.astype(np.float32), np.ones((9, 9), np.uint8)), (0, 0), 6.0)
    reduced = [_reduce(_apodize(f, soft), PHASE_MAX_SIDE) for f in frames8]
    window = cv2.createHanningWindow(reduced[0][0].shape[::-1], cv2.CV_32F)
    return pair_shifts([r[0] for r in reduced], reduced[0][1], window)


class _PairMatcher:
    """Matches pairs of the frames one at a time (:func:`_match_pair`), keeping the pairs
    with at least :data:`MIN_PAIR_MATCHES` matches and their matches."""

    def __init__(self, frames8, valid, shifts, response, limits, stages):
        import cv2

        self.frames8, self.shifts, self.response = frames8, shifts, response
        self.inside = _inside(valid)  # one mask for every pair
        self.max_per_pair, self.max_fb_px = limits
        self.stages = stages
        self.dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
        self.pairs: list[Pair] = []
        self._found: list[tuple] = []  # per kept pair: (points in a, points in b, eigenvalues)

    def match(self, candidate) -> None:
        _, overlap, a, b = candidate
        pa, pb, eig = _match_pair(
            self.frames8[a],
            self.frames8[b],
            self.shifts[a, b],
            self.dis,
            self.max_per_pair,
            self.max_fb_px,
            self.inside,
        )
        self.stages.advance(description=f"matching frames {a} and {b}")
        if len(pa) < MIN_PAIR_MATCHES:
            return
        shift = (float(self.shifts[a, b, 0]), float(self.shifts[a, b, 1]))
        self.pairs.append(Pair(a, b, shift, float(self.response[a, b]), float(overlap), len(pa)))
        self._found.append((pa, pb, eig))

    def matches(self, prior, n: int, size) -> Matches:
        """The :class:`Matches` of the kept pairs (taken back to the frames' own pixels
        through the ``prior``'s forward map when the frames were pre-corrected)."""
        frame_a = np.concatenate([np.full(p.n_matches, p.a) for p in self.pairs])
        frame_b = np.concatenate([np.full(p.n_matches, p.b) for p in self.pairs])
        xa = np.concatenate([f[0] for f in self._found])
        xb = np.concatenate([f[1] for f in self._found])
        if prior is not None:  # back to the frames' own pixels
            xa, xb = prior(xa), prior(xb)
        weight = np.concatenate([f[2] for f in self._found])
        weight = np.clip(weight / np.median(weight), 0.05, 20.0)
        return Matches(frame_a, frame_b, xa, xb, weight, tuple(self.pairs), n, size)


def _match_until_connected(matcher: _PairMatcher, candidates, n: int, per_frame: int) -> None:
    """Match each frame's ``per_frame`` clearest candidates (:func:`_bounded_pairs`); then,
    for frames cut off (their clearest peaks were spurious or their pairs gave too few
    matches), their further candidates, clearest first, until they join the rest."""
    keep = _bounded_pairs(candidates, n, per_frame)
    matcher.stages.total = len(keep) + 1
    for candidate in keep:
        matcher.match(candidate)
    tried = set(keep)
    for candidate in sorted(candidates, reverse=True):
        labels = _components(matcher.pairs, n)
        if (labels == labels[0]).all():
            break
        _, _, a, b = candidate
        if candidate in tried or labels[a] == labels[b]:
            continue
        tried.add(candidate)
        matcher.stages.total += 1
        matcher.match(candidate)


def _frames8(frames: list) -> list:
    """The frames (of one size, each with texture to match: else refused, naming the frame)
    as 8 bits over their common 0.5-99.5 % range of levels."""
    # one frame in float at a time (two passes: the levels, then 8 bits), so 50 frames of
    # 2048 x 2048 hold 200 MB rather than 800
    shape = grey(frames[0]).shape
    levels = []
    for i, frame in enumerate(frames):
        f = grey(frame)
        if f.shape != shape:
            raise DataError(
                f"frame {i} is {f.shape[1]}x{f.shape[0]} px but frame 0 is "
                f"{shape[1]}x{shape[0]}: all frames must have one size",
                param="frames",
            )
        ratio = texture_ratio(f)
        if ratio < MIN_TEXTURE_RATIO:
            raise SelfcalRefused(
                f"frame {i} has no texture to match (its smoothed contrast is {ratio:.2g} times its "
                f"pixel noise, needs {MIN_TEXTURE_RATIO:g}): image a textured, in-focus sample",
                "texture",
                param="frames",
            )
        levels.append(np.percentile(f, [0.5, 99.5]))
    lo = float(min(v[0] for v in levels))
    hi = float(max(v[1] for v in levels))
    return [_to_uint8(grey(f), lo, hi) for f in frames]


def _candidates(shifts, response, size, min_overlap: float, min_response: float) -> list:
    """The frame pairs ``(response, overlap, a, b)`` whose phase-correlation shift leaves
    ``min_overlap`` of a ``size = (w, h)`` frame shared, with a peak of ``min_response``."""
    w, h = size
    n = len(shifts)
    out = []
    for a in range(n):
        for b in range(a + 1, n):
            dx, dy = shifts[a, b]
            overlap = max(0.0, (w - abs(dx)) * (h - abs(dy)) / (w * h))
            if overlap >= min_overlap and response[a, b] >= min_response:
                out.append((float(response[a, b]), overlap, a, b))
    return out


def _precorrect(frames8, prior):
    """The frames corrected by the prior model, and where the correction samples them."""
    import cv2

    from oapcal.imaging.remap import correction_map

    h, w = frames8[0].shape
    mx, my = correction_map(prior, (h, w), check=False)
    valid = np.isfinite(mx) & np.isfinite(my) & (mx >= 0) & (mx <= w - 1) & (my >= 0) & (my <= h - 1)
    mx = np.where(valid, mx, -1e6).astype(np.float32)
    my = np.where(valid, my, -1e6).astype(np.float32)
    out = [cv2.remap(f, mx, my, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE) for f in frames8]
    return out, valid


def _apodize(f8, soft):
    """The frame less its mean, faded out where the (pre-)correction has no data."""
    f = f8.astype(np.float32)
    return (f - float(f[soft > 0.5].mean() if (soft > 0.5).any() else f.mean())) * soft


def _bounded_pairs(candidates, n: int, per_frame: int):
    """The pairs to match: each frame's ``per_frame`` clearest phase-correlation peaks (a
    pair is kept when either frame keeps it).  By the peak, not the overlap: a spurious peak
    near zero shift claims a large overlap (50 frames of 2048 x 2048: such pairs took every
    place of 8 frames, which then overlapped no other)."""
    best: dict[int, list] = {i: [] for i in range(n)}
    for c in sorted(candidates, reverse=True):
        for i in c[2:]:
            best[i].append(c)
    chosen = {c for i in range(n) for c in best[i][:per_frame]}
    return sorted(chosen, key=lambda c: (c[2], c[3]))


def _components(pairs, n: int) -> np.ndarray:
    """The connected component of every frame in the graph of the matched pairs."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    if not pairs:
        return np.arange(n)
    graph = coo_matrix((np.ones(len(pairs)), ([p.a for p in pairs], [p.b for p in pairs])), shape=(n, n))
    return connected_components(graph, directed=False)[1]


def _check_connected(pairs, n: int, min_overlap: float) -> None:
    """Refuse frames that overlap no other, or groups of frames with no overlap between them."""
    labels = _components(pairs, n)
    count = len(np.unique(labels))
    if count > 1:
        sizes = np.bincount(labels)
        lonely = [i for i in range(n) if sizes[labels[i]] < sizes.max()] or list(range(1, n))
        what = f"frame {lonely[0]}" if len(lonely) == 1 else f"frames {', '.join(map(str, lonely[:8]))}"
        raise SelfcalRefused(
            f"{what} overlap{'s' if len(lonely) == 1 else ''} too little with the others (no pair shares "
            f"{min_overlap:.0%} of the frame with a clear phase-correlation peak and enough matches): "
            "move the stage by less than about half the field between neighbouring frames",
            "overlap",
            param="frames",
        )


def _strongest_per_cell(eig, box, max_points: int) -> np.ndarray:
    """``(n, 3)``: in each cell of a grid of about ``max_points`` cells over ``box = (x0, y0,
    x1, y1)``, the pixel of largest corner strength ``eig``, as ``(x, y, strength)``."""
    x0, y0, x1, y1 = box
    k = max(2, int(np.ceil(np.sqrt(max_points * (x1 - x0) / (y1 - y0)))))
    m = max(2, int(np.ceil(max_points / k)))
    xe = np.linspace(x0, x1, k + 1).astype(int)
    ye = np.linspace(y0, y1, m + 1).astype(int)
    pts = []
    for i in range(m):
        for j in range(k):
            cell = eig[ye[i] : ye[i + 1], xe[j] : xe[j + 1]]
            if cell.size == 0:
                continue
            r, c = np.unravel_index(int(np.argmax(cell)), cell.shape)
            pts.append((xe[j] + c, ye[i] + r, cell[r, c]))
    return np.array(pts, float).reshape(-1, 3)


def _inside(valid) -> np.ndarray:
    """Where matches may lie: where the (pre-)correction has data, a window's width from
    its edge (the window and its coarser pyramid levels clear of the border streaks; less
    in small frames)."""
    import cv2

    h, w = valid.shape
    margin = LK_WINDOW // 2 + 2
    edge = min(2 * LK_WINDOW + 1, max(margin, min(h, w) // 12))
    return cv2.erode(valid.astype(np.uint8), np.ones((2 * edge + 1, 2 * edge + 1), np.uint8)) > 0


def _corner_strength(a8, inside_a, box) -> np.ndarray:
    """``cv2.cornerMinEigenVal`` (7 px blocks) of frame ``a`` over the ``box = (x0, y0, x1,
    y1)`` where candidates lie, 0 elsewhere and outside ``inside_a``: computed on the box
    and a border of 8 px (the block and its Sobel reach 4), so its values in the box are the
    whole frame's (50 frames of 2048 x 2048: 0.14 s a pair on the whole frame)."""
    import cv2

    h, w = a8.shape
    x0, y0 = max(int(box[0]) - 8, 0), max(int(box[1]) - 8, 0)
    x1, y1 = min(int(np.ceil(box[2])) + 8, w), min(int(np.ceil(box[3])) + 8, h)
    eig = np.zeros((h, w), np.float32)
    crop = cv2.cornerMinEigenVal(np.ascontiguousarray(a8[y0:y1, x0:x1]), 7)
    eig[y0:y1, x0:x1] = np.where(inside_a[y0:y1, x0:x1], crop, 0.0)
    return eig


def _overlap_flow(a8, bs, box, dis):
    """The dense flow ``a -> b_s`` over the ``box = (x0, y0, x1, y1)`` of the overlap and
    :data:`FLOW_PAD` px of the reduced frames around it (the flow elsewhere would only be
    discarded: 50 frames of 2048 x 2048 spent 0.24 s a pair on the whole frame): the flow
    ``(rows, cols, 2)`` in reduced px, the reduction ``factor`` and the crop's corner
    ``(col, row)`` in reduced px."""
    small_a, factor = _reduce(a8, FLOW_MAX_SIDE)
    small_b, _ = _reduce(bs, FLOW_MAX_SIDE)
    rows, cols = small_a.shape
    c0, r0 = max(int(box[0] / factor) - FLOW_PAD, 0), max(int(box[1] / factor) - FLOW_PAD, 0)
    c1 = min(int(np.ceil(box[2] / factor)) + FLOW_PAD, cols)
    r1 = min(int(np.ceil(box[3] / factor)) + FLOW_PAD, rows)
    crop_a = np.ascontiguousarray(small_a[r0:r1, c0:c1])
    crop_b = np.ascontiguousarray(small_b[r0:r1, c0:c1])
    return dis.calc(crop_a, crop_b, None), factor, np.array([c0, r0])


def _match_pair(a8, b8, shift, dis, max_points: int, max_fb: float, inside_a):
    """Matches of one pair: points ``(k, 2)`` in ``a``, in ``b``, and their LK eigenvalues
    (``inside_a``: :func:`_inside`)."""
    import cv2

    h, w = a8.shape
    dx, dy = float(shift[0]), float(shift[1])
    # b moved back by the shift (b_s(x) = b(x + shift)), so the flow a -> b_s is small
    move = np.float32([[1, 0, dx], [0, 1, dy]])
    bs = cv2.warpAffine(
        b8, move, (w, h), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_REPLICATE
    )
    margin = LK_WINDOW // 2 + 2
    x0, x1 = max(0.0, -dx) + margin, min(w, w - dx) - margin
    y0, y1 = max(0.0, -dy) + margin, min(h, h - dy) - margin
    if x1 - x0 < 2 * margin or y1 - y0 < 2 * margin:
        return np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0)
    flow, factor, corner = _overlap_flow(a8, bs, (x0, y0, x1, y1), dis)
    eig = _corner_strength(a8, inside_a, (x0, y0, x1, y1))
    pts = _strongest_per_cell(eig, (x0, y0, x1, y1), max_points)
    if not len(pts):
        return np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0)
    floor = 0.05 * float(np.percentile(pts[:, 2], 90))
    pts = pts[pts[:, 2] > max(floor, 1e-12)]
    pa = pts[:, :2].astype(np.float32)
    fi = np.clip((pa / factor).round().astype(int) - corner, 0, [flow.shape[1] - 1, flow.shape[0] - 1])
    guess = pa + np.float32([dx, dy]) + flow[fi[:, 1], fi[:, 0]] * factor
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-3)
    flags = cv2.OPTFLOW_USE_INITIAL_FLOW | cv2.OPTFLOW_LK_GET_MIN_EIGENVALS
    win = (LK_WINDOW, LK_WINDOW)
    pb, ok, err = cv2.calcOpticalFlowPyrLK(
        a8,
        b8,
        pa.reshape(-1, 1, 2),
        guess.reshape(-1, 1, 2).copy(),
        winSize=win,
        maxLevel=LK_LEVELS,
        criteria=crit,
        flags=flags,
    )
    back, ok2, _ = cv2.calcOpticalFlowPyrLK(
        b8, a8, pb, pa.reshape(-1, 1, 2).copy(), winSize=win, maxLevel=LK_LEVELS, criteria=crit, flags=flags
    )
    pb = pb.reshape(-1, 2).astype(float)
    fb = np.linalg.norm(back.reshape(-1, 2) - pa, axis=1)
    inside = ImageSize(w, h).contains(pb, margin)  # and finite
    good = ok.ravel().astype(bool) & ok2.ravel().astype(bool) & (fb <= max_fb) & inside
    ib = np.clip(pb.round().astype(int), 0, [w - 1, h - 1])
    good &= inside_a[ib[:, 1], ib[:, 0]]
    return pa[good].astype(float), pb[good], err.ravel()[good].astype(float)


__all__ = ["Matches", "Pair", "SelfcalRefused", "find_matches", "grey", "texture_ratio"]
