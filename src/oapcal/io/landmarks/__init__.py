"""Landmark files from labelling tools, paired into :class:`~oapcal.io.points.PointPairs`.

Formats (``docs/file-formats.md`` has a worked example of each):

* ``via``: VGG Image Annotator 2 CSV/JSON exports and VIA 3 projects (point regions);
* ``napari``: a napari Points layer saved as CSV (``index,axis-0,axis-1``);
* ``bigwarp``: a BigWarp landmarks CSV (moving = distorted, fixed = reference);
* ``csv``: any CSV/TSV with a header, coordinate columns named by the caller.

Every reader converts to oapcal's pixel convention (origin at the centre of the top-left
pixel).  The distorted image's and the reference image's landmarks are paired by an
attribute (``pair_by``, e.g. a corner id), or by order only when asked
(``pair_by_order``); BigWarp rows are pairs already.  Landmarks left without a partner,
disabled ones and non-point regions are not used and are listed in
``PointPairs.warnings``.

>>> import pathlib, tempfile
>>> d = pathlib.Path(tempfile.mkdtemp())
>>> _ = (d / "dist.csv").write_text("corner,x,y\\nA,10,12\\nB,50,11\\nC,31,40\\n")
>>> _ = (d / "ref.csv").write_text("corner,x,y\\nB,48,10\\nA,9,10\\nC,30,41\\nD,5,5\\n")
>>> pairs = read_landmark_pairs(d / "dist.csv", d / "ref.csv", pair_by="corner")
>>> pairs.ids, pairs.xy_u[0].tolist(), pairs.xy_d[0].tolist()
(('A', 'B', 'C'), [9.0, 10.0], [10.0, 12.0])
>>> pairs.warnings
('1 reference landmark has no distorted partner and is not used: D',)
"""

from __future__ import annotations

import numpy as np

from oapcal.errors import DataError, InputFileError
from oapcal.io.landmarks._base import Landmark, LandmarkSet, read_text
from oapcal.io.landmarks.tables import (
    is_bigwarp_row,
    is_napari_header,
    read_bigwarp,
    read_napari,
    read_table,
)
from oapcal.io.landmarks.via import is_via_csv_header, json_kind, load_json, read_via
from oapcal.io.points import PAIR_COLUMNS, PointPairs

__all__ = [
    "FORMATS",
    "Landmark",
    "LandmarkSet",
    "detect_format",
    "pair_landmarks",
    "read_landmark_pairs",
    "read_landmarks",
]

#: Accepted values of ``fmt``.
FORMATS = ("auto", "csv", "via", "napari", "bigwarp")


def detect_format(path, text: str | None = None) -> str:
    """The format of a landmark file from its content: ``via``, ``napari``, ``bigwarp`` or
    ``csv``.  JSON that is not VIA raises :class:`InputFileError`."""
    name = str(path)
    text = read_text(path) if text is None else text
    stripped = text.lstrip()
    if stripped.startswith(("{", "[")):
        if json_kind(load_json(text, name)) is None:
            raise InputFileError(
                f"{name}: is JSON but not a VIA 2 export or VIA 3 project; "
                "oapcal reads VIA JSON, and napari/BigWarp/plain landmarks as CSV"
            )
        return "via"
    first = stripped.splitlines()[0]
    if is_via_csv_header(first):
        return "via"
    if is_napari_header(first):
        return "napari"
    if is_bigwarp_row(first):
        return "bigwarp"
    return "csv"


def read_landmarks(path, fmt: str = "auto", *, image: str | None = None, x_column: str = "x",
                   y_column: str = "y", origin: str = "center") -> LandmarkSet:  # fmt: skip
    """The landmarks of one image in ``path`` (for BigWarp: the moving image's)."""
    fmt = _check_format(fmt)
    text = read_text(path)
    if fmt == "auto":
        fmt = detect_format(path, text)
    if image is not None and fmt != "via":
        raise InputFileError(f"{path}: an image name ({image!r}) applies only to VIA files, not {fmt}")
    if fmt == "via":
        return read_via(path, image, text=text)
    if fmt == "napari":
        return read_napari(path, text=text)
    if fmt == "bigwarp":
        return read_bigwarp(path, text=text)[0]
    return read_table(path, x_column=x_column, y_column=y_column, origin=origin, text=text)


