"""The fabrication package (``doefab fab``): masks, layer images, manifest, report.

- ``masks``: L levels -> log2(L) binary masks with Sellmeier etch depths, deepest first
- ``layer_images``: per-mask tile TIFF and plate preview PNG (OpenImageIO)
- ``manifest``: ``fab_manifest.json`` (CONVENTIONS.md)
- ``report``, ``figures``: the process engineer's report (Markdown, HTML, figures)
"""
