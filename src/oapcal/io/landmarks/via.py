"""VGG Image Annotator (VIA) point regions: VIA 2 CSV and JSON exports, VIA 3 projects.

* VIA 2 CSV: ``filename,file_size,file_attributes,region_count,region_id,
  region_shape_attributes,region_attributes``, one row per region; the two last cells are
  JSON, a point is ``{"name":"point","cx":120,"cy":85}``.
* VIA 2 JSON (export or project): ``{key: {"filename", "regions": [{"shape_attributes",
  "region_attributes"}, ...]}}``, inside ``"_via_img_metadata"`` for a project.
* VIA 3 project: ``"metadata": {id: {"vid", "xy": [1, x, y], "av": {attr_id: value}}}``
  (shape 1 = point), images under ``"file"`` and ``"view"``, attribute names under
  ``"attribute"``.

Pixel convention: VIA draws the image with its top-left *corner* at (0, 0) and stores
canvas positions scaled to image pixels, so the centre of the top-left pixel is
(0.5, 0.5); VIA 2 rounds point positions to whole pixels.  oapcal puts that centre at
(0, 0): ``x = cx - 0.5``, ``y = cy - 0.5``.
"""

from __future__ import annotations

import json
import re
from collections import Counter

from oapcal.errors import InputFileError
from oapcal.io.landmarks._base import (
    Landmark,
    LandmarkSet,
    attribute_text,
    coordinate,
    csv_rows,
    first_row,
    read_text,
    unusable_attributes,
)
from oapcal.io.userfile import parse_json

#: VIA's image coordinates minus this are oapcal's (corner origin -> centre origin).
PIXEL_OFFSET = 0.5
VIA2_CSV_HEADER = (
    "filename", "file_size", "file_attributes", "region_count", "region_id",
    "region_shape_attributes", "region_attributes",
)  # fmt: skip
_VIA3_SHAPES = {1: "point", 2: "rectangle", 3: "circle", 4: "ellipse", 5: "line", 6: "polyline",
                7: "polygon", 8: "extreme rectangle", 9: "extreme circle"}  # fmt: skip


def is_via_csv_header(first_line: str) -> bool:
    cells = [c.strip().lstrip("#").strip('"') for c in first_line.split(",")]
    return tuple(cells[:7]) == VIA2_CSV_HEADER


def load_json(text: str, name: str):
    """Parse JSON text; malformed or absurdly nested JSON raises :class:`InputFileError`."""
    return parse_json(text, name, "landmark file")


def json_kind(data) -> str | None:
    """``"via3"``, ``"via2"`` or None for parsed JSON."""
    if not isinstance(data, dict):
        return None
    if "metadata" in data and "file" in data and ("view" in data or "project" in data):
        return "via3"
    if "_via_img_metadata" in data:
        return "via2"
    if data and all(isinstance(v, dict) and "regions" in v for v in data.values()):
        return "via2"
    return None


def read_via(
    path, image: str | None = None, *, text: str | None = None, role: str | None = None
) -> LandmarkSet:
    """Read the point regions of one image from a VIA 2 CSV/JSON or VIA 3 JSON file.

    ``image`` picks the image by file name or base name (``IMG.jpg`` matches VIA's
    ``file://C:\\...\\IMG.jpg``) when the file holds point regions on several images;
    ``role`` (``"distorted"`` or ``"reference"``) names the parameter that chooses one in messages.
    """
    name = str(path)
    text = read_text(path, "VIA file") if text is None else text
    return _pick_image(_images(name, text), name, image, role)


def point_images(path, *, text: str | None = None) -> list[str]:
    """The names of the images of a VIA file that have point regions (each one a ``image``
    for :func:`read_via`), in the file's order."""
    name = str(path)
    text = read_text(path, "VIA file") if text is None else text
    return [im[0] for im in _images(name, text) if any(isinstance(r, Landmark) for r in im[1])]


