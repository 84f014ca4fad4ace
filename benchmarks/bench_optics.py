"""Speed of the OAP relay ray tracer.

Peers, timed in the same run: a straightforward per-ray Python loop over the same
closed-form geometry (what a script without vectorization does); for the distortion
field, SciPy's ``RectBivariateSpline.ev`` (FITPACK) evaluating the same splines and
Newton inversion on it; plus the CLI as a whole process. Medians of repeats; ratios
printed (peer time / oapcal time).  Misaligned relays (every mirror degree of freedom,
camera and object tilts) are timed against the same per-ray loop, which handles any
mirror placement; tolerancing (``oapcal.optics.tolerance``) against the per-ray loop
tracing the same grids.  With an older ``src`` on ``PYTHONPATH`` the rows that need
misalignment are skipped, so the aligned rows can be compared before and after.

    PYTHONPATH=src .venv/bin/python benchmarks/bench_optics.py
"""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
from _timing import median_time

from oapcal.optics.field import relay_distortion
from oapcal.optics.relay import chief_rays, grid_distortion, oap_relay, object_grid


def loop_chief_rays(relay, xy_obj):
    """The peer: one chief ray at a time (stop at the first mirror), plain Python + NumPy."""
    m1c = np.asarray(relay.m1.aperture_centre)
    out = []
    for p in xy_obj:
        point = relay.object_plane.world(p)
        d = m1c - point
        d = d / np.linalg.norm(d)
        n1 = relay.m1.normal(m1c)
        d = d - 2 * (d @ n1) * n1
        t = relay.m2.intersect(m1c, d)
        hit = m1c + t * d
        n2 = relay.m2.normal(hit)
        d = d - 2 * (d @ n2) * n2
        s = relay.image_plane.intersect(hit, d)
        out.append(relay.image_plane.local(hit + s * d))
    return np.array(out)


MISALIGNED = dict(
    m1_tilt_x=0.03, m1_tilt_y=-0.02, m1_decentre_x=0.1, m1_decentre_y=-0.15, m1_clock=0.5,
    m2_tilt_x=-0.04, m2_tilt_y=0.05, m2_decentre_x=0.2, m2_decentre_y=0.1, m2_clock=-0.3,
    camera_tilt_x=0.5, camera_tilt_y=-0.7, camera_defocus=0.1, object_tilt_x=0.4, object_tilt_y=-0.3,
)  # fmt: skip


def fitpack_eval(field, xy):
    """The peer of the bicubic patches: value and both derivatives of both components."""
    x, y = xy[:, 0], xy[:, 1]
    return [s.ev(x, y, dx=dx, dy=dy) for s in (field._spline_x, field._spline_y)
            for dx, dy in ((0, 0), (1, 0), (0, 1))]  # fmt: skip


def fitpack_inverse(field, target, tol=1e-9, max_iter=30):
    """The peer of ``DistortionField.inverse``: the same Newton iteration (same k-d tree
    start) evaluating the splines with FITPACK."""
    _, idx = field._start_tree.query(target)
    u = field._start_nodes[idx].copy()
    sx, sy = field._spline_x, field._spline_y
    for _ in range(max_iter):
        x, y = u[:, 0], u[:, 1]
        rx = x + sx.ev(x, y) - target[:, 0]
        ry = y + sy.ev(x, y) - target[:, 1]
        if np.hypot(rx, ry).max() <= tol:
            break
        a, b = 1 + sx.ev(x, y, dx=1), sx.ev(x, y, dy=1)
        c, d = sy.ev(x, y, dx=1), 1 + sy.ev(x, y, dy=1)
        det = a * d - b * c
        u = u - np.stack([d * rx - b * ry, -c * rx + a * ry], -1) / det[:, None]
    return u


