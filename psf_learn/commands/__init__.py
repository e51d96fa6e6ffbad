"""Command modules of ``psf_learn``: parse flags, call the library, print, set the exit code.

- ``learn``: ``doefab learn``, ``doefab evaluate``, ``doefab sr``
- ``depth``: ``doefab depth``, ``doefab transient``
"""
