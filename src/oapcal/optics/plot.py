"""Figures of a traced relay: grid distortion arrows and spot diagrams (Matplotlib, Agg)."""

from __future__ import annotations

import numpy as np

from oapcal.io.atomic import atomic_path


def plot_grid(grid, path, *, units: str = "mm", pixel_size_um: float = 4.8, max_side: int = 33) -> None:
    """Arrows from paraxial to real image points, coloured by distortion normalised by the
    field radius (the largest paraxial distance from the axis), in percent.  The image is
    drawn as a camera shows it: x to the right, y down.  Grids larger than ``max_side``
    points a side are drawn on a regular subgrid (border included) so arrows stay legible;
    the title's max and mean are over every point."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scale = 1.0 if units == "mm" else 1e3 / pixel_size_um
    radius = np.hypot(*grid.xy_u.T).max()
    use = np.arange(len(grid.xy_u))
    shown = grid.n
    if grid.n > max_side:
        k = np.unique(np.round(np.linspace(0, grid.n - 1, int(max_side))).astype(int))
        use = (k[:, None] * grid.n + k[None, :]).ravel()
        shown = len(k)
    u = grid.xy_u[use] * scale
    d = grid.xy_d[use] * scale
    colour = 100.0 * grid.distortion[use] / radius
    fig, ax = plt.subplots(figsize=(6.4, 5.6), layout="constrained")
    arrows = ax.quiver(
        u[:, 0], u[:, 1], d[:, 0] - u[:, 0], d[:, 1] - u[:, 1], colour,
        angles="xy", scale_units="xy", scale=1.0, cmap="viridis", width=0.004,
    )  # fmt: skip
    ax.plot(u[:, 0], u[:, 1], ".", color="0.5", markersize=2)
    fig.colorbar(arrows, ax=ax, label=f"|real - paraxial| / field radius {radius * scale:.4g} {units} (%)")
    ax.set_xlabel(f"x image ({units})")
    ax.set_ylabel(f"y image ({units})")
    both = np.concatenate([u, d])
    both = both[np.isfinite(both).all(axis=1)]
    lo, hi = both.min(axis=0), both.max(axis=0)
    pad = 0.04 * (hi - lo).max()
    ax.set_xlim(lo[0] - pad, hi[0] + pad)
    ax.set_ylim(hi[1] + pad, lo[1] - pad)  # y down, as a camera shows the image
    ax.set_aspect("equal")
    relay = grid.relay
    ax.set_title(
        f"Grid distortion, d1 = {relay.d1_mm:g} mm, orientation {relay.orientation}, "
        f"{grid.n}x{grid.n} over {grid.field_mm:g} mm"
        + (f" (arrows: {shown}x{shown} subgrid)" if shown != grid.n else "")
        + f"\nmax {grid.distortion.max() * 1e3:.1f} um, "
        f"mean {grid.distortion.mean() * 1e3:.1f} um (arrows: paraxial -> real)",
        fontsize=9,
    )
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=120)
    plt.close(fig)


def plot_spots(spots: dict, path, *, airy_radius_um: float | None = None) -> None:
    """Spot diagrams: one row per orientation, one column per field point, all on the
    same scale (um, relative to the chief ray), with the Airy radius as a circle."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    keys = list(spots)
    n_col = max(len(v) for v in spots.values())
    extent = max(np.abs(s.xy_um[s.clear]).max() for row in spots.values() for s in row) * 1.1 or 1.0
    fig, axes = plt.subplots(len(keys), n_col, figsize=(2.6 * n_col, 2.7 * len(keys)), squeeze=False,
                             layout="constrained")  # fmt: skip
    for i, key in enumerate(keys):
        for j, spot in enumerate(spots[key]):
            ax = axes[i, j]
            xy = spot.xy_um[spot.clear]
            ax.plot(xy[:, 0], xy[:, 1], ".", markersize=2)
            if airy_radius_um:
                ax.add_patch(plt.Circle((0, 0), airy_radius_um, fill=False, color="k", lw=0.8))
            ax.set_xlim(-extent, extent)
            ax.set_ylim(extent, -extent)
            ax.set_aspect("equal")
            fx, fy = spot.field_mm
            ax.set_title(f"{key}: field ({fx:g}, {fy:g}) mm\nRMS {spot.rms_um:.2f} um", fontsize=8)
            ax.set_xlabel("x (um)", fontsize=8)
            ax.set_ylabel("y (um)", fontsize=8)
            ax.tick_params(labelsize=7)
    fig.suptitle("Spot diagrams (circle: Airy radius)", fontsize=10)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=120)
    plt.close(fig)
