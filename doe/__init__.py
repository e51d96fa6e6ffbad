"""Optics of diffractive phase plates (numpy, scipy, nlopt; never torch).

- ``design``: the TOML design schema, presets, loading and validation
- ``derived``: the optics that follow from a design, and its JSON summary
- ``design_match``: whether a record (a tile, a PSF) was made for a design
- ``materials``: Sellmeier refractive indices
- ``fraunhofer``: the forward model of CONVENTIONS.md and its quality figures
- ``goals``: the quality goals and the fidelity figures measured against them
- ``retrieval``: phase retrieval, from a target PSF to an L-level tile, in stages:
  ``gerchberg_saxton`` (GS, MRAF), ``refinement`` (nlopt L-BFGS),
  ``quantisation`` (the discrete finish), ``rule_finish`` (no corner contacts)
- ``mask_rules``: corner contacts of a level map's binary masks, counted and checked
- ``retrieve``: the retrieve stage as a library (a PSF file in, a folder out)
- ``targets``: named target PSFs for tests, benchmarks and demonstrations
- ``figures``: the retrieval figure
- ``bounds``, ``lbfgs``: efficiency bounds of a target, the L-BFGS driver
- ``records``: the stage files, one module each (typed record, reader, writer)
- ``infra``: the shared infrastructure (files, errors, flags, images, interrupts, dispatcher)
- ``commands``: the command modules (only the dispatcher imports them)
"""
