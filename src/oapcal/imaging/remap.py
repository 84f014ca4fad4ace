"""Correction maps: for each output (corrected) pixel, the source pixel in the distorted
image; applied with ``cv2.remap``.

With the paper's model the map needs no inversion: an output pixel at undistorted
coordinates ``(x_u, y_u)`` samples the distorted image at ``distort((x_u, y_u))``, computed
by the model's compiled point function over the pixel grid (``oapcal._kernels.grid_map``).

The *output geometry* (:class:`OutputGeometry`) says which undistorted point each output
pixel shows: output pixel ``(col, row)`` is the undistorted point
``(x0 + scale * col, y0 + scale * row)``.  By default the output has the input's size and
the calibration's undistorted coordinates (``x0 = y0 = 0``, ``scale = 1``); see
:func:`output_geometry` for ``extent="full"`` / ``"calibrated"`` and an output scale in um/px.

>>> import numpy as np
>>> from oapcal.model import identity_params
>>> mx, my = correction_map(identity_params(), (3, 4))
>>> mx.shape, mx.dtype.name, float(mx[2, 3]), float(my[2, 3])
((3, 4), 'float32', 3.0, 2.0)
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from oapcal import eq1_closed_form
from oapcal.errors import DataError, InputFileError, ModelSpecError
from oapcal.model import Model, as_model
from oapcal.records import ImageSize
from oapcal.validate import image as _valid_image

INTERPOLATIONS = ("nearest", "linear", "cubic", "lanczos")
EXTENTS = ("input", "full", "calibrated")
#: The largest correction map built (two float32 arrays): 4 GiB, a 2**29 px output, twice the
#: default largest frame (--max-pixels 2**28).
MAX_MAP_BYTES = 4 * 2**30
#: An output larger than this many times the input's pixel count is refused (a guard
#: against a folded map or a tiny --um-per-px asking for a huge image).
MAX_GROWTH = 16
#: The smallest output side (px): an output geometry that collapses below it (a huge
#: --um-per-px, a degenerate region) is refused, as --out-size under 2x2 is.
MIN_OUTPUT_SIDE = 2
#: The default largest predicted error (px) of a written output pixel (``oapcal correct
#: --max-error-px``): beyond it the trust region ends and the pixel gets the border value.
DEFAULT_MAX_ERROR_PX = 1.0
#: Samples of the predicted error along the output's longer side (interpolated between):
#: the error is smooth, and the relay's parameter Jacobian costs central differences.
ERROR_SAMPLES = {"analytic": 160, "finite-difference": 64}
#: Map value given to output pixels outside the trust region: far enough outside any input
#: that every interpolation kernel (Lanczos reaches 4 px) samples only the border.
MASKED = -64.0
#: A map is refused (:class:`EmptyMapError`) when fewer than this fraction of its output
#: pixels take their value from inside the input image: 0.1 %, far below what any allowed
#: output geometry of a usable calibration gives (at least 1 / MAX_GROWTH).
MIN_SAMPLED_FRACTION = 1e-3


class EmptyMapError(DataError):
    """A correction map whose output pixels sample no (or almost no) pixel of the input
    image: the output would be all border (an offset of 1e29 px, a magnification of 1e12,
    a relay mirror tilted far off, a --map built for another camera)."""


def sampled_fraction(maps, input_shape: tuple[int, int]) -> float:
    """The fraction of a map's output pixels whose source lies inside an input image of
    ``input_shape = (rows, cols)`` (pixel centres ``0 .. cols - 1``, ``0 .. rows - 1``;
    NaN counts as outside).  Counted a block of rows at a time (no full-size temporaries).

    >>> from oapcal.model import identity_params
    >>> sampled_fraction(correction_map(identity_params(), (3, 4)), (3, 4))
    1.0
    """
    map_x, map_y = maps
    rows, cols = int(input_shape[0]), int(input_shape[1])
    n = map_x.size
    if n == 0:
        return 0.0
    step = max(1, (1 << 20) // max(1, map_x.shape[1]))
    inside = 0
    with np.errstate(invalid="ignore"):
        for lo in range(0, map_x.shape[0], step):
            mx, my = map_x[lo : lo + step], map_y[lo : lo + step]
            inside += int(np.count_nonzero((mx >= 0) & (mx <= cols - 1) & (my >= 0) & (my <= rows - 1)))
    return inside / n


def check_map_samples(maps, input_shape: tuple[int, int]) -> None:
    """Raise :class:`EmptyMapError` when fewer than :data:`MIN_SAMPLED_FRACTION` of the
    map's output pixels sample the input image of ``input_shape = (rows, cols)``: the
    corrected image would be all (or nearly all) border.  The rule is on the map, so it
    holds for every model family and for maps loaded from files."""
    fraction = sampled_fraction(maps, input_shape)
    if fraction >= MIN_SAMPLED_FRACTION:
        return
    map_x = maps[0] if not isinstance(maps, CorrectionMap) else maps.map_x
    n = map_x.size
    count = round(fraction * n)
    rows, cols = int(input_shape[0]), int(input_shape[1])
    what = "no pixel" if count == 0 else f"almost no pixel (under {MIN_SAMPLED_FRACTION:.1%} of the output)"
    raise EmptyMapError(
        f"the map samples {what} of the image: {count} of {n} output pixels take their value from "
        f"inside the {cols}x{rows} px input, the rest would be border; the calibration's offsets, "
        "scale or design (or the map file) do not fit this image: check them, or the output options"
    )


def check_model_samples(
    calibration_or_params, input_shape: tuple[int, int], geometry: OutputGeometry
) -> None:
    """:func:`check_map_samples` for the map of ``geometry`` without building it whole: the
    map at every k-th output pixel (at most 512 along the longer side), for a caller that
    needs no map (``export-opencv`` of an Eq. (1) calibration writes coefficients)."""
    rows, cols = geometry.shape
    k = max(1, -(-max(rows, cols) // 512))
    coarse = OutputGeometry(
        ((rows - 1) // k + 1, (cols - 1) // k + 1), geometry.x0, geometry.y0, geometry.scale * k
    )
    correction_map(calibration_or_params, input_shape, geometry=coarse, allow_size_mismatch=True)


def _model_of(calibration_or_params) -> Model:
    """The model of a calibration, a :class:`~oapcal.model.Model` or (legacy) a bare
    parameter vector of a built-in family."""
    try:
        return as_model(calibration_or_params)
    except ModelSpecError:
        shape = np.shape(getattr(calibration_or_params, "params", calibration_or_params))
        raise DataError(
            f"a correction map needs one parameter vector of a model family, not {shape}"
        ) from None  # noqa: E501


@dataclass(frozen=True)
class OutputGeometry:
    """Which undistorted point each output pixel shows.

    Output pixel ``(col, row)`` is the undistorted point ``(x0 + scale * col, y0 + scale * row)``
    (coordinates and ``scale`` in the calibration's undistorted units, normally px).

    ``shape`` is the output's ``(rows, cols)``; ``um_per_px`` the object-space size of one
    output pixel when the calibration knows its scale, else None.
    """

    shape: tuple[int, int]
    x0: float = 0.0
    y0: float = 0.0
    scale: float = 1.0
    um_per_px: float | None = None

    def to_dict(self) -> dict:
        return {
            "shape": [int(v) for v in self.shape],
            "x0": float(self.x0),
            "y0": float(self.y0),
            "scale": float(self.scale),
            "um_per_px": None if self.um_per_px is None else float(self.um_per_px),
        }


def output_geometry(
    calibration_or_params,
    input_shape: tuple[int, int],
    *,
    extent: str = "input",
    um_per_px: float | None = None,
    out_size: tuple[int, int] | None = None,
    trust_region: bool = False,
) -> OutputGeometry:
    """The output geometry for an input image of ``input_shape = (rows, cols)``.

    ``extent`` is the undistorted region shown:

    * ``"input"`` (default): ``[0, cols-1] x [0, rows-1]``, the input's own coordinates;
    * ``"full"``: the bounding box of the whole corrected field, i.e. of the input frame's
      border pixels mapped back through the inverse model (nothing of the input is cut);
    * ``"calibrated"``: the bounding box of the calibration's reference points
      (``Calibration.bounds``), where the model is supported by data.

    The scale is one undistorted unit per output pixel unless ``um_per_px`` (output pixel
    size in um; needs a calibration with ``um_per_px``) or ``out_size = (width, height)``
    (fit the region into that size, aspect ratio kept, centred) is given.

    The model must be finite and must not fold over in the region shown
    (:func:`oapcal.calibration.check_model_region`); with ``trust_region`` (the output is
    written only where its predicted error is small: :func:`correction_map`'s
    ``max_error_px``) a calibration with an error model may fold beyond its reference
    points' bounds, where its trust region has ended.

    >>> from oapcal.model import params_from_dict
    >>> g = output_geometry(params_from_dict({}), (480, 640), extent="input")
    >>> g.shape, g.x0, g.scale
    ((480, 640), 0.0, 1.0)
    """
    rows, cols = int(input_shape[0]), int(input_shape[1])
    model = _model_of(calibration_or_params)
    cal_um = getattr(calibration_or_params, "um_per_px", None)
    if extent not in EXTENTS:
        raise DataError(f"unknown extent {extent!r}: use one of {', '.join(EXTENTS)}")
    if um_per_px is not None and out_size is not None:
        raise DataError("give either an output scale (um per px) or an output size, not both")
    x0, y0, x1, y1 = _region(calibration_or_params, model, extent, rows, cols)
    from oapcal.calibration import Calibration, ModelRegion, check_model_region

    # the model must be finite and not fold over where the output samples it; a calibration
    # (read from a file) is an input file's mistake, a Model or vector given in memory a value's
    what = f"{cols}x{rows} px image" if extent == "input" else f"output region of a {cols}x{rows} px image"
    error = InputFileError if isinstance(calibration_or_params, Calibration) else DataError
    # written only where trusted, a calibration with an error model may fold beyond its
    # landmarks' bounds: its trust region ends before the fold (check_model_region)
    region = ModelRegion(model.params, model.family, bounds=getattr(calibration_or_params, "bounds", None),
                         error_model=getattr(calibration_or_params, "error_model", None))  # fmt: skip
    check_model_region(region, boxes=[((x0, y0, x1, y1), what)], source="the calibration", error=error,
                       folds_beyond_bounds=None if trust_region else False, check_bounds=False)  # fmt: skip
    shape, x0, y0, scale = _layout((x0, y0, x1, y1), _output_scale(um_per_px, cal_um), out_size, um_per_px)
    _check_output_shape(shape, (rows, cols), (x1 - x0, y1 - y0), um_per_px, cal_um)
    out_um = None if not cal_um else float(cal_um) * scale
    return OutputGeometry(shape=shape, x0=x0, y0=y0, scale=scale, um_per_px=out_um)


def _layout(region, scale: float, out_size, um_per_px) -> tuple[tuple[int, int], float, float, float]:
    """The output ``(rows, cols)``, origin and scale showing ``region = (x0, y0, x1, y1)``:
    at ``scale`` units per pixel, or fitted into ``out_size = (w, h)`` (centred, aspect kept)."""
    x0, y0, x1, y1 = region
    if out_size is not None:
        w, h = int(out_size[0]), int(out_size[1])
        if w < MIN_OUTPUT_SIDE or h < MIN_OUTPUT_SIDE:
            raise DataError(f"the output size must be at least 2x2 px, got {w}x{h}")
        scale = max((x1 - x0) / (w - 1), (y1 - y0) / (h - 1))
        cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
        return ImageSize(w, h).shape, cx - scale * (w - 1) / 2, cy - scale * (h - 1) / 2, scale
    if not (math.isfinite(scale) and scale > 0):
        raise DataError(
            f"the output scale {um_per_px} um per px is outside what a float can represent here; "
            "choose another um_per_px",
            param="um_per_px",
        )
    # (x1 - x0) / scale may overflow to inf for a tiny scale: capped, the size check refuses it
    span = [min((y1 - y0) / scale, 2.0**40), min((x1 - x0) / scale, 2.0**40)]
    return (int(math.floor(span[0] + 1e-9)) + 1, int(math.floor(span[1] + 1e-9)) + 1), x0, y0, scale


def _region(calibration, model: Model, extent: str, rows: int, cols: int) -> tuple[float, ...]:
    """The undistorted region ``(x0, y0, x1, y1)`` an ``extent`` of :func:`output_geometry` shows."""
    if extent == "input":
        return 0.0, 0.0, float(cols - 1), float(rows - 1)
    if extent == "calibrated":
        bounds = getattr(calibration, "bounds", None)
        if bounds is None:
            raise DataError(
                "extent 'calibrated' needs a calibration with 'bounds' (the reference points' "
                "bounding box); refit with this oapcal or use extent 'input' or 'full'"
            )
        x0, y0, x1, y1 = (float(v) for v in bounds)
        return x0, y0, x1, y1
    return _full_extent(model, rows, cols)


def _output_scale(um_per_px: float | None, cal_um: float | None) -> float:
    """Undistorted units per output pixel for an output pixel of ``um_per_px`` um (1 without)."""
    if um_per_px is None:
        return 1.0
    if not cal_um:
        raise DataError(
            "an output scale in um per px needs a calibration with 'um_per_px'; "
            "refit it with um_per_px given, or leave um_per_px out",
            param="um_per_px",
        )
    if not um_per_px > 0:
        raise DataError(f"the output scale must be positive, got {um_per_px} um per px", param="um_per_px")
    return float(um_per_px) / float(cal_um)


def _check_output_shape(shape, input_shape, span, um_per_px, cal_um) -> None:
    """Refuse an output that collapses under :data:`MIN_OUTPUT_SIDE` or grows over
    :data:`MAX_GROWTH` times the input (``span``: the region's width and height)."""
    rows, cols = input_shape
    if min(shape) < MIN_OUTPUT_SIDE:
        coarsest = ""
        if um_per_px is not None and cal_um:
            limit = float(cal_um) * min(span) / (MIN_OUTPUT_SIDE - 1)
            coarsest = f" (at most {limit:.4g} um per px here)"
        raise DataError(
            f"the output would be {shape[1]}x{shape[0]} px, under {MIN_OUTPUT_SIDE} px on a side: the "
            f"output region collapses; choose a finer um_per_px{coarsest}, a larger out_size or "
            "another extent",
            param=("um_per_px", "out_size", "extent"),
        )
    if shape[0] * shape[1] > MAX_GROWTH * rows * cols:
        raise DataError(
            f"the output would be {shape[1]}x{shape[0]} px, more than {MAX_GROWTH} times the "
            f"input's {cols}x{rows}; choose a smaller out_size, a coarser um_per_px or another extent",
            param=("out_size", "um_per_px", "extent"),
        )


def _full_extent(model: Model, rows: int, cols: int) -> tuple[float, float, float, float]:
    """Bounding box of the input frame's border pixels mapped to undistorted coordinates."""
    xs = np.arange(cols, dtype=float)
    ys = np.arange(rows, dtype=float)
    border = np.concatenate(
        [
            np.stack([xs, np.zeros_like(xs)], -1),
            np.stack([xs, np.full_like(xs, rows - 1)], -1),
            np.stack([np.zeros_like(ys), ys], -1),
            np.stack([np.full_like(ys, cols - 1), ys], -1),
        ]
    )
    inv = model.inverse(border)
    if not inv.converged.all():
        raise DataError(
            f"extent 'full': the inverse model fails at {int((~inv.converged).sum())} of "
            f"{len(border)} border pixels (the fitted map folds over inside the frame); "
            "use extent 'input' or 'calibrated'"
        )
    lo = inv.xy.min(axis=0)
    hi = inv.xy.max(axis=0)
    return float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])


