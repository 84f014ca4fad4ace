"""Exhaustive AICc model selection: oapcal against a plain loop of SciPy fits.

Data: the paper's workflow on simulated data, a 17 x 17 grid (289 points) of paraxial
points over 640 x 480 px distorted by ``oapcal.synthetic.EXAMPLE_TRUTH`` (the ``paper``
model, up to ~40 px) plus 0.05 px Gaussian noise, normalized with ``--normalize grid``;
every fit starts from zero (m = 1).

oapcal: :func:`oapcal.select.select_models` (fits, inverses and AICc of all 4,096 models),
median of ``--repeats`` runs after one warm-up run (which also loads or compiles the Numba
kernels; the compile time is printed separately).

Peer: for each model, ``scipy.optimize.least_squares(method="lm")`` with the analytic
Jacobian and its default tolerances, then the NumPy inverse (``tests/reference_model.py``) and
the same AICc.  By default the peer runs on ``--sample`` random subsets plus oapcal's 20
best and its time is extrapolated to 4,096 models (stated in the output); ``--full`` runs
all 4,096.  Checks: the AICc of every model valid in both agrees to 1e-6 relative, and
both pick the same best model among the models the peer fitted.

``--command N`` also times the whole command, ``oapcal select FILE --normalize grid --top 1``
on the same 289 points written to a temporary point-pair file, as N fresh processes (after
one that may compile the kernels into the cache and writes the modules' ``.pyc`` files, as
an installed package has them), and prints the median wall and CPU time, with a bare
``python -c "import numpy"`` process as the reference (the goal is absolute: 1 s).

    PYTHONPATH=src python benchmarks/bench_select.py [--full] [--sample 256] [--repeats 5] [--command 9]
"""

from __future__ import annotations

import argparse
import os
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy.optimize import least_squares

from oapcal.model import all_masks, names_from_mask, pack, unpack
from oapcal.normalize import normalize

# The peer uses the NumPy implementation of Eq. (1), its Jacobian and inverse (the tests'
# reference), not oapcal's compiled kernels.
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from oapcal.stats import information_criteria
from oapcal.synthetic import EXAMPLE_TRUTH
from reference_model import distort, jacobian_params, undistort  # noqa: E402


def grid_data(seed: int = 0):
    gx, gy = np.meshgrid(np.linspace(0, 640, 17), np.linspace(0, 480, 17))
    xy_u = np.stack([gx.ravel(), gy.ravel()], -1)
    xy_d = distort(xy_u, EXAMPLE_TRUTH) + np.random.default_rng(seed).normal(0, 0.05, xy_u.shape)
    return xy_u, xy_d


def scipy_score(u, d, mask):
    """One model the plain way: SciPy LM from zero, NumPy inverse, AICc. (aicc, valid)."""
    p0 = np.zeros(13)
    p0[12] = 1.0

    def fun(q):
        return (distort(u, unpack(q, mask)) - d).ravel()

    def jac(q):
        return jacobian_params(u, unpack(q, mask)).reshape(-1, 13)[:, mask]

    res = least_squares(fun, pack(p0, mask), jac=jac, method="lm")
    params = unpack(res.x, mask)
    inv = undistort(d, params)
    rss = float(np.sum((inv.xy - u) ** 2))
    aicc = float(information_criteria(rss, 2 * len(u), int(mask.sum())).aicc)
    valid = bool(res.success and inv.converged.all() and np.isfinite(aicc))
    return aicc, valid


