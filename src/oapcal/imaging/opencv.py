"""A calibration as OpenCV camera parameters, so OpenCV alone can correct images (the
conversion; :mod:`oapcal.io.opencv_export` writes the files).

oapcal's model (Eq. 1) is OpenCV's distortion model in other units: with any scale ``F``
(here ``F = max(width, height)`` of the input image), normalized coordinates
``x = xb / F`` turn the model into OpenCV's with

* ``camera_matrix = [[F, 0, c_x], [0, F, c_y], [0, 0, 1]]``,
* ``dist_coeffs = [k1 F^2, k2 F^4, p1 F, p2 F, 0, 0, 0, 0, s1 F, s2 F^3, s3 F, s4 F^3]``
  (OpenCV's order ``k1 k2 p1 p2 k3 k4 k5 k6 s1 s2 s3 s4``; oapcal's ``p1``/``p2`` already
  follow OpenCV's convention),
* ``new_camera_matrix = [[F/(m s), 0, -(x0 + x_off)/s], [0, F/(m s), -(y0 + y_off)/s], [0, 0, 1]]``
  for the output geometry ``(x0, y0, s)`` (default ``x0 = y0 = 0``, ``s = 1``).

``cv2.initUndistortRectifyMap(camera_matrix, dist_coeffs, None, new_camera_matrix,
new_image_size, cv2.CV_32FC1)`` computes, for output pixel ``u``, ``x = (u - cx') / fx' =
m (x0 + s u + x_off) / F = xb / F``, distorts it, and returns ``F x'' + c_x``: oapcal's map.

The other model families (:func:`opencv_export`):

* Eq. (1) with the target's rotation (``brown-conrady+rotation``) is exact too: the
  rotation by ``theta`` of the reference points is OpenCV's rectification rotation
  ``R = [[cos, sin, 0], [-sin, cos, 0], [0, 0, 1]]`` (``R^-1`` turns the normalized
  coordinates by ``theta``), with the offsets turned back by ``theta`` into
  ``new_camera_matrix``; pass ``R`` to ``initUndistortRectifyMap``.
* Eq. (1) with the perspective terms (``brown-conrady+tilt``) is exact as well, through the
  same ``R``, which is then a homography: the terms act on the reference points before the
  distortion, ``w = 1 + tilt . (Rot(theta) u + off)``, and in OpenCV's normalized
  coordinates ``q = m (Rot(theta) u + off) / F`` that is ``w = 1 + (F / m) tilt . q``, so
  ``R = Rot(-theta) T^-1`` with ``T^-1 = [[1, 0, 0], [0, 1, 0], [-F tilt_x / m, -F tilt_y / m, 1]]``
  (``initUndistortRectifyMap`` and ``undistortPoints`` divide by the third coordinate).
  OpenCV's own tilted model (``tauX``, ``tauY``, ``dist_coeffs`` 13-14) is not used: it tilts
  the image after the distortion, and its angles also set an anisotropic scale and shear
  that no Eq. (1) model has, so it cannot hold these terms exactly.
* The physical relay has no OpenCV coefficient set: the export holds the exact dense maps
  (``map_x``, ``map_y`` for ``cv2.remap``, oapcal's :func:`~oapcal.imaging.remap.correction_map`)
  and the best Eq. (1) approximation's coefficients, with that approximation's error in
  px (:func:`brown_conrady_approximation`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from oapcal.errors import DataError
from oapcal.imaging.remap import CorrectionMap, OutputGeometry
from oapcal.model import (
    BROWN_CONRADY,
    BROWN_CONRADY_POSE,
    BROWN_CONRADY_TILT,
    INDEX,
    N_PARAMS,
    ModelFamily,
    family_of,
    scale_params,
)
from oapcal.records import ImageSize

#: Memory of a relay export per output pixel: the exact maps (8 B), the approximation's maps
#: and their error in float64 (about 30 B): measured 41 B (290 MB at 1024 x 1024, 420 MB at
#: 2048 x 2048); with room.
EXPORT_BYTES_PER_PX = 48
#: Largest memory estimate of an export (4 GiB): about 9,400 x 9,400 output px.
MAX_EXPORT_BYTES = 4 * 2**30


#: The families OpenCV's coefficients (with ``R`` for the rotation and the tilt) reproduce exactly.
EXACT_FAMILIES = (BROWN_CONRADY, BROWN_CONRADY_POSE, BROWN_CONRADY_TILT)


def _params_and_family(value) -> tuple[np.ndarray, ModelFamily]:
    """The parameter vector of a calibration, a :class:`~oapcal.model.Model` or a bare vector,
    and its family: the one it carries, else (a bare vector) the built-in family of its length."""
    params = np.asarray(getattr(value, "params", value), float)
    carried = getattr(value, "family", None)
    return params, family_of(params, carried if isinstance(carried, ModelFamily) else None)


def opencv_parameters(params, image_size: tuple[int, int], geometry: OutputGeometry | None = None) -> dict:
    """OpenCV's ``camera_matrix`` (3x3), ``dist_coeffs`` (12) and ``new_camera_matrix``
    (3x3) reproducing oapcal's correction map, plus ``image_size`` and ``new_image_size``
    (``[width, height]``, the latter to pass to ``initUndistortRectifyMap``).

    ``image_size`` is the distorted input's ``(width, height)``; ``geometry`` the output
    geometry (default: the input's size and coordinates).  ``params`` is Eq. (1) ``(13,)``,
    or Eq. (1) with the target's rotation ``(14,)`` or the perspective terms ``(16,)``: then
    the export also holds ``R``, the rectification rotation (with the perspective terms a
    homography) to pass to ``initUndistortRectifyMap``, plus ``model_family`` and ``exact``.
    The relay has no such parameters (:func:`opencv_export`).

    >>> from oapcal.model import params_from_dict
    >>> d = opencv_parameters(params_from_dict({"k1": 1e-7, "c_x": 320, "x_off": -320}), (640, 480))
    >>> d["camera_matrix"][0], round(d["dist_coeffs"][0], 12), d["new_camera_matrix"][0]
    ([640.0, 0.0, 320.0], 0.04096, [640.0, 0.0, 320.0])
    """
    params, family = _params_and_family(params)
    if family not in EXACT_FAMILIES or params.shape != (family.n_params,):
        raise DataError(
            f"no OpenCV camera parameters reproduce the {family.name} model; export it with "
            "opencv_export (the exact maps and the best Eq. (1) approximation)"
        )
    rotation = tilt = None
    if family is BROWN_CONRADY_TILT:
        params, tilt = params[: N_PARAMS + 1], params[N_PARAMS + 1 :]
    if family is not BROWN_CONRADY:
        params, rotation = _rectification(params)
    size = _image_size(image_size)
    width, height = size
    if geometry is None:
        geometry = OutputGeometry(size.shape)
    f = float(max(width, height))
    # scale_params(p, f) is the model for coordinates divided by f: exactly OpenCV's units.
    q = scale_params(params, f)
    k1, k2, p1, p2, s1, s2, s3, s4 = (
        float(q[INDEX[n]]) for n in ("k1", "k2", "p1", "p2", "s1", "s2", "s3", "s4")
    )
    m = float(params[INDEX["m"]])
    s = float(geometry.scale)
    if not np.isfinite([geometry.x0, geometry.y0, s]).all():
        raise DataError(
            "the output geometry is unknown (a map loaded from .npy/.tiff); export needs a calibration"
        )
    fx_new = f / (m * s)
    cam = [[f, 0.0, float(params[INDEX["c_x"]])], [0.0, f, float(params[INDEX["c_y"]])], [0.0, 0.0, 1.0]]
    new = [
        [fx_new, 0.0, -(geometry.x0 + float(params[INDEX["x_off"]])) / s],
        [0.0, fx_new, -(geometry.y0 + float(params[INDEX["y_off"]])) / s],
        [0.0, 0.0, 1.0],
    ]
    out = {
        "camera_matrix": cam,
        "dist_coeffs": [k1, k2, p1, p2, 0.0, 0.0, 0.0, 0.0, s1, s2, s3, s4],
        "new_camera_matrix": new,
        "image_size": [width, height],
        "new_image_size": list(ImageSize.of(geometry)),
        "um_per_px": geometry.um_per_px,
    }
    if tilt is not None:  # R = Rot(-theta) T^-1 (the module's docstring)
        rotation = (np.array(rotation) @ [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [*(-f * tilt / m), 1.0]]).tolist()
    if rotation is not None:
        out = {"model_family": family.name, "exact": True, **out, "R": rotation}
    return out


def _image_size(image_size) -> ImageSize:
    """``image_size`` ``(width, height)`` as whole px."""
    return ImageSize(int(image_size[0]), int(image_size[1]))


def _rectification(params: np.ndarray) -> tuple[np.ndarray, list]:
    """Eq. (1) with the target's rotation ``(14,)`` as Eq. (1) ``(13,)`` (its offsets turned
    back) and OpenCV's rectification rotation ``R``.

    Eq. (1) of Rot(theta) u: m (Rot(theta) u + off) = Rot(theta) m (u + Rot(-theta) off);
    OpenCV applies R^-1 to the normalized coordinates, so R = Rot(-theta).
    """
    theta = np.deg2rad(params[N_PARAMS])
    c, s = float(np.cos(theta)), float(np.sin(theta))
    params = params[:N_PARAMS].copy()
    off = params[[INDEX["x_off"], INDEX["y_off"]]]
    params[INDEX["x_off"]], params[INDEX["y_off"]] = c * off[0] + s * off[1], -s * off[0] + c * off[1]
    return params, [[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]]


#: Samples along the longer side of the output of the grid on which the Eq. (1)
#: approximation of another family is fitted (:func:`brown_conrady_approximation`).
APPROX_GRID = 64
#: Fewest grid samples inside the input image for that fit.
APPROX_MIN_SAMPLES = 100


@dataclass(frozen=True)
class Approximation:
    """The best Eq. (1) approximation of another family's correction map.

    ``params`` ``(13,)`` is Eq. (1) 'full' in the calibration's coordinates; ``mean_px`` and
    ``max_px`` the distance (input px) between the approximation's and the exact map over
    the ``n_pixels`` output pixels whose exact source lies in the input image; the
    ``calibrated_*`` values the same over those of them inside the calibration's bounds
    (None without bounds or when none is inside); ``converged`` the fit's verdict.
    """

    params: np.ndarray
    mean_px: float
    max_px: float
    n_pixels: int
    calibrated_mean_px: float | None
    calibrated_max_px: float | None
    n_calibrated: int
    converged: bool

    def to_dict(self) -> dict:
        return {
            "model": "brown-conrady full (Eq. 1, all 13 terms)",
            "mean_px": self.mean_px,
            "max_px": self.max_px,
            "n_pixels": self.n_pixels,
            "over": "output pixels whose exact source lies in the input image",
            "calibrated_mean_px": self.calibrated_mean_px,
            "calibrated_max_px": self.calibrated_max_px,
            "n_calibrated_pixels": self.n_calibrated,
            "converged": self.converged,
        }


def _inside(map_x, map_y, image_size) -> np.ndarray:
    """Where a map's source lies in an input of ``image_size = (width, height)`` (pixel
    centres ``0 .. width - 1``, ``0 .. height - 1``)."""
    w, h = image_size
    with np.errstate(invalid="ignore"):
        return (map_x >= 0) & (map_x <= w - 1) & (map_y >= 0) & (map_y <= h - 1)


def _check_samples(calibration_or_params, params, image_size, geometry: OutputGeometry) -> None:
    """:func:`~oapcal.imaging.remap.check_model_samples`, its message naming the image size the
    calibration was made for when the image is another."""
    from oapcal.imaging.remap import EmptyMapError, check_model_samples

    made_for = getattr(calibration_or_params, "image_size", None)
    try:
        check_model_samples(params, _image_size(image_size).shape, geometry)
    except EmptyMapError as exc:
        if made_for is None or tuple(made_for) == tuple(image_size):
            raise
        raise EmptyMapError(
            f"{exc}; the calibration was made for {made_for[0]}x{made_for[1]} px, not "
            f"{image_size[0]}x{image_size[1]}",
            param=exc.param,
        ) from None


def _approximation_samples(calibration_or_params, image_size, geometry: OutputGeometry):
    """The samples of the forward map an approximation is fitted to (``xy_u``, ``xy_d`` and
    whether ``xy_d`` lies in the input), refused when too few lie in the input: cheap, so
    checked before any map is built."""
    from oapcal.model import distort

    params = np.asarray(getattr(calibration_or_params, "params", calibration_or_params), float)
    width, height = image_size
    rows, cols = geometry.shape
    n_long = min(APPROX_GRID, max(rows, cols))
    nx = max(2, min(cols, round(n_long * cols / max(rows, cols))))
    ny = max(2, min(rows, round(n_long * rows / max(rows, cols))))
    gx, gy = np.meshgrid(np.linspace(0, cols - 1, nx), np.linspace(0, rows - 1, ny))
    xy_u = np.stack([gx.ravel(), gy.ravel()], -1) * geometry.scale + (geometry.x0, geometry.y0)
    with np.errstate(all="ignore"):
        xy_d = distort(xy_u, params)
    keep = _inside(xy_d[:, 0], xy_d[:, 1], (width, height))
    if keep.sum() >= APPROX_MIN_SAMPLES:
        return xy_u, xy_d, keep
    found = f"{int(keep.sum())} of {len(keep)} samples"
    is_input = (geometry.shape == ImageSize(width, height).shape and geometry.x0 == 0 and geometry.y0 == 0
                and geometry.scale == 1)  # fmt: skip
    if is_input:  # the output already is the input's region: the image is the wrong size
        made = getattr(calibration_or_params, "image_size", None)
        made = f" (the calibration was made for {made[0]}x{made[1]} px)" if made else ""
        raise DataError(
            f"the model maps only {found} of the {width}x{height} px image into itself: its field "
            f"covers too little of an image this size to fit an Eq. (1) approximation; give the image "
            f"size the calibration was made for{made}",
            param="image_size",
        )
    raise DataError(
        f"the output region shows too little of the {width}x{height} px input image ({found}) to fit "
        "an Eq. (1) approximation; use extent 'input' or a larger output",
        param=("extent", "out_size", "um_per_px"),
    )


def brown_conrady_approximation(
    calibration_or_params,
    image_size: tuple[int, int],
    geometry: OutputGeometry,
    exact: CorrectionMap | None = None,
) -> Approximation:
    """Fit Eq. (1) 'full' to a model's forward map and measure it against the exact map.

    The forward map is sampled on a grid of :data:`APPROX_GRID` points along the output's
    longer side (output pixels of ``geometry``, i.e. the undistorted points they show)
    whose distorted point lies in the input image of ``image_size = (width, height)``,
    and fitted with :func:`oapcal.fitting.fit` (in the units the solver scales to).  The
    error is the distance between the approximation's correction map and ``exact`` (the
    model's :func:`~oapcal.imaging.remap.correction_map` for ``geometry``; built when not
    given) at every output pixel whose exact source lies in the input image.
    """
    from oapcal.fitting import fit
    from oapcal.imaging.remap import correction_map

    params = np.asarray(getattr(calibration_or_params, "params", calibration_or_params), float)
    size = _image_size(image_size)
    xy_u, xy_d, keep = _approximation_samples(calibration_or_params, size, geometry)
    if exact is None:
        exact = correction_map(params, size.shape, geometry=geometry)
    rows, cols = geometry.shape
    result = fit(xy_u[keep], xy_d[keep], "full")
    approx = np.asarray(result.params, float)
    inside = _inside(exact.map_x, exact.map_y, size)
    if np.isfinite(approx).all():
        ax, ay = correction_map(approx, size.shape, geometry=geometry, check=False)
        err = np.hypot(ax.astype(float) - exact.map_x, ay.astype(float) - exact.map_y)
    else:
        err = np.full(exact.shape, np.nan)
    over = err[inside]
    bounds = getattr(calibration_or_params, "bounds", None)
    cal_mean = cal_max = None
    n_cal = 0
    if bounds is not None:
        xs = geometry.x0 + geometry.scale * np.arange(cols)
        ys = geometry.y0 + geometry.scale * np.arange(rows)
        in_x = (xs >= bounds[0]) & (xs <= bounds[2])
        in_box = ((ys >= bounds[1]) & (ys <= bounds[3]))[:, None] & in_x[None]
        sub = err[inside & in_box]
        n_cal = int(sub.size)
        if n_cal:
            cal_mean, cal_max = float(sub.mean()), float(sub.max())
    return Approximation(
        params=approx,
        mean_px=float(over.mean()) if over.size else float("nan"),
        max_px=float(over.max()) if over.size else float("nan"),
        n_pixels=int(over.size),
        calibrated_mean_px=cal_mean,
        calibrated_max_px=cal_max,
        n_calibrated=n_cal,
        converged=bool(result.converged),
    )


def opencv_export(calibration_or_params, image_size: tuple[int, int], geometry: OutputGeometry | None = None):
    """What ``oapcal export-opencv`` writes, for a calibration of any model family.

    Eq. (1): :func:`opencv_parameters` (exact).  Eq. (1) with the target's rotation: the
    same with the rectification rotation ``R`` (exact); with the perspective terms, ``R`` a
    homography (exact).  The relay: ``model_family``,
    ``exact`` False, ``maps`` (the exact :class:`~oapcal.imaging.remap.CorrectionMap` for
    ``cv2.remap``), the best Eq. (1) approximation's ``camera_matrix``, ``dist_coeffs``
    and ``new_camera_matrix`` (:func:`brown_conrady_approximation`) and its error in
    ``approximation`` (a dict), and a ``note`` saying so.

    A calibration whose correction map samples no pixel of the image raises
    :class:`~oapcal.imaging.remap.EmptyMapError`, whatever the family.
    """
    from oapcal.imaging.remap import correction_map

    params, family = _params_and_family(calibration_or_params)
    size = _image_size(image_size)
    if geometry is None:
        geometry = OutputGeometry(size.shape)
    if family in EXACT_FAMILIES:
        # coefficients only, but a calibration whose map samples nothing of the image is refused
        _check_samples(calibration_or_params, params, size, geometry)
        return opencv_parameters(params, size, geometry)
    rows, cols = geometry.shape
    need = EXPORT_BYTES_PER_PX * rows * cols
    if need > MAX_EXPORT_BYTES:
        raise DataError(
            f"exporting the {family.name} model's exact maps for a {cols}x{rows} px output would need "
            f"about {need / 2**30:.3g} GiB of memory, over the {MAX_EXPORT_BYTES / 2**30:g} GiB limit; "
            "give a smaller image size or output (the maps hold every output pixel)",
            param=("image_size", "out_size", "um_per_px"),
        )
    _check_samples(calibration_or_params, params, size, geometry)  # a map of nothing: refused
    _approximation_samples(calibration_or_params, size, geometry)  # cheap: before the maps
    exact = correction_map(params, size.shape, geometry=geometry)
    approx = brown_conrady_approximation(calibration_or_params, size, geometry, exact)
    coefficients = opencv_parameters(approx.params, size, geometry)
    note = (
        f"no OpenCV coefficient set reproduces the {family.name} model: the exact correction is "
        "cv2.remap with map_x, map_y; camera_matrix, dist_coeffs and new_camera_matrix are the best "
        f"Brown-Conrady (Eq. 1) approximation, off by {approx.mean_px:.3g} px mean and "
        f"{approx.max_px:.3g} px max over the image"
    )
    return {
        "model_family": family.name,
        "exact": False,
        **coefficients,
        "maps": exact,
        "approximation": approx.to_dict(),
        "note": note,
    }


def opencv_maps(export: dict) -> tuple[np.ndarray, np.ndarray]:
    """The maps OpenCV builds from an export's coefficients (what a user of
    ``docs/opencv.md`` gets; for the relay, its Eq. (1) approximation's maps)."""
    import cv2

    rotation = export.get("R")
    return cv2.initUndistortRectifyMap(
        np.array(export["camera_matrix"]),
        np.array(export["dist_coeffs"]),
        None if rotation is None else np.array(rotation, float),
        np.array(export["new_camera_matrix"]),
        tuple(export["new_image_size"]),
        cv2.CV_32FC1,
    )
