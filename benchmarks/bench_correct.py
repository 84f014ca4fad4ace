"""Speed of image correction against OpenCV, measured in the same run.

1. map build (640x480 and 2048x2048) against ``cv2.initUndistortRectifyMap`` building the
   same map from the exported OpenCV parameters (``docs/opencv.md``; the two maps are
   checked equal), interleaved, medians: first the NumPy closed form a process without the
   kernels uses for maps of at most ``eq1_closed_form.MAX_POINTS`` px, then the compiled builder;
2. per-frame correction through oapcal's API (``correct_image`` with a built map) against
   a bare ``cv2.remap`` with the same precomputed maps (the floor), for 640x480 8-bit and
   2048x2048 16-bit frames;
3. whole-stack throughput of ``oapcal correct`` (in-process CLI, progress bar off) on a
   1,000-frame 640x480 8-bit TIFF stack against read + remap + write done directly with
   tifffile and OpenCV;
4. the 500-frame fixed cost: ``python -m oapcal correct`` as a new process (imports, loading
   and checking the calibration, the map, the trust region, then the frames) on a 500-frame
   640x480 stack (uint8 and uint16) against a new process doing ``tifffile.imread`` +
   ``cv2.remap`` + ``tifffile.imwrite`` with the same map (saved by ``oapcal correct
   --save-map``, loaded with ``np.load``); medians of the repeats, interleaved.

Goals: the map build at most 2x OpenCV's; per-frame within 10% of the bare remap; the stack
command within 20% of the direct pipeline; the 500-frame command within 1.2x of the plain
process.
Run:  PYTHONPATH=src python benchmarks/bench_correct.py [--frames N] [--repeats R] [--fixed-cost-only]
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
import tifffile
from _timing import median_time

from oapcal.calibration import Calibration, FitSummary
from oapcal.cli import main
from oapcal.eq1_closed_form import MAX_POINTS
from oapcal.imaging.remap import correct_image, correction_map
from oapcal.io.calibration import save_calibration
from oapcal.io.opencv_export import opencv_parameters
from oapcal.model import PRESETS, scale_params
from oapcal.stats import ResidualStats
from oapcal.synthetic import EXAMPLE_TRUTH


def params_for(width, height):
    """The example distortion scaled to a camera of this size."""
    return scale_params(EXAMPLE_TRUTH, 640 / width)


def main_bench():
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=1000)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--fixed-cost-only", action="store_true", help="only the 500-frame fixed-cost case")
    args = ap.parse_args()
    print(f"OpenCV {cv2.__version__}, {cv2.getNumThreads()} threads; tifffile {tifffile.__version__}")
    if args.fixed_cost_only:
        fixed_cost(args.repeats)
        return

    print("\n== map build: oapcal correction_map vs cv2.initUndistortRectifyMap (same map; medians)")
    sizes = [(640, 480), (2048, 2048)]
    # A process that has not loaded the kernels builds an Eq. (1) map of at most
    # eq1_closed_form.MAX_POINTS px in NumPy (what `oapcal correct` does): timed first, before
    # anything loads Numba; then the compiled builder, the kernels loaded.
    for w, h in sizes:
        if w * h <= MAX_POINTS:
            map_build_case(w, h, "closed form (no Numba loaded)", args.repeats)
    assert "numba" not in sys.modules, "the closed-form case loaded the kernels"
    import oapcal._kernels  # noqa: F401  (every map below: the compiled builder)

    for w, h in sizes:
        map_build_case(w, h, "compiled", args.repeats)

    print("\n== per frame: oapcal correct_image vs bare cv2.remap (same maps; medians)")
    rng = np.random.default_rng(0)
    for (w, h), dtype in [((640, 480), np.uint8), ((2048, 2048), np.uint16)]:
        cmap = correction_map(params_for(w, h), (h, w))
        mx, my = cmap.map_x, cmap.map_y
        frame = rng.integers(0, np.iinfo(dtype).max, (h, w), dtype=dtype)
        n = 200 if w == 640 else 20
        ours = []
        bare = []
        for _ in range(args.repeats):  # interleaved so both see the same machine load
            bare.append(median_time(lambda f=frame, x=mx, y=my: cv2.remap(
                f, x, y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0), n))  # fmt: skip
            ours.append(median_time(lambda f=frame, c=cmap: correct_image(f, c, "linear", 0), n))
        b, o = statistics.median(bare), statistics.median(ours)
        print(
            f"{w}x{h} {np.dtype(dtype).name}: bare {b * 1e3:7.3f} ms, "
            f"oapcal {o * 1e3:7.3f} ms, ratio {o / b:5.3f}"
        )

    print(f"\n== stack: {args.frames} frames 640x480 uint8 TIFF (medians of {args.repeats})")
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        stack = rng.integers(0, 255, (args.frames, 480, 640), dtype=np.uint8)
        src = tmp / "stack.tif"
        tifffile.imwrite(src, stack, photometric="minisblack")
        del stack
        _calibration_file(tmp / "calib.json")

        def direct():
            mx, my = correction_map(EXAMPLE_TRUTH, (480, 640))  # the maps, built once per run
            frames = tifffile.imread(src)
            out = np.empty_like(frames)
            for i, f in enumerate(frames):
                cv2.remap(f, mx, my, cv2.INTER_LINEAR, dst=out[i], borderMode=cv2.BORDER_CONSTANT)
            tifffile.imwrite(tmp / "direct.tif", out, photometric="minisblack")

        def command():
            out = tmp / "out"
            shutil.rmtree(out, ignore_errors=True)  # outputs and the resume records
            code = main(["correct", str(tmp / "calib.json"), str(src), "--out-dir", str(out), "--quiet"])
            assert code == 0

        d_times, c_times = [], []
        for _ in range(args.repeats):
            d_times.append(median_time(direct, 1))
            c_times.append(median_time(command, 1))
        d, c = statistics.median(d_times), statistics.median(c_times)
        assert np.array_equal(tifffile.imread(tmp / "out" / "stack.tif"), tifffile.imread(tmp / "direct.tif"))
        print(f"direct tifffile+cv2.remap: {d:6.3f} s ({args.frames / d:7.1f} frames/s)")
        print(f"oapcal correct:            {c:6.3f} s ({args.frames / c:7.1f} frames/s), ratio {c / d:5.3f}")
    fixed_cost(args.repeats)


def map_build_case(w: int, h: int, label: str, repeats: int) -> None:
    """``correction_map`` of a ``w x h`` camera against ``cv2.initUndistortRectifyMap``
    building the same map, interleaved, medians."""
    p = params_for(w, h)
    cv = opencv_parameters(p, (w, h))
    keys = ("camera_matrix", "dist_coeffs", "new_camera_matrix")
    k, dist, k_new = (np.array(cv[key], float) for key in keys)

    def peer():
        return cv2.initUndistortRectifyMap(k, dist, None, k_new, (w, h), cv2.CV_32FC1)

    ours_map = correction_map(p, (h, w))  # also the first call (with the compiled builder: its load)
    peer_map = peer()
    diff = max(float(np.abs(a - b).max()) for a, b in zip(ours_map, peer_map))
    n = 20 if w == 640 else 5
    ours, theirs = [], []
    for _ in range(repeats):  # interleaved so both see the same machine load
        theirs.append(median_time(peer, n))
        ours.append(median_time(lambda: correction_map(p, (h, w)), n))
    o, t = statistics.median(ours), statistics.median(theirs)
    print(f"{w}x{h} {label}: oapcal {o * 1e3:7.2f} ms, OpenCV {t * 1e3:7.2f} ms, ratio {o / t:5.2f} "
          f"(maps differ by at most {diff:.1e} px)")  # fmt: skip


#: The plain process of the fixed-cost case: what a script written with tifffile and OpenCV
#: alone does with a saved map.
PLAIN = """
import sys
import cv2, numpy as np, tifffile
maps = np.load(sys.argv[1])
mx, my = maps["map_x"], maps["map_y"]
frames = tifffile.imread(sys.argv[2])
out = np.empty((len(frames), *mx.shape), frames.dtype)
for i, f in enumerate(frames):
    cv2.remap(f, mx, my, cv2.INTER_LINEAR, dst=out[i], borderMode=cv2.BORDER_CONSTANT)
