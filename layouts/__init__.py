"""Photomask geometry and GDSII (gdstk writes, KLayout reads back).

- ``rectangles``: bitmap -> disjoint rectangles (row runs merged vertically).
- ``marks``: cross-in-box alignment marks, 10 / 9.8 um verniers, labels, plate outline.
- ``gds``: the library: one tile cell, one AREF over the aperture, 1 nm DBU, pinned timestamp.
- ``readback``: KLayout rasterisation of the written tile, the self-check of ``doefab fab``.
"""
