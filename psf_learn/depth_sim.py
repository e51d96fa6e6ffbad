"""Simulated gated-SPAD cubes that follow the timing convention of ``psf_learn.depth``.

Sample k of a pixel is taken at scan time ``k * shift``; its expected count is
``A h(k * shift - mu) + b`` with h the response of a ``GateModel`` (peak 1), and
the recorded count is Poisson distributed around it.
"""

import dataclasses

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


def random_gate_skew(shape, sigma, rng=None, offset=0.0):
    """Return a (H, W) map of per-pixel gate delays (s): Gaussian, std ``sigma``, mean ``offset``.

    A gated SPAD array's gates do not open together: published arrays show gate
    skews of 140 - 410 ps FWHM (sigma 60 - 175 ps).
    """
    rng = rng if rng is not None else np.random.default_rng(0)
    return offset + sigma * rng.standard_normal(shape)


def simulate_skewed_cube(
    amplitude,
    timing,
    background,
    gate_delay,
    n_samples,
    shift,
    response=None,
    rng=None,
    gate_width=None,
    model=None,
):
    """Return a gated cube of an array whose pixel p opens gate k at ``k * shift + gate_delay[p]``.

    A gate opened ``d`` late sees the light as if it had come ``d`` early, so the
    expected count is ``A h(t_k + d - mu) + b``: the cube of :func:`simulate_cube`
    with every arrival time moved by ``-d``.

    Parameters
    ----------
    gate_delay : (H, W) array (or broadcastable)
        Each pixel's gate delay (s), e.g. from :func:`random_gate_skew`.
    gate_width : (H, W) array or None
        Each pixel's gate width (s); pixels of one width share the response of
        ``model`` with that width (round the widths to bin them). None: every pixel
        has ``response``.
    model : GateModel or None
        The gate model whose width ``gate_width`` replaces (default ``GateModel()``).

    Other parameters and the return value are those of :func:`simulate_cube`.
    """
    amplitude, timing, background, gate_delay = np.broadcast_arrays(
        *(np.asarray(v, dtype=np.float64) for v in (amplitude, timing, background, gate_delay))
    )
    if gate_width is None:
        return simulate_cube(amplitude, timing - gate_delay, background, n_samples, shift,
                             response, rng)  # fmt: skip
    gate_width = np.broadcast_to(np.asarray(gate_width, dtype=np.float64), timing.shape)
    model = model or GateModel()
    m = np.zeros((*timing.shape, n_samples))
    for width in np.unique(gate_width):
        sel = gate_width == width
        r = gate_response(dataclasses.replace(model, width=float(width)))
        m[sel] = simulate_cube(amplitude[sel], timing[sel] - gate_delay[sel], background[sel],
                               n_samples, shift, r)  # fmt: skip
    return m if rng is None else rng.poisson(m)
