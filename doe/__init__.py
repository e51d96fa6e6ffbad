"""Optics of diffractive phase plates (numpy, scipy, nlopt; never torch).

- ``design``: the TOML design schema, presets and derived optics
- ``materials``: Sellmeier refractive indices
- ``fraunhofer``: the forward model of CONVENTIONS.md and its quality figures
- ``retrieval``: Gerchberg-Saxton, nlopt refinement, L-level quantisation
- ``targets``: named target PSFs for tests, benchmarks and demonstrations
- ``figures``: the retrieval figure
- ``files``: reading/writing the contract files safely (staged, atomic)
- ``errors``: InputError (exit code 2)
- ``cli``, ``cli_design``, ``cli_retrieve``: the ``doefab`` command line
"""
