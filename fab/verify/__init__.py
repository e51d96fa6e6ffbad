"""Hardware verification (``doefab verify``, ``doefab mtf``).

- ``capture``: reading captures and dark frames (the only module opening images)
- ``simulate``: a physical simulator of captures for tests and benchmarks
- ``lattice``: registering the dot lattice, order photometry
- ``analysis``: measured PSF, comparison with the design, pass/fail
- ``etch_fit``, ``overlay``: fits of etch-depth and overlay errors
- ``diagnosis``: the rules that name a fault from the fits
- ``report``: the figures and HTML report
- ``mtf``: slanted-edge MTF
"""