def main():
    relay = oap_relay(1)
    small = object_grid(17, 1.0)
    assert np.allclose(loop_chief_rays(relay, small), chief_rays(relay, small).xy_mm, atol=1e-12)
    rows = []
    t_vec = median_time(lambda: grid_distortion(relay, 17), 21)
    t_loop = median_time(lambda: loop_chief_rays(relay, small), 5)
    rows.append(("17 x 17 grid (incl. paraxial map)", t_vec, "per-ray loop", t_loop))
    t_big = median_time(lambda: grid_distortion(relay, 1001), 5)
    sub = object_grid(101, 1.0)
    t_loop_big = median_time(lambda: loop_chief_rays(relay, sub), 1) * (1001 * 1001) / len(sub)
    rows.append(("1001 x 1001 grid", t_big, "per-ray loop (extrapolated from 101 x 101)", t_loop_big))
    stopped = oap_relay(1, stop_distance_mm=300.0)
    t_aim = median_time(lambda: grid_distortion(stopped, 1001), 3)
    rows.append(("1001 x 1001 grid, stop at 300 mm (Newton aiming)", t_aim, "-", float("nan")))
    t_field = median_time(lambda: relay_distortion(1), 3)
    rows.append(("relay_distortion() build, 640 x 480, 97 nodes", t_field, "-", float("nan")))
    field = relay_distortion(1)
    rng = np.random.default_rng(0)
    px = rng.uniform([-0.5, -0.5], [639.5, 479.5], size=(640 * 480, 2))
    rows.append(("forward, 307,200 px", median_time(lambda: field.forward(px), 3),
                 "exact trace of the same points", median_time(lambda: field.traced(px), 3)))  # fmt: skip
    patches = field._patches
    assert np.allclose(patches(px[:, 0], px[:, 1])[1][:, 0], fitpack_eval(field, px)[1], atol=1e-9)
    t_patch = median_time(lambda: patches(px[:, 0], px[:, 1]), 3)
    t_fitpack = median_time(lambda: fitpack_eval(field, px), 3)
    rows.append(("spline value + gradient (2 comp.), 307,200 px", t_patch,
                 "RectBivariateSpline.ev (FITPACK), 6 calls", t_fitpack))  # fmt: skip
    assert np.abs(fitpack_inverse(field, px) - field.inverse(px)).max() < 1e-6
    rows.append(("inverse, 307,200 px", median_time(lambda: field.inverse(px), 3),
                 "same Newton on FITPACK", median_time(lambda: fitpack_inverse(field, px), 3)))  # fmt: skip
    try:
        from oapcal.optics.tolerance import Tolerancing
    except ImportError:  # an older oapcal: no misalignment
        Tolerancing = None
    if Tolerancing is not None:
        bent = oap_relay(1, misalignment=MISALIGNED)
        assert np.allclose(loop_chief_rays(bent, small), chief_rays(bent, small).xy_mm, atol=1e-12)
        t_bent = median_time(lambda: grid_distortion(bent, 1001), 5)
        t_loop_bent = median_time(lambda: loop_chief_rays(bent, sub), 1) * (1001 * 1001) / len(sub)
        rows.append(("1001 x 1001 grid, misaligned (15 degrees of freedom)", t_bent,
                     "per-ray loop (extrapolated from 101 x 101)", t_loop_bent))  # fmt: skip
        bent_stop = oap_relay(1, stop_distance_mm=300.0, misalignment=MISALIGNED)
        rows.append(("1001 x 1001 grid, misaligned, stop at 300 mm", median_time(
            lambda: grid_distortion(bent_stop, 1001), 3), "-", float("nan")))  # fmt: skip
        t_loop_small = median_time(lambda: loop_chief_rays(bent, small), 5)
        rows.append(("build a misaligned relay + 17 x 17 grid", median_time(
            lambda: grid_distortion(oap_relay(1, misalignment=MISALIGNED), 17), 21),
            "per-ray loop, same grid", t_loop_small))  # fmt: skip
        tol = Tolerancing(relay, n=17)
        t_sens = median_time(lambda: tol.sensitivity(), 3)
        rows.append(("tolerance: 20 sensitivities (40 misaligned 17 x 17 grids)", t_sens,
                     "per-ray loop tracing the 40 grids only", 40 * t_loop_small))  # fmt: skip
        tols = {k: 0.05 for k in ("m1_tilt_x", "m1_tilt_y", "m2_tilt_x", "m2_tilt_y")}
        t_mc = median_time(lambda: tol.monte_carlo(tols, 500), 3)
        rows.append(("tolerance: Monte Carlo, 500 trials, 17 x 17", t_mc,
                     "per-ray loop tracing the 500 grids only", 500 * t_loop_small))  # fmt: skip
    env = dict(os.environ, PYTHONPATH=os.environ.get("PYTHONPATH", "src"))
    cmd = [sys.executable, "-m", "oapcal", "simulate", "relay", "--setup", "1", "--json"]
    t_cli = median_time(lambda: subprocess.run(cmd, env=env, capture_output=True, check=True), 5)
    t_py = median_time(lambda: subprocess.run([sys.executable, "-c", "pass"], check=True), 5)
    rows.append(("`oapcal simulate relay --setup 1 --json` (whole process)", t_cli,
                 "bare `python -c pass`", t_py))  # fmt: skip
    print(f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
    print(f"{'task':60s} {'oapcal':>10s}   {'peer':44s} {'peer time':>10s} {'ratio':>7s}")
    for name, t, peer, tp in rows:
        ratio = f"{tp / t:7.1f}" if np.isfinite(tp) else "      -"
        tp_s = f"{tp * 1e3:8.1f}ms" if np.isfinite(tp) else "         -"
        print(f"{name:60s} {t * 1e3:8.1f}ms   {peer:44s} {tp_s} {ratio}")


if __name__ == "__main__":
    main()
