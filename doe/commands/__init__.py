"""Command modules of ``doe``: parse flags, call the library, print, set the exit code.

- ``design``: ``doefab presets``, ``doefab config show``
- ``retrieve``: ``doefab retrieve``
"""
