"""First-use cost of the compiled kernels: compile (empty cache) and load (warm cache).

Runs, in fresh processes with a temporary ``NUMBA_CACHE_DIR``, the first call of every
compiled path a session uses (a fit, a selection with cross-validation, a robustness run,
an inverse with and without a start, a correction map, the uncertainty map) and prints the
CPU and wall time: first with an empty cache (what a fresh checkout pays once), then again
with the cache it left (what every later process pays).  The peer is a bare
``python -c "import numpy"`` process.

With ``--session relay`` the session is the physical relay's instead: a relay
calibration (fit, covariance, residual statistics), an inverse and a correction map.

    PYTHONPATH=src python benchmarks/bench_compile.py [--repeats 2] [--session eq1|relay]

With ``--variants`` it also lists what the empty-cache run compiled: one line per cached
kernel with its number of compiled signatures (the cache's ``.nbc`` files), and the total,
so two checkouts can be compared variant by variant.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time

SESSION = r"""
import time
c0, w0 = time.process_time(), time.perf_counter()
from oapcal.calibration import calibrate
from oapcal.imaging.remap import correction_map
from oapcal.model import undistort
from oapcal.select import robustness, select_models
from oapcal.synthetic import synthetic_pairs
from oapcal.uncertainty import uncertainty_map
d = synthetic_pairs(seed=3)
cal = calibrate(d.xy_u, d.xy_d, "paper", image_size=(640, 480))
select_models(d.xy_u[:40], d.xy_d[:40], cv=3)
robustness(d.xy_u, d.xy_d, ["paper"], trials=10)
undistort(d.xy_d, d.params, xy_start=d.xy_u)
correction_map(cal, (480, 640))
uncertainty_map(cal, step=40)
print(f"{time.process_time() - c0:.2f} {time.perf_counter() - w0:.2f}")
"""

RELAY_SESSION = r"""
import time
c0, w0 = time.process_time(), time.perf_counter()
import numpy as np
from oapcal.imaging.remap import correction_map
from oapcal.model import distort, undistort
from oapcal.optics.relay_model import RelayDesign, calibrate_relay, relay_params
design = RelayDesign(setup=1, pixel_size_um=4.8, centre=(319.5, 239.5))
g = np.stack(np.meshgrid(np.linspace(40, 600, 17), np.linspace(40, 440, 13)), -1).reshape(-1, 2)
truth = relay_params(design, {"m2_decentre_x": 0.2, "d1": 0.5})
xy_d = distort(g, truth)
cal = calibrate_relay(g, xy_d, design, image_size=(640, 480))
undistort(xy_d, cal.params)
correction_map(cal, (480, 640))
print(f"{time.process_time() - c0:.2f} {time.perf_counter() - w0:.2f}")
"""


def run(code: str, cache: str) -> tuple[float, float, float]:
    env = {**os.environ, "NUMBA_CACHE_DIR": cache}
    t = time.perf_counter()
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    wall = time.perf_counter() - t
    cpu, inner = (float(v) for v in (out.stdout.split() or ["nan", "nan"])[-2:])
    return cpu, inner, wall


def cached_variants(cache: str) -> dict[str, int]:
    """``{kernel: compiled signatures}`` of a Numba cache directory (its ``.nbc`` files are
    named ``<module>.<function>-<line>.py<ver>.<n>.nbc``)."""
    counts: dict[str, int] = {}
    for _root, _dirs, names in os.walk(cache):
        for name in names:
            if name.endswith(".nbc"):
                kernel = name.split("-", 1)[0]
                counts[kernel] = counts.get(kernel, 0) + 1
    return dict(sorted(counts.items()))


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--session", choices=("eq1", "relay"), default="eq1",
                    help="the Brown-Conrady session (default) or the relay's")  # fmt: skip
    ap.add_argument("--variants", action="store_true",
                    help="list the kernels and signatures the empty-cache run compiled")  # fmt: skip
    args = ap.parse_args()
    session = SESSION if args.session == "eq1" else RELAY_SESSION
    for i in range(args.repeats):
        with tempfile.TemporaryDirectory() as cache:
            cold = run(session, cache)
            warm = run(session, cache)
            bare = run("import time, numpy; print(time.process_time(), 0)", cache)
            variants = cached_variants(cache)
        print(f"run {i + 1}: empty cache (compile): {cold[0]:5.1f} s CPU, {cold[1]:5.1f} s wall; "
              f"warm cache (load): {warm[0]:4.2f} s CPU, {warm[1]:4.2f} s wall; "
              f"bare python+numpy process {bare[2]:.2f} s")  # fmt: skip
        if args.variants:
            for kernel, n in variants.items():
                print(f"  {n} x {kernel}")
            print(f"  {sum(variants.values())} compiled signatures of {len(variants)} kernels")
    print(f"load average: {os.getloadavg()[0]:.1f} (2 = both cores of a 2-core machine busy)")


if __name__ == "__main__":
    main()