def _images(name: str, text: str):
    """The images of a VIA file's text, each ``(file name, regions, key)``."""
    stripped = text.lstrip()
    if stripped.startswith(("{", "[")):
        data = load_json(text, name)
        kind = json_kind(data)
        if kind == "via3":
            images = _via3_images(data, name)
        elif kind == "via2":
            images = _via2_json_images(data, name)
        else:
            raise InputFileError(
                f"{name}: is JSON but not a VIA 2 export or VIA 3 project (expected an object of "
                "images with 'regions', '_via_img_metadata', or 'file'/'view'/'metadata')"
            )
    elif is_via_csv_header(stripped.splitlines()[0]):
        images = _via2_csv_images(text, name)
    else:
        raise InputFileError(
            f"{name}: line 1: not a VIA file (a VIA 2 CSV starts with filename,file_size,...; "
            "VIA JSON starts with '{')"
        )
    return images


# -- VIA 2 ------------------------------------------------------------------------------------


def _via2_json_images(data: dict, name: str) -> list[tuple[str, list]]:
    meta = data.get("_via_img_metadata", data)
    if not isinstance(meta, dict):
        raise InputFileError(f"{name}: field '_via_img_metadata' must be an object of images")
    images = []
    for key, entry in meta.items():
        if not isinstance(entry, dict):
            raise InputFileError(f"{name}: image {key!r}: must be an object, not {type(entry).__name__}")
        fname = entry.get("filename", key)
        if not isinstance(fname, str):
            raise InputFileError(f"{name}: image {key!r}: field 'filename' must be text")
        regions = entry.get("regions", [])
        if isinstance(regions, dict):  # VIA 1 stored regions as {"0": {...}, "1": {...}}
            regions = list(regions.values())
        if not isinstance(regions, list):
            raise InputFileError(f"{name}: image {fname!r}: field 'regions' must be a list")
        parsed = []
        for i, region in enumerate(regions):
            where = f"image {fname!r}, region {i}"
            if not isinstance(region, dict):
                raise InputFileError(f"{name}: {where}: must be an object, not {type(region).__name__}")
            parsed.append(_via2_region(region.get("shape_attributes"), region.get("region_attributes", {}),
                                       name, where))  # fmt: skip
        images.append((fname, parsed, key))
    return images


def _via2_csv_images(text: str, name: str) -> list[tuple[str, list]]:
    by_name: dict[str, list] = {}
    rows = csv_rows(text, name)
    first_row(rows, name)  # the header
    for line, cells in rows:
        where = f"line {line}"
        if len(cells) < 7:
            raise InputFileError(
                f"{name}: {where}: {len(cells)} cells, a VIA CSV row has 7; is the file truncated?"
            )
        fname = cells[0].strip()
        shape = _cell_json(cells[5], name, where, "region_shape_attributes")
        attrs = _cell_json(cells[6], name, where, "region_attributes")
        regions = by_name.setdefault(fname, [])
        if shape == {}:  # an image without regions
            continue
        regions.append(_via2_region(shape, attrs, name, where))
    return [(fname, regions, fname) for fname, regions in by_name.items()]


#: A JSON string, or VIA's bare ``undefined`` (its exporter writes ``{"Label":undefined}``
#: for an attribute left unset).
_UNDEFINED = re.compile(r'"(?:[^"\\]|\\.)*"|\bundefined\b')


def _cell_json(cell: str, name: str, where: str, column: str):
    """The JSON object in one VIA CSV cell (``{}`` for an empty cell).  VIA's ``undefined``
    reads as missing (null); VIA 1.0's ``name=point;cx=...;`` cells are named as
    unsupported; malformed JSON is one message naming the line and column."""
    text = cell.strip()
    if not text:
        return {}
    if re.match(r"^[A-Za-z_]+=", text):
        raise InputFileError(
            f"{name}: {where}: column {column} is {_short(text)}, VIA 1.0's 'name=...;' format, which "
            "oapcal does not read; open the file in VIA 2 or 3 and export it as CSV or JSON"
        )
    text = _UNDEFINED.sub(lambda m: "null" if m.group() == "undefined" else m.group(), text)
    try:
        return json.loads(text)
    except (json.JSONDecodeError, RecursionError, ValueError) as exc:
        why = f"{exc.msg} at character {exc.pos}" if isinstance(exc, json.JSONDecodeError) else "unreadable"
        raise InputFileError(
            f"{name}: {where}: column {column}: malformed JSON ({why}): {_short(text)}"
        ) from None


