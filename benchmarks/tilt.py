"""Eq. (1) with and without the perspective (keystone) terms on misaligned relays.

The truths of ``benchmarks/models.py`` (setup 1, all 20 misalignment values drawn within
the tolerances, camera and object planes tilted by up to 1 deg, the target turned by up to
1 deg; traced by the NumPy tracer), 250 landmarks over the whole field with 0.3 or 0.03 px
noise, and the noise-free floor (each model fitted to 21 x 21 points of the traced field).
Each Eq. (1) variant is fitted in the paper's grid-normalized frame (as ``models.py`` fits
``paper``) and corrects the 101 x 101 grid; error = distance to the true reference point (px).

    .venv/bin/python benchmarks/tilt.py --seeds 10
    .venv/bin/python benchmarks/tilt.py --seeds 5 --select     # select --families, ~6 min
"""

from __future__ import annotations

import argparse

import numpy as np
from models import GRID_N, _frame, draw_truth, errors, landmark_positions, reference_grid, trace

from oapcal.fitting import fit

MODELS = ("paper", "paper+tilt", "paper+rotation", "paper+rotation+tilt", "full+rotation",
          "full+rotation+tilt")  # fmt: skip


def fit_eq1(lm_u, lm_d, spec):
    """The model ``spec`` fitted in the grid-normalized frame, as a corrector of distorted px."""
    cu, su = _frame(lm_u)
    cd, sd = _frame(lm_d)
    res = fit((lm_u - cu) * su, (lm_d - cd) * sd, spec)
    return lambda grid_d: res.model.inverse((grid_d - cd) * sd).xy / su + cu


def run(seeds: int, first: int = 0) -> dict:
    grid_u = reference_grid()
    inside = np.ones(len(grid_u), bool)
    sub = grid_u.reshape(GRID_N, GRID_N, 2)[::5, ::5].reshape(-1, 2)
    rows = {}
    for seed in range(first, first + seeds):
        mis, turn = draw_truth(seed)
        grid_d = trace(mis, turn, grid_u)
        lm_u = landmark_positions(seed, "whole", grid_u)
        lm_clean = trace(mis, turn, lm_u)
        unit = np.random.default_rng([seed, 7, 0]).normal(size=lm_u.shape)
        cases = {"floor": (sub, trace(mis, turn, sub))}
        cases.update({f"{noise} px": (lm_u, lm_clean + noise * unit) for noise in (0.3, 0.03)})
        for case, (u, d) in cases.items():
            for spec in MODELS:
                e = errors(fit_eq1(u, d, spec)(grid_d), grid_u, inside)
                rows.setdefault((case, spec), []).append((e["mean"], e["max"]))
    return rows


def run_select(seeds: int, first: int = 0):
    """``select --families`` with and without the tilt variants on the 0.3 px landmarks (in
    px, as given): the recommended spec and its error over the field, per seed."""
    from oapcal.families import select_families

    grid_u = reference_grid()
    inside = np.ones(len(grid_u), bool)
    print("| seed | families | recommended | k | mean px | max px |")
    print("|---|---|---|---|---|---|")
    for seed in range(first, first + seeds):
        mis, turn = draw_truth(seed)
        grid_d = trace(mis, turn, grid_u)
        lm_u = landmark_positions(seed, "whole", grid_u)
        lm_d = trace(mis, turn, lm_u) + 0.3 * np.random.default_rng([seed, 7, 0]).normal(size=lm_u.shape)
        for families in ("bc,bc+rotation", "bc,bc+rotation,bc+tilt,bc+rotation+tilt"):
            rec = select_families(lm_u, lm_d, None, families, cv=5, image_size=(640, 480)).recommended
            e = errors(fit(lm_u, lm_d, rec.spec).model.inverse(grid_d).xy, grid_u, inside)
            row = f"| {seed} | {families} | `{rec.spec}` | {rec.k} | {e['mean']:.3f} | {e['max']:.2f} |"
            print(row, flush=True)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--first-seed", type=int, default=0)
    ap.add_argument("--select", action="store_true", help="the family selection with and without the tilt")
    args = ap.parse_args()
    if args.select:
        return run_select(args.seeds, args.first_seed)
    rows = run(args.seeds, args.first_seed)
    print("| landmarks | model | mean px (mean over seeds) | worst seed's mean | max px (mean over seeds) |")
    print("|---|---|---|---|---|")
    for (case, spec), vals in rows.items():
        v = np.array(vals)
        print(f"| {case} | {spec} | {v[:, 0].mean():.3f} | {v[:, 0].max():.3f} | {v[:, 1].mean():.2f} |")


if __name__ == "__main__":
    main()
