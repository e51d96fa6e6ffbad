"""Compact 4x super-resolution networks that train in minutes on a CPU.

Sun et al. 2020 use D-DBPN (10 M parameters, 40 GPU-hours). Two scaled-down
designs are offered, both predicting a residual over a bicubic upsampling of
the SPAD frame:

- ``resnet`` (default): residual blocks at the SPAD resolution, then a
  sub-pixel (pixel-shuffle) convolution to the f x finer grid. Every
  convolution runs on the coarse grid, so a step costs ~18 F^2 multiply-adds
  per SPAD pixel and block.
- ``dbpn``: iterative up/down back-projection units (the paper's design) with
  fewer stages and filters; each stage runs transposed convolutions on the fine
  grid (~380 F^2 multiply-adds per SPAD pixel and stage), about 20x the cost.

At equal CPU time the ``resnet`` variant reaches the better PSNR (see
``docs/learn.md``), hence the default.
"""

import torch
import torch.nn.functional as F
from torch import nn

ARCHS = ("resnet", "dbpn")
# The largest networks learn trains (its --features and --stages); larger ones exhaust
# a workstation's memory, and a model.pt asking for more is refused before it is built.
FEATURES_MAX = 512
STAGES_MAX = 64


def check_arch(arch, factor):
    """Raise ValueError unless network ``arch`` can super-resolve by ``factor``.

    A DBPN projection (kernel 2 f, stride f, padding f // 2) maps h to f h + 1 at an odd
    f: its output would then miss the bicubic base by a row (a RuntimeError in training).
    """
    if arch not in ARCHS:
        raise ValueError(f"arch must be 'resnet' or 'dbpn', got {arch!r}")
    if arch == "dbpn" and factor % 2:
        raise ValueError(f"dbpn needs an even super-resolution factor, not {factor}")


class ResBlock(nn.Module):
    """conv-ReLU-conv with an identity skip (EDSR style, no batch norm)."""

    def __init__(self, features):
        super().__init__()
        self.conv1 = nn.Conv2d(features, features, 3, padding=1)
        self.conv2 = nn.Conv2d(features, features, 3, padding=1)

    def forward(self, x):
        return x + self.conv2(F.relu(self.conv1(x)))


class _Projection(nn.Module):
    """A DBPN up- (or down-) projection unit: project, back-project, correct the error."""

    def __init__(self, features, factor, up):
        super().__init__()
        k, s, p = 2 * factor, factor, factor // 2
        there = nn.ConvTranspose2d if up else nn.Conv2d
        back = nn.Conv2d if up else nn.ConvTranspose2d
        self.a = nn.Sequential(there(features, features, k, s, p), nn.PReLU(features))
        self.b = nn.Sequential(back(features, features, k, s, p), nn.PReLU(features))
        self.c = nn.Sequential(there(features, features, k, s, p), nn.PReLU(features))

    def forward(self, x):
        h0 = self.a(x)
        return h0 + self.c(self.b(h0) - x)


class SRNet(nn.Module):
    """Map a (B, 1, h, w) SPAD frame (scene units) to a (B, 1, f h, f w) image.

    Parameters
    ----------
    factor : int
        Super-resolution factor f (4).
    features : int
        Feature channels F.
    stages : int
        Residual blocks (``resnet``) or up/down projection pairs (``dbpn``).
    arch : {"resnet", "dbpn"}
    """

    def __init__(self, factor=4, features=24, stages=4, arch="resnet"):
        super().__init__()
        check_arch(arch, factor)
        self.factor, self.arch = factor, arch
        self.head = nn.Conv2d(1, features, 3, padding=1)
        if arch == "resnet":
            self.body = nn.Sequential(*(ResBlock(features) for _ in range(stages)))
            self.tail = nn.Sequential(
                nn.Conv2d(features, factor**2, 3, padding=1), nn.PixelShuffle(factor)
            )
        else:  # dbpn
            self.ups = nn.ModuleList(_Projection(features, factor, True) for _ in range(stages))
            self.downs = nn.ModuleList(
                _Projection(features, factor, False) for _ in range(stages - 1)
            )
            self.tail = nn.Conv2d(features * stages, 1, 3, padding=1)
        # start as plain bicubic upsampling: the residual branch learns from zero
        last = self.tail[0] if arch == "resnet" else self.tail
        nn.init.zeros_(last.weight)
        nn.init.zeros_(last.bias)

    def forward(self, lr):
        base = F.interpolate(lr, scale_factor=self.factor, mode="bicubic", align_corners=False)
        x = self.head(lr)
        if self.arch == "resnet":
            return base + self.tail(x + self.body(x))
        highs = []
        for i, up in enumerate(self.ups):
            highs.append(up(x))
            if i < len(self.downs):
                x = self.downs[i](highs[-1])
        return base + self.tail(torch.cat(highs, dim=1))


def count_parameters(model):
    """Return the number of trainable parameters."""
    return sum(p.numel() for p in model.parameters() if p.requires_grad)
