"""Writers of landmark files as the labelling tools lay them out, for tests.

Written from the tools' documented layouts, independently of oapcal's readers: VIA puts
the image's top-left *corner* at (0, 0) (so a pixel-centre position ``x`` is stored as
``x + 0.5``); napari and BigWarp put pixel centres at integers (stored as they are),
napari as (row, column).
"""

import csv
import json


def via2_json(path, images):
    """``images``: {filename: [(x, y, {attr: value}), ...]} in oapcal coordinates."""
    meta = {}
    for fname, points in images.items():
        regions = [
            {"shape_attributes": {"name": "point", "cx": x + 0.5, "cy": y + 0.5}, "region_attributes": attrs}
            for x, y, attrs in points
        ]
        meta[f"{fname}12345"] = {"filename": fname, "size": 12345, "regions": regions, "file_attributes": {}}
    path.write_text(json.dumps(meta))
    return path


def via2_csv(path, images):
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["filename", "file_size", "file_attributes", "region_count", "region_id",
                    "region_shape_attributes", "region_attributes"])  # fmt: skip
        for fname, points in images.items():
            for i, (x, y, attrs) in enumerate(points):
                shape = json.dumps({"name": "point", "cx": x + 0.5, "cy": y + 0.5})
                w.writerow([fname, 12345, "{}", len(points), i, shape, json.dumps(attrs)])
    return path


def via3_json(path, images, attribute="corner"):
    files, views, meta = {}, {}, {}
    for n, (fname, points) in enumerate(images.items(), start=1):
        files[str(n)] = {"fid": str(n), "fname": fname, "type": 2, "loc": 1, "src": ""}
        views[str(n)] = {"fid_list": [str(n)]}
        for i, (x, y, attrs) in enumerate(points):
            meta[f"{n}_{i}"] = {"vid": str(n), "flg": 0, "z": [], "xy": [1, x + 0.5, y + 0.5],
                                "av": {"1": attrs[attribute]}}  # fmt: skip
    project = {
        "project": {"pid": "__VIA_PROJECT_ID__", "vid_list": list(views)},
        "config": {},
        "attribute": {"1": {"aname": attribute, "anchor_id": "FILE1_Z0_XY1", "type": 1, "options": {}}},
        "file": files,
        "view": views,
        "metadata": meta,
    }
    path.write_text(json.dumps(project))
    return path


def napari_csv(path, points, feature="corner"):
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["index", "axis-0", "axis-1", feature])
        for i, (x, y, attrs) in enumerate(points):
            w.writerow([i, repr(y), repr(x), attrs[feature]])
    return path


def bigwarp_csv(path, moving, fixed):
    """``moving``/``fixed``: lists of (x, y) of the same length; names Pt-0, Pt-1, ..."""
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh, quoting=csv.QUOTE_ALL)
        for i, ((mx, my), (fx, fy)) in enumerate(zip(moving, fixed)):
            w.writerow([f"Pt-{i}", "true", *(repr(float(v)) for v in (mx, my, fx, fy))])
    return path


def plain_csv(path, points, x="x", y="y", key="corner", delimiter=","):
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh, delimiter=delimiter)
        w.writerow([key, x, y])
        for px, py, attrs in points:
            w.writerow([attrs[key], repr(px), repr(py)])
    return path


def labelled(xy, ids):
    return [(float(p[0]), float(p[1]), {"corner": str(i)}) for p, i in zip(xy, ids)]
