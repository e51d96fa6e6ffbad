"""Optics of diffractive phase plates (numpy, scipy, nlopt; never torch).

- ``design``: the TOML design schema, presets and derived optics
- ``materials``: Sellmeier refractive indices
- ``fraunhofer``: the forward model of CONVENTIONS.md and its quality figures
- ``files``: reading/writing the contract files safely
- ``errors``: InputError (exit code 2)
- ``cli``: the ``doefab`` command line
"""
