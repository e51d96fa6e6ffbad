"""Exact-shape efficiency bounds beside doefab's designs: how far retrieval is from the physics.

For every named target of :mod:`doe.targets` and the robustness set it prints

- the bound for a continuous phase and for an L-level plate
  (:func:`doe.bounds.efficiency_bound`: the most light any phase-only plate can
  put into a window of exactly the target's shape);
- for targets with dark orders, the L-level bound of the target plus a uniform
  background in them that spends the rmse budget the design aims at
  (:func:`doe.bounds.with_background`, rmse 0.0045): an estimate of what such a
  background could buy, reachable only if the plate's own errors cost nothing;
- for those targets also the L-level bound maximised over every window pattern
  within the goals the design aims at (:func:`doe.bounds.within_goals`, free
  amplitudes and phases, exact figures within the cap 0.81): no plate whose PSF
  meets those goals can pass it (up to the estimate);
- doefab's quantised efficiency (:func:`doe.retrieval.retrieve_phase`) and the
  floor issue 2 asks for (0.90 compact, 0.85 the rest).

The bounds are maxima found by L-BFGS from random phases, so estimates from
below of the true maxima.

Run::

    python bench/efficiency_bound.py            # N = 175, L = 8, ~6 min on 2 cores
    python bench/efficiency_bound.py --bounds-only
"""

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from doe import bounds, retrieval, targets

BACKGROUND_RMSE = retrieval.RMSE_GOAL * retrieval.CAP**0.5
"""rmse spent on the uniform background: all the design aims at (0.0045)."""


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--tile-pixels", type=int, default=175)
    ap.add_argument("--levels", type=int, default=8)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--bounds-only", action="store_true", help="skip the doefab designs")
    args = ap.parse_args(argv)
    n, n_levels = args.tile_pixels, args.levels
    cases = {name: targets.make_target(name) for name in targets.TARGETS}
    cases.update(targets.robustness_set(11))
    print(f"exact-shape efficiency bounds, N = {n}, L = {n_levels}")
    print(f"{'target':16s} {'lit':>4s} {'continuous':>10s} {f'{n_levels} levels':>10s}", end="")
    print(f" {'+background':>11s} {'in goals':>8s}", end="")
    print("" if args.bounds_only else f" {'doefab':>8s} {'floor':>6s}  verdict")
    for name, target in cases.items():
        rng = np.random.default_rng(args.seed)
        continuous = bounds.efficiency_bound(target, n, None, rng)
        levelled = bounds.efficiency_bound(target, n, n_levels, rng)
        row = f"{name:16s} {int((target > 0).sum()):4d} {continuous:10.4f} {levelled:10.4f}"
        bound = levelled  # the highest L-level bound, for the verdict
        if (target == 0).any():
            padded = bounds.efficiency_bound(
                bounds.with_background(target, BACKGROUND_RMSE), n, n_levels, rng
            )
            free, _ = bounds.within_goals(target, n, n_levels, retrieval.CAP)
            row += f" {padded:11.4f} {free:8.4f}"
            bound = max(padded, free)
        else:
            row += f" {'-':>11s} {'-':>8s}"
        if not args.bounds_only:
            t0 = time.perf_counter()
            design = retrieval.retrieve_phase(target, n, n_levels, seed=args.seed)
            eff = design.quality_quantised["efficiency"]
            floor = targets.efficiency_floor(name)
            if eff >= floor:
                verdict = "meets the floor"
            elif floor > bound:
                verdict = f"floor {floor - bound:+.3f} above every {n_levels}-level bound"
            else:
                verdict = f"below the floor, {bound - eff:.3f} under a bound"
            row += f" {eff:8.4f} {floor:6.2f}  {verdict} ({time.perf_counter() - t0:.1f} s)"
        print(row, flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
