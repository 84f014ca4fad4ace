"""Pictures of simulated images, detected corners and corrected images (Matplotlib, Agg)."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def plot_image(
    image: np.ndarray,
    path: str | Path,
    *,
    title: str,
    points: dict | None = None,
    crop: np.ndarray | None = None,
    units: str = "grey level (DN)",
) -> None:
    """Save ``image`` with optional marker sets ``points`` (label -> ``(N, 2)`` px) to ``path``.

    ``crop`` ``(x0, y0, x1, y1)`` limits the axes.  Axes in px with the pixel-centre
    convention of ``docs/conventions.md``; a colour bar shows the grey levels.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from oapcal.io.atomic import atomic_path

    h, w = image.shape[:2]
    fig, ax = plt.subplots(figsize=(6.4, 4.6), dpi=100)
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
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp)
    plt.close(fig)
