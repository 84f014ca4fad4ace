"""oapcal values <-> napari layer data, without napari: plain arrays and dicts.

napari places a point at ``(row, col)``; oapcal at ``(x, y) = (col, row)`` with the same
origin (the centre of the top-left pixel, ``docs/conventions.md``), so converting is a swap
of the two columns.  A layer is returned as napari's *layer data tuple*
``(data, keyword arguments, layer type)``.

The points layers of point pairs carry ``metadata["oapcal_role"]`` (``"distorted"`` or
``"reference"``) and the corner ``id`` as a feature; layers made from a calibration carry
the :class:`~oapcal.Calibration` itself as ``metadata["oapcal_calibration"]`` (the *Correct*
widget finds it there).
"""

from __future__ import annotations

import numpy as np

#: ``metadata`` key of a points layer's role in a pair of layers.
ROLE = "oapcal_role"
#: ``metadata`` key of the calibration a layer shows.
CALIBRATION = "oapcal_calibration"
#: ``metadata`` key of the reference points' scale (um per px), when known.
SCALE = "oapcal_um_per_px"
#: Names of the two points layers of point pairs.
DISTORTED, REFERENCE = "distorted", "reference"
#: The distortion-magnitude image of a calibration is sampled on at most this many pixels.
MAX_FIELD_PIXELS = 2**22
#: Grid spacing of the distortion-field vectors, as a fraction of the longer image side.
FIELD_STEP_FRACTION = 1.0 / 24.0


def xy_to_rc(xy) -> np.ndarray:
    """oapcal ``(N, 2)`` x, y -> napari ``(N, 2)`` row, col."""
    return np.asarray(xy, float).reshape(-1, 2)[:, ::-1].copy()


def rc_to_xy(rc) -> np.ndarray:
    """napari ``(N, 2)`` row, col (the last two axes of any points layer) -> oapcal x, y."""
    return np.asarray(rc, float)[:, -2:][:, ::-1].copy()


def points_layers(xy_u, xy_d, ids=None, *, um_per_px=None, source=None, extra=None) -> list[tuple]:
    """The ``distorted`` and ``reference`` points layers of point pairs (``id`` as a feature;
    ``extra`` more features, e.g. ``stderr_px``)."""
    xy_u = np.asarray(xy_u, float)
    xy_d = np.asarray(xy_d, float)
    ids = [str(i) for i in (ids if ids is not None else range(len(xy_d)))]
    features = {"id": np.array(ids, dtype=object), **{k: np.asarray(v) for k, v in (extra or {}).items()}}
    meta = {SCALE: um_per_px, "oapcal_source": source}
    text = {"string": "{id}", "size": 7, "color": "white", "translation": np.array([-6.0, 0.0])}
    common = {"features": features, "size": 5, "text": text if len(ids) <= 40 else None}
    return [
        (xy_to_rc(xy_d), {**common, "name": DISTORTED, "face_color": "orange",
                          "metadata": {**meta, ROLE: DISTORTED}}, "points"),
        (xy_to_rc(xy_u), {**common, "name": REFERENCE, "face_color": "cyan", "visible": False,
                          "metadata": {**meta, ROLE: REFERENCE}}, "points"),
    ]  # fmt: skip


def layer_ids(data, features) -> list[str]:
    """The ``id`` feature of a points layer as strings, or the row numbers without one."""
    if features is not None and "id" in getattr(features, "columns", features):
        return [str(v) for v in np.asarray(features["id"])]
    return [str(i) for i in range(len(data))]


def pair_layers(distorted, reference) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """``(xy_u, xy_d, ids)`` from two points layers (or ``(data, features)`` pairs), paired by
    the ``id`` feature (the order of the distorted layer; points without a partner are left
    out).  Without ids the layers must have the same number of points, paired in order."""
    d_data, d_feat = distorted
    r_data, r_feat = reference
    d_ids, r_ids = layer_ids(d_data, d_feat), layer_ids(r_data, r_feat)
    xy_d_all, xy_u_all = rc_to_xy(d_data), rc_to_xy(r_data)
    where = {i: k for k, i in enumerate(r_ids)}
    keep = [k for k, i in enumerate(d_ids) if i in where]
    if len(set(d_ids)) != len(d_ids) or len(set(r_ids)) != len(r_ids):
        from oapcal.errors import DataError

        raise DataError("the points layers repeat an id; each landmark must appear once in each layer")
    xy_d = xy_d_all[keep]
    xy_u = xy_u_all[[where[d_ids[k]] for k in keep]]
    return xy_u, xy_d, [d_ids[k] for k in keep]


def field_grid(width: int, height: int) -> np.ndarray:
    """A regular grid of x, y points over a ``width x height`` px frame for field vectors."""
    step = max(4.0, max(width, height) * FIELD_STEP_FRACTION)
    xs = np.arange(step / 2, width, step)
    ys = np.arange(step / 2, height, step)
    gx, gy = np.meshgrid(xs, ys)
    return np.stack([gx.ravel(), gy.ravel()], -1)


