"""The report's figures, drawn with Matplotlib (Agg backend, no pyplot state).

Every function returns a :class:`matplotlib.figure.Figure`.  Image axes are in px with the
origin at the centre of the top-left pixel and y down (``docs/conventions.md``); when a
scale is known a second pair of axes (top and right) reads in um.
"""

from __future__ import annotations

import numpy as np

CMAP = "viridis"


def new_figure(width: float, height: float, dpi: float | None = 110):
    """A figure with its own Agg canvas: no pyplot state, and the caller's (e.g. a
    notebook's) Matplotlib backend is left as it is.  ``dpi=None`` is Matplotlib's default."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width, height), dpi=dpi, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def _image_axes(ax, um_per_px: float | None, shape=None) -> None:
    """Label an image axes in px (x = column, y = row, y down) and add um axes when known."""
    ax.set_xlabel("x (column) [px]")
    ax.set_ylabel("y (row) [px]")
    if shape is not None:
        ax.set_xlim(-0.5, shape[1] - 0.5)
        ax.set_ylim(shape[0] - 0.5, -0.5)
    ax.set_aspect("equal")
    if um_per_px:
        s = float(um_per_px)
        top = ax.secondary_xaxis("top", functions=(lambda v: v * s, lambda v: v / s))
        top.set_xlabel("x [um]")
        right = ax.secondary_yaxis("right", functions=(lambda v: v * s, lambda v: v / s))
        right.set_ylabel("y [um]")


def _colorbar(fig, mappable, ax, label: str, um_per_px: float | None = None):
    cbar = fig.colorbar(mappable, ax=ax, shrink=0.85, pad=0.02)
    cbar.set_label(label + (f"   (1 px = {float(um_per_px):.3g} um)" if um_per_px else ""))
    return cbar


def _hull_outline(ax, hull, **kwargs) -> None:
    if hull is None or len(hull) < 3:
        return
    closed = np.vstack([hull, hull[:1]])
    style = {"color": "white", "lw": 1.2, "ls": "--", "label": "hull of the calibration points"}
    style.update(kwargs)
    ax.plot(closed[:, 0], closed[:, 1], **style)


def residual_vectors_figure(vectors, um_per_px=None, shape=None, title_suffix: str = ""):
    """Quiver of corrected-minus-reference vectors at the reference points, magnified."""
    fig = new_figure(7.5, 5.6)
    ax = fig.add_subplot()
    ok = np.isfinite(vectors.dxy).all(axis=1)
    xy, dxy, length = vectors.xy_u[ok], vectors.dxy[ok], vectors.length[ok]
    span = float(np.ptp(vectors.xy_u, axis=0).max()) if len(vectors.xy_u) > 1 else 1.0
    biggest = float(length.max()) if length.size and length.max() > 0 else 1.0
    gain = _nice(0.06 * span / biggest)
    q = ax.quiver(xy[:, 0], xy[:, 1], dxy[:, 0] * gain, dxy[:, 1] * gain, length, cmap=CMAP,
                  angles="xy", scale_units="xy", scale=1.0, width=0.004)  # fmt: skip
    if (~ok).any():
        bad = vectors.xy_u[~ok]
        ax.plot(bad[:, 0], bad[:, 1], "rx", label="inverse did not converge")
        ax.legend(loc="lower right", fontsize=8)
    _colorbar(fig, q, ax, "residual length [px]", um_per_px)
    if shape is None:
        pad = 0.05 * span
        lo, hi = vectors.xy_u.min(axis=0) - pad, vectors.xy_u.max(axis=0) + pad
        ax.set_xlim(lo[0], hi[0])
        ax.set_ylim(hi[1], lo[1])
    _image_axes(ax, um_per_px, shape)
    ax.set_title(f"Residuals after correction (corrected - reference), arrows x{gain:g}{title_suffix}")
    return fig


def _nice(value: float) -> float:
    """Round a magnification down to 1, 2 or 5 times a power of ten."""
    if not value > 0 or not np.isfinite(value):
        return 1.0
    exp = np.floor(np.log10(value))
    for m in (5, 2, 1):
        if value >= m * 10**exp:
            return float(m * 10**exp)
    return float(10**exp)


def distortion_field_figure(params, shape, hull=None, um_per_px=None, n_arrows: int = 16):
    """The model's distortion ``distort(u) - u`` over the output frame: magnitude as an image,
    direction as true-scale arrows, the calibrated region outlined.  ``params``: a
    calibration, a :class:`~oapcal.model.Model` or a parameter vector."""
    from oapcal.model import as_model

    model = as_model(params)

    rows, cols = int(shape[0]), int(shape[1])
    step = max(1, max(rows, cols) // 200)
    gx, gy = np.meshgrid(np.arange(0, cols, step, float), np.arange(0, rows, step, float))
    d = model(np.stack([gx, gy], -1)) - np.stack([gx, gy], -1)
    mag = np.hypot(d[..., 0], d[..., 1])
    fig = new_figure(7.5, 5.6)
    ax = fig.add_subplot()
    im = ax.imshow(mag, cmap=CMAP, extent=(-0.5, cols - 0.5, rows - 0.5, -0.5), interpolation="bilinear")
    _colorbar(fig, im, ax, "distortion |x_d - x_u| [px]", um_per_px)
    ax_step = max(cols, rows) / n_arrows
    qx, qy = np.meshgrid(np.arange(ax_step / 2, cols, ax_step), np.arange(ax_step / 2, rows, ax_step))
    q = np.stack([qx, qy], -1).reshape(-1, 2)
    dq = model(q) - q
    ax.quiver(q[:, 0], q[:, 1], dq[:, 0], dq[:, 1], color="white", angles="xy", scale_units="xy",
              scale=1.0, width=0.003)  # fmt: skip
    _hull_outline(ax, hull)
    if hull is not None:
        ax.legend(loc="lower right", fontsize=8, framealpha=0.6)
    _image_axes(ax, um_per_px, (rows, cols))
    ax.set_title(f"Distortion field (arrows true scale), max {mag.max():.1f} px")
    return fig


def _map_extent(umap) -> tuple[float, float, float, float]:
    """``imshow``'s extent of an uncertainty map's grid (pixel edges, rows downwards)."""
    step_x = umap.x[1] - umap.x[0] if len(umap.x) > 1 else 1.0
    step_y = umap.y[1] - umap.y[0] if len(umap.y) > 1 else 1.0
    return (umap.x[0] - step_x / 2, umap.x[-1] + step_x / 2, umap.y[-1] + step_y / 2, umap.y[0] - step_y / 2)


def uncertainty_figure(umap):
    """The 1-sigma positional uncertainty of the correction; extrapolated region hatched."""
    fig = new_figure(7.5, 5.6)
    ax = fig.add_subplot()
    extent = _map_extent(umap)
    im = ax.imshow(umap.sigma_px, cmap="magma", extent=extent, interpolation="nearest")
    _colorbar(fig, im, ax, "1-sigma position uncertainty [px]", umap.um_per_px)
    if umap.outside_hull.any():
        if min(umap.outside_hull.shape) >= 2:
            ax.contourf(umap.x, umap.y, umap.outside_hull.astype(float), levels=[0.5, 1.5], colors="none",
                        hatches=["//"])  # fmt: skip
        else:  # a map one sample wide (an image 1 px high or wide) has no contour: shade it
            shade = np.ma.masked_where(~umap.outside_hull, umap.outside_hull.astype(float))
            ax.imshow(shade, cmap="Greys", vmin=0, vmax=2, alpha=0.5, extent=extent, interpolation="nearest")
        _hull_outline(
            ax, umap.hull, color="cyan", label="hull of the calibration points (outside: extrapolated)"
        )
        ax.legend(loc="lower right", fontsize=8, framealpha=0.7)
    rows, cols = int(round(extent[2] + 0.5)), int(round(extent[1] + 0.5))
    _image_axes(ax, umap.um_per_px, (rows, cols))
    inside = umap.sigma_px[~umap.outside_hull]
    med = float(np.nanmedian(inside)) if inside.size else float("nan")
    ax.set_title(f"Uncertainty of the corrected position (median {med:.3g} px inside the hull)")
    return fig


def predicted_error_figure(umap, max_error_px: float = 1.0):
    """The predicted 1-sigma error of the correction (covariance, model floor and
    extrapolation: :func:`oapcal.uncertainty.predicted_error`) on a log scale, with the
    trust region's border (predicted error = ``max_error_px``) and the landmarks' hull."""
    from matplotlib.colors import LogNorm

    fig = new_figure(7.5, 5.6)
    ax = fig.add_subplot()
    pred = umap.sigma_px if umap.predicted_px is None else umap.predicted_px
    extent = _map_extent(umap)
    finite = pred[np.isfinite(pred) & (pred > 0)]
    lo = float(finite.min()) if finite.size else 1e-3
    hi = float(finite.max()) if finite.size else 1.0
    lo, hi = min(lo, max_error_px / 10), max(hi, max_error_px * 10)
    shown = np.clip(np.where(np.isfinite(pred), pred, hi), lo, hi)
    im = ax.imshow(shown, cmap="viridis", norm=LogNorm(lo, hi), extent=extent, interpolation="nearest")
    _colorbar(fig, im, ax, "predicted 1-sigma error [px]", umap.um_per_px)
    trusted = umap.trusted(max_error_px)
    if min(pred.shape) >= 2 and trusted.any() and not trusted.all():
        ax.contour(umap.x, umap.y, trusted.astype(float), levels=[0.5], colors="red", linewidths=1.6)
        ax.contourf(umap.x, umap.y, (~trusted).astype(float), levels=[0.5, 1.5], colors="none", hatches=["/"])
        ax.plot([], [], color="red", lw=1.6, label=f"trust region: predicted error <= {max_error_px:g} px")
    _hull_outline(ax, umap.hull, color="white", label="hull of the calibration points")
    ax.legend(loc="lower right", fontsize=8, framealpha=0.7)
    rows, cols = int(round(extent[2] + 0.5)), int(round(extent[1] + 0.5))
    _image_axes(ax, umap.um_per_px, (rows, cols))
    ax.set_title(
        f"Where the correction is trusted: {100 * trusted.mean():.0f} % of the frame at {max_error_px:g} px"
    )
    return fig


def before_after_figure(before, after, check_before, check_after, um_per_px=None):
    """The image before and after correction with the fitted edge lines coloured by their
    RMS deviation from straight, and the boxes of the aspect-ratio checks."""
    from matplotlib.collections import LineCollection
    from matplotlib.colors import Normalize
    from matplotlib.patches import Rectangle

    fig = new_figure(12.0, 5.2)
    axes = fig.subplots(1, 2)
    values = [e.rms_px for c in (check_before, check_after) for e in c.edges]
    vmax = max(0.5, float(np.percentile(values, 98))) if values else 1.0
    norm = Normalize(0.0, vmax)
    lc = None
    for ax, image, check, name in (
        (axes[0], before, check_before, "before"),
        (axes[1], after, check_after, "after"),
    ):
        import matplotlib

        grey = matplotlib.colormaps["gray"].with_extremes(bad="#3b4252")  # no data: slate
        # A figure shows a few hundred pixels across: draw large images strided (matplotlib
        # would resample all 48 million pixels of an 8000 x 6000 image), in image coordinates.
        step = max(1, max(image.shape[:2]) // 2000)
        shown = image[::step, ::step]
        extent = (-step / 2, (shown.shape[1] - 0.5) * step, (shown.shape[0] - 0.5) * step, -step / 2)
        ax.imshow(shown, cmap=grey, interpolation="nearest", extent=extent)
        for shape in check.shapes:
            x0, y0, x1, y1 = shape.box
            ax.add_patch(Rectangle((x0 - 0.5, y0 - 0.5), x1 - x0 + 1, y1 - y0 + 1, fill=False, lw=0.5,
                                   ec="deepskyblue"))  # fmt: skip
        segments = [e.ends for e in check.edges]
        lc = LineCollection(segments, cmap="plasma", norm=norm, linewidths=1.6)
        lc.set_array(np.array([e.rms_px for e in check.edges]))
        ax.add_collection(lc)
        _image_axes(ax, um_per_px, image.shape)
        s = check.summary()
        straight = "n/a" if s["straightness_rms_px"] is None else f"{s['straightness_rms_px']:.2f} px"
        aspect = "n/a" if s["aspect_error_mean_pct"] is None else f"{s['aspect_error_mean_pct']:.1f} %"
        ax.set_title(f"{name} correction: edge RMS {straight}, aspect error {aspect}", fontsize=10)
    if lc is not None:
        fig.colorbar(lc, ax=axes, shrink=0.8, pad=0.02).set_label(
            "edge deviation from a straight line, RMS [px]"
        )
    return fig


def esf_figure(summary, n_examples: int = 8):
    """The distribution of fitted sigma over the edges and a few example fits (the largest
    sigma first, then a spread over the range)."""
    from oapcal.imaging.esf import erf_edge

    good = sorted(summary.good, key=lambda e: -e.sigma_px)
    n_examples = min(n_examples, len(good))
    fig = new_figure(12.0, 5.6)
    grid = fig.add_gridspec(2, 1 + (n_examples + 1) // 2)
    ax = fig.add_subplot(grid[:, 0])
    um = summary.um_per_px
    if good:
        sig = np.array([e.sigma_px for e in good])
        ax.hist(sig, bins=min(30, max(5, len(sig) // 4)), color="tab:blue", alpha=0.8)
        ax.axvline(sig.max(), color="tab:red", label=f"max {sig.max():.2f} px")
        ax.axvline(sig.mean(), color="k", ls="--", label=f"mean {sig.mean():.2f} px")
        ax.legend(fontsize=8)
        if um:
            ax.secondary_xaxis("top", functions=(lambda v: v * um, lambda v: v / um)).set_xlabel("sigma [um]")
    ax.set_xlabel("Gaussian PSF sigma [px]")
    ax.set_ylabel("number of edges")
    ax.set_title(f"{len(good)} edges")
    picks = (
        [good[0]] + [good[i] for i in np.linspace(1, len(good) - 1, n_examples - 1).astype(int)]
        if good
        else []
    )
    for i, edge in enumerate(picks[:n_examples]):
        sub = fig.add_subplot(grid[i % 2, 1 + i // 2])
        sub.plot(edge.distance, edge.values, ".", ms=2, color="0.4", label="pixels")
        d = np.linspace(edge.distance.min(), edge.distance.max(), 200)
        sub.plot(d, erf_edge(d, edge.low, edge.high, edge.sigma_px), color="tab:red", lw=1.4, label="erf fit")
        sub.set_title(f"{edge.label}: sigma {edge.sigma_px:.2f} px", fontsize=8)
        sub.set_xlabel("distance from edge [px]", fontsize=8)
        sub.set_ylabel("intensity", fontsize=8)
        sub.tick_params(labelsize=7)
    fig.suptitle("Edge spread functions fitted with an error function (Gaussian PSF)")
    return fig


def save_figure(fig, path, *, dpi: float | None = None) -> None:
    """Write a figure to ``path`` atomically (:func:`oapcal.io.atomic.atomic_path`); the
    format follows the suffix (PNG, SVG, PDF)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    from oapcal.io.atomic import atomic_path

    FigureCanvasAgg(fig)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi)


def figure_png(fig) -> bytes:
    """PNG bytes of a figure."""
    import io

    from matplotlib.backends.backend_agg import FigureCanvasAgg

    FigureCanvasAgg(fig)
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    return buf.getvalue()
