"""The plugin's reader and writer (npe2 ``readers`` and ``writers`` contributions).

* ``*.json`` written by ``oapcal fit`` (``"format": "oapcal-calibration"``): the distortion
  field (magnitude image, vectors) and the hull, with the calibration in the layers'
  metadata (:func:`oapcal.napari_plugin._layers.calibration_layers`);
* ``*.csv`` / ``*.tsv`` point-pair files (``x_u, y_u, x_d, y_d``, optional ``id``): the
  ``distorted`` and ``reference`` points layers with ``id`` as a feature;
* ``*.zarr`` OME-Zarr directories (what ``oapcal correct`` writes as OME-Zarr, or any NGFF
  image): the full-resolution array as an image layer, read lazily (Dask), scaled in um
  by its ``multiscales`` transform, with the provenance in the layer's metadata;
* writing: two points layers (one ``distorted``, one ``reference``, told apart by their
  ``oapcal_role`` metadata or their names) paired by ``id``, through
  :func:`oapcal.write_point_pairs` (atomic).

Files that are not oapcal's (other JSON, CSVs without the pair columns) are left to other
readers (``None``).  oapcal's own checks name the file, line and field of a bad file.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from oapcal.io.userfile import sniff
from oapcal.napari_plugin import _layers as L
from oapcal.napari_plugin._layers import (
    DISTORTED,
    REFERENCE,
    ROLE,
    calibration_layers,
    pair_layers,
    points_layers,
)

#: Bytes read to decide whether a file is oapcal's.
SNIFF_BYTES = 4096


def _is_calibration(path: Path) -> bool:
    return '"oapcal-calibration"' in sniff(path, SNIFF_BYTES)


def _is_point_pairs(path: Path) -> bool:
    header = sniff(path, SNIFF_BYTES).split("\n", 1)[0]
    names = {h.strip() for h in header.replace("\t", ",").split(",")}
    return {"x_u", "y_u", "x_d", "y_d"} <= names


def _landmark_format(path: Path) -> str | None:
    """``"bigwarp"`` or ``"via"`` for a BigWarp landmarks CSV or a VIA CSV/JSON file
    (:mod:`oapcal.io.landmarks`), else None."""
    from oapcal.errors import OapcalError
    from oapcal.io.landmarks import detect_format
    from oapcal.io.landmarks.tables import is_bigwarp_row
    from oapcal.io.landmarks.via import is_via_csv_header

    head = sniff(path, SNIFF_BYTES)  # "" for anything but a regular file (never blocks)
    if path.suffix.lower() == ".json":
        if not head.lstrip().startswith(("{", "[")):
            return None
        try:  # VIA JSON is told apart by its structure: the whole (regular) file is read
            return "via" if detect_format(path) == "via" else None
        except (OapcalError, OSError, ValueError):
            return None
    lines = head.lstrip().splitlines()
    first = lines[0] if lines else ""
    return "bigwarp" if is_bigwarp_row(first) else "via" if is_via_csv_header(first) else None


def napari_get_reader(path):
    """The reader for ``path`` when it is an oapcal calibration, a point-pair file, a BigWarp
    or VIA landmark file or a zarr image, else None."""
    if isinstance(path, list | tuple):
        if len(path) != 1:
            return None
        path = path[0]
    p = Path(path)
    suffix = p.suffix.lower()
    if suffix == ".zarr" and _ome_zarr_array(p) is not None:
        return read_ome_zarr
    if suffix == ".zarr" and _zarr_array(p):
        return read_zarr_array
    if suffix == ".json" and _is_calibration(p):
        return read_calibration
    if suffix in (".csv", ".tsv") and _is_point_pairs(p):
        return read_point_pairs
    if suffix in (".csv", ".json") and _landmark_format(p) is not None:
        return read_landmark_file
    return None


def _zarr_array(path: Path) -> bool:
    """Is ``path`` a plain zarr array (what ``oapcal correct --dask`` writes by default)?"""
    from oapcal.io.userfile import read_json

    if (path / ".zarray").is_file():
        return True
    if not (path / "zarr.json").is_file():
        return False
    try:
        return read_json(path / "zarr.json", "zarr metadata").get("node_type") == "array"
    except Exception:  # unreadable metadata: not ours to open
        return False


def read_zarr_array(path) -> list[tuple]:
    """A plain zarr array as an image layer, read lazily (Dask)."""
    from oapcal.extras import require

    da = require("dask.array")
    path = Path(path[0] if isinstance(path, list | tuple) else path)
    return [(da.from_zarr(str(path)), {"name": path.name.removesuffix(".zarr")}, "image")]


def read_landmark_file(path) -> list[tuple]:
    """A BigWarp landmarks CSV as the ``distorted`` (moving) and ``reference`` (fixed) points
    layers paired by landmark name; a VIA file's point regions as one points layer per
    labelled image (at most :data:`MAX_VIA_LAYERS`; the others are named in a warning), the
    regions' attributes as features.  (To fit, pair a VIA file's two images with ``oapcal
    fit --distorted-image ... --reference-image ...``, docs/landmarks.md.)"""
    from oapcal.io.landmarks import read_landmark_pairs
    from oapcal.io.landmarks._base import read_text
    from oapcal.io.landmarks.via import point_images, read_via

    path = Path(path[0] if isinstance(path, list | tuple) else path)
    if _landmark_format(path) == "bigwarp":
        pairs = read_landmark_pairs(path, check_geometry=False)
        return points_layers(pairs.xy_u, pairs.xy_d, pairs.ids, source=str(path))
    text = read_text(path, "VIA file")
    images = point_images(path, text=text)
    if not images:
        read_via(path, text=text)  # raises oapcal's message: what the file holds instead
    if len(images) > MAX_VIA_LAYERS:
        from napari.utils.notifications import show_warning

        left = ", ".join(images[MAX_VIA_LAYERS:][:3])
        show_warning(f"oapcal: {path.name} has point regions on {len(images)} images; opened the first "
                     f"{MAX_VIA_LAYERS} ({left}, ... left out)")  # fmt: skip
    return [_via_layer(read_via(path, image, text=text), f"{path.stem}: {image}", path)
            for image in images[:MAX_VIA_LAYERS]]  # fmt: skip


#: Most points layers opened from one VIA file (one per labelled image).
MAX_VIA_LAYERS = 16


def _via_layer(marks, name: str, path: Path) -> tuple:
    xy = np.array([(m.x, m.y) for m in marks.landmarks], float).reshape(-1, 2)
    names = sorted({k for m in marks.landmarks for k in m.attrs})
    features = {k: np.array([m.attrs.get(k, "") for m in marks.landmarks], object) for k in names}
    text = {"string": "{" + names[0] + "}", "size": 7, "color": "white"} if names else None
    kwargs = {"name": name, "features": features, "face_color": "yellow", "size": 5, "text": text,
              "metadata": {"oapcal_source": str(path)}}  # fmt: skip
    return L.xy_to_rc(xy), kwargs, "points"


def _ome_zarr_array(path: Path):
    """The full-resolution array of an OME-Zarr directory, or None for anything else."""
    from oapcal.errors import OapcalError
    from oapcal.io.ome import ome_zarr_array_path

    try:
        return ome_zarr_array_path(path) if path.is_dir() else None
    except (OapcalError, OSError):
        return None


def read_ome_zarr(path) -> list[tuple]:
    """The image layer of an OME-Zarr (module docstring): ``(t[, c], y, x)`` data, the
    channel axis split into layers, the scale of ``multiscales[0].datasets[0]``."""
    from oapcal.extras import require

    da = require("dask.array")
    zarr = require("zarr")
    path = Path(path[0] if isinstance(path, list | tuple) else path)
    group = zarr.open_group(str(path), mode="r")
    attrs = group.attrs.asdict()
    ms = (attrs.get("ome") or attrs)["multiscales"][0]
    dataset = ms["datasets"][0]
    data = da.from_zarr(group[str(dataset["path"])])
    axes = [a if isinstance(a, dict) else {"name": str(a)} for a in ms.get("axes", [])]
    names = [a.get("name") for a in axes]
    transforms = dataset.get("coordinateTransformations", [])
    scale = next((t["scale"] for t in transforms if t.get("type") == "scale"), [1.0] * data.ndim)
    name = path.name.removesuffix(".zarr").removesuffix(".ome")
    kwargs = {"name": name, "metadata": {"oapcal": attrs.get("oapcal")}}
    if "c" in names:
        channel = names.index("c")
        kwargs["channel_axis"] = channel
        scale = [v for i, v in enumerate(scale) if i != channel]
    kwargs["scale"] = tuple(float(v) for v in scale)
    unit = next((a.get("unit") for a in axes if a.get("name") == "x"), None)
    if unit:
        kwargs["metadata"]["unit"] = unit
    return [(data, kwargs, "image")]


def read_calibration(path) -> list[tuple]:
    """Layers of an oapcal calibration file (module docstring)."""
    import oapcal

    path = path[0] if isinstance(path, list | tuple) else path
    cal = oapcal.load_calibration(path)
    return calibration_layers(cal, name=Path(path).stem, source=str(path))


def read_point_pairs(path) -> list[tuple]:
    """The ``distorted`` and ``reference`` layers of a point-pair file."""
    import oapcal

    path = path[0] if isinstance(path, list | tuple) else path
    pairs = oapcal.read_points(path)
    return points_layers(pairs.xy_u, pairs.xy_d, pairs.ids, source=str(path))


def _role(meta: dict, name: str) -> str | None:
    role = (meta or {}).get(ROLE)
    if role in (DISTORTED, REFERENCE):
        return role
    lowered = name.lower()
    if "ref" in lowered or "undist" in lowered:
        return REFERENCE
    if "dist" in lowered:
        return DISTORTED
    return None


def write_point_pairs(path: str, layer_data: list[tuple]) -> list[str]:
    """Write two points layers as a point-pair CSV ``id,x_u,y_u,x_d,y_d`` (module docstring)."""
    import oapcal
    from oapcal.errors import DataError

    roles = {}
    for data, meta, _kind in layer_data:
        role = _role(meta.get("metadata", {}), meta.get("name", ""))
        if role is None or role in roles:
            raise DataError(
                "save two points layers, one of distorted and one of reference points (named "
                "'distorted' and 'reference', or as the oapcal widgets make them)"
            )
        roles[role] = (data, meta.get("features"))
    xy_u, xy_d, ids = pair_layers(roles[DISTORTED], roles[REFERENCE])
    if len(ids) == 0:
        raise DataError("the two points layers share no id: nothing to save")
    oapcal.write_point_pairs(path, xy_u, xy_d, ids=ids)
    return [str(path)]
