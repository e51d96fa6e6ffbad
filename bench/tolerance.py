"""Benchmark the tolerance analysis and the fabrication report at full size (N = 175).

Prints, for a small Gerchberg-Saxton design of the default preset:
the wall time of ``tolerance_analysis`` (median of --repeat runs), the time of
one fabricated-plate evaluation (nominal and with every error at once), the
time of ``write_fab_report``, the largest rmse difference between the
continuous model and a 20x supersampled grid over the whole table, and the
model's zero-order slope for a balanced 8-level tile against 1.053 eps^2.

Run: ``python bench/tolerance.py [--repeat 3]``
"""

import argparse
import hashlib
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from doe.fraunhofer import round_levels
from doe.gerchberg_saxton import gerchberg_saxton
from doe.infra import flags


def gs_levels(n, target, n_levels, seed=0, iters=120):
    """Return a level map from a plain Gerchberg-Saxton run, rounded to the levels."""
    rng = np.random.default_rng(seed)
    phase, _ = gerchberg_saxton(target, n, iters, rng, weighted=False)
    return round_levels(phase, n_levels)


def median_time(fn, repeat):
    times = []
    result = None
    for _ in range(repeat):
        t0 = time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), result


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=flags.count, default=3)
    args = parser.parse_args(argv)

    from doe.derived import derive, design_summary
    from doe.design import load_design
    from doe.fraunhofer import simulate_levels
    from fab.package.masks import masks_from_levels
    from fab.package.report import write_fab_report
    from fab.plate.model import PlateFaults, plate_model, window_amplitudes
    from fab.plate.tolerance import tolerance_analysis

    design = load_design()
    der = derive(design)
    n, k, n_levels = der.tile_pixels, design.kernel_size, design.fabrication.levels
    rng = np.random.default_rng(0)
    target = rng.uniform(0.2, 1.0, (k, k))
    target /= target.sum()
    levels = gs_levels(n, target, n_levels)
    masks = masks_from_levels(levels, n_levels, der.level_step)
    optics = (der.mask_pixel_pitch, der.level_step, design.optics.wavelength,
              der.refractive_index)  # fmt: skip

    def analyse(supersample=None):
        return tolerance_analysis(levels, n_levels, target, masks, *optics,
                                  supersample=supersample)  # fmt: skip

    t_table, result = median_time(analyse, args.repeat)
    print(
        f"tolerance_analysis N={n} K={k}: median {t_table:.2f} s over {args.repeat} runs "
        f"({len(result['rows'])} rows, {len(result['monte_carlo']['rmse'])} Monte Carlo plates)"
    )

    model = plate_model(masks, der.mask_pixel_pitch, der.level_step, n_levels,
                        design.optics.wavelength, der.refractive_index, k)  # fmt: skip
    worst = PlateFaults(
        etch_errors=(0.05, -0.05, 0.05),
        overlay=((0, 0), (0.3e-6, -0.4e-6), (-0.7e-6, 0.2e-6)),
        cd_bias=0.1e-6,
    )
    t_nom, _ = median_time(lambda: window_amplitudes(model), 20)
    t_all, _ = median_time(lambda: window_amplitudes(model, worst), 5)
    print(
        f"one plate evaluation: nominal {t_nom * 1e3:.2f} ms, every error at once "
        f"{t_all * 1e3:.1f} ms (median)"
    )

    s = 20
    t_s20, grid = median_time(lambda: analyse(s), 1)
    # A value the grid cannot represent is rounded to whole sub-samples (0.1 um of CD
    # bias is 0.4 of a 0.25 um sub-sample: no bias at all), so compare kind by kind.
    sub_um = der.mask_pixel_pitch * 1e6 / s
    gaps = {}
    for a, b in zip(result["rows"], grid["rows"], strict=True):
        gaps.setdefault(a["kind"], []).append(abs(a["rmse"] - b["rmse"]))
    cd = sorted({abs(r["value"]) for r in result["rows"] if r["kind"] == "cd_bias"})
    rounded = ", ".join(f"{v:g} um -> {round(v / sub_um) * sub_um:.3g} um" for v in cd)
    print(
        f"continuous vs {s}x supersampled table ({sub_um:.4f} um sub-samples; supersampled "
        f"run {t_s20:.2f} s): max |delta rmse| "
        + ", ".join(f"{kind} {max(g):.2e}" for kind, g in gaps.items() if kind != "nominal")
        + f" (CD biases on the grid: {rounded})"
    )

    balanced = np.random.default_rng(1).permutation(np.arange(64 * 64) % 8).reshape(64, 64)
    bmasks = masks_from_levels(balanced, 8, der.level_step)
    bmodel = plate_model(bmasks, der.mask_pixel_pitch, der.level_step, 8,
                         design.optics.wavelength, der.refractive_index, 3)  # fmt: skip
    eps = 0.01
    p0 = abs(window_amplitudes(bmodel, PlateFaults(etch_errors=(eps, 0, 0)))[1, 1]) ** 2
    print(
        f"balanced 8-level tile, deep etch eps={eps}: P0/eps^2 = {p0 / eps**2:.4f} "
        f"(analytic small-eps slope 1.0530)"
    )

    simulated, eff = simulate_levels(levels, n_levels, k)
    context = {
        "design": design_summary(design),
        "manifest": {
            "wavelength_nm": design.optics.wavelength * 1e9,
            "refractive_index": der.refractive_index, "levels": n_levels,
            "level_step_nm": der.level_step * 1e9,
            "pixel_pitch_nm": round(der.mask_pixel_pitch * 1e9), "tile_pixels": n,
            "tiles": [der.tiles, der.tiles], "array_origin_nm": [0, 0],
        },
        "masks": [{"name": mk.name, "gds_layer": mk.gds_layer,
                   "etch_depth_nm": mk.etch_depth * 1e9, "exposure_order": mk.exposure_order,
                   "fill_fraction": mk.fill_fraction, "polygon_count": 0,
                   "min_feature_um": der.mask_pixel_pitch * 1e6} for mk in masks],
        "levels": levels, "target_psf": target, "simulated_psf": simulated,
        "efficiency": eff, "tolerance": result, "orientation": "bench",
        "files": [{"path": "levels.npy", "bytes": levels.nbytes,
                   "sha256": hashlib.sha256(levels.tobytes()).hexdigest()}],
    }  # fmt: skip
    with tempfile.TemporaryDirectory() as tmp:
        t_rep, names = median_time(lambda: write_fab_report(Path(tmp) / "r", context), 1)
    print(
        f"write_fab_report: {t_rep:.2f} s ({len(names)} files, first call incl. matplotlib import)"
    )


if __name__ == "__main__":
    main()