@dataclass(frozen=True, eq=False)
class CorrectionMap:
    """``map_x``, ``map_y`` (``float32 (rows, cols)``, for ``cv2.remap``) and the geometry
    they were built for.  Unpacks like a pair: ``map_x, map_y = cmap``.

    ``input_shape`` is the ``(rows, cols)`` of the distorted images the map expects, or
    None when unknown (a map loaded from a ``.npy`` or ``.tiff`` file).
    ``predicted_error`` ``(rows, cols)`` float32 is the predicted 1-sigma error of every
    output pixel (:func:`predicted_error_map`) when the map was built with
    ``max_error_px``, which it then holds: the pixels above it sample nothing (the border).
    """

    map_x: np.ndarray
    map_y: np.ndarray
    geometry: OutputGeometry
    input_shape: tuple[int, int] | None = None
    predicted_error: np.ndarray | None = None
    max_error_px: float | None = None

    def __iter__(self):
        return iter((self.map_x, self.map_y))

    @property
    def shape(self) -> tuple[int, int]:
        return self.map_x.shape

    @property
    def trusted(self) -> np.ndarray | None:
        """``(rows, cols)`` bool: the trust region (None for a map built without it)."""
        if self.predicted_error is None or self.max_error_px is None:
            return None
        return np.isfinite(self.predicted_error) & (self.predicted_error <= self.max_error_px)


