"""Fabrication: process, masks, meshes, reports, verification, and the pipeline.

Masks and the fabrication package (``doefab fab``)
- ``masks``: L levels -> log2(L) binary masks with Sellmeier etch depths, deepest first
- ``layer_images``: per-mask tile TIFF and plate preview PNG (OpenImageIO)
- ``tolerance``: model of the fabricated plate (etch, overlay, CD bias), table, budget
- ``manifest``: ``fab_manifest.json`` (CONVENTIONS.md)
- ``report``, ``figures``: the process engineer's report (Markdown, HTML, figures)
- ``cli_fab``: the command

3-D models (``doefab mesh``)
- ``mesh``: watertight height-field tile mesh, instancing, volume
- ``mesh_io``: PLY, GLB, 3MF, STL encoders (instanced aperture scenes)
- ``step``: the tile as one closed STEP solid, the aperture as an assembly
- ``cli_mesh``: the command

Hardware verification (``doefab verify``, ``doefab mtf``)
- ``capture``: reading captures and dark frames (the only module opening images)
- ``lattice``: registering the dot lattice, order photometry
- ``verify``: measured PSF, comparison with the design, diagnosis, pass/fail
- ``plate``: the fabricated plate's phase and far field, faults included (one model
  for the simulator and for verify's fits)
- ``capture_sim``: a physical simulator of captures for tests and benchmarks
- ``mtf``: slanted-edge MTF
- ``verify_figures``, ``cli_verify``: report and commands

The pipeline (``doefab run``)
- ``pipeline``: stages with content-hash skipping and resume
- ``run_report``: ``index.html`` and ``manifest.json``
- ``cli_run``: the command
"""
