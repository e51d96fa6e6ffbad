"""Optics of diffractive phase plates (numpy, scipy, nlopt; never torch).

- ``design``: the TOML design schema, presets and derived optics
- ``materials``: Sellmeier refractive indices
- ``fraunhofer``: the forward model of CONVENTIONS.md and its quality figures
- ``retrieval``: Gerchberg-Saxton, nlopt refinement, L-level quantisation
- ``targets``: named target PSFs for tests, benchmarks and demonstrations
- ``figures``: the retrieval figure
- ``bounds``, ``lbfgs``: efficiency bounds of a target, the L-BFGS driver
- ``infra``: the shared infrastructure (files, errors, flags, images, interrupts, dispatcher)
- ``commands``: the command modules (only the dispatcher imports them)
"""