def predicted_error_map(calibration, geometry: OutputGeometry, *, samples: int | None = None) -> np.ndarray:
    """The predicted 1-sigma error (:func:`oapcal.uncertainty.predicted_error`) of every
    output pixel of ``geometry``, in output px (the calibration's reference units over
    ``geometry.scale``), ``float32 (rows, cols)``: computed on a grid of ``samples`` points
    along the longer side (default :data:`ERROR_SAMPLES`) and interpolated linearly in
    between; inf where the map folds."""
    from oapcal.uncertainty import predicted_error

    family = _model_of(calibration).family
    if samples is None:
        samples = ERROR_SAMPLES["analytic" if family.analytic_jacobian else "finite-difference"]
    rows, cols = geometry.shape
    n = max(rows, cols)
    step = max(1.0, (n - 1) / max(samples - 1, 1))
    ny = int(np.ceil((rows - 1) / step)) + 1
    nx = int(np.ceil((cols - 1) / step)) + 1
    cx = np.minimum(np.arange(nx) * step, cols - 1)
    cy = np.minimum(np.arange(ny) * step, rows - 1)
    gx, gy = np.meshgrid(geometry.x0 + geometry.scale * cx, geometry.y0 + geometry.scale * cy)
    with np.errstate(all="ignore"):
        coarse = predicted_error(np.stack([gx, gy], -1), calibration)
    coarse = np.where(np.isfinite(coarse), coarse / geometry.scale, np.inf)
    out = np.empty((rows, cols), np.float32)
    cols_f = np.interp(np.arange(cols, dtype=float), cx, np.arange(nx, dtype=float))
    for lo in range(0, rows, SPLINE_ROWS):
        r = np.arange(lo, min(lo + SPLINE_ROWS, rows), dtype=float)
        rows_f = np.interp(r, cy, np.arange(ny, dtype=float))
        with np.errstate(invalid="ignore"):
            out[lo : lo + len(r)] = _bilinear_on_grid(coarse, rows_f, cols_f)
    out[~np.isfinite(out)] = np.inf
    return out


