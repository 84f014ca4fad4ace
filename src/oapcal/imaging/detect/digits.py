"""The target's printed numbers as chirality evidence: which of a pose and its mirror image
the image shows, where the bars alone cannot tell.

A single element in view (its H and V triplets side by side, centred on one line) is mirror
symmetric about that line: the pose and its reflection give every triplet the same place and
id, and only the corner ids within each bar differ.  The numbers printed beside the element
and above its group ("7", "1") are not symmetric.  :func:`mirror_from_digits` predicts, for
both hypotheses, where the numbers near the matched triplets fall in the image and how they
look (OpenCV's Hershey font in their boxes, :func:`oapcal.imaging.usaf.render_digits`; the
target's own font differs, its strokes are in the same places to within a stroke), and keeps
the hypothesis whose prediction correlates clearly better with the image.  It answers None
when the numbers are out of view, too small, or neither hypothesis stands out.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from oapcal.records import ImageSize

#: The digits of the better hypothesis must correlate with the image at least this well ...
MIN_NCC = 0.2
#: ... and by at least this much more than those of the other.
MIN_NCC_MARGIN = 0.2
#: Numbers within this many triplet spans of the matched triplets' centre are read.
NEAR_SPANS = 3.0
#: A number's box must be at least this many camera px high to be read.
MIN_DIGIT_PX = 8.0


@dataclass(frozen=True)
class DigitEvidence:
    """What the printed numbers say: ``mirrored`` the hypothesis they pick (None: neither),
    the correlation of each hypothesis' predicted numbers with the image (``ncc_unmirrored``,
    ``ncc_mirrored``) and how many numbers were read."""

    mirrored: bool | None
    ncc_unmirrored: float
    ncc_mirrored: float
    n_numbers: int


def reflected_matrix(lin: np.ndarray, centres_um: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """The reflection of the target about the line through ``centres_um`` (the matched
    triplets' centres, ``(n, 2)`` um, n >= 2), as ``(F, c)``: ``u -> c + F (u - c)``; None
    when the centres are not on one line (the layout then decides the mirror itself)."""
    c = centres_um.mean(axis=0)
    d = centres_um - c
    if len(centres_um) < 2 or not np.any(d):
        return None
    _, sv, vt = np.linalg.svd(d, full_matrices=False)
    if len(sv) > 1 and sv[1] > 1e-6 * sv[0]:
        return None
    axis = vt[0]
    return 2.0 * np.outer(axis, axis) - np.eye(2), c


def mirror_from_digits(image: np.ndarray, target, s: float, lin: np.ndarray, t: np.ndarray,
                       centres_um: np.ndarray, polarity: float) -> DigitEvidence:  # fmt: skip
    """Whether the image is the pose ``camera = s lin um + t`` or its reflection about the
    line through the matched triplets' centres ``centres_um`` (module docstring), read from
    the numbers of ``target`` (a :class:`~oapcal.imaging.usaf.UsafTarget`) near them.
    ``image`` ``(h, w)`` float; ``polarity`` +1 for bright print on dark, -1 for dark."""
    none = DigitEvidence(None, float("nan"), float("nan"), 0)
    refl = reflected_matrix(lin, np.asarray(centres_um, float))
    if refl is None or not len(target.labels):
        return none
    f, c = refl
    a0 = s * np.asarray(lin, float)
    hyps = {  # camera = A u + b for each hypothesis
        False: (a0, np.asarray(t, float)),
        True: (a0 @ f, a0 @ (c - f @ c) + t),
    }
    if np.linalg.det(a0) < 0:  # the pose itself is mirrored: its reflection is not
        hyps = {True: hyps[False], False: hyps[True]}
    boxes = np.asarray(target.labels, float)
    centre = (boxes[:, :2] + boxes[:, 2:]) / 2
    span = max(float(np.ptp(centres_um, axis=0).max()), 1e-9)
    near = np.hypot(*(centre - c).T) <= NEAR_SPANS * span
    heights_px = s * np.abs(boxes[:, 3] - boxes[:, 1])
    picked = np.flatnonzero(near & (heights_px >= MIN_DIGIT_PX))
    h, w = image.shape
    # a number in view in either hypothesis counts: where one predicts print and the other
    # does not, the image's dark or bright there decides
    size = ImageSize(w, h)
    picked = [k for k in picked if any(size.contains(_box_px(boxes[k], *hyps[m])).all() for m in hyps)]
    if not picked:
        return none
    preds = {m: _render(target, picked, *hyps[m], (h, w)) for m in hyps}
    region = preds[False][1] | preds[True][1]
    ncc = {m: _ncc(image[region], polarity * preds[m][0][region]) for m in hyps}
    best = max(ncc, key=lambda m: ncc[m])
    decided = ncc[best] >= MIN_NCC and ncc[best] - ncc[not best] >= MIN_NCC_MARGIN
    return DigitEvidence(best if decided else None, ncc[False], ncc[True], len(picked))


def _box_px(box: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    corners = np.array([[box[0], box[1]], [box[2], box[1]], [box[0], box[3]], [box[2], box[3]]])
    return corners @ a.T + b


def _render(target, picked, a, b, shape) -> tuple[np.ndarray, np.ndarray]:
    """The numbers ``picked`` as ``camera = a u + b`` shows them: their ink ``(h, w)`` and
    their boxes, grown by a fifth, as a mask (clipped to the image)."""
    import cv2

    from oapcal.imaging.usaf import render_digits

    h, w = shape
    ink = np.zeros((h, w), np.float32)
    mask = np.zeros((h, w), bool)
    for k in picked:
        box = np.asarray(target.labels[k], float)
        size = box[2:] - box[:2]
        lo, hi = box[:2] - 0.2 * size, box[2:] + 0.2 * size
        step = 0.5 / np.sqrt(abs(np.linalg.det(a)))  # um per cell: two cells per camera px
        cells = (int(np.ceil((hi[1] - lo[1]) / step)) + 1, int(np.ceil((hi[0] - lo[0]) / step)) + 1)
        cover = render_digits(box[None], [target.label_text[k]], cells, start=tuple(lo), step=step)
        # the print is blurred by about a stroke: the target's font is not OpenCV's
        stroke_cells = 0.14 * size[1] / step
        cover = cv2.GaussianBlur(cover.astype(np.float32), (0, 0), max(1.0, stroke_cells))
        m = np.hstack([a * step, (a @ lo + b)[:, None]])  # cell (col, row) -> camera px
        ink = np.maximum(ink, cv2.warpAffine(cover, m, (w, h), flags=cv2.INTER_LINEAR))
        mask |= cv2.warpAffine(np.ones(cells, np.uint8), m, (w, h), flags=cv2.INTER_NEAREST) > 0
    return ink, mask


def _ncc(values: np.ndarray, model: np.ndarray) -> float:
    """Normalized cross-correlation of two samples (0 when either is constant)."""
    v, p = values - values.mean(), model - model.mean()
    den = float(np.sqrt((v @ v) * (p @ p)))
    return float(v @ p / den) if den > 0 else 0.0
