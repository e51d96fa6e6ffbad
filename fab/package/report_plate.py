"""The fab report's plate: tiles across, the patterned fraction of the clear aperture,
what fewer tiles cost, the dies on the substrate, and the goals judged on the plate as
built (:mod:`doe.aperture`) beside the tile model's."""

from doe.figures import correlation_text
from doe.goals import CORRELATION_GOAL, RMSE_GOAL


def _verdict(missed):
    return "met" if not missed else "MISSED: " + "; ".join(missed)


def summary_rows(context, missed, plate_missed):
    """The Summary's rows on the plate and the design goals (tile model and as built)."""
    man, built = context["manifest"], context.get("as_built")
    plate = man.get("plate")
    rows = []
    if plate is not None:
        rows.append(["patterned fraction of the clear aperture", _fraction(plate)])
    tile = _verdict(missed)
    if built is not None and built.missed and not missed:
        # the tile model's "met" must not stand for the plate that is made
        tile = "met by the tile repeated without end; MISSED by the plate as built"
    rows += [
        [f"design goals (correlation >= {CORRELATION_GOAL}, rmse <= {RMSE_GOAL})", tile],
        ["design goals as a plate of square pixels (sinc^2 envelope)", _verdict(plate_missed)],
    ]
    if built is not None:
        rows.append(
            ["design goals as built (the pattern over its clear aperture)",
             _verdict(built.missed)]
        )  # fmt: skip
    return rows


def _fraction(plate):
    text = f"{plate['patterned_fraction']:.4%}"
    if plate["clear_aperture_nm"] < plate["design_aperture_nm"]:
        text += (
            f" (frame shrunk: {1 - plate['aperture_light_kept']:.2%} of the design's light lost)"
        )
    return text


def plate_blocks(context):
    """The report's "Plate and clear aperture" section."""
    man, built = context["manifest"], context.get("as_built")
    plate = man.get("plate")
    if plate is None:
        return []
    e = plate["edge_pixels"]
    x0, y0, x1, y1 = plate["pattern_extent_nm"]
    n, p = man["tile_pixels"], man["pixel_pitch_nm"]
    nx, ny = man["tiles"]
    rows = [
        ["whole tiles (one AREF)", f"{nx} x {ny} ({nx * n * p / 1e6:.4f} mm)"],
        [
            "clipped edge tiles (pixels left / right / bottom / top)",
            f"{e['left']} / {e['right']} / {e['bottom']} / {e['top']}"
            + (f" in {len(plate['edge_cells'])} cells" if plate.get("edge_cells") else ""),
        ],
        [
            "tiles across the clear aperture",
            f"{(x1 - x0) / (n * p):.3f} x {(y1 - y0) / (n * p):.3f}",
        ],
        ["pattern extent", f"{(x1 - x0) / 1e6:.4f} x {(y1 - y0) / 1e6:.4f} mm"],
        [
            "clear aperture: drawn frame (layer 200) / design",
            f"{plate['clear_aperture_nm'] / 1e6:.4f} / {plate['design_aperture_nm'] / 1e6:g} mm",
        ],
        ["patterned fraction of the clear aperture", _fraction(plate)],
        ["plain glass inside the frame", f"{1 - plate['patterned_fraction']:.4%}"],
    ]
    out = [
        ("h2", "Plate and clear aperture"),
        (
            "p",
            "The pattern is the tile repeated without end, restricted to the clear "
            "aperture: whole tiles are one AREF, and clipped edge tiles (the tile's pixels "
            "in a window, at whole mask pixels) continue it to the aperture's edge, which "
            "the pattern overlaps by less than one pixel. With whole tiles only, the "
            "clear-aperture frame shrinks to them, or plain glass fills the rest.",
        ),
        ("table", ["quantity", "value"], rows),
    ]
    if built is not None:
        out += _as_built_blocks(context, built)
    out += _die_blocks(man)
    return out


def _as_built_blocks(context, built):
    sim = context["simulated_psf"]
    from doe.fraunhofer import correlation, rmse

    target = context["target_psf"]
    rows = [
        [
            "tile repeated without end",
            correlation_text(correlation(sim, target)),
            f"{rmse(sim, target):.5f}",
            f"{context['efficiency']:.4f}",
            "-",
        ],
        [
            "plate as built",
            correlation_text(built.correlation),
            f"{built.rmse:.5f}",
            f"{built.efficiency:.4f}",
            f"{built.zero_order:.5f}",
        ],
        [
            "plate as built, each order's cell (the clear aperture as the stop)",
            correlation_text(built.cell_correlation),
            f"{built.cell_rmse:.5f}",
            "-",
            "-",
        ],
    ]
    return [
        ("h3", "The plate as built"),
        (
            "p",
            "Order powers of the plate over its clear aperture (the far field in each "
            "order's direction, square pixels, plain glass where unpatterned) against the "
            f"tile model's. Goals as built: {_verdict(built.missed)}. The last row is what "
            "each order's cell of the far field collects when the clear aperture is the "
            "stop: its diffraction spreads every dot into its neighbours' cells (the "
            "camera's part, not judged against the goals).",
        ),
        ("table", ["model", "correlation", "rmse", "window efficiency", "zero order"], rows),
    ]


def _die_blocks(man):
    dies = man.get("dies")
    if dies is None or "substrate_size_nm" not in dies:
        return []
    w, h = (v / 1e6 for v in dies["substrate_size_nm"])
    rows = [
        [
            "dies (plates)",
            f"{dies['nx']} x {dies['ny']} (one AREF of the plate cell {man.get('plate_cell', '')})",
        ],
        ["plate size", f"{dies['plate_size_nm'][0] / 1e6:.4f} mm"],
        [
            "dicing lane",
            f"{dies['lane_nm'] / 1000:g} um (layer {dies['dicing_lane_layer']}, not written)",
        ],
        ["die pitch", f"{dies['pitch_nm'][0] / 1e6:.4f} mm"],
        ["substrate", f"{w:.4f} x {h:.4f} mm"],
    ]
    return [("h3", "Dies on the substrate"), ("table", ["quantity", "value"], rows)]
