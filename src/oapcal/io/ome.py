"""OME outputs: OME-TIFF and OME-Zarr (NGFF 0.4), with the physical pixel size and the
calibration's provenance in their metadata, written one frame at a time.

* **OME-TIFF** (``NAME.ome.tif``): a multi-page TIFF whose first page's ImageDescription
  is OME-XML made by tifffile's own OME writer (:class:`tifffile.OmeXml`, what
  ``tifffile.imwrite(..., ome=True)`` writes; used directly because ``ome=True`` cannot
  append frames one by one): one Image of ``SizeT`` frames, ``PhysicalSizeX/Y`` the output
  pixel size in um (when the calibration has one), and in its ``Description`` the JSON
  :func:`provenance`.  Read by tifffile, Fiji/Bio-Formats, napari.
* **OME-Zarr** (``NAME.ome.zarr``): a zarr (format 2) group holding one array ``0`` of
  ``(t, y, x)`` or ``(t, c, y, x)`` frames, one chunk per frame (``/`` chunk keys, as NGFF
  0.4 asks), and the group's ``multiscales`` metadata (version 0.4: the axes, with
  ``micrometer`` units when the size is known, and a ``scale`` transform of
  ``[1, um_per_px, um_per_px]``); the provenance under ``multiscales[0].metadata`` and
  the group's ``oapcal`` attribute.  Read by zarr, ``ome-zarr`` and napari-ome-zarr.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from oapcal.errors import InputFileError

OME_TIFF_SUFFIXES = (".ome.tif", ".ome.tiff")
OME_ZARR_SUFFIX = ".ome.zarr"
NGFF_VERSION = "0.4"


def is_ome_tiff_path(path: str | Path) -> bool:
    return Path(path).name.lower().endswith(OME_TIFF_SUFFIXES)


def provenance(calibration_name, um_per_px, source=None, calibration=None) -> dict:
    """What an output was made from: the calibration (its name, and from the record its
    model family, free parameters, fitted points' file, date and fit's RMS residual), the
    output pixel size, the input, the oapcal version.

    >>> provenance("calib.json", 2.4, "run.avi")["source"]
    'run.avi'
    """
    from oapcal import __version__

    out = {
        "oapcal_calibration": calibration_name,
        "um_per_px": um_per_px,
        "source": None if source is None else str(source),
        "software": f"oapcal {__version__}",
    }
    if calibration is not None and hasattr(calibration, "family"):
        rms = getattr(getattr(calibration, "residuals", None), "rms_px", None)
        out["calibration"] = {
            "model_family": calibration.family.name,
            "free": list(calibration.free),
            "points": calibration.source,
            "created_utc": calibration.created_utc,
            "oapcal_version": calibration.oapcal_version,
            "rms_px": None if rms is None or rms != rms else float(rms),
        }
    return out


def ome_xml(
    n_frames: int, frame_shape: tuple[int, ...], dtype, um_per_px, description: dict, name: str
) -> bytes:
    """The OME-XML of an OME-TIFF of ``n_frames`` frames ``(rows, cols[, samples])``
    (UTF-8 bytes: OME writes the micro sign of ``PhysicalSizeXUnit``)."""
    import tifffile

    rows, cols = frame_shape[:2]
    samples = frame_shape[2] if len(frame_shape) == 3 else 1
    axes = "TYXS" if samples > 1 else "TYX"
    shape = (n_frames, rows, cols, samples) if samples > 1 else (n_frames, rows, cols)
    meta = {"axes": axes, "Name": name, "Description": json.dumps(description)}
    if um_per_px:
        size, unit = float(um_per_px), "\u00b5m"
        meta.update(PhysicalSizeX=size, PhysicalSizeXUnit=unit, PhysicalSizeY=size, PhysicalSizeYUnit=unit)
    omexml = tifffile.OmeXml()
    omexml.addimage(np.dtype(dtype), shape, (n_frames, 1, 1, rows, cols, samples), **meta)
    return omexml.tostring().encode("utf-8")


def ngff_multiscales(n_dims: int, um_per_px, name: str, description: dict) -> list:
    """The NGFF 0.4 ``multiscales`` attribute of one array ``0`` of ``(t[, c], y, x)``."""
    space = {"type": "space", **({"unit": "micrometer"} if um_per_px else {})}
    axes = [{"name": "t", "type": "time"}]
    if n_dims == 4:
        axes.append({"name": "c", "type": "channel"})
    axes += [{"name": "y", **space}, {"name": "x", **space}]
    size = float(um_per_px) if um_per_px else 1.0
    scale = [1.0] * (n_dims - 2) + [size, size]
    return [
        {
            "version": NGFF_VERSION,
            "name": name,
            "axes": axes,
            "datasets": [{"path": "0", "coordinateTransformations": [{"type": "scale", "scale": scale}]}],
            "type": "none",
            "metadata": description,
        }
    ]


class OmeZarrWriter:
    """Frames ``(rows, cols[, ch])`` written one by one into a new OME-Zarr group at
    ``path`` (a directory: give a temporary one, :func:`oapcal.io.atomic.atomic_dir`) of
    ``n_frames`` frames; the group and its metadata are made at the first frame."""

    def __init__(self, path: str | Path, n_frames: int, um_per_px, description: dict, name: str):
        self.path = Path(path)
        self.n_frames = int(n_frames)
        self.um_per_px = um_per_px
        self.description = description
        self.name = name
        self.n = 0
        self._array = None

    def write(self, frame: np.ndarray) -> None:
        if self._array is None:
            self._array = create_ome_zarr(self.path, self.n_frames, frame.shape, frame.dtype, self.um_per_px,
                                          self.description, self.name)  # fmt: skip
        if self.n >= self.n_frames:
            raise InputFileError(f"{self.path}: more frames than the {self.n_frames} planned")
        self._array[self.n] = to_ngff(frame)
        self.n += 1


def zarr_compressors(zarr_format: int = 3) -> tuple:
    """The compression of every zarr and OME-Zarr array oapcal writes: Blosc LZ4 (level 1)
    with bit shuffle, which microscopy's readers (zarr, ome-zarr, napari-ome-zarr, Fiji's
    N5/Zarr) all decode. Zarr's own default (Zstd) took 2.5 times as long to write the same
    frames (128 MB of uint16 frames: 0.85 s against 0.34 s, no compression 0.30 s), and made a
    zarr output of ``correct --dask`` twice as slow as the TIFF one (docs/benchmarks.md)."""
    if zarr_format == 2:
        import numcodecs

        return (numcodecs.Blosc(cname="lz4", clevel=1, shuffle=numcodecs.Blosc.BITSHUFFLE),)
    import zarr

    return (zarr.codecs.BloscCodec(cname="lz4", clevel=1, shuffle="bitshuffle"),)


def create_ome_zarr(path, n_frames: int, frame_shape, dtype, um_per_px, description: dict, name: str):
    """Make the OME-Zarr group at ``path`` (replacing what is there) and return its
    array ``0`` of ``n_frames`` frames of ``frame_shape`` ``(rows, cols[, ch])``, stored
    ``(t[, c], y, x)``, one chunk per frame."""
    import zarr

    rows, cols = int(frame_shape[0]), int(frame_shape[1])
    shape = (n_frames, rows, cols) if len(frame_shape) == 2 else (n_frames, int(frame_shape[2]), rows, cols)
    group = zarr.open_group(str(path), mode="w", zarr_format=2)
    array = group.create_array(
        "0", shape=shape, chunks=(1, *shape[1:]), dtype=np.dtype(dtype),
        chunk_key_encoding={"name": "v2", "separator": "/"}, compressors=zarr_compressors(2),
    )  # fmt: skip
    group.attrs.update({"multiscales": ngff_multiscales(len(shape), um_per_px, name, description),
                        "oapcal": description})  # fmt: skip
    return array


def to_ngff(frame: np.ndarray) -> np.ndarray:
    """A frame ``(rows, cols[, ch])`` in NGFF's axis order ``([c,] y, x)``."""
    return np.moveaxis(frame, -1, 0) if frame.ndim == 3 else frame


def ome_zarr_array_path(path: str | Path) -> Path | None:
    """The full-resolution array of an OME-Zarr group (``multiscales[0].datasets[0]``), or
    None when ``path`` is not one."""
    path = Path(path)
    attrs_file = path / ".zattrs"
    meta = None
    if attrs_file.is_file():
        meta = _json(attrs_file)
    elif (path / "zarr.json").is_file():
        meta = (_json(path / "zarr.json").get("attributes") or {}).get("ome") or {}
    if not isinstance(meta, dict) or not meta.get("multiscales"):
        return None
    try:
        return path / str(meta["multiscales"][0]["datasets"][0]["path"])
    except (KeyError, IndexError, TypeError):
        raise InputFileError(f"{path}: its OME-Zarr multiscales metadata names no dataset") from None


def _json(path: Path):
    from oapcal.io.userfile import read_json

    return read_json(path, "zarr metadata")


def ome_zarr_frames(path: str | Path) -> int:
    """Frames (the first axis) of the OME-Zarr at ``path`` (0 if it has none)."""
    import zarr

    array = ome_zarr_array_path(path)
    if array is None:
        return 0
    return int(zarr.open_array(str(array), mode="r").shape[0])
