"""Labelling by hand: register the USAF-1951 target from a few clicked corners and propose
the others (the *Label by hand* widget; no napari here).

oapcal's detection (:func:`oapcal.detect_usaf`) has no entry that starts from given
point matches, so this is the smallest honest version: the clicked corners (each with its
id, e.g. ``G4E1H0C0``) fix a map from the target (object um,
:func:`oapcal.usaf_target`) to the image, by least squares: affine from 3 corners,
quadratic from :data:`QUADRATIC_FROM` on (it follows the relay's distortion better).
Every other corner of the given groups is proposed where that map puts it, if it lies
inside the image and its bars are resolved.  The map's scale and orientation give the
reference points in detection's convention (:meth:`oapcal.imaging.usaf.UsafTarget.reference_px`:
target centre at the image centre, nearest of the 8 orientations) and hints for
:func:`oapcal.detect_usaf` (scale, orientation, mirror), which the widget can run to
refine the proposal.  The clicked corners are kept where they were clicked.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from oapcal.errors import DataError
from oapcal.imaging.detect.warp import PolyWarp

#: From this many clicked corners the map is quadratic instead of affine.
QUADRATIC_FROM = 10
#: Proposed corners must be this far inside the image (px).
MARGIN_PX = 2.0
#: Corners of bars narrower than this (image px) are not proposed.
RESOLVED_BAR_PX = 1.0


@dataclass(frozen=True)
class Proposal:
    """All corners proposed from the clicks: ``ids``, ``xy_u`` (reference px at
    ``um_per_px``, oriented), ``xy_d`` (image px: clicked or predicted), ``clicked`` (bool
    per corner); ``um_per_px`` (given, or the clicks' scale), ``orientation`` and
    ``mirrored`` of the target in the image, ``map_kind`` (``"affine"``/``"quadratic"``)
    and ``click_rms_px``, the RMS distance of the clicked corners from the fitted map (large
    when an id was mistyped)."""

    ids: tuple[str, ...]
    xy_u: np.ndarray
    xy_d: np.ndarray
    clicked: np.ndarray
    um_per_px: float
    orientation: str
    mirrored: bool
    map_kind: str
    click_rms_px: float


def propose_corners(
    clicks: dict[str, tuple[float, float]],
    image_size: tuple[int, int],
    groups=(4, 5),
    um_per_px: float | None = None,
) -> Proposal:
    """Propose every corner of ``groups`` from ``clicks`` (id -> image x, y px) in an image
    of ``image_size = (width, height)`` px (module docstring).  Raises
    :class:`~oapcal.errors.DataError` naming what is wrong with the clicks."""
    import oapcal
    from oapcal.imaging.usaf import nearest_orientation, parse_groups

    groups = parse_groups(groups)
    target = oapcal.usaf_target(groups)
    index = {i: k for k, i in enumerate(target.corner_ids)}
    unknown = sorted(set(clicks) - set(index))
    if unknown:
        raise DataError(
            f"unknown corner id {unknown[0]!r} for groups {groups}: ids look like "
            f"{target.corner_ids[0]} (group, element, H/V triplet, bar 0-2, corner 0-3)"
        )
    if len(clicks) < 3:
        raise DataError(f"click at least 3 corners with their ids ({len(clicks)} so far)")
    ids = list(clicks)
    um = target.corners_um[[index[i] for i in ids]]
    px = np.array([clicks[i] for i in ids], float)
    centre = um.mean(axis=0)
    spread = float(np.abs(um - centre).max()) or 1.0
    uv = (um - centre) / spread
    if np.linalg.matrix_rank(uv - uv.mean(axis=0), tol=1e-6) < 2:
        raise DataError(
            "the clicked corners lie on one line of the target: click corners of bars in 2 directions"
        )
    quadratic = len(ids) >= QUADRATIC_FROM
    warp = PolyWarp.fit(um, px, 2 if quadratic else 1, centre, spread)
    click_rms = float(np.sqrt(np.mean(np.sum((warp(um) - px) ** 2, -1))))
    linear = warp.coef[1:3].T / spread  # d px / d um at the clicks' centre (2x2)
    det = float(np.linalg.det(linear))
    if not np.isfinite(det) or abs(det) < 1e-12:
        raise DataError("the clicked corners do not fix a map of the target (degenerate)")
    found_um_per_px = 1.0 / np.sqrt(abs(det))
    scale = float(um_per_px) if um_per_px else float(found_um_per_px)
    orientation = nearest_orientation(linear)
    w, h = int(image_size[0]), int(image_size[1])

    predicted = warp(target.corners_um)
    inside = (
        (predicted[:, 0] >= MARGIN_PX) & (predicted[:, 0] <= w - 1 - MARGIN_PX)
        & (predicted[:, 1] >= MARGIN_PX) & (predicted[:, 1] <= h - 1 - MARGIN_PX)
        & (target.corner_width_um / found_um_per_px >= RESOLVED_BAR_PX)
    )  # fmt: skip
    clicked = np.zeros(len(target.corner_ids), bool)
    for i in ids:
        clicked[index[i]] = True
        predicted[index[i]] = clicks[i]
    keep = inside | clicked
    xy_u = target.reference_px(scale, (w, h), orientation)
    return Proposal(
        ids=tuple(np.asarray(target.corner_ids, object)[keep]),
        xy_u=xy_u[keep],
        xy_d=predicted[keep],
        clicked=clicked[keep],
        um_per_px=scale,
        orientation=orientation,
        mirrored=det < 0,
        map_kind="quadratic" if quadratic else "affine",
        click_rms_px=click_rms,
    )


def refine_with_detection(proposal: Proposal, detection, image_size: tuple[int, int], groups) -> Proposal:
    """The proposal with every corner that ``detection`` (run with the proposal's scale,
    orientation and mirror as hints) found at its detected position; corners it did not find
    stay as clicked or proposed.  The reference points of all corners are then those of the
    detection's scale and orientation."""
    import oapcal

    if detection.status != 0 or not len(detection.ids):
        return proposal
    target = oapcal.usaf_target(groups)
    ref = dict(
        zip(target.corner_ids, target.reference_px(detection.um_per_px, image_size, detection.orientation))
    )
    found = dict(zip(detection.ids, np.asarray(detection.xy_d, float)))
    ids = list(proposal.ids) + [i for i in detection.ids if i not in set(proposal.ids)]
    old = dict(zip(proposal.ids, proposal.xy_d))
    clicked = dict(zip(proposal.ids, proposal.clicked))
    xy_d = np.array([found[i] if i in found else old[i] for i in ids])
    return Proposal(
        ids=tuple(ids),
        xy_u=np.array([ref[i] for i in ids]),
        xy_d=xy_d,
        clicked=np.array([bool(clicked.get(i, False)) and i not in found for i in ids]),
        um_per_px=float(detection.um_per_px),
        orientation=detection.orientation,
        mirrored=proposal.mirrored,
        map_kind=proposal.map_kind + "+detection",
        click_rms_px=proposal.click_rms_px,
    )
