"""The fabricated plate: one model of its faults, and its tolerance to them.

- ``model``: the fault type (``PlateFaults``) and the plate's far field with its faults
- ``cells``: a mask pixel cut at the faulty plate's mask edges
- ``basis``: the model's window with its parts precomputed, for fits
- ``tolerance``: the tolerance table and budget of a design
"""
