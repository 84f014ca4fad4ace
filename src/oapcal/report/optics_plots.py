"""Figures of a traced relay: grid distortion arrows, spot diagrams, the tolerancing
figure and the relay's layout in its fold plane.

Each ``*new_figure`` function returns a :class:`matplotlib.figure.Figure` with its own Agg
canvas (no pyplot state, the caller's backend untouched); each ``plot_*`` function draws
one and writes it as a PNG (120 dpi) atomically with :func:`oapcal.report.plots.save_figure`.
"""

from __future__ import annotations

import numpy as np

from oapcal.report.plots import new_figure, save_figure

#: Resolution of the written figures (dots per inch).
DPI = 120


def grid_figure(grid, *, units: str = "mm", pixel_size_um: float = 4.8, max_side: int = 33):
    """Arrows from paraxial to real image points, coloured by distortion normalised by the
    field radius (the largest paraxial distance from the axis), in percent.  The image is
    drawn as a camera shows it: x to the right, y down.  Grids larger than ``max_side``
    points a side are drawn on a regular subgrid (border included) so arrows stay legible;
    the title's max and mean are over every point."""
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
    fig = new_figure(6.4, 5.6, dpi=None)
    ax = fig.add_subplot()
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
    return fig


def spots_figure(spots: dict, *, airy_radius_um: float | None = None):
    """Spot diagrams: one row per orientation, one column per field point, all on the
    same scale (um, relative to the chief ray), with the Airy radius as a circle."""
    from matplotlib.patches import Circle

    keys = list(spots)
    n_col = max(len(v) for v in spots.values())
    extent = max(np.abs(s.xy_um[s.clear]).max() for row in spots.values() for s in row) * 1.1 or 1.0
    fig = new_figure(2.6 * n_col, 2.7 * len(keys), dpi=None)
    axes = fig.subplots(len(keys), n_col, squeeze=False)
    for i, key in enumerate(keys):
        for j, spot in enumerate(spots[key]):
            ax = axes[i, j]
            xy = spot.xy_um[spot.clear]
            ax.plot(xy[:, 0], xy[:, 1], ".", markersize=2)
            if airy_radius_um:
                ax.add_patch(Circle((0, 0), airy_radius_um, fill=False, color="k", lw=0.8))
            ax.set_xlim(-extent, extent)
            ax.set_ylim(extent, -extent)
            ax.set_aspect("equal")
            fx, fy = spot.field_mm
            ax.set_title(f"{key}: field ({fx:g}, {fy:g}) mm\nRMS {spot.rms_um:.2f} um", fontsize=8)
            ax.set_xlabel("x (um)", fontsize=8)
            ax.set_ylabel("y (um)", fontsize=8)
            ax.tick_params(labelsize=7)
    fig.suptitle("Spot diagrams (circle: Airy radius)", fontsize=10)
    return fig


def tolerance_figure(result: dict):
    """The tolerance figure of ``oapcal tolerance`` (``result`` its JSON object): the
    first-order rates per unit of every misalignment (log scale; zero rates omitted), and,
    with a Monte Carlo, the distributions of the corrected-image errors over the trials."""
    from oapcal.optics.tolerance import RESOLUTION_PX

    keys = ("field_change_mean_px", "corrected_mean_px", "recentred_mean_px")
    rows = [r for r in result["sensitivity"] if max(r[k] for k in keys) >= RESOLUTION_PX]
    mc = result.get("monte_carlo")
    n_panels = 2 if mc else 1
    fig = new_figure(6.0 * n_panels, 0.28 * len(rows) + 2.2, dpi=None)
    axes = fig.subplots(1, n_panels, squeeze=False)
    ax = axes[0, 0]
    y = np.arange(len(rows))
    series = (("field_change_mean_px", "distortion pattern change"),
              ("corrected_mean_px", "corrected-image error"),
              ("recentred_mean_px", "corrected error, recentred"))  # fmt: skip
    for k, (key, label) in enumerate(series):
        values = np.array([r[key] for r in rows])
        ax.barh(
            y + (k - 1) * 0.27, np.where(values >= RESOLUTION_PX, values, np.nan), height=0.27, label=label
        )
    ax.set_yticks(y, [f"{r['parameter']} (/{r['unit']})" for r in rows], fontsize=7)
    ax.invert_yaxis()
    ax.set_xscale("log")
    ax.set_xlabel(f"mean over the grid, camera px per unit (first order; rates < {RESOLUTION_PX:g} omitted)")
    ax.legend(fontsize=7, loc="lower right")
    ax.set_title("Sensitivity to each misalignment", fontsize=9)
    if mc:
        ax = axes[0, 1]
        for key, label in (("corrected_mean_px", "corrected, mean"), ("corrected_max_px", "corrected, max"),
                           ("recentred_mean_px", "recentred, mean")):  # fmt: skip
            values = np.array([s[key] for s in mc["samples"] if s[key] is not None])
            if values.size:
                ax.hist(values, bins=30, histtype="step", label=label)
        if "refit_mean_px" in mc["summary"]:
            values = np.array([s["refit_mean_px"] for s in mc["samples"] if s["refit_mean_px"] is not None])
            if values.size:
                ax.hist(values, bins=30, histtype="step", label="refit floor, mean")
        ax.set_xlabel("error over the grid (camera px)")
        ax.set_ylabel("trials")
        ax.legend(fontsize=7)
        ax.set_title(f"Monte Carlo, {mc['trials']} trials ({mc['distribution']})", fontsize=9)
    a = result["aligned"]
    fig.suptitle(f"Tolerancing: aligned distortion max {a['max_px']:.1f} px; {result['model']} calibration "
                 f"floor mean {a['corrected_mean_px']:.2f} px", fontsize=10)  # fmt: skip
    return fig


