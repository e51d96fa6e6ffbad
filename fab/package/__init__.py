"""The fabrication package (``doefab fab``): masks, layer images, manifest, report.

- ``build``: :func:`build_package`, the whole package of a design folder's tile
- ``masks``: L levels -> log2(L) binary masks with Sellmeier etch depths, deepest first
- ``layer_images``: per-mask tile TIFF and plate preview PNG (OpenImageIO)
- ``manifest``: the package's file records and the layout's manifest keys
  (``fab_manifest.json`` itself is ``doe.records.fab_manifest``)
- ``order``: the photomask order sheet (``mask_order.md``, ``mask_order.json``)
- ``report``, ``report_marks``, ``figures``: the process engineer's report (Markdown,
  HTML, figures)
"""
