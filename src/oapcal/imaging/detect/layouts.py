"""Which layout of the target the detected corners follow.

Makers draw the layers of a USAF-1951 target with slightly different gaps between triplets,
elements and groups (:data:`oapcal.imaging.usaf.LAYOUTS`).  The pose search chooses a layout
from where the bar triplets are, through a similarity; under a strongly distorted field and
some poses a wrong layout's similarity explains more triplets than the right one's
(measured: a real micrograph through the aligned relay, turned by 135 degrees and mirrored:
``whole-target`` matched 14 triplets at 5.02 um/px, the true ``compact`` 10 at 4.63; the
corners kept were right, but their reference points 3.3 px rms off the truth, so every fit
from them was 3.4 px off).

The corners themselves decide it.  Within one element every layout is the same; across
elements the layouts differ by up to a bar width.  A smooth map (a cubic polynomial, the
map :mod:`.checks` uses) from a layout's um to the detected px fits the right layout to the
corners' noise and a wrong one to about half a pixel or more (on the case above: 0.22 px
for ``compact`` against 0.61 px for the layout chosen; 0.03 against 0.86-2.0 px on the same
images detected in the right layout).  :func:`better_layout` names a layout that fits the
detected corners clearly better than the one they were detected in; detection then runs
again in that layout (:func:`oapcal.imaging.detect.core.detect_usaf`).

Too few corners to tell are a sign of their own: in a wrong layout the registration drops the
corners of the elements that the layout puts elsewhere as "moved" (measured: the same
micrograph turned by 225 degrees, ``whole-target`` kept 124 corners, group 4 and one element
of group 5, where the layouts agree; ``compact`` keeps 264), or refuses the whole target
(turned by 285 degrees and mirrored, ``spaced``: "the global alignment is inconsistent";
that refusal stands: a refused detection is not run again, :func:`layouts_to_retry`).
:func:`layouts_to_retry` names the layouts to try again then, and :func:`prefer` decides
between two detections.
"""

from __future__ import annotations

import numpy as np

from oapcal.imaging.detect.warp import PolyWarp

#: Corners needed before the layouts are compared (a cubic map has 10 terms per coordinate).
MIN_CORNERS = 40
#: The layout the corners were detected in is questioned only when its cubic map leaves
#: more than this rms (px): detected in the right layout, the corners of real micrographs
#: rendered through aligned and misaligned relays leave 0.03-0.05 px.
SUSPECT_RMS_PX = 0.15
#: ... and another layout must leave at most this fraction of that rms for a detection in
#: it to be kept over the one in the layout questioned (:func:`prefer`) ...
BETTER_RATIO = 0.5
#: ... and at most this fraction for the detection to run again in it (:func:`layouts_to_retry`;
#: :func:`prefer` then decides on the corners that run finds).  Milder than
#: :data:`BETTER_RATIO`: corners detected in a wrong layout carry its error, so even the
#: right layout fits them only so well (measured: the real FPM micrograph through the
#: aligned relay, turned by 15 degrees, detected in ``whole-target``: 0.40 px against
#: ``compact``'s 0.20, a ratio of 0.503; detected in ``compact`` itself its corners leave
#: 0.03 px).  A run too many costs time, never an id.
RETRY_RATIO = 0.75


def _element(cid: str) -> str:
    return cid[: min(k for k in (cid.find("H"), cid.find("V")) if k > 0)]


def layout_residuals(ids, xy_d, groups, layouts) -> dict:
    """The rms (px, vector length) of the cubic map from each layout's corner positions (um)
    to the detected ones ``xy_d`` of corners ``ids``: ``{layout: rms}``; empty when the
    corners are too few (:data:`MIN_CORNERS`) or lie in one element (where the layouts agree)."""
    from oapcal.imaging.usaf import usaf_target

    ids = list(ids)
    xy_d = np.asarray(xy_d, float).reshape(-1, 2)
    if len(ids) < MIN_CORNERS or len({_element(c) for c in ids}) < 2:
        return {}
    out = {}
    for layout in layouts:
        target = usaf_target(groups, layout_name=layout)
        index = {c: k for k, c in enumerate(target.corner_ids)}
        if any(c not in index for c in ids):
            continue
        um = target.corners_um[[index[c] for c in ids]]
        r = PolyWarp.fit(um, xy_d, 3)(um) - xy_d
        out[layout] = float(np.sqrt(np.mean(np.sum(r**2, axis=1))))
    return out


