"""The plate over its clear aperture: how much of it the GDS patterns, and the plate as built.

    python bench/plate_fill.py FAB_DIR [FAB_DIR ...]

For each ``doefab fab`` package (this version's or an older one's): the fraction of
the design's clear aperture whose pixel centres, read back from every mask layer of
mask.gds with KLayout, carry the tile repeated without end (plain glass matches it
only where the tile is unetched), the geometric patterned fraction, the GDS size;
then the plate as built (doe.aperture) against the target for the three layouts
``doefab fab`` can draw: filled (default), whole tiles with the frame shrunk
(``--whole-tiles``), whole tiles in the design's frame (``--whole-tiles
--keep-aperture``, what a package without edge tiles is).
"""

import json
import sys
import time
from pathlib import Path

import numpy as np

from doe import fraunhofer
from doe.aperture import as_built
from fab.package.masks import masks_from_levels
from layouts.plate_plan import plan_pattern
from layouts.plate_raster import aperture_match


def main(folders):
    for folder in map(Path, folders):
        m = json.loads((folder / "fab_manifest.json").read_text())
        levels = np.load(folder / "levels.npy")
        target = np.load(folder / "target_psf.npy")
        n_levels, n, p = m["levels"], m["tile_pixels"], m["pixel_pitch_nm"]
        masks = masks_from_levels(levels, n_levels, m["level_step_nm"] * 1e-9)
        aperture = round(m["aperture_mm"] * 1e6)
        tiles, origin = m["tiles"], m["array_origin_nm"]
        plate = plan_pattern(n, p, tiles, origin, aperture, "glass")  # the design's frame
        cell = m.get("plate_cell", m["top_cell"])
        t = time.perf_counter()
        match, written, _ = aperture_match(
            folder / "mask.gds", cell, masks, levels, plate, window_nm=aperture
        )
        seconds = time.perf_counter() - t
        geometric = m["plate"]["patterned_fraction"] if "plate" in m else plate.patterned_fraction()
        print(
            f"{folder}: {m['design_name']}, N = {n}, p = {p} nm, {tiles[0]} x {tiles[1]} whole "
            f"tiles in {aperture / 1e6:g} mm; periodic pattern read back over {match:.5%} of "
            f"{written.size} aperture pixels ({seconds:.1f} s); geometric {geometric:.5%}; "
            f"mask.gds {(folder / 'mask.gds').stat().st_size} bytes"
        )
        sim, eff = fraunhofer.simulate_levels(levels, n_levels, target.shape[0])
        print(
            f"  tile model: correlation {fraunhofer.correlation(sim, target):.6f}, "
            f"rmse {fraunhofer.rmse(sim, target):.5f}, efficiency {eff:.4f}"
        )
        for mode in ("fill", "shrink", "glass"):
            layout = plan_pattern(n, p, tiles, origin, aperture, mode)
            t = time.perf_counter()
            b = as_built(levels, n_levels, layout, target)
            print(
                f"  {mode:6s}: patterned {layout.patterned_fraction():.5f}, light kept "
                f"{layout.aperture_light_kept():.4f}; correlation {b.correlation:.6f}, rmse "
                f"{b.rmse:.5f}, efficiency {b.efficiency:.4f}, zero order {b.zero_order:.5f}, "
                f"goals {'met' if not b.missed else 'MISSED'}; per cell correlation "
                f"{b.cell_correlation:.6f}, rmse {b.cell_rmse:.5f} "
                f"({time.perf_counter() - t:.2f} s)"
            )


if __name__ == "__main__":
    main(sys.argv[1:])
