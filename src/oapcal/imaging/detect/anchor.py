"""Anchors: elements of the USAF-1951 target that the user names (``docs/detection.md``).

A user who can read one element's printed numbers on screen names it, ``G6E3`` (group 6,
element 3), optionally one of its triplets (``G6E3H``, ``G6E3V``) and where it is in the
image (``G6E3@512,300``: camera px, x then y, a point on or between its bars).  The pose
search then tries only poses that lay that element of the target onto a bar triplet of
the image (so the scale and the one-element and two-group slips are decided by the name),
and keeps only poses that honour every anchor: the named triplet matched to an image
triplet and, with a position, the element predicted there.  What the name leaves open (a
mirror, a half turn, for one element in view) the layout must still decide, else the
detection is refused, saying what would decide it.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np

from oapcal.errors import DataError

_ANCHOR = re.compile(
    r"^\s*G(?P<g>-?[0-9]+)E(?P<e>[1-6])(?P<o>[HV])?"
    r"(?:@(?P<x>[-+]?[0-9]*\.?[0-9]+(?:[eE][-+]?[0-9]+)?),(?P<y>[-+]?[0-9]*\.?[0-9]+(?:[eE][-+]?[0-9]+)?))?\s*$"
)
#: A positioned anchor is honoured when the pose puts its element's centre within this many
#: of the element's bar widths of the point (an element is 5 w wide and 12 w long: a point
#: anywhere on its bars is within about 6.5 w of its centre).
POSITION_TOL_W = 7.0
#: Groups an anchor may name (the whole target the pose search knows).
ANCHOR_GROUPS = (-2, 9)


@dataclass(frozen=True)
class Anchor:
    """One named element: ``group``, ``element``, ``orient`` (``"H"``, ``"V"`` or None: either
    triplet) and ``xy`` (camera px, or None: anywhere in the image)."""

    group: int
    element: int
    orient: str | None = None
    xy: tuple[float, float] | None = None

    @property
    def name(self) -> str:
        return f"G{self.group}E{self.element}{self.orient or ''}"

    def text(self) -> str:
        """The anchor as it is written (``G6E3``, ``G6E3H@512,300``)."""
        at = f"@{self.xy[0]:.0f},{self.xy[1]:.0f}" if self.xy is not None else ""
        return self.name + at


def parse_anchor(text) -> Anchor:
    """``"G6E3"``, ``"G6E3V"``, ``"G6E3@512,300"`` (an :class:`Anchor` is returned as is)."""
    if isinstance(text, Anchor):
        return text
    m = _ANCHOR.match(str(text))
    if m is None:
        raise DataError(
            f"anchors: {text!r} is not an element name; write G<group>E<element>, e.g. G6E3, optionally "
            f"H or V for one of its triplets and @x,y for where it is (camera px), e.g. G6E3@512,300",
            param="anchors",
        )
    g = int(m["g"])
    if not ANCHOR_GROUPS[0] <= g <= ANCHOR_GROUPS[1]:
        raise DataError(
            f"anchors: {text!r}: group {g} is not on the target "
            f"(groups {ANCHOR_GROUPS[0]} to {ANCHOR_GROUPS[1]})",
            param="anchors",
        )
    xy = None
    if m["x"] is not None:
        xy = (float(m["x"]), float(m["y"]))
        if not np.isfinite(xy).all():
            raise DataError(f"anchors: {text!r}: the position must be finite camera px", param="anchors")
    return Anchor(g, int(m["e"]), m["o"], xy)


def parse_anchors(anchors) -> tuple[Anchor, ...]:
    """A tuple of :class:`Anchor` from None, one text or a sequence of texts / anchors;
    the same element named twice is refused."""
    if anchors is None:
        return ()
    if isinstance(anchors, (str, Anchor)):
        anchors = [anchors]
    out = tuple(parse_anchor(a) for a in anchors)
    seen = set()
    for a in out:
        if a.name in seen:
            raise DataError(f"anchors: {a.name} is named twice; name each element once", param="anchors")
        seen.add(a.name)
    return out


def anchor_triplets(anchor: Anchor, ref) -> np.ndarray:
    """Indices of the reference triplets (:class:`~oapcal.imaging.detect.pose.RefTriplets`)
    that ``anchor`` names (one or both triplets of its element)."""
    k = (ref.group == anchor.group) & (ref.element == anchor.element)
    if anchor.orient is not None:
        k &= ref.orient == anchor.orient
    return np.flatnonzero(k)


def honours(pose, ref, anchors, image_triplets=None) -> bool:
    """Whether ``pose`` honours every anchor: one of the named triplets is matched to an
    image triplet and, for an anchor with a position, the named element's centre lies within
    :data:`POSITION_TOL_W` of its bar widths of that point.  The centre is predicted from the
    matched image triplet (``image_triplets``) through the pose's linear part, so that a
    distortion of tens of px over the field does not move it; without the image triplets,
    from the pose alone."""
    if not anchors:
        return True
    matched = {j: i for i, j in pose.matches}
    for a in anchors:
        js = [int(j) for j in anchor_triplets(a, ref) if int(j) in matched]
        if not js:
            return False
        if a.xy is not None:
            k = (ref.group == a.group) & (ref.element == a.element)
            centre_um = ref.centre[k].mean(axis=0)
            w_px = float(ref.width[k][0]) * pose.s
            if image_triplets is not None:
                j = js[0]
                centre_px = image_triplets.centre[matched[j]] + pose.matrix() @ (centre_um - ref.centre[j])
            else:
                centre_px = pose.apply(centre_um[None])[0]
            if np.hypot(*(centre_px - np.asarray(a.xy))) > POSITION_TOL_W * w_px:
                return False
    return True


def seed_mask(anchor: Anchor, ref, img) -> np.ndarray:
    """(image triplets, reference triplets) pairs a pose may be seeded from for ``anchor``:
    the named triplets against every image triplet, or only those near its position."""
    mask = np.zeros((len(img), len(ref.width)), bool)
    js = anchor_triplets(anchor, ref)
    near = np.ones(len(img), bool)
    if anchor.xy is not None:
        d = np.hypot(*(img.centre - np.asarray(anchor.xy)).T)
        # the element's far triplet centre is about 7 w from any point on its bars
        near = d <= (POSITION_TOL_W + 1.0) * img.width
    mask[np.ix_(near, js)] = True
    return mask
