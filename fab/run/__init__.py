"""The pipeline (``doefab run``).

- ``pipeline``: stages with content-hash skipping and resume
- ``summary``: the run folder's ``index.html`` and ``manifest.json``
"""
