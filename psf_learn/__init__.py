"""Learning, super-resolution and depth for SPAD cameras (the only package importing torch).

PSF co-design (``doefab learn``, ``evaluate``, ``sr``)
- ``sensor``: PSF convolution, SPAD active-area sampling, Poisson noise (straight-through)
- ``psf``: learnable K x K PSF (softmax) and the fixed baselines
- ``network``: compact 4x super-resolution networks
- ``images``: training and evaluation images (embedded default set included)
- ``train``, ``evaluate``, ``sr``, ``store``: training with checkpoints, metrics, inference, files
- ``linear_optimum``: the Wiener reconstruction's error for any PSF, and the best PSF for it
- ``scores``: PSNR / SSIM in both conventions (full-range grey, the SR papers' MATLAB Y)
- ``heldout``: the no-plate model trained alongside, both scored on held-back images
- ``learn_plan``, ``learn``: a training's settings checked, then run and written (``learn()``)
- ``commands.learn``: the commands' flags and printing

Depth and transients (``doefab depth``, ``transient``; numpy only)
- ``depth_response``: the gate response model, or a measured IRF
- ``depth``: the vectorised per-pixel fit
- ``depth_sim``: simulated gate-scanned cubes
- ``cubes``: reading cubes and frames (and super-resolving them, with torch)
- ``depth_plots``, ``commands.depth``: figures and commands
"""
