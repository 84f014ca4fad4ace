"""Write an OpenCV export of a calibration: JSON (with the relay's maps in ``FILE.maps.npz``)
or OpenCV FileStorage YAML/XML.

What the export holds, and how oapcal's models become OpenCV's camera parameters, is the
conversion in :mod:`oapcal.imaging.opencv` (:func:`opencv_parameters`, :func:`opencv_export`,
:func:`brown_conrady_approximation`); its names are importable from here too.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from oapcal.errors import OutputError

# The conversion lives beside the model; these names stay importable from here.
from oapcal.imaging.opencv import (  # noqa: F401
    APPROX_GRID,
    APPROX_MIN_SAMPLES,
    EXPORT_BYTES_PER_PX,
    MAX_EXPORT_BYTES,
    Approximation,
    brown_conrady_approximation,
    opencv_export,
    opencv_maps,
    opencv_parameters,
)
from oapcal.io.atomic import atomic_path, atomic_write

SUFFIXES = (".json", ".yml", ".yaml", ".xml")


def maps_path(path: str | Path) -> Path:
    """Where a JSON export's maps go: ``FILE.maps.npz`` beside ``FILE.json``."""
    path = Path(path)
    return path.with_name(f"{path.stem}.maps.npz")


#: The export file's version: 1 for Eq. (1) (unchanged), 2 for the other families (their
#: files add ``model_family``, ``exact``, ``R`` or the maps and the approximation).
FAMILY_VERSION = 2


def save_opencv(export: dict, path: str | Path, calibration_name: str | None = None) -> None:
    """Write an export as JSON (``.json``) or OpenCV FileStorage YAML/XML (``.yml``,
    ``.yaml``, ``.xml``), atomically.

    An export with ``maps`` (the relay) keeps them as FileStorage matrices ``map_x``,
    ``map_y``, or for JSON in the map file :func:`maps_path` (``oapcal correct --map`` reads
    it; the JSON names it under ``maps``); both files are renamed into place only when both
    were written.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in SUFFIXES:
        raise OutputError(f"{path}: the export file must end in {', '.join(SUFFIXES)}")
    cmap = export.get("maps")
    if suffix == ".json":
        # Eq. (1): the version-1 file, unchanged; the other families: version 2
        version = FAMILY_VERSION if "model_family" in export else 1
        data = {"format": "oapcal-opencv", "version": version, "calibration": calibration_name, **export}
        if cmap is not None:
            side = maps_path(path)
            data["maps"] = {"file": side.name, "map_x": "map_x", "map_y": "map_y",
                            "shape": [int(v) for v in cmap.shape]}  # fmt: skip
        with atomic_write(path) as fh:
            fh.write(json.dumps(data, indent=2) + "\n")
            if cmap is not None:
                from oapcal.io.maps import save_map

                with atomic_path(side) as tmp:  # the maps are renamed first, the JSON after them
                    save_map(cmap, tmp)
        return
    with atomic_path(path) as tmp:
        _write_filestorage(export, tmp, calibration_name)


def _write_filestorage(export: dict, path: Path, calibration_name: str | None) -> None:
    """Write an export as OpenCV FileStorage (YAML or XML by ``path``'s suffix)."""
    import cv2

    cmap = export.get("maps")
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    try:
        if "model_family" in export:
            fs.write("model_family", str(export["model_family"]))
            fs.write("exact", int(bool(export["exact"])))
        fs.write("camera_matrix", np.array(export["camera_matrix"], float))
        fs.write("dist_coeffs", np.array(export["dist_coeffs"], float).reshape(1, -1))
        fs.write("new_camera_matrix", np.array(export["new_camera_matrix"], float))
        fs.write("image_size", np.array(export["image_size"], np.int32).reshape(1, 2))
        fs.write("new_image_size", np.array(export["new_image_size"], np.int32).reshape(1, 2))
        if export.get("um_per_px"):
            fs.write("um_per_px", float(export["um_per_px"]))
        if calibration_name:
            fs.write("calibration", str(calibration_name))
        if export.get("R") is not None:
            fs.write("R", np.array(export["R"], float))
        approx = export.get("approximation")
        if approx is not None:
            for key in ("mean_px", "max_px", "calibrated_mean_px", "calibrated_max_px"):
                if approx.get(key) is not None:
                    fs.write(f"approximation_{key}", float(approx[key]))
            fs.write("approximation_n_pixels", int(approx["n_pixels"]))
        if export.get("note"):
            fs.write("note", str(export["note"]))
        if cmap is not None:
            fs.write("map_x", np.ascontiguousarray(cmap.map_x, np.float32))
            fs.write("map_y", np.ascontiguousarray(cmap.map_y, np.float32))
    finally:
        fs.release()
