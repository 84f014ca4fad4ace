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
refine the proposal.

Real targets differ in how far apart their elements are drawn (the layouts of
:data:`oapcal.imaging.usaf.LAYOUTS`); the map is fitted in each layout and the one the clicks
fit best is kept (a wrong layout puts the clicked corners several px off any affine map and
its scale 15 % off on the LAB-UMK target).  The scale is that of the affine map through the
clicks (their mean scale, as detection measures it), also when the proposal's map is
quadratic: the quadratic map's slope at one point is the local scale there, which a
distorted field moves away from the mean.

Without refinement the clicked corners are kept where they were clicked (``clicked``).  With
it (:func:`refine_with_detection`) only the corners that detection found enter the pairs, at
detection's sub-pixel positions; a clicked or proposed corner that detection did not find is
left out and named (``dropped``): a click is a few px off (the LAB-UMK clicks were 5-19 px
off), which a fit would take as distortion.  OpenCV's ``cornerSubPix`` was measured as a
refinement of such clicks and does not serve: on the demo image, from clicks 0.7-3 px off,
it left half of them where they were and moved the others to a median 0.3 px from the
corner (the bar's other edges fall into any window wider than half a bar).
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
    when an id was mistyped); ``layout`` the target layout the clicks fit best (or detection
    found) and ``dropped`` the ids left out by :func:`refine_with_detection`."""

    ids: tuple[str, ...]
    xy_u: np.ndarray
    xy_d: np.ndarray
    clicked: np.ndarray
    um_per_px: float
    orientation: str
    mirrored: bool
    map_kind: str
    click_rms_px: float
    layout: str = "compact"
    dropped: tuple[str, ...] = ()


def propose_corners(
    clicks: dict[str, tuple[float, float]],
    image_size: tuple[int, int],
    groups=(4, 5),
    um_per_px: float | None = None,
    layout: str | None = None,
) -> Proposal:
    """Propose every corner of ``groups`` from ``clicks`` (id -> image x, y px) in an image
    of ``image_size = (width, height)`` px (module docstring), in the target ``layout``
    (:data:`oapcal.imaging.usaf.LAYOUTS`; None or ``"auto"``: the one the clicks fit best).
    Raises :class:`~oapcal.errors.DataError` naming what is wrong with the clicks."""
    from oapcal.imaging import usaf

    groups = usaf.parse_groups(groups)
    names = list(usaf.LAYOUTS) if layout in (None, "auto") else [usaf.layout(layout).name]
    fits = [_fit_clicks(clicks, groups, name) for name in names]
    # the layout whose affine map fits the clicks best (a quadratic map through a few clicks
    # absorbs part of a wrong layout's spacing); on a tie (3 clicks fit every layout exactly)
    # the first, the default layout
    best = min(fits, key=lambda f: round(f["affine_rms"], 6))
    target, warp, index = best["target"], best["warp"], best["index"]
    linear = best["affine"]
    det = float(np.linalg.det(linear))
    found_um_per_px = 1.0 / np.sqrt(abs(det))
    scale = float(um_per_px) if um_per_px else float(found_um_per_px)
    orientation = usaf.nearest_orientation(linear)
    w, h = int(image_size[0]), int(image_size[1])

    predicted = warp(target.corners_um)
    inside = (
        (predicted[:, 0] >= MARGIN_PX) & (predicted[:, 0] <= w - 1 - MARGIN_PX)
        & (predicted[:, 1] >= MARGIN_PX) & (predicted[:, 1] <= h - 1 - MARGIN_PX)
        & (target.corner_width_um / found_um_per_px >= RESOLVED_BAR_PX)
    )  # fmt: skip
    clicked = np.zeros(len(target.corner_ids), bool)
    for i in clicks:
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
        map_kind="quadratic" if warp.degree == 2 else "affine",
        click_rms_px=best["rms"],
        layout=target.layout,
    )


def _fit_clicks(clicks: dict, groups, layout: str) -> dict:
    """The map of the target in ``layout`` through the clicks: ``target``, ``index`` (id ->
    corner), ``warp`` (affine, or quadratic from :data:`QUADRATIC_FROM` clicks), ``rms``
    (the clicks' RMS distance from it, px), ``affine_rms`` (from the affine map) and
    ``affine`` (d px / d um of the affine map, 2 x 2: its scale is the clicks' mean scale)."""
    import oapcal

    target = oapcal.usaf_target(groups, layout)
    index = {i: k for k, i in enumerate(target.corner_ids)}
    unknown = sorted(set(clicks) - set(index))
    if unknown:
        raise DataError(
            f"unknown corner id {unknown[0]!r} for groups {groups}: ids look like "
            f"{target.corner_ids[0]} (group, element, H/V triplet, bar 0-2, corner 0-3)"
        )
    if len(clicks) < 3:
        raise DataError(f"click at least 3 corners with their ids ({len(clicks)} so far)")
    um = target.corners_um[[index[i] for i in clicks]]
    px = np.array(list(clicks.values()), float)
    centre = um.mean(axis=0)
    spread = float(np.abs(um - centre).max()) or 1.0
    uv = (um - centre) / spread
    if np.linalg.matrix_rank(uv - uv.mean(axis=0), tol=1e-6) < 2:
        raise DataError(
            "the clicked corners lie on one line of the target: click corners of bars in 2 directions"
        )
    affine = PolyWarp.fit(um, px, 1, centre, spread)
    linear = affine.coef[1:3].T / spread  # d px / d um (2x2)
    if not np.isfinite(np.linalg.det(linear)) or abs(np.linalg.det(linear)) < 1e-12:
        raise DataError("the clicked corners do not fix a map of the target (degenerate)")
    warp = PolyWarp.fit(um, px, 2, centre, spread) if len(clicks) >= QUADRATIC_FROM else affine
    rms = [float(np.sqrt(np.mean(np.sum((m(um) - px) ** 2, -1)))) for m in (warp, affine)]
    return {"target": target, "index": index, "warp": warp, "rms": rms[0], "affine_rms": rms[1],
            "affine": linear}  # fmt: skip


def refine_with_detection(
    proposal: Proposal, detection, image_size: tuple[int, int], groups, um_per_px: float | None = None
) -> Proposal:
    """The corners that ``detection`` (run with the proposal's scale, orientation and mirror
    as hints) found, at their detected sub-pixel positions; every clicked or proposed corner
    it did not find is left out and named in ``dropped`` (module docstring).  The reference
    points are those of the detection's layout and orientation at ``um_per_px`` (the user's
    scale) or, without one, the pixel size that detection measured from its corners (the
    scale of the clicks was only its hint).  A detection that failed leaves the proposal as
    it was."""
    import oapcal

    if detection.status != 0 or not len(detection.ids):
        return proposal
    measured = (detection.pixel_size or {}).get("um_per_px")
    scale = float(um_per_px or measured or detection.um_per_px)
    target = oapcal.usaf_target(groups, detection.pose.get("layout"))
    ref = dict(zip(target.corner_ids, target.reference_px(scale, image_size, detection.orientation)))
    ids = list(detection.ids)
    found = set(ids)
    return Proposal(
        ids=tuple(ids),
        xy_u=np.array([ref[i] for i in ids]),
        xy_d=np.asarray(detection.xy_d, float),
        clicked=np.zeros(len(ids), bool),
        um_per_px=scale,
        orientation=detection.orientation,
        mirrored=proposal.mirrored,
        map_kind=proposal.map_kind + "+detection",
        click_rms_px=proposal.click_rms_px,
        layout=target.layout,
        dropped=tuple(i for i in proposal.ids if i not in found),
    )
