"""The fabricated plate: one model of its faults, and its tolerance to them.

- ``model``: the plate's phase and far field with etch, overlay and CD-bias faults
- ``tolerance``: the tolerance table and budget of a design
"""