def _cells(f: np.ndarray, n: int):
    """The lower node ``i0``, the upper node ``i1 = min(i0 + 1, n - 1)`` and the fraction
    ``f - i0`` of fractional grid indices ``f`` in ``[0, n - 1]``."""
    i0 = np.clip(np.floor(f).astype(np.intp), 0, n - 1)
    return i0, np.minimum(i0 + 1, n - 1), f - i0


def _bilinear_on_grid(values: np.ndarray, rows_f: np.ndarray, cols_f: np.ndarray) -> np.ndarray:
    """Bilinear interpolation of ``values (ny, nx)`` at the fractional grid indices
    ``rows_f (R,) x cols_f (C,)`` (each in ``[0, n - 1]``), ``(R, C)`` float64: the result of
    ``scipy.ndimage.map_coordinates(values, ..., order=1, mode="nearest")`` on the grid.

    Written out because the grid is regular and separable (one node and fraction per row
    and per column: interpolate the rows, then the columns), and because importing
    ``scipy.ndimage`` costs a command about a third of a second, more than the whole
    trust region.  Like ``map_coordinates``, all four nodes of a cell enter the sum, with
    their weights: a non-finite node makes its cell non-finite even at a zero weight
    (``0 * inf`` is NaN), so a pixel next to an untrusted node is never trusted.
    (``tests/imaging/test_remap_bilinear.py`` compares the two.)"""
    values = np.asarray(values, float)
    r0, r1, fr = _cells(np.asarray(rows_f, float), values.shape[0])
    c0, c1, fc = _cells(np.asarray(cols_f, float), values.shape[1])
    with np.errstate(invalid="ignore"):
        along = (1.0 - fr)[:, None] * values[r0] + fr[:, None] * values[r1]  # (R, nx)
        return (1.0 - fc) * along[:, c0] + fc * along[:, c1]