def _short(text: str, limit: int = 40) -> str:
    return repr(text) if len(text) <= limit else repr(text[: limit - 3] + "...")


def _via2_region(shape, attrs, name: str, where: str):
    """``Landmark`` for a point region, or a string naming the ignored shape."""
    if not isinstance(shape, dict):
        raise InputFileError(f"{name}: {where}: 'shape_attributes' must be an object like "
                             '{"name": "point", "cx": 10, "cy": 20}')  # fmt: skip
    if attrs is None:
        attrs = {}
    if not isinstance(attrs, dict):
        raise InputFileError(f"{name}: {where}: 'region_attributes' must be an object")
    kind = shape.get("name")
    if kind != "point":
        return f"{where}: a {kind!r} region (only point regions are landmarks)"
    for key in ("cx", "cy"):
        if key not in shape:
            raise InputFileError(f"{name}: {where}: point region has no {key!r}")
    x = coordinate(shape["cx"], name, where, "cx") - PIXEL_OFFSET
    y = coordinate(shape["cy"], name, where, "cy") - PIXEL_OFFSET
    text_attrs = {str(k): t for k, v in attrs.items() if (t := attribute_text(v)) is not None}
    return Landmark(x, y, text_attrs, where, unusable_attributes(attrs))


# -- VIA 3 ------------------------------------------------------------------------------------


def _via3_images(data: dict, name: str) -> list[tuple[str, list]]:
    files, views, meta = data.get("file"), data.get("view"), data.get("metadata")
    attributes = data.get("attribute", {})
    for field, value in (("file", files), ("metadata", meta), ("attribute", attributes)):
        if not isinstance(value, dict):
            raise InputFileError(f"{name}: field {field!r} must be an object")
    if views is None:
        views = {fid: {"fid_list": [fid]} for fid in files}
    if not isinstance(views, dict):
        raise InputFileError(f"{name}: field 'view' must be an object")
    anames, options = _via3_attributes(attributes)
    view_name = _via3_view_names(views, files)
    images: dict[str, list] = {vid: [] for vid in view_name}
    skipped: Counter = Counter()
    for mid, item in meta.items():
        where = f"metadata {mid!r}"
        if not isinstance(item, dict):
            raise InputFileError(f"{name}: {where}: must be an object, not {type(item).__name__}")
        xy, av, vid = item.get("xy", []), item.get("av", {}), str(item.get("vid"))
        if not isinstance(xy, list):
            raise InputFileError(f"{name}: {where}: field 'xy' must be a list like [1, x, y]")
        if not xy:  # a file or time-segment annotation, not a region
            if item.get("z"):
                skipped["temporal segment"] += 1
            else:
                skipped["file annotation"] += 1
            continue
        if vid not in images:
            raise InputFileError(f"{name}: {where}: view {vid!r} is not in the project's 'view' list")
        if not isinstance(av, dict):
            raise InputFileError(f"{name}: {where}: field 'av' must be an object")
        shape = xy[0]
        if shape != 1:
            kind = _VIA3_SHAPES.get(shape, f"shape {shape!r}") if isinstance(shape, int) else repr(shape)
            images[vid].append(f"{where}: a {kind} region (only point regions are landmarks)")
            continue
        if len(xy) != 3:
            raise InputFileError(
                f"{name}: {where}: a point region needs xy = [1, x, y], got {len(xy)} values"
            )
        x = coordinate(xy[1], name, where, "x") - PIXEL_OFFSET
        y = coordinate(xy[2], name, where, "y") - PIXEL_OFFSET
        attrs, raw = {}, {}
        for aid, value in av.items():
            aid = str(aid)
            label = options.get(aid, {}).get(value, value) if isinstance(value, str) else value
            raw[anames.get(aid, aid)] = label
            text = attribute_text(label)
            if text is not None:
                attrs[anames.get(aid, aid)] = text
        images[vid].append(Landmark(x, y, attrs, where, unusable_attributes(raw)))
    result = [(view_name[vid], regions, vid) for vid, regions in images.items()]
    return _Images(result, skipped)


def _via3_attributes(attributes: dict) -> tuple[dict, dict]:
    """A VIA 3 project's attribute names and option labels, by attribute id."""
    anames, options = {}, {}
    for aid, attr in attributes.items():
        if isinstance(attr, dict):
            anames[str(aid)] = str(attr.get("aname", aid))
            if isinstance(attr.get("options"), dict):
                options[str(aid)] = attr["options"]
    return anames, options


