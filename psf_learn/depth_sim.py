"""Simulated gated-SPAD cubes that follow the timing convention of ``psf_learn.depth``.

Sample k of a pixel is taken at scan time ``k * shift``; its expected count is
``A h(k * shift - mu) + b`` with h the response of a ``GateModel`` (peak 1), and
the recorded count is Poisson distributed around it.
"""

import numpy as np

from psf_learn.depth import expected_counts, scan_times
from psf_learn.depth_response import GateModel, gate_response


def simulate_cube(amplitude, timing, background, n_samples, shift, response=None, rng=None):
    """Return a gated cube (H, W, T) of expected or Poisson counts.

    Parameters
    ----------
    amplitude, timing, background : (H, W) arrays (or broadcastable)
        Peak signal counts A, arrival time mu (s) and background counts b.
    n_samples : int
        Number of gate positions T.
    shift : float
        Scan step (s).
    response : Response or None
        Temporal response (default: ``gate_response(GateModel())``).
    rng : numpy.random.Generator or None
        Source of Poisson noise; None returns the noiseless expected counts.

    Returns
    -------
    (H, W, T) float64 array (noiseless) or int64 array (Poisson counts)
    """
    response = response if response is not None else gate_response(GateModel())
    m = expected_counts(response, scan_times(n_samples, shift), amplitude, timing, background)
    if rng is None:
        return m
    return rng.poisson(m)


def random_scene(
    shape, amplitude, background, shift, n_samples, response=None, rng=None, margin=None
):
    """Return (amplitude, timing, background) maps of a random scene.

    Arrival times are uniform over the scan, kept ``margin`` (default: the
    response's full support) away from both ends so every profile is complete.
    Amplitude and background are constant maps of the given values.
    """
    response = response if response is not None else gate_response(GateModel())
    rng = rng if rng is not None else np.random.default_rng(0)
    first, last = response.support
    t_end = (n_samples - 1) * shift
    lo, hi = -first, t_end - last
    if margin is not None:
        lo, hi = margin, t_end - margin
    if not hi > lo:
        raise ValueError("the scan is too short for a complete profile")
    timing = rng.uniform(lo, hi, size=shape)
    return np.full(shape, float(amplitude)), timing, np.full(shape, float(background))
