"""Detection on the real USAF-1951 images in ../shared/real/usaf/ (issue 11's measured goals).

Run: .venv/bin/python benchmarks/real_usaf.py [--pictures docs/img]
     .venv/bin/python benchmarks/real_usaf.py --poses [--only NAME]   (turned, mirrored, binned)
     .venv/bin/python benchmarks/real_usaf.py --large [--only NAME]   (enlarged to 2048 px, time)

Each image is detected by the CLI (``oapcal detect IMAGE --groups ... --json``, without
``--um-per-px``: the scale is found) in a subprocess of its own, which reports its wall time
and its peak memory (``resource.getrusage``).  Printed per image: exit code, time, peak
memory, corners with right ids / corners of the fully visible elements of the groups run,
wrong ids, the found scale against the pixel size measured in SOURCES.md, and the rms of a
quadratic map reference -> image fitted to the detected corners.

Ground truth, independent of the detector: for every image a few bars were identified by
eye from the printed element and group numbers on the target (``ANCHORS``: the id of the
middle bar of a triplet and a point on it).  Each anchor's bar centre is measured here by
thresholding the image around that point (midpoint of the local minimum and maximum, the
connected blob through the point, its centroid).  An affine map from the target's geometry
(object um, the layout the detection reports) to these centres predicts every corner: a
detected corner has the right id when it lies within one bar width of the prediction for
its id (a neighbouring bar's corner is two bar widths away).  Elements count as fully
visible when all 24 predicted corners are at least 3 px inside the image and the bars are
at least 2 px wide (narrower bars are not resolved).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np

REAL = Path(__file__).resolve().parents[1] / ".." / "shared" / "real" / "usaf"

#: runs: (file, groups in view, pixel size measured in SOURCES.md (um/px), extra CLI options).
#: The single-element view cannot name its element or tell a mirror from the bars alone: it
#: is run as a user would first (refused), then with a scale and --mirror no, then named with
#: --anchor G7E1 alone (its printed numbers decide the mirror: imaging/detect/digits.py).  Its scale is
#: not SOURCES.md's rough 0.083 um/px (read off bars that look 47 px wide; overexposed bright
#: bars look wider than they are) but 0.115 um/px from the bar period (68 px = 2 w).
RUNS = [
    ("fpm_brightfield.png", "3-7", 1.02, []),
    ("labumk_negative.tif", "4-7", 3.7, []),
    ("whole_target.png", "-2-1", 130.0, []),
    ("highmag_g7e1.jpg", "7", 0.083, []),
    ("highmag_g7e1.jpg", "7", 0.083, ["--um-per-px", "0.11", "--mirror", "no"]),
    ("highmag_g7e1.jpg", "7", 0.083, ["--anchor", "G7E1"]),
]

#: file -> [(id of a triplet's middle bar, x, y)]: a point on that bar, read off the image;
#: the ids from the numbers printed on the target next to the elements.
ANCHORS = {
    "fpm_brightfield.png": [
        ("G4E2H1", 360, 272), ("G4E2V1", 552, 272), ("G5E1H1", 988, 246), ("G5E6V1", 940, 658),
        ("G4E6H1", 332, 891), ("G4E1H1", 944, 862), ("G4E1V1", 730, 860), ("G6E2H1", 674, 496),
    ],
    "labumk_negative.tif": [
        ("G4E3H1", 83, 63), ("G4E3V1", 131, 64), ("G4E6H1", 78, 214), ("G4E1H1", 284, 205),
        ("G4E1V1", 224, 205), ("G5E3H1", 298, 61), ("G5E6V1", 283, 135),
    ],
    "highmag_g7e1.jpg": [
        ("G7E1H1", 257, 567), ("G7E1H0", 342, 567), ("G7E1H2", 172, 567), ("G7E1V1", 250, 335),
        ("G7E1V0", 250, 272), ("G7E1V2", 255, 395),
    ],
    "whole_target.png": [
        ("G-2E2H1", 100, 155), ("G-2E2V1", 196, 155), ("G-1E1H1", 445, 140), ("G-1E6V1", 422, 353),
        ("G-2E1H1", 425, 459), ("G-2E6H1", 88, 476), ("G0E2H1", 327, 272), ("G0E1H1", 245, 349),
    ],
}  # fmt: skip

RUNNER = """
import resource, sys, time, json
t = time.perf_counter()
from oapcal.cli import main
code = main(sys.argv[1:])
sys.stderr.write("\\nBENCH " + json.dumps({"code": code, "time_s": time.perf_counter() - t,
                 "peak_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}) + "\\n")
"""


def read_image(path: Path) -> np.ndarray:
    from oapcal.io.imagefile import read_image_grey

    return read_image_grey(path)


def bar_centre(img: np.ndarray, x: float, y: float, win: int = 40) -> np.ndarray:
    """Centroid of the thresholded blob through (x, y) (midpoint of the local min and max)."""
    import cv2

    h, w = img.shape
    x0, x1 = max(0, int(x) - win), min(w, int(x) + win + 1)
    y0, y1 = max(0, int(y) - win), min(h, int(y) + win + 1)
    patch = img[y0:y1, x0:x1].astype(float)
    thr = 0.5 * (patch.min() + patch.max())
    inside = patch[int(y) - y0, int(x) - x0] > thr
    mask = ((patch > thr) == inside).astype(np.uint8)
    _, labels = cv2.connectedComponents(mask, connectivity=4)
    blob = labels == labels[int(y) - y0, int(x) - x0]
    ys, xs = np.nonzero(blob)
    return np.array([xs.mean() + x0, ys.mean() + y0])


def truth_map(name: str, img: np.ndarray, groups, layout):
    """Affine map object um -> image px through the anchors (see the module docstring)."""
    from oapcal.imaging.usaf import parse_groups, usaf_target

    anchors = ANCHORS.get(name)
    if not anchors:
        return None, None
    target = usaf_target(
        parse_groups(sorted({int(a[0][1 : a[0].index("E")]) for a in anchors})), layout_name=layout
    )
    rows = zip(target.bar_group, target.bar_element, target.bar_orientation, target.bar_index)
    bar_ids = [f"G{g}E{e}{o}{b}" for g, e, o, b in rows]
    src, dst = [], []
    for bid, x, y in anchors:
        k = bar_ids.index(bid)
        src.append(0.5 * (target.bars[k, :2] + target.bars[k, 2:]))
        dst.append(bar_centre(img, x, y))
    src, dst = np.array(src), np.array(dst)
    design = np.column_stack([src, np.ones(len(src))])
    coef, *_ = np.linalg.lstsq(design, dst, rcond=None)
    rms = float(np.sqrt(np.mean(np.sum((design @ coef - dst) ** 2, axis=1))))
    return (lambda um: np.column_stack([um, np.ones(len(um))]) @ coef), rms


def quadratic_rms(xy_u: np.ndarray, xy_d: np.ndarray) -> float:
    if len(xy_u) < 24:  # fewer than two triplets' corners: not a test of a smooth map
        return float("nan")
    c = xy_u.mean(axis=0)
    z = (xy_u - c) / max(float(np.ptp(xy_u, axis=0).max()) / 2, 1.0)
    design = np.column_stack([np.ones(len(z)), z, z**2, z[:, 0] * z[:, 1]])
    coef, *_ = np.linalg.lstsq(design, xy_d, rcond=None)
    return float(np.sqrt(np.mean(np.sum((design @ coef - xy_d) ** 2, axis=1))))


def run_one(path: Path, groups: str, extra: list, workdir: Path, pictures: Path | None, n: int):
    out = workdir / f"{path.stem}_{n}.csv"
    args = [str(path), "--groups", groups, "--out", str(out), "--json", *extra]
    if pictures is not None:
        suffix = "_with_scale" if extra else ""
        args += ["--plot", str(pictures / f"real_{path.stem}{suffix}.png")]
    proc = subprocess.run([sys.executable, "-c", RUNNER, "detect", *args], capture_output=True, text=True)
    bench = json.loads(proc.stderr.rsplit("BENCH ", 1)[1])
    summary = json.loads(proc.stdout) if proc.stdout.strip() else {}
    return bench, summary, out


#: --poses: the element a user reads on each image (named with --anchor when the image alone
#: is refused), and the options every run of that image gets.
POSE_ANCHORS = {
    "fpm_brightfield.png": ("G4E2", {}),
    "labumk_negative.tif": ("G4E3", {}),
    "whole_target.png": ("G-2E2", {}),
    "highmag_g7e1.jpg": ("G7E1", {"mirror_of_base": "no"}),  # the base run with a scale and the mirror
}
#: --poses: the transforms (cv2): turned counter-clockwise on screen by 30, 90 and 135 degrees
#: onto a canvas that holds the whole image (the rest filled with the image's median),
#: mirrored left-right, mirrored and turned by 30 degrees, binned 2 x 2 (INTER_AREA).
POSES = ("rot30", "rot90", "rot135", "mirror", "rot30m", "bin2")


def transform(img: np.ndarray, kind: str):
    """``img`` transformed by ``kind`` (:data:`POSES`, or ``"none"``) and the 2x3 affine map
    from its pixel coordinates to the new image's (pixel centres, docs/conventions.md)."""
    import cv2

    h, w = img.shape
    img = img.astype(np.float32)
    if kind == "none":
        return img, np.array([[1.0, 0, 0], [0, 1.0, 0]])
    if kind == "bin2":
        out = cv2.resize(img, (w // 2, h // 2), interpolation=cv2.INTER_AREA)
        return out, np.array([[0.5, 0, -0.25], [0, 0.5, -0.25]])
    if kind == "mirror":
        return img[:, ::-1].copy(), np.array([[-1.0, 0, w - 1], [0, 1.0, 0]])
    mirror = kind.endswith("m")
    angle = float(kind.rstrip("m").removeprefix("rot"))
    src = img[:, ::-1].copy() if mirror else img
    flip = np.array([[-1.0, 0, w - 1], [0, 1, 0], [0, 0, 1]]) if mirror else np.eye(3)
    c = ((w - 1) / 2, (h - 1) / 2)
    m = cv2.getRotationMatrix2D(c, angle, 1.0)
    nw = int(np.ceil(w * abs(m[0, 0]) + h * abs(m[0, 1])))
    nh = int(np.ceil(h * abs(m[0, 0]) + w * abs(m[0, 1])))
    m[0, 2] += (nw - 1) / 2 - c[0]
    m[1, 2] += (nh - 1) / 2 - c[1]
    out = cv2.warpAffine(src, m, (nw, nh), flags=cv2.INTER_LINEAR, borderValue=float(np.median(src)))
    return out, (np.vstack([m, [0, 0, 1]]) @ flip)[:2]


def check_turned(base, det, groups, affine, shape) -> dict:
    """Ids of ``det`` (a transformed image's detection) against ``base`` (the image's own),
    mapped through ``affine``.  A corner's expected place is the base's corner of that id, or,
    for ids the base did not keep, a cubic map target um -> base px through the base's corners.
    Wrong: nearer to another id's expected place than to its own, or more than 3 px from it
    (3 px of the source image when ``affine`` enlarges it: at 6.4 times, corners of 31-35 px
    bars 3.1-4.4 px from the image's own, the same 0.5-0.7 source px, are not wrong ids).
    ``strict`` counts those farther than min(that, half the distance to the nearest other
    expected corner), as ``e2e_real.py`` counts wrong ids (a corner of a bar under 2 px is
    0.9 px from its neighbour).  Corners whose place lies outside the source image (the turned
    canvas shows the bars cut by the source's edge) are counted apart (``off_source``), and so
    are corners the base did not keep that lie outside the convex hull of the base's corners
    in um (``unreferenced``: their expected place would be the cubic map extrapolated, e.g. a
    binned single element whose base kept only the H triplet)."""
    from scipy.spatial import Delaunay, cKDTree

    from oapcal.imaging.usaf import usaf_target

    t = usaf_target(groups, layout_name=base.pose.get("layout"))
    index = {i: k for k, i in enumerate(t.corner_ids)}
    um = t.corners_um[[index[i] for i in base.ids]]
    c, sc = um.mean(axis=0), float(np.ptp(um, axis=0).max()) / 2

    def design(u):
        z = (u - c) / sc
        return np.column_stack([z[:, 0] ** i * z[:, 1] ** (n - i) for n in range(4) for i in range(n + 1)])

    coef, *_ = np.linalg.lstsq(design(um), base.xy_d, rcond=None)
    expected = design(t.corners_um) @ coef
    bidx = {i: n for n, i in enumerate(base.ids)}
    for i, n in bidx.items():
        expected[index[i]] = base.xy_d[n]
    mapped = expected @ affine[:, :2].T + affine[:, 2]
    tree = cKDTree(mapped)
    nn = tree.query(mapped, k=2)[0][:, 1]
    tol = 3.0 * max(1.0, float(np.sqrt(abs(np.linalg.det(affine[:, :2])))))
    h, w = shape
    out = {"found": len(det.ids), "in_base": 0, "off_source": 0, "unreferenced": 0, "wrong": 0, "strict": 0,
           "errors": []}  # fmt: skip
    hull = Delaunay(um) if len(um) >= 3 else None
    for cid, xy in zip(det.ids, det.xy_d):
        k = index[cid]
        e = expected[k]
        if not (3 <= e[0] <= w - 4 and 3 <= e[1] <= h - 4):
            out["off_source"] += 1
            continue
        if cid not in bidx and (hull is None or hull.find_simplex(t.corners_um[k]) < 0):
            out["unreferenced"] += 1
            continue
        d = float(np.hypot(*(xy - mapped[k])))
        nearest = int(tree.query(xy)[1])
        out["in_base"] += cid in bidx
        out["wrong"] += int(d > tol or nearest != k)
        out["strict"] += int(d > min(tol, 0.5 * nn[k]))
        out["errors"].append(d)
    out["median_px"] = float(np.median(out.pop("errors"))) if out["found"] else float("nan")
    return out


def _real_images(only: str | None, count: int):
    """``(file, groups, image, parsed groups)`` of the first ``count`` runs of :data:`RUNS`
    whose file name contains ``only`` (all without it)."""
    from oapcal.imaging.usaf import parse_groups

    for name, groups, _, _ in RUNS[:count]:
        if not only or only in name:
            yield name, groups, read_image(REAL / name), parse_groups(groups)


def run_poses(only: str | None) -> None:
    """Detection of every real image turned, mirrored and binned (:data:`POSES`), in this
    process (``detect_usaf`` with the command's defaults): without an anchor, and, when
    refused, with the element of :data:`POSE_ANCHORS` named (``--anchor``)."""
    import time

    from oapcal.imaging.detect import detect_usaf

    print("| image | transform | anchor | exit | corners | wrong ids | strict | beyond the source | "
          "not in the reference | median (px) | um/px +/- sigma | time (s) | reason |")  # fmt: skip
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for name, _, img, g in _real_images(only, 4):
        anchor, opts = POSE_ANCHORS[name]
        base_kw = {"um_per_px": 0.11, "mirror": "no"} if opts.get("mirror_of_base") else {}
        base = detect_usaf(img, g, **base_kw)
        if not base.ok:
            print(f"| {name} | none | | the unturned image is refused: {base.message} |")
            continue
        for kind in POSES:
            im2, affine = transform(img, kind)
            runs = [None, anchor]
            for a in runs:
                kw = {}
                if a is not None:
                    kw["anchors"] = a
                t0 = time.perf_counter()
                det = detect_usaf(im2, g, **kw)
                dt = time.perf_counter() - t0
                label = "" if a is None else a + (f" --mirror {kw['mirror']}" if "mirror" in kw else "")
                if det.ok:
                    r = check_turned(base, det, g, affine, img.shape)
                    sig = f" +/- {det.um_per_px_sigma:.2g}" if det.um_per_px_sigma is not None else ""
                    print(f"| {name} | {kind} | {label} | 0 | {r['found']} | {r['wrong']} | {r['strict']} | "
                          f"{r['off_source']} | {r['unreferenced']} | {r['median_px']:.3f} | "
                          f"{det.um_per_px:.4g}{sig} | {dt:.1f} | |", flush=True)  # fmt: skip
                    break
                print(
                    f"| {name} | {kind} | {label} | 3 | | | | | | | | {dt:.1f} | {det.message} |", flush=True
                )


#: --large: the images enlarged (bicubic) to the largest size within LARGE_SIDE x LARGE_SIDE
#: px, as they are and turned by 30 degrees on their canvas first (the detection goal: 30 s
#: and 2 GB per image up to 2048 x 2048).
LARGE_SIDE = 2048
LARGE_POSES = ("none", "rot30")


def run_large(only: str | None) -> None:
    """Detection time and peak memory at the goal's largest image size (:data:`LARGE_SIDE`):
    each image (and its canvas turned by 30 degrees) enlarged to fit, written as a float32
    TIFF and detected by the command line in a subprocess (as ``main`` does); ids checked
    against the image's own detection mapped through the transform (:func:`check_turned`)."""
    import tempfile
    from types import SimpleNamespace

    import cv2
    import tifffile

    from oapcal.imaging.detect import detect_usaf
    from oapcal.io.points import read_points

    workdir = Path(tempfile.mkdtemp(prefix="real_usaf_large_"))
    print("| image | transform | size (px) | exit | time (s) | peak memory (MB) | corners | wrong ids | "
          "strict | median (px) | reason |")  # fmt: skip
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for name, groups, img, g in _real_images(only, 3):
        base = detect_usaf(img, g)
        for kind in LARGE_POSES:
            im2, affine = transform(img, kind)
            f = LARGE_SIDE / max(im2.shape)
            size = (int(round(im2.shape[1] * f)), int(round(im2.shape[0] * f)))
            big = cv2.resize(im2, size, interpolation=cv2.INTER_CUBIC)
            # cv2.resize keeps pixel centres aligned: x' = f (x + 1/2) - 1/2
            aff = np.array([[f, 0, 0.5 * f - 0.5], [0, f, 0.5 * f - 0.5]]) @ np.vstack([affine, [0, 0, 1]])
            path = workdir / f"{Path(name).stem}_{kind}.tif"
            tifffile.imwrite(path, big.astype(np.float32))
            bench, summary, out = run_one(path, groups, [], workdir, None, 0)
            cells = f"| {name} | {kind} | {size[0]} x {size[1]} | {bench['code']} | {bench['time_s']:.1f} | "
            cells += f"{bench['peak_mb']:.0f} |"
            if bench["code"] != 0 or not base.ok:
                why = summary.get("message", "") if base.ok else "the image itself is refused"
                print(f"{cells} | | | | {why} |", flush=True)
                continue
            pairs = read_points(out)
            r = check_turned(base, SimpleNamespace(ids=list(pairs.ids), xy_d=pairs.xy_d), g, aff, img.shape)
            cells += f" {r['found']} | {r['wrong']} | {r['strict']} | {r['median_px']:.3f} | |"
            print(cells, flush=True)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--pictures", type=Path, default=None, help="write the --plot pictures here")
    ap.add_argument("--poses", action="store_true", help="the images turned, mirrored and binned (run_poses)")
    ap.add_argument("--large", action="store_true", help="the images enlarged to 2048 px (run_large)")
    ap.add_argument("--only", default=None, help="--poses, --large: only the images whose name has this text")
    args = ap.parse_args()
    if not REAL.is_dir():
        sys.exit(f"{REAL}: not found (the real images are kept beside the repository)")
    if args.poses:
        run_poses(args.only)
        return
    if args.large:
        run_large(args.only)
        return
    import tempfile

    from oapcal.io.points import read_points

    workdir = Path(tempfile.mkdtemp(prefix="real_usaf_"))
    if args.pictures is not None:
        args.pictures.mkdir(parents=True, exist_ok=True)
    print("| image | exit | time (s) | peak memory (MB) | right ids / corners of fully visible elements | "
          "wrong ids | scale found (um/px) | measured (SOURCES.md) | scale error | pixel size (um/px) | "
          "quadratic-map rms (px) | anchor-map rms (px) | reason |")  # fmt: skip
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for n, (name, groups, measured, extra) in enumerate(RUNS):
        path = REAL / name
        if not path.exists():
            print(f"| {name} | missing | | | | | | | | | | | |")
            continue
        bench, summary, out = run_one(path, groups, extra, workdir, args.pictures, n)
        # the scale the pose search found (with --um-per-px, x_u,y_u use the given one)
        scale = summary.get("pose", {}).get("best", {}).get("um_per_px") or summary.get("um_per_px")
        scale = scale if bench["code"] == 0 else None  # a refused pose has no scale to report
        right = wrong = visible = 0
        qrms = anchor_rms = float("nan")
        if bench["code"] == 0:
            from oapcal.imaging.usaf import parse_groups, usaf_target

            pairs = read_points(out)
            img = read_image(path)
            layout = summary.get("pose", {}).get("layout")
            fmap, anchor_rms = truth_map(name, img, groups, layout)
            qrms = quadratic_rms(pairs.xy_u, pairs.xy_d)
            if fmap is not None:
                target = usaf_target(parse_groups(groups), layout_name=layout)
                pred = fmap(target.corners_um)
                o, ex, ey = fmap(np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]]))
                px_per_um = abs(np.linalg.det(np.array([ex - o, ey - o]))) ** 0.5
                wpx = target.corner_width_um * px_per_um
                index = {i: k for k, i in enumerate(target.corner_ids)}
                h, w = img.shape
                # fully visible elements: all 24 corners 3 px inside, bars >= 2 px wide
                elem = {}
                for k, cid in enumerate(target.corner_ids):
                    elem.setdefault(cid[: cid.index("H") if "H" in cid else cid.index("V")], []).append(k)
                vis_ids = set()
                for ks in elem.values():
                    p = pred[ks]
                    ok = (p[:, 0] >= 3).all() and (p[:, 0] <= w - 4).all() and (p[:, 1] >= 3).all()
                    ok = ok and (p[:, 1] <= h - 4).all() and wpx[ks[0]] >= 2.0
                    if ok:
                        vis_ids.update(target.corner_ids[k] for k in ks)
                visible = len(vis_ids)
                for cid, xy in zip(pairs.ids, pairs.xy_d):
                    k = index[cid]
                    good = np.hypot(*(xy - pred[k])) <= wpx[k]
                    right += int(good and cid in vis_ids)
                    wrong += int(not good)
        err = f"{100 * (scale / measured - 1):+.1f} %" if scale else ""
        reason = "" if bench["code"] == 0 else summary.get("reason", "")
        found = scale if scale else float("nan")
        label = name + (" " + " ".join(extra) if extra else "")
        # the pixel-size answer: found (+/- its sigma), or, with a scale given, the measured one
        psize = ""
        if bench["code"] == 0 and summary.get("um_per_px_sigma") is not None:
            psize = f"{summary['um_per_px']:.4g} +/- {summary['um_per_px_sigma']:.2g}"
        elif bench["code"] == 0 and summary.get("pixel_size"):
            ps = summary["pixel_size"]
            psize = f"given; measured {ps['um_per_px']:.4g} (anisotropy {ps['anisotropy']:.2g})"
        print(f"| {label} | {bench['code']} | {bench['time_s']:.1f} | {bench['peak_mb']:.0f} | "
              f"{right} / {visible} | {wrong} | {found:.4g} | {measured:g} | {err} | {psize} | "
              f"{qrms:.3f} | {anchor_rms:.2f} | {reason} |", flush=True)  # fmt: skip


if __name__ == "__main__":
    main()