def better_layout(ids, xy_d, groups, current, layouts, ratio: float = BETTER_RATIO) -> tuple:
    """``(layout, residuals)``: a layout whose cubic map fits the detected corners clearly
    better than ``current``'s (its rms at most ``ratio`` times ``current``'s, which leaves
    more than :data:`SUSPECT_RMS_PX`; module docstring; None when ``current`` fits them,
    when no other does clearly better, or when the corners cannot tell) and the residuals of
    :func:`layout_residuals`."""
    rms = layout_residuals(ids, xy_d, groups, layouts)
    if current not in rms or rms[current] <= SUSPECT_RMS_PX:
        return None, rms
    best = min(rms, key=rms.get)
    if best == current or rms[best] > ratio * rms[current]:
        return None, rms
    return best, rms


#: A detection that keeps less than this fraction of the resolved corners it expects in view
#: (:func:`resolved_coverage`) is run again in the other layouts (``layouts_to_retry``);
#: right layouts keep 90-100 % on the renders of real micrographs through aligned and
#: misaligned relays.
RETRY_COVERAGE = 0.8
#: Corners of bars at least this wide (px) count for the retry (wider than the 2 px from
#: which detection expects a corner, ``core.RESOLVED_BAR_PX``): narrower ones are often
#: lost to blur in a right layout too (the real LAB-UMK micrograph's group 6, 2.2 px and
#: less, 235 of 547 corners in view dropped by a right registration).
WIDE_BAR_PX = 2.5


def resolved_coverage(det, groups) -> float:
    """The fraction of the corners ``det`` expected in view (``det.predicted``) whose bars are
    at least :data:`WIDE_BAR_PX` wide that it kept (1.0 when it expected none)."""
    from oapcal.imaging.usaf import usaf_target

    target = usaf_target(groups)
    width = dict(zip(target.corner_ids, target.corner_width_um))
    scale = float(det.um_per_px)
    wide = [c for c in det.predicted if c in width and width[c] / scale >= WIDE_BAR_PX]
    if not wide or not np.isfinite(scale):
        return 1.0
    kept = set(det.ids)
    return sum(c in kept for c in wide) / len(wide)


#: ... and another layout's detection is preferred when it keeps this many times the corners.
MORE_CORNERS = 1.2


def layouts_to_retry(det, groups, current, layouts) -> tuple[list, dict]:
    """``(layouts, residuals)``: the layouts to run the detection ``det`` (found in layout
    ``current``) again in, and the residuals of its corners (:func:`layout_residuals`):
    the one that fits its corners better (:func:`better_layout` at :data:`RETRY_RATIO`); else, when it kept
    too few of the resolved corners (:func:`resolved_coverage`, :data:`RETRY_COVERAGE`),
    every other layout; else none.  A refused detection is not run again: its refusal
    (e.g. two registrations that disagree) is evidence against the image as much as
    against the layout (measured: a misaligned relay, target turned by 45 degrees and
    mirrored, refused in the layout the pose chose, was accepted in another with 119
    corners of group 4 alone, 9 of them 0.5-0.8 px off)."""
    if not det.ok:
        return [], {}
    others = [name for name in layouts if name != current]
    choice, rms = better_layout(det.ids, det.xy_d, groups, current, layouts, RETRY_RATIO)
    if choice is not None:
        return [choice], rms
    return (others if resolved_coverage(det, groups) < RETRY_COVERAGE else []), rms


def _own_residual(det, groups, name) -> float:
    """The rms (px) of ``det``'s corners against layout ``name`` (0 when they cannot tell)."""
    return layout_residuals(det.ids, det.xy_d, groups, [name]).get(name, 0.0)


def prefer(new, new_layout, old, old_layout, groups) -> bool:
    """Whether detection ``new`` (in layout ``new_layout``) is kept rather than ``old``: it
    found the target, its corners follow its layout (within :data:`SUSPECT_RMS_PX`, or better
    than ``old``'s follow theirs), and ``old`` failed, or its corners fit its own layout
    clearly worse (:data:`BETTER_RATIO`), or it kept clearly fewer corners (:data:`MORE_CORNERS`)."""
    if not new.ok:
        return False
    r_new = _own_residual(new, groups, new_layout)
    if not old.ok:
        return r_new <= SUSPECT_RMS_PX
    r_old = _own_residual(old, groups, old_layout)
    if r_new > max(SUSPECT_RMS_PX, r_old):
        return False
    clearly_better = r_old > SUSPECT_RMS_PX and r_new <= BETTER_RATIO * r_old
    return clearly_better or len(new.ids) >= MORE_CORNERS * len(old.ids)