def layout_figure(relay, *, title: str | None = None):
    """The relay in its fold plane (``x = 0``; ``z`` to the right, ``y`` up, ``+x`` into the
    page) with the frames that the misalignment conventions use (``docs/optics.md``):
    each mirror's ``b`` and ``n`` at its centre (``a = +x``), the object and image planes'
    in-plane ``y`` axes and normals, the stop, and the central ray.  Everything is drawn
    from the relay as built, so the figure shows the code's own conventions."""
    from oapcal.optics.relay import chief_rays, mirror_frame

    def zy(p):
        p = np.asarray(p, dtype=float)
        return p[..., 2], p[..., 1]

    fig = new_figure(9.0, 4.8, dpi=None)
    ax = fig.add_subplot()
    f1, f2 = relay.focal_lengths_mm
    size = 0.45 * min(f1, f2)
    rays = chief_rays(relay, np.zeros(2))
    path_pts = np.array([relay.object_plane.point, *rays.trace.hits, rays.trace.points])
    ax.plot(*zy(path_pts), color="tab:red", lw=1.2, label="central chief ray")
    for i, mirror in enumerate(relay.mirrors, start=1):
        a, b, n = mirror_frame(mirror)
        c = np.asarray(mirror.aperture_centre)
        t = np.linspace(-1.0, 1.0, 41)[:, None] * 0.5 * relay.diameter_mm
        # the mirror's trace in the fold plane: rays along its axis through points along b
        axis = np.asarray(mirror.axis)
        starts = c + t * b - 3.0 * size * axis
        hits = np.array([s + mirror.intersect(s, axis) * axis for s in starts])
        ax.plot(*zy(hits), color="k", lw=2.5)
        for vec, name, colour in ((b, "b", "tab:blue"), (n, "n", "tab:green")):
            ax.annotate(
                "", xy=zy(c + size * vec), xytext=zy(c), arrowprops=dict(arrowstyle="->", color=colour)
            )
            ax.text(*zy(c + 1.12 * size * vec), name, color=colour, ha="center", va="center")
        z, y = zy(c)
        ax.text(z, y + 0.55 * relay.diameter_mm, f"OAP {i}\na = +x (into page)", fontsize=7, ha="center",
                va="bottom")  # fmt: skip
    for plane, name in ((relay.object_plane, "object"), (relay.image_plane, "camera")):
        p = np.asarray(plane.point)
        ey, nz = np.asarray(plane.ey), np.asarray(plane.normal)
        ax.plot(*zy(np.array([p - 0.8 * size * ey, p + 0.8 * size * ey])), color="0.4", lw=3)
        ax.annotate(
            "", xy=zy(p + size * ey), xytext=zy(p), arrowprops=dict(arrowstyle="->", color="tab:purple")
        )
        ax.text(
            *zy(p + 1.15 * size * ey), f"{name} y", color="tab:purple", ha="center", va="center", fontsize=8
        )
        ax.annotate(
            "", xy=zy(p + 0.7 * size * nz), xytext=zy(p), arrowprops=dict(arrowstyle="->", color="0.3")
        )
        ax.text(*zy(p + 0.85 * size * nz), "normal", color="0.3", ha="center", va="center", fontsize=7)
        ax.text(*zy(p - 0.9 * size * ey), f"{name} x: into page", fontsize=7, ha="center", va="top")
    stop = np.asarray(relay.stop.point)
    sy = np.asarray(relay.stop.ey)
    ax.plot(*zy(np.array([stop - 0.5 * relay.diameter_mm * sy, stop + 0.5 * relay.diameter_mm * sy])),
            ls="--", color="tab:orange", label="stop plane")  # fmt: skip
    ax.set_xlabel("z (mm)")
    ax.set_ylabel("y (mm)")
    ax.set_aspect("equal")
    ax.set_ylim(min(-1.2 * size, f1 - f2 - 1.2 * size) - 5, f1 + 0.55 * relay.diameter_mm + 18)
    ax.margins(x=0.06)
    ax.legend(loc="center", fontsize=8)
    default = (f"Relay in the fold plane x = 0 (d1 = {relay.d1_mm:g} mm, orientation {relay.orientation}); "
               "positive angles are right-handed: about an axis into the page, clockwise here")  # fmt: skip
    ax.set_title(title or default, fontsize=8)
    return fig


# ------------------------------------------------------------------- written figures


def plot_grid(grid, path, *, units: str = "mm", pixel_size_um: float = 4.8, max_side: int = 33) -> None:
    """Write :func:`grid_figure` to ``path`` (PNG, atomically)."""
    save_figure(grid_figure(grid, units=units, pixel_size_um=pixel_size_um, max_side=max_side), path, dpi=DPI)


def plot_spots(spots: dict, path, *, airy_radius_um: float | None = None) -> None:
    """Write :func:`spots_figure` to ``path`` (PNG, atomically)."""
    save_figure(spots_figure(spots, airy_radius_um=airy_radius_um), path, dpi=DPI)


def plot_tolerance(result: dict, path) -> None:
    """Write :func:`tolerance_figure` to ``path`` (PNG, atomically)."""
    save_figure(tolerance_figure(result), path, dpi=DPI)


def plot_layout(relay, path, *, title: str | None = None) -> None:
    """Write :func:`layout_figure` to ``path`` (PNG, atomically)."""
    save_figure(layout_figure(relay, title=title), path, dpi=DPI)
