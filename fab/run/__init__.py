"""The pipeline (``doefab run``).

- ``stages``: ``run_pipeline``, the run stage: checks, plan, stages, summaries
- ``pipeline``: stages with content-hash skipping and resume
- ``summary``: the run folder's ``index.html`` and ``manifest.json``
"""
