"""Export a calibration as OpenCV camera parameters, so OpenCV alone can correct images.

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
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from oapcal.errors import DataError, OutputError
from oapcal.imaging.remap import OutputGeometry
from oapcal.io.atomic import atomic_path, atomic_write
from oapcal.model import INDEX, scale_params

SUFFIXES = (".json", ".yml", ".yaml", ".xml")


def opencv_parameters(params, image_size: tuple[int, int], geometry: OutputGeometry | None = None) -> dict:
    """OpenCV's ``camera_matrix`` (3x3), ``dist_coeffs`` (12) and ``new_camera_matrix``
    (3x3) reproducing oapcal's correction map, plus ``image_size`` and ``new_image_size``
    (``[width, height]``, the latter to pass to ``initUndistortRectifyMap``).

    ``image_size`` is the distorted input's ``(width, height)``; ``geometry`` the output
    geometry (default: the input's size and coordinates).

    >>> from oapcal.model import params_from_dict
    >>> d = opencv_parameters(params_from_dict({"k1": 1e-7, "c_x": 320, "x_off": -320}), (640, 480))
    >>> d["camera_matrix"][0], round(d["dist_coeffs"][0], 12), d["new_camera_matrix"][0]
    ([640.0, 0.0, 320.0], 0.04096, [640.0, 0.0, 320.0])
    """
    params = np.asarray(getattr(params, "params", params), float)
    width, height = int(image_size[0]), int(image_size[1])
    if geometry is None:
        geometry = OutputGeometry((height, width))
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
    return {
        "camera_matrix": cam,
        "dist_coeffs": [k1, k2, p1, p2, 0.0, 0.0, 0.0, 0.0, s1, s2, s3, s4],
        "new_camera_matrix": new,
        "image_size": [width, height],
        "new_image_size": [int(geometry.shape[1]), int(geometry.shape[0])],
        "um_per_px": geometry.um_per_px,
    }


def opencv_maps(export: dict) -> tuple[np.ndarray, np.ndarray]:
    """The maps OpenCV builds from an export (what a user of ``docs/opencv.md`` gets)."""
    import cv2

    return cv2.initUndistortRectifyMap(
        np.array(export["camera_matrix"]),
        np.array(export["dist_coeffs"]),
        None,
        np.array(export["new_camera_matrix"]),
        tuple(export["new_image_size"]),
        cv2.CV_32FC1,
    )


def save_opencv(export: dict, path: str | Path, calibration_name: str | None = None) -> None:
    """Write an export as JSON (``.json``) or OpenCV FileStorage YAML/XML (``.yml``,
    ``.yaml``, ``.xml``), atomically."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in SUFFIXES:
        raise OutputError(f"{path}: the export file must end in {', '.join(SUFFIXES)}")
    if suffix == ".json":
        data = {"format": "oapcal-opencv", "version": 1, "calibration": calibration_name, **export}
        with atomic_write(path) as fh:
            fh.write(json.dumps(data, indent=2) + "\n")
        return
    import cv2

    with atomic_path(path) as tmp:
        fs = cv2.FileStorage(str(tmp), cv2.FILE_STORAGE_WRITE)
        try:
            fs.write("camera_matrix", np.array(export["camera_matrix"], float))
            fs.write("dist_coeffs", np.array(export["dist_coeffs"], float).reshape(1, -1))
            fs.write("new_camera_matrix", np.array(export["new_camera_matrix"], float))
            fs.write("image_size", np.array(export["image_size"], np.int32).reshape(1, 2))
            fs.write("new_image_size", np.array(export["new_image_size"], np.int32).reshape(1, 2))
            if export.get("um_per_px"):
                fs.write("um_per_px", float(export["um_per_px"]))
            if calibration_name:
                fs.write("calibration", str(calibration_name))
        finally:
            fs.release()