def trust_summary(
    calibration,
    geometry: OutputGeometry,
    max_error_px: float | None = None,
    predicted: np.ndarray | None = None,
) -> dict:
    """Where the output of ``geometry`` extrapolates, and how well it is predicted: on a grid
    of at most :data:`ERROR_SAMPLES` points along the longer side, ``{"output_px",
    "outside_fraction", "max_distance_px", "max_predicted_px", "median_predicted_outside_px",
    "max_error_px", "trusted_fraction", "has_error_model"}`` (distances and errors in
    output px; ``trusted_fraction`` the share with a predicted error of
    at most ``max_error_px``, from ``predicted`` when given, None without a threshold)."""
    from oapcal.uncertainty import extrapolation_report

    rows, cols = geometry.shape
    n = max(ERROR_SAMPLES["finite-difference"], 2)
    step = max(1.0, (max(rows, cols) - 1) / (n - 1))
    cx = np.unique(np.minimum(np.arange(int(np.ceil((cols - 1) / step)) + 1) * step, cols - 1))
    cy = np.unique(np.minimum(np.arange(int(np.ceil((rows - 1) / step)) + 1) * step, rows - 1))
    gx, gy = np.meshgrid(geometry.x0 + geometry.scale * cx, geometry.y0 + geometry.scale * cy)
    with np.errstate(all="ignore"):
        rep = extrapolation_report(calibration, np.stack([gx.ravel(), gy.ravel()], -1))
    trusted = None
    coarse = np.asarray(rep.pop("predicted")) / geometry.scale
    if max_error_px is not None:
        if predicted is not None:
            trusted = float((np.isfinite(predicted) & (predicted <= max_error_px)).mean())
        else:
            trusted = float(np.mean(coarse <= max_error_px))

    def px(v):
        return None if v is None else float(v) / geometry.scale

    return {
        "output_px": [int(cols), int(rows)],
        "outside_fraction": rep["outside"] / max(rep["n"], 1),
        "max_distance_px": px(rep["max_distance_px"]),
        "max_predicted_px": px(rep["max_predicted_px"]),
        "median_predicted_outside_px": px(rep["median_predicted_outside_px"]),
        "max_error_px": max_error_px,
        "trusted_fraction": trusted,
        "has_error_model": getattr(calibration, "error_model", None) is not None,
    }


def mask_untrusted(cmap: CorrectionMap, predicted: np.ndarray, max_error_px: float) -> CorrectionMap:
    """``cmap`` with every output pixel whose ``predicted`` error exceeds ``max_error_px``
    sampling nothing (it gets the border value), and the error and threshold kept.
    Raises :class:`DataError` when no pixel is trusted."""
    if not max_error_px > 0:
        raise DataError(f"max_error_px must be positive, got {max_error_px}", param="max_error_px")
    trusted = np.isfinite(predicted) & (predicted <= max_error_px)
    if trusted.mean() < MIN_SAMPLED_FRACTION:
        raise DataError(
            f"{'no' if not trusted.any() else 'almost no'} output pixel (under {MIN_SAMPLED_FRACTION:.1%}) "
            f"has a predicted error of {max_error_px:g} px or less (the smallest is "
            f"{float(np.nanmin(predicted)):.3g} px): the calibration does not support a correction this "
            "accurate here; raise the threshold, or correct the whole output without a trust region "
            "(max_error_px None; on the command line an explicit extent)",
            param=("max_error_px", "extent"),
        )
    map_x = np.where(trusted, cmap.map_x, np.float32(MASKED)).astype(np.float32)
    map_y = np.where(trusted, cmap.map_y, np.float32(MASKED)).astype(np.float32)
    return CorrectionMap(map_x, map_y, cmap.geometry, cmap.input_shape, predicted.astype(np.float32),
                         float(max_error_px))  # fmt: skip


