"""Photomask geometry and GDSII (gdstk writes, KLayout reads back).

- ``rectangles``: bitmap -> disjoint rectangles (row runs merged vertically).
- ``marks``: cross-in-box alignment marks and verniers sized to the feature size, labels,
  plate outline; where the monitors go.
- ``labels``: text as a pixel font without corner contacts, strokes at the feature size.
- ``monitors``: etch-depth pads (one per etch code) and CD line/space gratings.
- ``gds``: the library: one tile cell, one AREF over the aperture, 1 nm DBU, pinned timestamp.
- ``readback``: KLayout rasterisation of the written tile, the self-check of ``doefab fab``.
"""
