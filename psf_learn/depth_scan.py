"""The scan direction of a gated-SPAD cube, told from its own profiles.

A cube scanned with the gate delayed from sample to sample follows the gate
direction's response (``h = G`` correlated with ``Pi``); one in the
time-reversed convention (the paper's Eq. 9, ``I = G * Pi``) follows the laser
direction's. Fitted with the other direction's response, every timing comes
out about 300 ps off, with fits that look plausible. :func:`choose_scan` fits
the cube both ways and keeps the direction whose reported models have the
higher total Poisson likelihood. numpy only: this module must not import torch.
"""

from dataclasses import dataclass, field

import numpy as np

from psf_learn.depth import SCANS, fit_profiles
from psf_learn.depth_response import gate_response

__all__ = ["MIN_LOG_LIKELIHOOD_DIFFERENCE", "ScanChoice", "choose_scan", "scan_responses"]

# A direction is told apart when its total log-likelihood exceeds the other's by
# at least this: a likelihood ratio of e^10 (about 22 000). The two fits have the
# same number of parameters, so no penalty applies; a symmetric response gives a
# difference of 0 and is never told apart.
MIN_LOG_LIKELIHOOD_DIFFERENCE = 10.0


@dataclass(frozen=True, eq=False)
class ScanChoice:
    """The direction chosen for a cube and the fits it was chosen from.

    Attributes
    ----------
    scan : str
        The direction kept ("gate" or "laser"): the likelier one, or "gate" where
        neither finds a return (nothing then depends on the direction).
    fit : ProfileFit
        The fit in that direction.
    log_likelihood : dict
        Direction -> total Poisson log-likelihood of its reported models, less that
        of the saturated model.
    difference : float
        The kept direction's total log-likelihood less the other's (>= 0).
    returns : int
        Pixels with a return in either direction.
    min_difference : float
        The difference needed to tell the two directions apart.
    fits : dict
        Direction -> ProfileFit, both fits.
    """

    scan: str
    fit: object
    log_likelihood: dict
    difference: float
    returns: int
    min_difference: float
    fits: dict = field(repr=False)

    @property
    def ambiguous(self):
        """True when there are returns but the two directions are not told apart."""
        return self.returns > 0 and not self.difference >= self.min_difference

    def summary(self):
        """Return the choice as a JSON-ready dict (direction, log-likelihoods, difference)."""
        return {
            "direction": self.scan,
            "chosen_by": "auto",
            "log_likelihood": {k: float(v) for k, v in self.log_likelihood.items()},
            "log_likelihood_difference": float(self.difference),
            "min_log_likelihood_difference": float(self.min_difference),
            "returns_either_direction": int(self.returns),
        }


def scan_responses(model=None, step=1e-12):
    """Return {direction: Response} of a gate model in both scan directions."""
    return {scan: gate_response(model, step, scan=scan) for scan in SCANS}


def choose_scan(
    cube, shift, responses, min_difference=MIN_LOG_LIKELIHOOD_DIFFERENCE, **fit_options
):
    """Fit ``cube`` in every direction of ``responses`` and keep the likelier one.

    Parameters
    ----------
    cube : (..., T) array
        Non-negative counts; sample k at scan time ``k * shift``.
    shift : float
        Scan step (s).
    responses : dict
        Direction -> Response, e.g. :func:`scan_responses`.
    min_difference : float
        Log-likelihood difference needed to tell the directions apart; below it
        (with returns in the cube) the choice is :attr:`ScanChoice.ambiguous`.
    **fit_options
        Passed to :func:`psf_learn.depth.fit_profiles` (``threshold``, ...).

    Returns
    -------
    ScanChoice
    """
    fits = {scan: fit_profiles(cube, shift, r, **fit_options) for scan, r in responses.items()}
    total = {scan: float(np.sum(f.log_likelihood)) for scan, f in fits.items()}
    returns = int(np.sum(np.logical_or.reduce([f.valid for f in fits.values()])))
    order = sorted(total, key=lambda scan: -total[scan])
    best = order[0] if returns else next(iter(fits))
    difference = total[order[0]] - total[order[1]] if returns and len(order) > 1 else 0.0
    return ScanChoice(
        scan=best,
        fit=fits[best],
        log_likelihood=total,
        difference=difference,
        returns=returns,
        min_difference=min_difference,
        fits=fits,
    )