def read_landmark_pairs(
    distorted,
    reference=None,
    *,
    fmt: str = "auto",
    pair_by: str | None = None,
    pair_by_order: bool = False,
    distorted_image: str | None = None,
    reference_image: str | None = None,
    x_column: str = "x",
    y_column: str = "y",
    origin: str = "center",
    require: tuple[str, ...] = PAIR_COLUMNS,
    check_geometry: bool = True,
) -> PointPairs:
    """Read and pair the landmarks of a distorted and a reference image.

    ``reference`` may be omitted when ``distorted`` holds both images (a BigWarp file, or a
    VIA file with ``distorted_image`` and ``reference_image``), or when only the distorted
    points are required (``require=("x_d", "y_d")``, as ``correct-points`` needs).
    Returns :class:`PointPairs` with columns ``id,x_u,y_u,x_d,y_d`` where ``id`` is each
    pair's pairing value.
    """
    # 12 parameters: the ways a user reads landmark files, each an option of the command
    # line (``--format``, ``--pair-by``, ...; cli._common.PointsSource) and a public keyword.
    fmt = _check_format(fmt)
    if pair_by is not None and pair_by_order:
        raise InputFileError("give either a pairing attribute or pairing by order, not both")
    need_reference = any(c in require for c in ("x_u", "y_u"))
    opts = {"x_column": x_column, "y_column": y_column, "origin": origin}
    d_text = read_text(distorted)
    d_fmt = detect_format(distorted, d_text) if fmt == "auto" else fmt
    if d_fmt == "bigwarp":
        _check_bigwarp_args(distorted, reference, distorted_image, reference_image)
        dist, ref = read_bigwarp(distorted, text=d_text)
        pairs = pair_landmarks(dist, ref, pair_by or "name")
        return _finish(pairs, check_geometry)
    if d_fmt != "via" and (distorted_image or reference_image):
        raise InputFileError(f"{distorted}: image names apply only to VIA files, not {d_fmt}")
    dist = _read_one(distorted, d_fmt, d_text, distorted_image, opts, "distorted")
    if reference is None and reference_image is not None and d_fmt == "via":
        reference = distorted
    if reference is None:
        if need_reference:
            via = d_fmt == "via"
            also = " (or, for a VIA file holding both, the reference image's name as reference_image)"
            raise InputFileError(
                f"{distorted}: holds the distorted landmarks only; give the reference landmarks "
                f"too: their file as reference{also if via else ''}",
                param=("reference", "reference_image") if via else "reference",
            )
        return _distorted_only(dist, pair_by, check_geometry)
    r_text = d_text if str(reference) == str(distorted) else read_text(reference)
    r_fmt = detect_format(reference, r_text) if fmt == "auto" else fmt
    _check_reference_args(distorted, reference, d_fmt, r_fmt, distorted_image, reference_image)
    ref = _read_one(reference, r_fmt, r_text, reference_image, opts, "reference")
    if pair_by is None and not pair_by_order:
        raise _no_pairing(dist, ref)
    pairs = pair_landmarks(dist, ref, pair_by) if pair_by else _pair_by_order(dist, ref)
    return _finish(pairs, check_geometry)


def _check_bigwarp_args(distorted, reference, distorted_image, reference_image) -> None:
    """A BigWarp file holds both images: no other reference file, no VIA image names."""
    if reference is not None and str(reference) != str(distorted):
        raise InputFileError(
            f"{distorted}: a BigWarp file holds both images' landmarks; give it once "
            "(without a separate reference file)"
        )
    if distorted_image or reference_image:
        raise InputFileError(f"{distorted}: image names apply only to VIA files, not BigWarp")


def _check_reference_args(distorted, reference, d_fmt, r_fmt, distorted_image, reference_image) -> None:
    """Refuse a reference file that cannot be one: a BigWarp file, image names for a file
    that is not VIA, or the distorted file again without two VIA image names."""
    if r_fmt == "bigwarp":
        raise InputFileError(f"{reference}: is a BigWarp file, which holds both images; give it as the "
                             "distorted file alone")  # fmt: skip
    if r_fmt != "via" and reference_image:
        raise InputFileError(f"{reference}: image names apply only to VIA files, not {r_fmt}")
    if str(reference) == str(distorted) and (d_fmt != "via" or distorted_image == reference_image):
        raise InputFileError(
            f"{distorted}: given as both the distorted and the reference landmarks; for a VIA file "
            "holding both images name them with distorted_image and reference_image",
            param=("distorted_image", "reference_image"),
        )