def frame_of(calibration) -> tuple[int, int]:
    """``(width, height)`` px the calibration applies to: its ``image_size``, else its
    reference points' bounds (from 0)."""
    if calibration.image_size:
        return int(calibration.image_size[0]), int(calibration.image_size[1])
    if calibration.bounds is not None:
        return int(np.ceil(calibration.bounds[2])) + 1, int(np.ceil(calibration.bounds[3])) + 1
    raise ValueError("the calibration has neither image_size nor bounds")


def hull_layer(calibration, name: str = "calibration hull") -> tuple | None:
    """The convex hull of the calibration's reference points as a shapes layer (or None)."""
    hull = getattr(calibration, "hull", None)
    if hull is None or len(hull) < 3:
        return None
    kwargs = {"name": name, "shape_type": "polygon", "edge_color": "yellow", "face_color": "transparent",
              "edge_width": 2, "metadata": {CALIBRATION: calibration}}  # fmt: skip
    return [xy_to_rc(hull)], kwargs, "shapes"


def calibration_layers(calibration, name: str = "calibration", source: str | None = None) -> list[tuple]:
    """The distortion field of a calibration: a magnitude image ``|distort(x) - x|`` px over its
    frame (every pixel, or every ``step`` px with the layer scaled by ``step`` for frames over
    :data:`MAX_FIELD_PIXELS`), a vectors layer from undistorted grid points to where the relay
    images them, and the hull of its calibration points.  ``source`` (the file it was read
    from) goes into the layers' metadata: the *Correct* widget never saves over it."""
    from oapcal.model import as_model

    model = as_model(calibration)
    width, height = frame_of(calibration)
    step = max(1, int(np.ceil(np.sqrt(width * height / MAX_FIELD_PIXELS))))  # large frames: sampled
    gx, gy = np.meshgrid(np.arange(0, width, step, dtype=float), np.arange(0, height, step, dtype=float))
    xy = np.stack([gx.ravel(), gy.ravel()], -1)
    magnitude = np.hypot(*(model(xy) - xy).T).reshape(gx.shape)
    grid = field_grid(width, height)
    shift = model(grid) - grid
    vectors = np.stack([xy_to_rc(grid), xy_to_rc(shift)], axis=1)
    meta = {CALIBRATION: calibration, "oapcal_source": source}
    layers = [
        (magnitude.astype(np.float32), {"name": f"{name}: distortion (px)", "colormap": "viridis",
                                        "scale": (step, step), "metadata": meta}, "image"),
        (vectors, {"name": f"{name}: distortion field", "features": {"shift_px": np.hypot(*shift.T)},
                   "edge_color": "shift_px", "edge_colormap": "plasma", "edge_width": 1.5,
                   "vector_style": "arrow", "metadata": meta}, "vectors"),
    ]  # fmt: skip
    hull = hull_layer(calibration, f"{name}: hull")
    if hull is not None:
        hull[1]["metadata"]["oapcal_source"] = source
    return layers + ([hull] if hull is not None else [])


def residual_vectors(calibration, xy_u, xy_d, ids, *, exaggerate: float = 20.0) -> dict:
    """The correction residual of every pair (the paper's Table 1): ``undistort(xy_d)`` of the
    calibration against ``xy_u``.  Returns ``residual_px`` ``(N,)``, the vectors layer (at
    each landmark in the camera image, ``xy_d``, the residual ``undistort(xy_d) - xy_u`` drawn
    ``exaggerate`` times longer, coloured by size) and the order of the pairs from the worst."""
    from oapcal.model import as_model

    corrected = as_model(calibration).inverse(np.asarray(xy_d, float)).xy
    delta = corrected - np.asarray(xy_u, float)
    size = np.hypot(*delta.T)
    vectors = np.stack([xy_to_rc(xy_d), xy_to_rc(delta * exaggerate)], axis=1)
    features = {"residual_px": size, "id": np.array(ids, object)}
    kwargs = {"name": f"residuals (x{exaggerate:g})", "features": features, "edge_color": "residual_px",
              "edge_colormap": "inferno", "edge_width": 2, "vector_style": "arrow",
              "metadata": {CALIBRATION: calibration}}  # fmt: skip
    order = np.argsort(-np.where(np.isfinite(size), size, np.inf), kind="stable")
    return {
        "residual_px": size,
        "corrected": corrected,
        "layer": (vectors, kwargs, "vectors"),
        "worst": order,
    }


def table1_text(residuals) -> str:
    """The paper's Table 1 (max, mean, RMS, total residual after correction) as text."""
    rows = [("px", residuals.max_px, residuals.mean_px, residuals.rms_px, residuals.total_px)]
    if residuals.um_per_px is not None:
        rows.append(("um", residuals.max_um, residuals.mean_um, residuals.rms_um, residuals.total_um))
    lines = [f"{'':>3} {'max':>8} {'mean':>8} {'rms':>8} {'total':>8}"]
    lines += [f"{u:>3} {a:8.4g} {b:8.4g} {c:8.4g} {d:8.4g}" for u, a, b, c, d in rows]
    return "\n".join(lines)
