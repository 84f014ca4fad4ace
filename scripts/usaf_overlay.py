"""Lay the reference USAF layout over the shared real images and check its fit.

For each image of ``oapcal.imaging.usaf_check.REAL_IMAGES`` (in ../shared/real/usaf by
default) the layout is fitted by least squares of triplet edges (no detector involved),
from two hand-picked triplet centres; the script prints one row per image and writes
``docs/img/usaf_overlay_<image>.png``: the image with the fitted reference outline (bars
green, reference squares cyan, number boxes yellow) and each edge residual as a red tick,
20 times enlarged.  ``--measure`` also fits the layout numbers themselves
(``measure_layout``: gaps, layer width, nested layer) and prints them: that is how
``LAYOUTS`` were obtained.  It also writes ``docs/img/usaf_layouts.png``, the three
layouts rendered side by side, and ``docs/img/usaf_simulated_target.png``, a simulated
camera image of the target through the traced relay.

Run: .venv/bin/python scripts/usaf_overlay.py [--real DIR] [--measure]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import cv2
import numpy as np

from oapcal.imaging.usaf import LAYOUTS, layout, render_usaf, usaf_target
from oapcal.imaging.usaf_check import (
    REAL_IMAGES,
    check_real_image,
    measure_layout,
    overlay_image,
    similarity_from_points,
)
from oapcal.io.imagefile import read_image_grey

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "docs" / "img"
#: zoom and crop (x0, y0, x1, y1 in image px) of each picture
VIEW = {
    "fpm_brightfield.png": (0.8, (170, 40, 1110, 980)),
    "labumk_negative.tif": (2.5, None),
    "whole_target.png": (1.6, None),
    "highmag_g7e1.jpg": (1.0, (40, 180, 700, 740)),
}


def picture(name: str, image, target, fit) -> np.ndarray:
    zoom, crop = VIEW.get(name, (1.0, None))
    if crop is not None:
        x0, y0, x1, y1 = crop
        image = image[y0:y1, x0:x1]

        offset = np.array([x0, y0], float)

        def mapping(xy):
            return fit(xy) - offset

        pic = overlay_image(image, target, mapping, zoom=zoom)
        shifted = [(p, q - [x0, y0]) for p, q in zip(fit.edge_um, fit.edge_px)]
        for p, q in shifted:
            a = mapping(p[None])[0]
            tip = a + 20 * (q - a)
            pa = tuple(int(v) for v in np.rint((a + 0.5) * zoom - 0.5))
            pb = tuple(int(v) for v in np.rint((tip + 0.5) * zoom - 0.5))
            cv2.line(pic, pa, pb, (0, 0, 255), 1, cv2.LINE_AA)
    else:
        pic = overlay_image(image, target, fit, zoom=zoom, fit=fit)
    text = (
        f"{name}: layout {target.layout}, {fit.n_triplets} triplets, edge rms {fit.rms_px:.3f} px (ticks x20)"
    )
    band = np.full((28, pic.shape[1], 3), 255, np.uint8)
    cv2.putText(band, text, (6, 19), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
    return np.concatenate([band, pic], axis=0)


def layouts_picture() -> np.ndarray:
    tiles = []
    for name in LAYOUTS:
        r = render_usaf((4, 5, 6, 7), um_per_px=1.6, image_size=(560, 560), layout_name=name, polarity="dark")
        tile = (r.image * 255).astype(np.uint8)
        tile = cv2.cvtColor(tile, cv2.COLOR_GRAY2BGR)
        cv2.putText(tile, name, (8, 552), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (0, 0, 200), 1, cv2.LINE_AA)
        tiles.append(tile)
    return np.concatenate(tiles, axis=1)


def simulated_picture() -> np.ndarray:
    """Groups 4-5 through the traced relay of setup 1 (turned by 180 degrees), sigma 0.8 px, SNR 50."""
    from oapcal.imaging.simulate import simulate_image
    from oapcal.optics import relay_distortion

    sim = simulate_image((4, 5), relay_distortion(1), sigma_px=0.8, snr=50, seed=0)
    x0, y0, x1, y1, z = 200, 170, 440, 400, 3.0  # crop and zoom
    crop = cv2.resize(sim.image[y0:y1, x0:x1], None, fx=z, fy=z, interpolation=cv2.INTER_NEAREST)
    pic = cv2.cvtColor(crop, cv2.COLOR_GRAY2BGR)
    for x, y in sim.xy_d[sim.visible] - [x0, y0]:
        cv2.circle(
            pic, (int(round((x + 0.5) * z - 0.5)), int(round((y + 0.5) * z - 0.5))), 2, (0, 0, 230), -1
        )
    text = "simulated: groups 4-5 through the traced relay (setup 1), sigma 0.8 px, SNR 50; red: true corners"  # noqa: E501
    band = np.full((28, pic.shape[1], 3), 255, np.uint8)
    cv2.putText(band, text, (6, 19), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    return np.concatenate([band, pic], axis=0)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--real", type=Path, default=ROOT.parent / "shared" / "real" / "usaf")
    ap.add_argument("--measure", action="store_true", help="also fit the layout numbers")
    ap.add_argument("--no-pictures", action="store_true")
    args = ap.parse_args(argv)
    OUT.mkdir(parents=True, exist_ok=True)
    print(f"{'image':22} {'layout':13} {'groups':12} {'triplets':>8} {'edges':>6} {'rms px':>7} "
          f"{'um/px':>9} {'time s':>6}")  # fmt: skip
    for name, cfg in REAL_IMAGES.items():
        path = args.real / name
        if not path.exists():
            print(f"{name:22} missing in {args.real}")
            continue
        t0 = time.perf_counter()
        target, fit = check_real_image(read_image_grey(path), name)
        dt = time.perf_counter() - t0
        groups = ",".join(str(g) for g in cfg["groups"])
        print(f"{name:22} {cfg['layout']:13} {groups:12} {fit.n_triplets:8d} {fit.n_edges:6d} "
              f"{fit.rms_px:7.3f} {fit.um_per_px:9.4f} {dt:6.1f}")  # fmt: skip
        if not args.no_pictures:
            pic = picture(name, read_image_grey(path), target, fit)
            out = OUT / f"usaf_overlay_{Path(name).stem}.png"
            cv2.imwrite(str(out), pic)
        if args.measure:
            t = usaf_target(cfg["groups"], cfg["layout"])
            start = similarity_from_points(t, cfg["start"])
            image = read_image_grey(path)
            lay, mfit = measure_layout(image, cfg["groups"], layout(cfg["layout"]), start, min_w_px=1.9)
            print(f"    measured: {lay} (edge rms {mfit.rms_px:.3f} px, {mfit.n_triplets} triplets)")
    if not args.no_pictures:
        cv2.imwrite(str(OUT / "usaf_layouts.png"), layouts_picture())
        cv2.imwrite(str(OUT / "usaf_simulated_target.png"), simulated_picture())


if __name__ == "__main__":
    main()