def _no_pairing(dist, ref) -> InputFileError:
    """The error for two landmark files given without a way to pair them."""
    common = sorted(set.intersection(*(set(lm.attrs) for lm in dist.landmarks + ref.landmarks)) - {""})
    hint = f" (attributes on every landmark: {', '.join(common[:6])})" if common else ""
    return InputFileError(
        f"{dist.source} + {ref.source}: say how landmarks pair up: by an attribute, pair_by{hint}, "
        "or by order, pair_by_order, if both files list them in the same order",
        param=("pair_by", "pair_by_order"),
    )


def _check_format(fmt: str) -> str:
    if fmt not in FORMATS:
        raise InputFileError(f"landmark format {fmt!r} is unknown; use one of {', '.join(FORMATS)}")
    return fmt


def _read_one(path, fmt: str, text: str, image: str | None, opts: dict, role: str) -> LandmarkSet:
    if fmt == "via":
        return read_via(path, image, text=text, role=role)
    if fmt == "napari":
        return read_napari(path, text=text)
    return read_table(path, text=text, **opts)


def _key(lm: Landmark, attr: str, source: str) -> str:
    if attr in lm.unusable:
        raise InputFileError(
            f"{source}: {lm.where}: attribute {attr!r} is {lm.unusable[attr]}, not a text or number that "
            "can name the landmark; give it a text value (e.g. the corner id)"
        )
    if attr not in lm.attrs:
        have = ", ".join(sorted(lm.attrs)[:6]) or "none"
        raise InputFileError(
            f"{source}: {lm.where}: the landmark has no attribute {attr!r} to pair by (it has: {have}); "
            "label it or choose another attribute"
        )
    value = lm.attrs[attr]
    if value == "":
        raise InputFileError(
            f"{source}: {lm.where}: attribute {attr!r} is empty; label the landmark or delete it"
        )
    return value


def _index(ls: LandmarkSet, attr: str) -> dict[str, Landmark]:
    out: dict[str, Landmark] = {}
    for lm in ls.landmarks:
        key = _key(lm, attr, ls.source)
        if key in out:
            raise InputFileError(
                f"{ls.source}: {lm.where}: {attr} {key!r} is already used at {out[key].where}; "
                "each landmark needs its own value"
            )
        out[key] = lm
    return out


def pair_landmarks(dist: LandmarkSet, ref: LandmarkSet, attr: str) -> PointPairs:
    """Pair two landmark sets by the value of attribute ``attr``, in the distorted file's
    order.  Values present on one side only are left out and reported in ``warnings``;
    no common value at all raises :class:`DataError`."""
    d_index, r_index = _index(dist, attr), _index(ref, attr)
    keys = [k for k in d_index if k in r_index]
    warnings = list(_ignored_notes(dist, ref))
    for label, own, other in (("distorted", d_index, r_index), ("reference", r_index, d_index)):
        lonely = [k for k in own if k not in other]
        if lonely:
            partner = "reference" if label == "distorted" else "distorted"
            shown = ", ".join(lonely[:8]) + (", ..." if len(lonely) > 8 else "")
            s = "" if len(lonely) == 1 else "s"
            has = "has" if len(lonely) == 1 else "have"
            warnings.append(f"{len(lonely)} {label} landmark{s} {has} no {partner} partner and "
                            f"{'is' if s == '' else 'are'} not used: {shown}")  # fmt: skip
    if not keys:
        raise DataError(
            f"{dist.source} + {ref.source}: no {attr} value is on both sides (distorted: "
            f"{', '.join(list(d_index)[:3])}...; reference: {', '.join(list(r_index)[:3])}...); "
            "check pair_by",
            param="pair_by",
        )
    return _make_pairs(dist, ref, [r_index[k] for k in keys], [d_index[k] for k in keys], keys, warnings)


