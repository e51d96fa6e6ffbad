"""Hardware verification (``doefab verify``, ``doefab mtf``).

- ``plate_check``: ``verify_plate``, the whole of ``doefab verify`` as a library
- ``mtf_check``: ``measure_mtf``, the whole of ``doefab mtf`` as a library
- ``design_ref``: what verify reads from a design folder (``read_design_dir``)
- ``capture``: reading captures and dark frames (the only module opening images)
- ``conditioning``: dark subtraction, saturation, hot pixels, noise
- ``simulate``: a physical simulator of captures for tests and benchmarks
- ``lattice``: registering the dot lattice
- ``hot_pixels``: repairing hot pixels off the dots once the lattice is known
- ``photometry``: the orders' powers on the lattice
- ``analysis``: measured PSF, comparison with the design, pass/fail
- ``zero_order``: where the zero order sits, the beam's power
- ``etch_fit``, ``overlay``: fits of etch-depth and overlay errors
- ``fault_fits``: those fits as recorded in the report
- ``diagnosis``: the rules that name a fault from the fits
- ``hints``: the notes and hints verify gives the lab
- ``report``: the figures and HTML report
- ``mtf``: slanted-edge MTF
"""
