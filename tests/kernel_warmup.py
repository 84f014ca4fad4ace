"""Compile the kernels into Numba's cache in a second process while the tests run.

A fresh checkout has an empty cache, and the first test to use each kernel pays its
compilation (about 30-50 s of CPU over the suite, one core; the tests themselves run on one
core).  :func:`start` (called by ``tests/conftest.py`` at the start of a session whose cache
is empty) runs this module in a background process on the other core: it makes the first
calls of the kernels in the order the suite needs them last-first (the relay, Eq. (1) with
the rotation, priors, then Eq. (1)'s selection, robustness and inverse paths), so that when
a test reaches them they load from the cache.  The same source files, so the same cache
entries; Numba writes each entry atomically, and a kernel both processes compile is only
compiled twice.  Nothing here is checked: the tests check the kernels.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path


def _relay() -> None:
    import numpy as np

    from oapcal.imaging.remap import correction_map
    from oapcal.model import distort, undistort
    from oapcal.optics.relay_model import RelayDesign, calibrate_relay, relay_params

    design = RelayDesign(setup=1, pixel_size_um=4.8, centre=(319.5, 239.5))
    g = np.stack(np.meshgrid(np.linspace(40, 600, 17), np.linspace(40, 440, 13)), -1).reshape(-1, 2)
    xy_d = distort(g, relay_params(design, {"m2_decentre_x": 0.2, "d1": 0.5}))
    cal = calibrate_relay(g, xy_d, design, image_size=(640, 480))
    undistort(xy_d, cal.params)
    correction_map(cal, (480, 640))


def _eq1() -> None:
    from oapcal.calibration import calibrate
    from oapcal.imaging.remap import correction_map
    from oapcal.model import undistort
    from oapcal.select import robustness, select_models
    from oapcal.synthetic import synthetic_pairs
    from oapcal.uncertainty import uncertainty_map

    d = synthetic_pairs(seed=3)
    cal = calibrate(d.xy_u, d.xy_d, "paper+rotation", image_size=(640, 480))
    correction_map(cal, (480, 640))
    undistort(d.xy_d, cal.params)
    select_models(d.xy_u[:40], d.xy_d[:40], cv=3)
    robustness(d.xy_u, d.xy_d, ["paper"], trials=10)
    undistort(d.xy_d, d.params, xy_start=d.xy_u)
    uncertainty_map(calibrate(d.xy_u, d.xy_d, "paper", image_size=(640, 480)), step=40)


def _cache_is_empty() -> bool:
    """Whether Numba's cache holds no entry of the kernels yet (a fresh checkout)."""
    import importlib.util

    package = Path(importlib.util.find_spec("oapcal").origin).parent
    where = os.environ.get("NUMBA_CACHE_DIR")
    pattern = "_relay_kernel.*.nbi"
    found = Path(where).rglob(pattern) if where else (package / "__pycache__").glob(pattern)
    return next(iter(found), None) is None


def start():
    """The background process compiling the kernels (:func:`stop` ends it), or None when the
    cache is not empty or ``OAPCAL_NO_KERNEL_WARMUP`` is set."""
    if os.environ.get("OAPCAL_NO_KERNEL_WARMUP") or not _cache_is_empty():
        return None
    import oapcal

    src = str(Path(oapcal.__file__).resolve().parents[1])
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([src, os.environ.get("PYTHONPATH", "")])}
    return subprocess.Popen(  # niced: the tests come first
        [sys.executable, __file__], env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        stdin=subprocess.DEVNULL, preexec_fn=lambda: os.nice(5) if hasattr(os, "nice") else None,
    )  # fmt: skip


def stop(process) -> None:
    if process is not None and process.poll() is None:
        process.terminate()
        try:
            process.wait(10)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()


if __name__ == "__main__":
    import warnings

    warnings.simplefilter("ignore")
    for step in (_relay, _eq1):
        try:
            step()
        except Exception:  # noqa: BLE001 - a warm-up only: the tests report real failures
            pass
