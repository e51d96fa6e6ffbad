"""How ``doefab fab`` lays out the plate: fill the clear aperture, or fewer whole tiles; dies.

By default the pattern covers the whole clear aperture (whole tiles and clipped
edge tiles, :mod:`layouts.plate_plan`). ``--whole-tiles`` or ``--tiles N`` place whole
tiles only and shrink the clear-aperture frame to them (the light outside is lost to
the design); with ``--keep-aperture`` the frame stays and plain glass fills the rest,
which adds to the zero order. The warnings say what either costs, and what the plate
as built (:mod:`doe.aperture`) misses of the design goals.
"""

from dataclasses import dataclass

from doe.infra.errors import InputError
from layouts.plate_plan import DEFAULT_LANE_NM


@dataclass(frozen=True)
class PlateChoice:
    """The plate ``doefab fab`` draws.

    Attributes
    ----------
    plate : layouts.plate_plan.PlatePattern
        Whole tiles, edge pixels and the clear-aperture frame.
    mode : str
        "fill", "shrink" or "glass" (:func:`layouts.plate_plan.plan_pattern`).
    dies : (int, int)
        Plates along x and y on the substrate.
    lane_nm : int
        Dicing lane width.
    """

    plate: object
    mode: str
    dies: tuple[int, int]
    lane_nm: int


def choose_plate(design, der, tiles=None, whole_tiles=False, keep_aperture=False,
                 dies=(1, 1), lane_um=None):  # fmt: skip
    """Return the :class:`PlateChoice` of the flags; InputError (naming the flag) if unusable."""
    from doe.aperture import design_plate

    if tiles is not None and (isinstance(tiles, bool) or int(tiles) != tiles or tiles < 1):
        raise InputError("--tiles", f"must be a whole number >= 1, got {tiles!r}")
    if tiles is not None and tiles > der.tiles:
        raise InputError(
            "--tiles",
            f"{tiles} tiles of {der.tile_size * 1e3:.4g} mm do not fit the "
            f"{design.fabrication.aperture * 1e3:g} mm clear aperture (at most {der.tiles})",
        )
    if keep_aperture and tiles is None and not whole_tiles:
        raise InputError("--keep-aperture", "goes with --whole-tiles or --tiles N")
    mode = "fill" if tiles is None and not whole_tiles else "glass" if keep_aperture else "shrink"
    nx, ny = _dies(dies)
    lane = DEFAULT_LANE_NM if lane_um is None else round(float(lane_um) * 1000)
    if not lane >= 0:
        raise InputError("--lane-um", f"must be >= 0, got {lane_um!r}")
    plate = design_plate(design, der.tile_pixels, tiles=tiles, mode=mode)
    return PlateChoice(plate, mode, (nx, ny), lane)


def _dies(dies):
    try:
        nx, ny = (int(d) for d in dies)
    except (TypeError, ValueError):
        raise InputError("--dies", f"must be two whole numbers NX NY, got {dies!r}") from None
    if nx < 1 or ny < 1 or (nx, ny) != tuple(dies):
        raise InputError("--dies", f"must be two whole numbers >= 1, got {dies!r}")
    return nx, ny


def plate_warnings(choice, figures, tile_missed):
    """Say what the plate's layout costs and whether the plate as built misses the goals.

    ``figures`` is the :class:`doe.aperture.AsBuilt` of the plate, ``tile_missed``
    the goals the tile model misses (then the plate's own are not repeated).
    """
    plate, out = choice.plate, []
    if choice.mode == "shrink":
        out.append(
            f"warning: whole tiles only: the clear aperture shrinks from "
            f"{plate.design_aperture_nm / 1e6:g} mm to {plate.aperture_nm / 1e6:.4g} mm, and "
            f"{1 - plate.aperture_light_kept():.1%} of the light through the design's "
            "aperture is lost to the design (stop the lens down to the frame)"
        )
    elif choice.mode == "glass":
        out.append(
            f"warning: whole tiles only inside the design's frame: "
            f"{1 - plate.patterned_fraction():.1%} of the clear aperture is plain glass, "
            f"which puts {figures.zero_order:.2%} of the light into the zero order"
        )
    if figures.missed and not tile_missed:
        out.append(
            "warning: the tile meets the design goals, but the plate as built misses them "
            f"({'; '.join(figures.missed)}); see the report's Plate section"
        )
    return out
