"""Pictures of simulated images, detected corners and corrected images.

Each figure is built with :func:`oapcal.report.plots.new_figure` (a ``Figure`` with its own
Agg canvas: no pyplot state, the caller's Matplotlib backend is left as it is) and written
atomically with :func:`oapcal.report.plots.save_figure`.  Axes are in px with the
pixel-centre convention of ``docs/conventions.md``.
"""

from __future__ import annotations

import textwrap
from pathlib import Path

import numpy as np

from oapcal.report.plots import new_figure, save_figure


def image_figure(
    image: np.ndarray,
    *,
    title: str,
    points: dict | None = None,
    crop: np.ndarray | None = None,
    units: str = "grey level (DN)",
):
    """``image`` with optional marker sets ``points`` (label -> ``(N, 2)`` px).

    ``crop`` ``(x0, y0, x1, y1)`` limits the axes; a colour bar shows the grey levels.
    """
    h, w = image.shape[:2]
    fig = new_figure(6.4, 4.6, dpi=100)
    ax = fig.add_subplot()
    im = ax.imshow(image, cmap="gray", extent=(-0.5, w - 0.5, h - 0.5, -0.5), interpolation="nearest")
    fig.colorbar(im, ax=ax, label=units, shrink=0.85)
    styles = [("+", "tab:red"), ("x", "tab:cyan"), ("o", "tab:orange")]
    for (label, xy), (marker, colour) in zip((points or {}).items(), styles):
        xy = np.asarray(xy, float).reshape(-1, 2)
        ax.plot(xy[:, 0], xy[:, 1], marker, color=colour, ms=4, mew=0.8, ls="none", label=label)
    if points:
        ax.legend(loc="lower left", fontsize=7, framealpha=0.8)
    if crop is not None:
        ax.set_xlim(crop[0], crop[2])
        ax.set_ylim(crop[3], crop[1])
    ax.set_xlabel("x (px)")
    ax.set_ylabel("y (px)")
    ax.set_title(title, fontsize=10)
    return fig


def plot_image(
    image: np.ndarray,
    path: str | Path,
    *,
    title: str,
    points: dict | None = None,
    crop: np.ndarray | None = None,
    units: str = "grey level (DN)",
) -> None:
    """Save :func:`image_figure` to ``path`` (atomically; the format follows the suffix)."""
    save_figure(image_figure(image, title=title, points=points, crop=crop, units=units), path)


def detection_figure(image: np.ndarray, det, *, groups: str = ""):
    """A detection, successful or not: the image, the bar triplets found (circles), the best
    pose's prediction of the named groups' triplets (boxes; dashed for a rival pose the
    detection could not rule out), the detected corners, and the outcome (or the reason for
    the refusal) as the title."""
    from matplotlib.patches import Circle

    h, w = image.shape[:2]
    fig = new_figure(7.2, 6.0, dpi=100)
    ax = fig.add_subplot()
    ax.imshow(image, cmap="gray", extent=(-0.5, w - 0.5, h - 0.5, -0.5), interpolation="nearest")
    dbg = getattr(det, "debug", {}) or {}
    trips = dbg.get("image_triplets")
    if trips is not None and len(trips):
        for (x, y), wd in zip(trips.centre, trips.width):
            ax.add_patch(Circle((x, y), max(2.5 * wd, 3.0), fill=False, color="tab:cyan", lw=0.7))
        ax.plot([], [], "o", mfc="none", color="tab:cyan", label=f"bar triplets found ({len(trips)})")
    ref = dbg.get("ref")
    for key, style, label in (("pose", "-", "best pose"), ("runner_up", "--", "rival pose")):
        pose = dbg.get(key)
        if pose is None or ref is None or (key == "runner_up" and det.status == 0):
            continue
        colour = "tab:orange" if key == "pose" else "tab:purple"
        for j in range(len(ref.width)):
            if ref.width[j] * pose.s < 1.5:
                continue
            half = 2.5 * ref.width[j]
            corners = np.array([[-half, -half], [half, -half], [half, half], [-half, half], [-half, -half]])
            xy = pose.apply(ref.centre[j] + corners)
            if (xy[:, 0].max() < 0) or (xy[:, 0].min() > w) or (xy[:, 1].max() < 0) or (xy[:, 1].min() > h):
                continue
            ax.plot(xy[:, 0], xy[:, 1], style, color=colour, lw=0.6)
        mirrored = ", mirrored" if pose.mirrored else ""
        ax.plot([], [], style, color=colour,
                label=f"{label}: {1 / pose.s:.4g} um/px, {pose.angle_deg:.1f} deg{mirrored}")  # fmt: skip
    if len(det.ids):
        ax.plot(det.xy_d[:, 0], det.xy_d[:, 1], "+", color="tab:red", ms=4, mew=0.8, ls="none",
                label=f"corners kept ({len(det.ids)})")  # fmt: skip
    ax.set_xlim(-0.5, w - 0.5)
    ax.set_ylim(h - 0.5, -0.5)
    if ax.get_legend_handles_labels()[0]:
        ax.legend(loc="lower left", fontsize=7, framealpha=0.8)
    ax.set_xlabel("x (px)")
    ax.set_ylabel("y (px)")
    if det.status == 0:
        title = f"{len(det.ids)} corners detected (groups {groups}), {det.um_per_px:.4g} um/px"
    else:
        title = "refused: " + det.message
    ax.set_title("\n".join(textwrap.wrap(title, 90)), fontsize=8)
    return fig


def plot_detection(image: np.ndarray, det, path: str | Path, *, groups: str = "") -> None:
    """Save :func:`detection_figure` to ``path`` (atomically; the format follows the suffix)."""
    save_figure(detection_figure(image, det, groups=groups), path)
