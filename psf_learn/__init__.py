"""Learning, super-resolution and depth for SPAD cameras (the only package importing torch).

PSF co-design (``doefab learn``, ``evaluate``, ``sr``)
- ``sensor``: PSF convolution, SPAD active-area sampling, Poisson noise (straight-through)
- ``psf``: learnable K x K PSF (softmax) and the fixed baselines
- ``network``: compact 4x super-resolution networks
- ``images``: training and evaluation images (embedded default set included)
- ``train``, ``evaluate``, ``sr``, ``store``: training with checkpoints, metrics, inference, files
- ``cli``: the commands

Depth and transients (``doefab depth``, ``transient``; numpy only)
- ``depth``: gate response model and the vectorised per-pixel fit
- ``depth_sim``: simulated gate-scanned cubes
- ``cubes``: reading cubes and frames
- ``depth_plots``, ``cli_depth``: figures and commands
"""