def correction_map(
    calibration_or_params,
    shape: tuple[int, int],
    *,
    extent: str = "input",
    um_per_px: float | None = None,
    out_size: tuple[int, int] | None = None,
    geometry: OutputGeometry | None = None,
    check: bool = True,
    allow_size_mismatch: bool = False,
    max_error_px: float | None = None,
) -> CorrectionMap:  # 9 parameters: the public keyword options of oapcal correct's map
    """The correction map for distorted images of ``shape = (rows, cols)``.

    Output pixel ``(col, row)`` shows the undistorted point
    ``(x_u, y_u) = (x0 + scale * col, y0 + scale * row)`` and samples the distorted image at
    ``distort((x_u, y_u))``.  The geometry comes from :func:`output_geometry` with
    ``extent``, ``um_per_px`` and ``out_size``, or is given as ``geometry``.  By default the
    output has the input's shape and output pixel ``(col, row)`` is the undistorted point
    ``(col, row)``.

    A map that samples no pixel of the input (:func:`check_map_samples`) raises
    :class:`EmptyMapError`, unless ``check`` is False.  A calibration with an
    ``image_size`` other than ``shape`` raises :class:`DataError` unless
    ``allow_size_mismatch`` (as ``oapcal correct`` refuses it without
    ``--allow-size-mismatch``).

    ``max_error_px`` (default None: every output pixel) builds the **trust region**: output
    pixels whose predicted error (:func:`predicted_error_map`) exceeds it sample nothing
    and get the border value when the map is applied; the map keeps ``predicted_error``.
    ``oapcal correct`` builds its maps with :data:`DEFAULT_MAX_ERROR_PX` unless told
    otherwise.
    """
    model = _model_of(calibration_or_params)
    if not allow_size_mismatch:
        _check_camera(getattr(calibration_or_params, "image_size", None), shape)
    if geometry is None:
        geometry = output_geometry(
            calibration_or_params, shape, extent=extent, um_per_px=um_per_px, out_size=out_size,
            trust_region=max_error_px is not None,
        )  # fmt: skip
    rows, cols = geometry.shape
    _check_map_memory(rows, cols)
    xs = geometry.x0 + geometry.scale * np.arange(cols, dtype=float)
    ys = geometry.y0 + geometry.scale * np.arange(rows, dtype=float)
    out_x = np.empty((rows, cols), np.float32)
    out_y = np.empty((rows, cols), np.float32)
    family = model.family
    if family.map_step and min(rows, cols) > 4 * family.map_step:
        _spline_map(model, xs, ys, family.map_step, out_x, out_y)
    else:
        _grid_map(model, xs, ys, out_x, out_y)
    if check:
        check_map_samples((out_x, out_y), shape)
    cmap = CorrectionMap(out_x, out_y, geometry, (int(shape[0]), int(shape[1])))
    if max_error_px is not None:
        if isinstance(calibration_or_params, np.ndarray) or not hasattr(calibration_or_params, "covariance"):
            raise DataError(
                "a trust region (max_error_px) needs a calibration, with its covariance: bare parameters "
                "know no uncertainty",
                param="max_error_px",
            )
        cmap = mask_untrusted(cmap, predicted_error_map(calibration_or_params, geometry), max_error_px)
    return cmap


def _check_camera(cal_size, shape) -> None:
    """Refuse images of another size than the calibration's ``image_size`` (when it has one)."""
    rows_in, cols_in = int(shape[0]), int(shape[1])
    if cal_size and tuple(int(v) for v in cal_size) != (cols_in, rows_in):
        raise DataError(
            f"the image is {cols_in}x{rows_in} px but the calibration is for {cal_size[0]}x{cal_size[1]} px "
            "images; give images of that camera, or allow_size_mismatch=True to correct it anyway",
            param="allow_size_mismatch",
        )


def _check_map_memory(rows: int, cols: int) -> None:
    """Refuse a map of more than :data:`MAX_MAP_BYTES`."""
    if 8 * rows * cols > MAX_MAP_BYTES:
        raise DataError(
            f"the correction map for a {cols}x{rows} px output would need "
            f"{8 * rows * cols / 2**30:.3g} GiB of memory, over the {MAX_MAP_BYTES / 2**30:g} GiB "
            "limit; choose a smaller out_size, a coarser um_per_px or another extent",
            param=("out_size", "um_per_px", "extent"),
        )


