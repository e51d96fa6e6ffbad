"""Fabrication: one room per concern.

- ``package``: masks, layer images, manifest, report (``doefab fab``)
- ``plate``: the plate model with its faults, the tolerance analysis
- ``verify``: captures, lattice, fits, diagnosis, report, MTF (``doefab verify``, ``mtf``)
- ``mesh``: relief meshes, file formats, STEP (``doefab mesh``)
- ``run``: the pipeline and its summary (``doefab run``)
- ``templates``: the HTML pages (jinja2) and their one stylesheet
- ``commands``: the command modules (only the dispatcher imports them)
"""