def _pair_by_order(dist: LandmarkSet, ref: LandmarkSet) -> PointPairs:
    if len(dist) != len(ref):
        raise DataError(
            f"{dist.source} has {len(dist)} landmarks but {ref.source} has {len(ref)}; pairing by "
            "order needs the same number in the same order (or pair by an attribute)"
        )
    keys = [str(i) for i in range(len(dist))]
    return _make_pairs(
        dist, ref, list(ref.landmarks), list(dist.landmarks), keys, list(_ignored_notes(dist, ref))
    )


def _ignored_notes(*sets: LandmarkSet):
    for ls in sets:
        if ls.ignored:
            shown = "; ".join(ls.ignored[:3]) + ("; ..." if len(ls.ignored) > 3 else "")
            n = len(ls.ignored)
            yield f"{ls.source}: {n} {'entry' if n == 1 else 'entries'} not used ({shown})"


def _make_pairs(dist, ref, ref_lms, dist_lms, keys, warnings) -> PointPairs:
    xy_u = np.array([[lm.x, lm.y] for lm in ref_lms], float).reshape(-1, 2)
    xy_d = np.array([[lm.x, lm.y] for lm in dist_lms], float).reshape(-1, 2)
    rows = tuple(
        {"id": k, "x_u": repr(float(u[0])), "y_u": repr(float(u[1])), "x_d": repr(float(d[0])),
         "y_d": repr(float(d[1]))}
        for k, u, d in zip(keys, xy_u, xy_d)
    )  # fmt: skip
    source = dist.source if dist.source.split(" [")[0] == ref.source.split(" [")[0] else None
    return PointPairs(
        xy_u=xy_u,
        xy_d=xy_d,
        ids=tuple(keys),
        rows=rows,
        fieldnames=("id", *PAIR_COLUMNS),
        lines=tuple(range(1, len(keys) + 1)),
        source=source.split(" [")[0] if source else f"{dist.source} + {ref.source}",
        warnings=tuple(warnings),
        where_d=tuple(f"{dist.source}: {lm.where}" for lm in dist_lms),
        where_u=tuple(f"{ref.source}: {lm.where}" for lm in ref_lms),
    )


def _distorted_only(dist: LandmarkSet, pair_by: str | None, check_geometry: bool) -> PointPairs:
    keys = list(_index(dist, pair_by)) if pair_by else [str(i) for i in range(len(dist))]
    xy_d = np.array([[lm.x, lm.y] for lm in dist.landmarks], float)
    rows = tuple({"id": k, "x_d": repr(float(d[0])), "y_d": repr(float(d[1]))} for k, d in zip(keys, xy_d))
    pairs = PointPairs(
        xy_u=np.full_like(xy_d, np.nan),
        xy_d=xy_d,
        ids=tuple(keys),
        rows=rows,
        fieldnames=("id", "x_d", "y_d"),
        lines=tuple(range(1, len(keys) + 1)),
        source=dist.source,
        warnings=tuple(_ignored_notes(dist)),
        where_d=tuple(f"{dist.source}: {lm.where}" for lm in dist.landmarks),
    )
    return _finish(pairs, check_geometry)


def _finish(pairs: PointPairs, check_geometry: bool) -> PointPairs:
    if check_geometry:
        _check_geometry(pairs)
    return pairs


def _check_geometry(pairs: PointPairs) -> None:
    """Duplicated or collinear landmarks, named by file and position (raises DataError)."""
    for label, xy, where in (
        ("reference", pairs.xy_u, pairs.where_u),
        ("distorted", pairs.xy_d, pairs.where_d),
    ):
        if np.isnan(xy).all() or not where:
            continue
        seen: dict[tuple[float, float], int] = {}
        for i, p in enumerate(map(tuple, xy)):
            if p in seen:
                raise DataError(
                    f"{where[seen[p]]} and {where[i].split(': ', 1)[-1]}: two {label} landmarks at the "
                    f"same point ({p[0]:g}, {p[1]:g}); remove the duplicate"
                )
            seen[p] = i
        from oapcal.io.points import check_spread

        check_spread(xy, f"paired {label} landmark", where[0].split(": ")[0])
        if len(xy) >= 3:
            sv = np.linalg.svd(xy - xy.mean(axis=0), compute_uv=False)
            if sv[0] == 0 or sv[1] <= 1e-9 * sv[0]:
                raise DataError(
                    f"{where[0].split(': ')[0]}: all {len(xy)} paired {label} landmarks lie on one line; "
                    "the model needs landmarks spread over the field in both x and y"
                )