def _grid_map(model: Model, xs, ys, out_x, out_y) -> None:
    """The model's compiled point function over the separable grid, rows in parallel; for
    an Eq. (1) map of a process that has not loaded the kernels, at most
    :data:`oapcal.eq1_closed_form.MAX_POINTS` px, the same expressions in NumPy
    (:func:`oapcal.eq1_closed_form.applies`: the map costs less than loading the kernels)."""
    if eq1_closed_form.applies(model.family, out_x.size, model.params):
        eq1_closed_form.grid_map(model.params, xs, ys, out_x, out_y)
        return
    from oapcal import _kernels
    from oapcal.model import kernel_array

    rows, cols = out_x.shape
    block = _kernels.block_size(rows, -(-(1 << 20) // max(cols, 1)))  # threads only for > 1 Mpx
    _kernels.run_blocks(_kernels.grid_map, rows, block, model.family.code,
                        kernel_array(model.params), xs, ys, out_x, out_y)  # fmt: skip


#: Output rows interpolated at a time by :func:`_spline_map` (bounds its float64 temporaries).
SPLINE_ROWS = 256


def _spline_map(model: Model, xs, ys, step: int, out_x, out_y) -> None:
    """The map of a family whose point function is costly (the relay traces a chief ray per
    point, ~2 us): the model exactly on a grid every ``step`` output px (ends included),
    then bicubic splines (:class:`scipy.interpolate.RectBivariateSpline`) in between.  The
    field is smooth on that scale: at ``step`` 8 the map equals the per-pixel one to float32
    rounding (tests/imaging/test_remap_families.py), ~15x faster at 640 x 480."""
    from scipy.interpolate import RectBivariateSpline

    def nodes(v):
        return np.linspace(v[0], v[-1], max(4, int(np.ceil(abs(v[-1] - v[0]) / step)) + 1))

    cx, cy = nodes(xs), nodes(ys)
    gx, gy = np.meshgrid(cx, cy)
    d = model(np.stack([gx.ravel(), gy.ravel()], -1)).reshape(len(cy), len(cx), 2)
    splines = [RectBivariateSpline(cy, cx, d[..., k], kx=3, ky=3) for k in (0, 1)]
    for lo in range(0, len(ys), SPLINE_ROWS):
        hi = min(lo + SPLINE_ROWS, len(ys))
        out_x[lo:hi] = splines[0](ys[lo:hi], xs)
        out_y[lo:hi] = splines[1](ys[lo:hi], xs)


_CV2_INTERP = {"nearest": 0, "linear": 1, "cubic": 2, "lanczos": 4}  # cv2.INTER_* values


#: cv2.remap refuses images and maps with a side of this many pixels or more (SHRT_MAX).
REMAP_LIMIT = 32767
#: Output tile side used when an image or map is too large for one cv2.remap call.
REMAP_TILE = 4096
#: Source pixels kept around a tile's footprint: covers the widest kernel (Lanczos, 8 taps).
_PAD = 6


def check_image(image, maps, out=None, *, allow_size_mismatch: bool = False) -> np.ndarray:
    """``image`` as an array once it is what :func:`correct_image` corrects, with the rules of
    ``oapcal correct``; else :class:`DataError` saying what to give.

    Refused: anything but a grey ``(rows, cols)`` or colour ``(rows, cols, 1, 3 or 4)``
    image (a stack ``(frames, rows, cols)`` is corrected frame by frame:
    :func:`oapcal.batch.stack.correct_frames`), a pixel type other than
    :data:`oapcal.validate.IMAGE_DTYPES`, an image of another size than the map was built for (when the map
    knows it; ``allow_size_mismatch`` allows it), and an ``out`` that is not a writable
    array of the output's shape and the image's dtype.
    """
    image = _valid_image(image)  # an array of pixels of a supported type, at least 2-D
    if image.ndim not in (2, 3) or (image.ndim == 3 and image.shape[2] not in (1, 3, 4)) or 0 in image.shape:
        raise DataError(
            f"an image of shape {image.shape} cannot be corrected: give one grey (rows, cols) or colour "
            "(rows, cols, 3 or 4) image; correct a stack (frames, rows, cols) frame by frame "
            "(oapcal.batch.stack.correct_frames)",
        )
    map_x = maps.map_x if isinstance(maps, CorrectionMap) else maps[0]
    expected = getattr(maps, "input_shape", None)
    if expected and tuple(image.shape[:2]) != tuple(expected) and not allow_size_mismatch:
        raise DataError(
            f"the image is {image.shape[1]}x{image.shape[0]} px but the map was built for "
            f"{expected[1]}x{expected[0]} px images; build a map for this size or give "
            "allow_size_mismatch=True to correct it anyway",
            param="allow_size_mismatch",
        )
    if out is not None:
        want = tuple(map_x.shape) + image.shape[2:]
        shapes = {want, tuple(map_x.shape)} if image.shape[2:] == (1,) else {want}
        if (
            not isinstance(out, np.ndarray)
            or tuple(out.shape) not in shapes
            or out.dtype != image.dtype
            or not out.flags.c_contiguous
            or not out.flags.writeable
        ):
            got = f"{out.shape} {out.dtype}" if isinstance(out, np.ndarray) else type(out).__name__
            raise DataError(
                f"out must be a writable C-contiguous array of shape {want} and dtype {image.dtype} "
                f"(the output's), got {got}",
                param="out",
            )
    return image


def correct_image(
    image: np.ndarray,
    maps,
    interp: str = "linear",
    border: float = 0,
    out: np.ndarray | None = None,
    *,
    allow_size_mismatch: bool = False,
) -> np.ndarray:
    """Correct one image (grey ``(rows, cols)`` or colour ``(rows, cols, ch)``) with a map
    from :func:`correction_map`; the output has the map's shape and keeps the input's dtype.

    Pixels whose source falls outside the input get the value ``border`` (in every
    channel).  ``out`` (an array of the output's shape and dtype) receives the result and
    is returned.  The image is checked first (:func:`check_image`): a stack, an unsupported
    pixel type, an image of another size than the map's (unless ``allow_size_mismatch``)
    or a wrong ``out`` raise :class:`DataError`.  Images or maps with a side of 32767 px
    or more (beyond ``cv2.remap``) are corrected tile by tile, with the same result.
    """
    import cv2

    if interp not in _CV2_INTERP:
        raise DataError(f"unknown interpolation {interp!r}: use one of {', '.join(INTERPOLATIONS)}")
    image = check_image(image, maps, out, allow_size_mismatch=allow_size_mismatch)
    map_x, map_y = maps
    if max(image.shape[:2]) < REMAP_LIMIT and max(map_x.shape) < REMAP_LIMIT:
        result = _remap(
            image, map_x, map_y, _CV2_INTERP[interp], dst=out, borderMode=cv2.BORDER_CONSTANT,
            borderValue=(border,) * 4,
        )  # fmt: skip
        if out is not None and result is not out:  # OpenCV made a new array: out receives it
            out[...] = result.reshape(out.shape)
            result = out
        return result
    if out is None:
        out = np.empty(map_x.shape + image.shape[2:], image.dtype)
    for r0 in range(0, map_x.shape[0], REMAP_TILE):
        for c0 in range(0, map_x.shape[1], REMAP_TILE):
            tile = (slice(r0, r0 + REMAP_TILE), slice(c0, c0 + REMAP_TILE))
            _remap_tile(image, map_x, map_y, tile, interp, border, out)
    return out


def _remap(*args, **kwargs):
    """``cv2.remap``, its errors as :class:`DataError` (one line, no C++ source path)."""
    import cv2

    try:
        return cv2.remap(*args, **kwargs)
    except cv2.error as exc:
        lines = [ln for ln in str(exc).splitlines() if ln.strip()]
        reason = lines[-1].split(") ", 1)[-1] if lines else "unknown error"
        raise DataError(f"OpenCV cannot correct this image: {reason}") from None


def _remap_tile(image, map_x, map_y, tile, interp, border, out) -> None:
    """Correct the output pixels ``tile`` (two slices) from the part of ``image`` their map
    values reach (plus a margin for the kernel); split the tile if that part is too large."""
    import cv2

    mx, my = map_x[tile], map_y[tile]
    rows, cols = image.shape[:2]
    ok = np.isfinite(mx) & np.isfinite(my)
    if ok.any():
        x0 = max(0, int(np.floor(mx[ok].min())) - _PAD)
        x1 = min(cols, int(np.ceil(mx[ok].max())) + _PAD + 1)
        y0 = max(0, int(np.floor(my[ok].min())) - _PAD)
        y1 = min(rows, int(np.ceil(my[ok].max())) + _PAD + 1)
    else:
        x0 = x1 = y0 = y1 = 0
    if x1 <= x0 or y1 <= y0:  # every source pixel is outside the image
        out[tile] = border
        return
    if x1 - x0 >= REMAP_LIMIT or y1 - y0 >= REMAP_LIMIT or max(mx.shape) >= REMAP_LIMIT:
        h, w = mx.shape
        if h * w <= 1:
            raise DataError("a correction map that spans more than 32767 px at one pixel cannot be applied")
        (rs, cs) = tile
        r0, c0 = rs.start, cs.start
        r1, c1 = r0 + h, c0 + w
        if h >= w:
            halves = [(slice(r0, r0 + h // 2), cs), (slice(r0 + h // 2, r1), cs)]
        else:
            halves = [(rs, slice(c0, c0 + w // 2)), (rs, slice(c0 + w // 2, c1))]
        for half in halves:
            _remap_tile(image, map_x, map_y, half, interp, border, out)
        return
    crop = np.ascontiguousarray(image[y0:y1, x0:x1])
    # Subtracting whole numbers is exact in float32 here, so the result equals one remap.
    result = _remap(
        crop, mx - np.float32(x0), my - np.float32(y0), _CV2_INTERP[interp],
        borderMode=cv2.BORDER_CONSTANT, borderValue=(border,) * 4,
    )  # fmt: skip
    out[tile] = result.reshape(out[tile].shape)