def _timed_process(argv: list[str], env: dict) -> tuple[float, float]:
    """Wall and CPU time (user + system of the child) of one process."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t = time.perf_counter()
    subprocess.run(argv, env=env, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    wall = time.perf_counter() - t
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def time_command(xy_u, xy_d, runs: int) -> None:
    """The whole ``oapcal select`` command as fresh processes, median of ``runs``."""
    from oapcal.io.points import write_point_pairs

    exe = shutil.which("oapcal", path=str(Path(sys.executable).parent)) or shutil.which("oapcal")
    command = [exe] if exe else [sys.executable, "-m", "oapcal"]
    # As an installed package runs: its modules byte-compiled (the first run writes the .pyc
    # files even where PYTHONDONTWRITEBYTECODE is set; compiling oapcal's ~40 modules from
    # source took ~50 ms of every run).
    env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
    with tempfile.TemporaryDirectory() as tmp:
        path = str(Path(tmp) / "grid.csv")
        write_point_pairs(path, xy_u, xy_d)
        argv = [*command, "select", path, "--normalize", "grid", "--top", "1"]
        _timed_process(argv, env)  # compiles the kernels into the cache (or loads them), writes the .pyc
        ours, bare = [], []
        for _ in range(runs):  # alternating, so both see the same load
            ours.append(_timed_process(argv, env))
            bare.append(_timed_process([sys.executable, "-c", "import numpy"], env))
    walls = [w for w, _ in ours]
    wall, cpu = statistics.median(walls), statistics.median(c for _, c in ours)
    print(f"oapcal select as a command (oapcal select grid.csv --normalize grid --top 1), median of {runs}: "
          f"{wall:.3f} s wall, {cpu:.3f} s CPU (runs {min(walls):.3f}-{max(walls):.3f} s); "
          f"bare python -c 'import numpy': {statistics.median(w for w, _ in bare):.3f} s; "
          f"load average {os.getloadavg()[0]:.1f}")  # fmt: skip


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--full", action="store_true", help="run the SciPy loop over all 4,096 models")
    ap.add_argument("--sample", type=int, default=256, help="random models for the SciPy loop")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--command", type=int, default=0, metavar="N", help="also time the whole command N times")
    ap.add_argument("--command-only", action="store_true", help="time only the whole command")
    args = ap.parse_args()

    from oapcal.select import select_models

    xy_u, xy_d = grid_data(args.seed)
    if args.command or args.command_only:
        time_command(xy_u, xy_d, args.command or 9)
        if args.command_only:
            return
    norm = normalize("grid", xy_u, xy_d)

    t = time.perf_counter()
    sel = select_models(xy_u, xy_d, normalization="grid", init="zero")
    first = time.perf_counter() - t
    times, cpu = [], []
    for _ in range(args.repeats):
        t, c = time.perf_counter(), time.process_time()
        sel = select_models(xy_u, xy_d, normalization="grid", init="zero")
        times.append(time.perf_counter() - t)
        cpu.append(time.process_time() - c)
    ours = statistics.median(times)
    ours_cpu = statistics.median(cpu)
    print(
          f"oapcal select: 4096 models on {len(xy_u)} points, median of {args.repeats}: {ours:.3f} s wall, "
          f"{ours_cpu:.3f} s CPU (first call incl. loading/compiling the kernels: {first:.2f} s)"
    )  # fmt: skip
    print(f"  best: {','.join(sel.best.free)}  AICc {sel.best.aicc:.6f}; {sel.n_valid} valid models")

    masks = all_masks()
    by_bits = {m.bits: m for m in sel.models}
    if args.full:
        chosen = np.arange(4096)
    else:
        rng = np.random.default_rng(args.seed)
        top = [m.bits for m in sel.models[:20]]
        chosen = np.unique(np.concatenate([rng.choice(4096, args.sample, replace=False), top]))
    peer = {}
    t_models = []
    t0, c0 = time.perf_counter(), time.process_time()
    for b in chosen:
        t = time.perf_counter()
        peer[int(b)] = scipy_score(norm.xy_u, norm.xy_d, masks[b])
        t_models.append(time.perf_counter() - t)
    total = time.perf_counter() - t0
    total_cpu = time.process_time() - c0
    if args.full:
        loop, loop_cpu = total, total_cpu
        how = "measured over all 4096 models"
    else:
        # extrapolate from the random sample only (the top 20 are excluded from the timing)
        sample_bits = set(np.random.default_rng(args.seed).choice(4096, args.sample, replace=False).tolist())
        sample_t = [tm for b, tm in zip(chosen, t_models) if int(b) in sample_bits]
        loop = float(np.mean(sample_t)) * 4096
        loop_cpu = total_cpu / len(chosen) * 4096
        how = f"extrapolated from {len(sample_t)} random models (mean {1e3 * np.mean(sample_t):.1f} ms each)"
    print(f"SciPy loop: {loop:.1f} s wall, {loop_cpu:.1f} s CPU for 4096 models ({how})")
    ratio_cpu = loop_cpu / ours_cpu
    print(f"speed ratio (SciPy loop / oapcal): {loop / ours:.0f}x wall clock, {ratio_cpu:.0f}x CPU time")

    rel = []
    far = []
    disagree_valid = 0
    for b, (aicc, valid) in peer.items():
        m = by_bits[b]
        if valid and m.valid:
            rel.append(abs(aicc - m.aicc) / abs(m.aicc))
            if rel[-1] > 1e-6:
                far.append(m.delta_aicc)
        elif valid != m.valid:
            disagree_valid += 1
    rel = np.array(rel)
    print(f"AICc agreement on {rel.size} models valid in both: {(rel <= 1e-6).sum()} within 1e-6 relative, "
          f"max rel diff {rel.max():.2e}; validity differs for {disagree_valid}")  # fmt: skip
    if far:
        print(
            f"  the {len(far)} models beyond 1e-6 are poor fits, dAICc >= {min(far):.0f} from the best "
            "(the two LM codes stop at different points of their flat, multi-minimum cost)"
        )
    best_peer = peer.get(sel.best.bits)
    if best_peer is not None:
        print(
            f"best model: oapcal AICc {sel.best.aicc:.9f}, SciPy {best_peer[0]:.9f}, "
            f"rel diff {abs(best_peer[0] - sel.best.aicc) / abs(sel.best.aicc):.1e}"
        )
    peer_best = min((aicc, b) for b, (aicc, valid) in peer.items() if valid)[1]
    same = peer_best == sel.best.bits
    scope = "all 4096" if args.full else f"the {len(peer)} models it fitted"
    rank = 1 + [m.bits for m in sel.models].index(peer_best)
    print(f"SciPy's best among {scope}: {','.join(names_from_mask(masks[peer_best]))} -> "
          f"{'SAME' if same else 'DIFFERENT'} model as oapcal (its oapcal rank: {rank})")  # fmt: skip


if __name__ == "__main__":
    main()
