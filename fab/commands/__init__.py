"""Command modules of ``fab``: parse flags, call the library, print, set the exit code.

- ``fab``: ``doefab fab`` (``fab.package``)
- ``mesh``: ``doefab mesh`` (``fab.mesh``)
- ``verify``: ``doefab verify`` and ``doefab mtf`` (``fab.verify``)
- ``run``: ``doefab run`` (``fab.run``)
"""