def _via3_view_names(views: dict, files: dict) -> dict:
    """The image name of each view of a VIA 3 project (its first file's ``fname``)."""
    view_name = {}
    for vid, view in views.items():
        fids = view.get("fid_list") if isinstance(view, dict) else None
        if not isinstance(fids, list) or not fids:
            continue
        entry = files.get(str(fids[0]))
        fname = entry.get("fname") if isinstance(entry, dict) else None
        view_name[str(vid)] = fname if isinstance(fname, str) else f"file {fids[0]}"
    return view_name


# -- choosing the image -----------------------------------------------------------------------


class _Images(list):
    """The images of a VIA file, and counts of entries that are not regions (VIA 3's
    temporal segments and file annotations), for the "found" part of messages."""

    def __init__(self, items, skipped=None):
        super().__init__(items)
        self.skipped = Counter(skipped or {})


def image_base_name(text: str) -> str:
    r"""The file name of a VIA image reference: without ``file://`` and folders, with
    ``/`` or ``\`` (Windows paths written by VIA on Windows) as separator.

    >>> image_base_name("file://C:\\data\\img\\IMG-0001.jpg"), image_base_name("a/b.png")
    ('IMG-0001.jpg', 'b.png')
    """
    text = text.strip()
    if text.lower().startswith("file://"):
        text = text[len("file://") :]
    return re.split(r"[\\/]", text)[-1]


def _found(images) -> str:
    """What a file holds, for a file without point regions: images and regions by shape."""
    shapes: Counter = Counter()
    for _, regions, _ in images:
        for r in regions:
            if isinstance(r, str):
                shapes[r.split(": a ", 1)[-1].split(" region")[0].strip("'")] += 1
    parts = [f"{len(images)} image{'s' if len(images) != 1 else ''}"]
    counts = [f"{n} {kind} region{'s' if n != 1 else ''}" for kind, n in shapes.most_common()]
    counts += [f"{n} {kind}{'s' if n != 1 else ''}" for kind, n in getattr(images, "skipped", {}).items()]
    return ", ".join(parts + counts) if counts else f"{parts[0]}, no regions"


_PARAM = {"distorted": ("distorted_image",), "reference": ("reference_image",)}


def _pick_image(images, name: str, image: str | None, role: str | None = None) -> LandmarkSet:
    def has_points(regions):
        return any(isinstance(r, Landmark) for r in regions)

    param = _PARAM.get(role, ("distorted_image", "reference_image"))
    if image is not None:
        wanted = image_base_name(image)
        chosen = [im for im in images if image in (im[0], im[2]) or image_base_name(im[0]) == wanted]
        if not chosen:
            listed = ", ".join(repr(im[0]) for im in images[:5]) + (", ..." if len(images) > 5 else "")
            raise InputFileError(f"{name}: has no image {image!r}; it has {listed or 'no images'}")
        if len(chosen) > 1:
            raise InputFileError(f"{name}: {len(chosen)} images match {image!r}; give the full file name")
    else:
        chosen = [im for im in images if has_points(im[1])]
        if not chosen:
            raise InputFileError(
                f"{name}: has no point regions (found {_found(images)}); label the landmarks with "
                "VIA's point tool"
            )
        if len(chosen) > 1:
            listed = ", ".join(repr(im[0]) for im in chosen[:5]) + (", ..." if len(chosen) > 5 else "")
            raise InputFileError(
                f"{name}: has point regions on {len(chosen)} images ({listed}); choose one by its "
                f"name with {' or '.join(param)}",
                param=param,
            )
    fname, regions, _ = chosen[0]
    landmarks = tuple(r for r in regions if isinstance(r, Landmark))
    if not landmarks:
        raise InputFileError(
            f"{name}: image {fname!r} has no point regions (found {_found([chosen[0]])[9:]}); label its "
            "landmarks as points"
        )
    ignored = tuple(r for r in regions if isinstance(r, str))
    source = name if len(images) == 1 else f"{name} [{fname}]"
    return LandmarkSet(source, landmarks, ignored)