tifffile.imwrite(sys.argv[3], out, photometric="minisblack")
"""


def _calibration_file(path: Path) -> None:
    free = PRESETS["paper"]
    cal = Calibration(free=free, params=EXAMPLE_TRUTH, stderr=np.full(13, np.nan),
                      covariance=np.zeros((len(free), len(free))),
                      fit=FitSummary(n_points=1, rss=0.0, converged=True),
                      residuals=ResidualStats(*[float("nan")] * 4, n_points=0),
                      um_per_px=4.8, image_size=(640, 480), name="bench")  # fmt: skip
    save_calibration(cal, path)


def _run(args, env) -> tuple[float, float]:
    """Wall time and CPU time (user + system, all threads) of a new process running ``args``."""
    import resource

    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t = time.perf_counter()
    subprocess.run(args, check=True, capture_output=True, env=env)
    wall = time.perf_counter() - t
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def fixed_cost(repeats: int, frames: int = 500) -> None:
    """``python -m oapcal correct`` as a process against the plain tifffile + OpenCV process."""
    print(f"\n== {frames}-frame fixed cost: python -m oapcal correct vs a plain tifffile + cv2.remap "
          f"process (same map; medians of {repeats})")  # fmt: skip
    rng = np.random.default_rng(1)
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1] / "src")}
    # bytecode cached as in any installation: with PYTHONDONTWRITEBYTECODE set (some sandboxes
    # set it) every run compiled oapcal's 32 imported modules from source, 45 ms of the ~0.5 s
    env.pop("PYTHONDONTWRITEBYTECODE", None)
    # in memory where the machine has a tmpfs: the disk's own speed is not what is measured
    where = "/dev/shm" if os.path.isdir("/dev/shm") else None
    with tempfile.TemporaryDirectory(dir=where) as tmp:
        tmp = Path(tmp)
        calib = tmp / "calib.json"
        _calibration_file(calib)
        maps = tmp / "map.npz"
        command = [sys.executable, "-m", "oapcal", "correct", str(calib)]
        subprocess.run([*command, "--save-map", str(maps)], check=True, capture_output=True, env=env)
        for dtype in (np.uint8, np.uint16):
            src = tmp / f"stack_{np.dtype(dtype).name}.tif"
            top = np.iinfo(dtype).max
            tifffile.imwrite(
                src, rng.integers(0, top, (frames, 480, 640), dtype=dtype), photometric="minisblack"
            )
            out = tmp / "out"
            ours = [*command, str(src), "--out-dir", str(out), "--quiet", "--overwrite"]
            plain = [sys.executable, "-c", PLAIN, str(maps), str(src), str(tmp / "plain.tif")]
            _run(ours, env), _run(plain, env)  # warm the page cache and the kernels' cache
            c_times, p_times = [], []
            for _ in range(repeats):  # interleaved so both see the same machine load
                p_times.append(_run(plain, env))
                c_times.append(_run(ours, env))
            assert np.array_equal(tifffile.imread(out / src.name), tifffile.imread(tmp / "plain.tif"))
            medians = (tuple(statistics.median(t) for t in zip(*x)) for x in (c_times, p_times))
            (c, c_cpu), (p, p_cpu) = medians
            print(f"{frames} frames 640x480 {np.dtype(dtype).name}: plain process {p:6.3f} s "
                  f"({p_cpu:5.3f} s CPU), oapcal correct {c:6.3f} s ({c_cpu:5.3f} s CPU), "
                  f"ratio {c / p:5.2f} wall, {c_cpu / p_cpu:5.2f} CPU")  # fmt: skip
            src.unlink()


if __name__ == "__main__":
    main_bench()
