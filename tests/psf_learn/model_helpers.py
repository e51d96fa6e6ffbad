"""Stand-in models of the evaluation tests (importable: pytest pythonpath)."""

import numpy as np
import torch

from psf_learn.psf import delta_psf
from psf_learn.sensor import SensorModel
from psf_learn.sr import SRModel

# the default sensor's point sample: cell (2, 2) of each 4 x 4 block
POINT = tuple(map(tuple, np.eye(4)[[2]].T @ np.eye(4)[[2]]))


class FixedNet(torch.nn.Module):
    """A "network" that ignores the frame and returns a fixed (H, W) estimate."""

    def __init__(self, estimate):
        super().__init__()
        self.estimate = torch.as_tensor(estimate, dtype=torch.float32)[None, None]

    def forward(self, frame):
        return self.estimate


def fixed_model(estimate, k=11):
    """Return an SRModel (delta PSF, noiseless point sample) whose estimate is ``estimate``."""
    return SRModel(FixedNet(estimate), delta_psf(k), SensorModel(POINT, 0.0), None)
