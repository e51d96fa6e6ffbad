"""The design-rule markers as a KLayout marker database (``.lyrdb``).

One category per layer and rule (``L1_width``, ...), each marker an item in the
top cell in micrometres, as KLayout's own DRC writes them: open it over the GDS
(``klayout mask.gds -m drc.lyrdb``, or Tools > Marker Browser) to step through them.
A category lists at most :data:`MAX_ITEMS` markers (a plate of random pixels has
hundreds of thousands, some 300 bytes each), and of a large tile array only those of
its 3 x 3 tiles at the origin (:mod:`layouts.drc_periodic`); its description then
gives the plate's count. The deck run in KLayout lists them all.
"""

from itertools import islice

MAX_ITEMS = 2_000  # markers listed per category (the plate's count is in the description)


def category_name(layer, rule):
    """The category of one layer and rule, shared by the deck and the database."""
    return f"L{int(layer)}_{rule}"


def category_text(layer, rule, limit):
    """The category's description."""
    return f"layer {int(layer)}/0 {rule}: {limit}"


def write_lyrdb(path, result, gds_name, design_name=""):
    """Write ``result``'s markers to ``path``.

    Parameters
    ----------
    path : path
    result : layouts.drc.DrcResult
    gds_name : str
        The layout the markers belong to (recorded as the database's original file).
    design_name : str
    """
    import klayout.db as kdb
    import klayout.rdb as rdb

    db = rdb.ReportDatabase(f"doefab DRC {design_name}".strip())
    db.description = f"doefab design-rule check of {gds_name}"
    db.generator = "doefab fab"
    db.original_file = str(gds_name)
    db.top_cell_name = result.top_cell
    cell = db.create_cell(result.top_cell)
    to_um = kdb.CplxTrans(0.001)
    limits = result.rules.limits()
    plate = {(c.layer, c.rule): c.count for c in result.counts}
    for (layer, rule), markers in result.markers.items():
        cat = db.create_category(category_name(layer, rule))
        cat.description = category_text(layer, rule, limits[rule])
        listed = min(sum(part.count() for part in markers), MAX_ITEMS)
        if listed < plate[(layer, rule)]:
            cat.description += f" ({plate[(layer, rule)]} markers on the plate, {listed} listed)"
        left = MAX_ITEMS
        for part in markers:
            if left <= 0:
                break
            items = part if part.count() <= left else list(islice(part.each(), left))
            db.create_items(cell.rdb_id(), cat.rdb_id(), to_um, items)
            left -= part.count()
    db.save(str(path))


def read_lyrdb_counts(path):
    """Return {category name: item count} of a marker database (KLayout's or ours)."""
    import klayout.rdb as rdb

    db = rdb.ReportDatabase("")
    db.load(str(path))
    return {cat.name(): cat.num_items() for cat in db.each_category()}
