"""Pictures of a self-calibration (``docs/selfcal.md``): the matches over a frame, and the
residual field of the solve with the correction's displacement.

Built with :func:`oapcal.report.plots.new_figure` (a ``Figure`` with its own Agg canvas) and
written with :func:`oapcal.report.plots.save_figure`.  Axes in camera px, pixel centres at
integers (``docs/conventions.md``).
"""

from __future__ import annotations

import numpy as np

from oapcal.report.plots import new_figure


def matches_figure(result, frame=None, *, frame_index: int | None = None):
    """The matches of a :class:`~oapcal.selfcal.SelfCalibration` drawn where they lie in
    their first frame (all frames' matches on one picture, each pair's colour its own), the
    outliers as crosses, over ``frame`` (an image, optional)."""
    m = result.matches
    w, h = m.image_size
    fig = new_figure(7.2, 7.2 * h / w + 0.8)
    ax = fig.add_subplot(1, 1, 1)
    if frame is not None:
        ax.imshow(np.asarray(frame), cmap="gray", extent=(-0.5, w - 0.5, h - 0.5, -0.5))
    pair_id = m.frame_a * m.n_frames + m.frame_b
    inl = result.inlier
    ax.scatter(m.xy_a[inl, 0], m.xy_a[inl, 1], s=4, c=pair_id[inl] % 20, cmap="tab20", label="matches")
    if (~inl).any():
        ax.scatter(m.xy_a[~inl, 0], m.xy_a[~inl, 1], s=14, marker="x", c="red", label="outliers")
    ax.set_xlim(-0.5, w - 0.5)
    ax.set_ylim(h - 0.5, -0.5)
    ax.set_aspect("equal")
    ax.set_xlabel("x (column) [px]")
    ax.set_ylabel("y (row) [px]")
    ax.set_title(
        f"{int(inl.sum())} matches in {len(m.pairs)} overlapping pairs of {m.n_frames} frames"
        f" ({int((~inl).sum())} outliers)",
        fontsize=9,
    )
    ax.legend(loc="lower right", fontsize=8)
    return fig


def residual_figure(result, *, arrow_scale: float | None = None):
    """Left: the residual of every inlier match (px) at its position, as arrows (magnified)
    coloured by size.  Right: the correction's displacement ``u(d) - d`` over the frame."""
    from oapcal.model import as_model

    m = result.matches
    w, h = m.image_size
    inl = result.inlier
    e = result.residuals[inl]
    xy = m.xy_a[inl]
    size = np.linalg.norm(e, axis=1)
    fig = new_figure(11.0, 11.0 * h / (2 * w) + 1.2)
    ax1, ax2 = fig.subplots(1, 2)
    scale = arrow_scale or (0.05 * w / max(float(np.percentile(size, 95)), 1e-9))
    q = ax1.quiver(xy[:, 0], xy[:, 1], e[:, 0] * scale, e[:, 1] * scale, size, angles="xy",
                   scale_units="xy", scale=1, cmap="viridis", width=0.003)  # fmt: skip
    fig.colorbar(q, ax=ax1, label="residual [px]", shrink=0.8)
    rms = float(np.sqrt(np.mean(size**2)))
    ax1.set_title(f"match residuals (x{scale:.0f}): RMS {rms:.3f} px, max {size.max():.3f} px", fontsize=9)
    gx, gy = np.meshgrid(np.linspace(0, w - 1, 17), np.linspace(0, h - 1, 13))
    d = np.stack([gx.ravel(), gy.ravel()], -1)
    u = as_model(result.calibration).inverse(d).xy
    disp = u - d
    mag = np.linalg.norm(disp, axis=1)
    q2 = ax2.quiver(d[:, 0], d[:, 1], disp[:, 0], disp[:, 1], mag, angles="xy", scale_units="xy", scale=1,
                    cmap="magma", width=0.003)  # fmt: skip
    fig.colorbar(q2, ax=ax2, label="|u(d) - d| [px]", shrink=0.8)
    ax2.set_title("the correction u(d) - d (true length)", fontsize=9)
    for ax in (ax1, ax2):
        ax.set_xlim(-0.5, w - 0.5)
        ax.set_ylim(h - 0.5, -0.5)
        ax.set_aspect("equal")
        ax.set_xlabel("x (column) [px]")
        ax.set_ylabel("y (row) [px]")
    return fig


def moves_figure(record: dict, image_size=None):
    """The frames' moves of a self-calibration record (the calibration file's ``selfcal``,
    :func:`oapcal.selfcal.solve.selfcal_record`): each frame a numbered dot, each
    overlapping pair a line coloured by the RMS residual of its inlier matches; the frame's
    outline (dashed, ``image_size`` ``(w, h)``) about the moves' middle for scale."""
    from matplotlib.collections import LineCollection

    t = np.asarray(record["translations_px"], float).reshape(-1, 2)
    fig = new_figure(6.4, 5.2)
    ax = fig.add_subplot(1, 1, 1)
    rows = [q for q in record.get("pair_table", []) if q.get("rms_px") is not None]
    if rows:
        segs = [[t[q["a"]], t[q["b"]]] for q in rows]
        lines = LineCollection(segs, array=np.array([q["rms_px"] for q in rows]), cmap="viridis", lw=1.2)
        ax.add_collection(lines)
        fig.colorbar(lines, ax=ax, label="pair RMS residual [px]", shrink=0.8)
    ax.scatter(t[:, 0], t[:, 1], s=18, c="black", zorder=3)
    for i, (x, y) in enumerate(t):
        ax.annotate(str(i), (x, y), textcoords="offset points", xytext=(3, 3), fontsize=7)
    if image_size:  # the frame's size, about the moves' middle
        w, h = image_size
        cx, cy = (t.min(axis=0) + t.max(axis=0)) / 2
        xs = [cx - w / 2, cx + w / 2, cx + w / 2, cx - w / 2, cx - w / 2]
        ax.plot(xs, [cy - h / 2, cy - h / 2, cy + h / 2, cy + h / 2, cy - h / 2], "--", color="grey", lw=0.8)
    ax.set_aspect("equal")
    ax.invert_yaxis()
    ax.set_xlabel("move x [px]")
    ax.set_ylabel("move y [px] (down)")
    ax.set_title(f"{len(t)} frames, {len(record.get('pair_table', []))} overlapping pairs", fontsize=9)
    return fig


__all__ = ["matches_figure", "moves_figure", "residual_figure"]
