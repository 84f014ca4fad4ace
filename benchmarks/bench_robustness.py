"""Subsampling robustness test: oapcal against a plain loop of SciPy fits.

Data: ``oapcal.synthetic.synthetic_pairs(seed=11)``: 252 point pairs over a 640 x 480 px
camera, ``paper``-model distortion up to ~40 px, 0.3 px noise, in pixel coordinates (as the
paper's experimental data).  Models ``paper`` and ``full``, each trial keeps 90 % of the
points, every fit starts from zero (m = 1).

oapcal: :func:`oapcal.select.robustness` with ``--trials`` trials (default 10,000) of both
models, including the fold-over check, the wrong-minimum check and the held-out
correction; median of ``--repeats`` runs after a warm-up run.

Peer: per trial and model, ``scipy.optimize.least_squares(method="lm")`` with the analytic
Jacobian and default settings on the kept points, then the NumPy inverse
(``tests/reference_model.py``) of the held-out points and the NumPy Jacobian determinant over
the same hull grid.  It runs ``--sample`` trials (the first ones of oapcal's own draw) and
its time is extrapolated to all trials (stated in the output).  The script also reports
how often SciPy claims success in a wrong minimum (RMS on the kept points > 1.5 x the
model's best all-points RMS) and how often oapcal's and SciPy's fits of the same trial
reach the same RMS (1e-6 relative).

    PYTHONPATH=src python benchmarks/bench_robustness.py [--trials 10000] [--sample 200]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np
from scipy.optimize import least_squares

from oapcal.fitting import fit_batch, initial_params
from oapcal.model import pack, parse_model, unpack
from oapcal.select import REASONS, hull_grid, robustness
from oapcal.synthetic import synthetic_pairs

# The peer uses the NumPy implementation of Eq. (1), its Jacobians and inverse (the tests'
# reference), not oapcal's compiled kernels.
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from reference_model import distort, jacobian_determinant, jacobian_params, undistort  # noqa: E402


def scipy_trial(u, d, keep, held, mask, grid):
    p0 = np.zeros(13)
    p0[12] = 1.0
    uk, dk = u[keep], d[keep]

    def fun(q):
        return (distort(uk, unpack(q, mask)) - dk).ravel()

    def jac(q):
        return jacobian_params(uk, unpack(q, mask)).reshape(-1, 13)[:, mask]

    res = least_squares(fun, pack(p0, mask), jac=jac, method="lm")
    params = unpack(res.x, mask)
    folded = not (jacobian_determinant(grid, params).min() > 0)
    inv = undistort(d[held], params)
    heldout = float(np.nanmean(np.hypot(*(inv.xy - u[held]).T)))
    return res.success, np.sqrt(2 * res.cost / len(keep)), folded, heldout


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=10000)
    ap.add_argument("--sample", type=int, default=200, help="trials per model in the SciPy loop")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()

    data = synthetic_pairs(seed=11)
    u, d = data.xy_u, data.xy_d
    models = ["paper", "full"]
    run = dict(trials=args.trials, seed=args.seed, init="zero")

    t = time.perf_counter()
    result = robustness(u, d, models, **run)
    first = time.perf_counter() - t
    times, cpu = [], []
    for _ in range(args.repeats):
        t, c = time.perf_counter(), time.process_time()
        result = robustness(u, d, models, **run)
        times.append(time.perf_counter() - t)
        cpu.append(time.process_time() - c)
    ours = statistics.median(times)
    ours_cpu = statistics.median(cpu)
    print(f"oapcal robustness: {args.trials} trials x {len(models)} models on {len(u)} points, "
          f"median of {args.repeats}: {ours:.2f} s wall, {ours_cpu:.2f} s CPU "
          f"(first call {first:.2f} s)")  # fmt: skip
    for m in result.models:
        reasons = ", ".join(f"{r} {m.by_reason[r]}" for r in REASONS)
        print(f"  {m.name}: not converged {m.not_converged} ({reasons}); "
              f"held-out mean error {m.heldout_mean_error:.4f} px")  # fmt: skip

    # The same subsets as oapcal (robustness() draws them this way).
    n = len(u)
    n_keep = result.n_keep
    perm = np.argsort(np.random.default_rng(args.seed).random((args.trials, n)), axis=1)
    keep = np.sort(perm[:, :n_keep], axis=1)
    held = np.sort(perm[:, n_keep:], axis=1)
    grid = hull_grid(u)
    total_time = 0.0
    total_cpu = 0.0
    for m in result.models:
        mask = parse_model(models[result.models.index(m)])
        ref_rms = m.reference_rms
        success = wrong = folded = same = 0
        t, c = time.perf_counter(), time.process_time()
        rms_ours = []
        for i in range(args.sample):
            ok, rms, fold, _ = scipy_trial(u, d, keep[i], held[i], mask, grid)
            success += ok
            folded += ok and fold
            wrong += ok and rms > 1.5 * ref_rms
            rms_ours.append(rms)
        dt = time.perf_counter() - t
        total_time += dt / args.sample * args.trials
        total_cpu += (time.process_time() - c) / args.sample * args.trials
        # oapcal's fits of the same trials, for the RMS agreement
        p0 = initial_params("zero", u, d, mask)
        fits = fit_batch(u, d, np.repeat(mask[None], args.sample, 0), p0, points=keep[: args.sample],
                         covariance=False)  # fmt: skip
        ours_rms = np.sqrt(fits.rss / n_keep)
        same = int(np.sum(np.abs(ours_rms - np.array(rms_ours)) <= 1e-6 * ours_rms))
        print(f"  SciPy {m.name}: {1e3 * dt / args.sample:.1f} ms per trial; of {args.sample} trials it "
              f"reports "
              f"success in {success}, of which {wrong} are wrong minima (RMS > 1.5 x {ref_rms:.4f}) and "
              f"{folded} fold; same RMS as oapcal in {same}")  # fmt: skip
    print(f"SciPy loop: {total_time:.1f} s wall, {total_cpu:.1f} s CPU for {args.trials} trials x "
          f"{len(models)} models "
          f"(extrapolated from {args.sample} trials per model)")  # fmt: skip
    print(f"speed ratio (SciPy loop / oapcal): {total_time / ours:.0f}x wall clock, "
          f"{total_cpu / ours_cpu:.0f}x CPU time")  # fmt: skip


if __name__ == "__main__":
    main()
