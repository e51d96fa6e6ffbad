"""Three levers that ``doefab learn`` does not offer, measured beside the same fixed PSFs.

- ``--base wiener``: the network refines a Wiener (linear MMSE) upsampling of the
  frame built from the current PSF, instead of a bicubic one, and sees it beside
  the frame, so it need not learn to undo a PSF (docs/learn.md, "Levers"). The
  Wiener filter is the closed form of :mod:`psf_learn.linear_optimum` on the
  frame's grid (mirrored by 4 SPAD pixels, so that the FFT's wrap-around falls
  outside), for a scene spectrum A (|nu|^2 + nu0^2)^(-a/2) fitted to the
  Sun-Hays 80 images and the frame's own shot noise.
- ``--alternate N``: the PSF steps on one network step in N (its gradient dropped on
  the others, as ``--psf-until`` drops it), an alternating schedule.
- ``--area``: the SPAD's 30 um disc integrated over the four 37.5 um sub-pixels it
  straddles (a quarter each), instead of the point sample of ``doefab learn``.

Each row trains ``psf_learn.train.train`` in this process (one thread) on the
Sun-Hays 80 images and prints Set5 / Set14 PSNR-Y:

    python bench/learn_variants.py --base wiener --psf box gaussian:1.5 learned \
        learned@gaussian:1.5   # learned from sigma 1.5
    python bench/learn_variants.py --area --psf gaussian:1 gaussian:1.5 learned
    python bench/learn_variants.py --base bicubic --alternate 2 --psf learned
    python bench/learn_variants.py --steps 20 --psf box   # proves the script
"""

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from psf_learn import images as imgio
from psf_learn import train as training
from psf_learn.evaluate import evaluate
from psf_learn.linear_optimum import transfer
from psf_learn.network import ResBlock
from psf_learn.psf import baseline_psf, gaussian_psf, starting_psf
from psf_learn.sensor import SensorModel, sensor_from_design, simulate_capture
from psf_learn.sr import SRModel

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
# log A, nu0 (cycles per sub-pixel), a: least squares on the log spectrum of the 80 images
SPECTRUM = (-11.6110595, 0.15679232, 5.21691147)
PAD = 4  # SPAD pixels mirrored around a frame before the FFT


def scene_spectrum(h, w):
    """Return the (h, w) model power spectrum of a scene per sub-pixel."""
    log_a, nu0, a = SPECTRUM
    fy = torch.fft.fftfreq(h, dtype=torch.float64)[:, None]
    fx = torch.fft.fftfreq(w, dtype=torch.float64)[None, :]
    return math.exp(log_a) * (fy**2 + fx**2 + nu0**2) ** (-a / 2)


def wiener_upsample(frames, psf, weights, photons):
    """Return the (B, 1, f h, f w) Wiener estimate of the scenes of (B, 1, h, w) frames."""
    f = len(weights)
    b, _, h, w = frames.shape
    pad = min(PAD, h - 1, w - 1)
    x = F.pad(frames, (pad,) * 4, mode="reflect").double()
    hl, wl = h + 2 * pad, w + 2 * pad
    mean = x.mean(dim=(-2, -1), keepdim=True)
    zero_filled = torch.zeros(b, 1, f * hl, f * wl, dtype=torch.float64)
    zero_filled[..., ::f, ::f] = x - mean  # pixel m read at f m: the transfer holds the offset
    t = transfer(psf, weights, (f * hl, f * wl))
    p = scene_spectrum(f * hl, f * wl)
    seen = (p * t.abs() ** 2).reshape(f, hl, f, wl).sum(dim=(0, 2)).repeat(f, f)
    noise = mean.clamp_min(1e-3) / photons if photons > 0 else torch.full_like(mean, 1e-6)
    gain = f**2 * p * t.conj() / (seen + f**2 * noise)
    estimate = torch.fft.ifft2(gain * torch.fft.fft2(zero_filled)).real + mean
    return estimate[..., f * pad : f * (pad + h), f * pad : f * (pad + w)].to(frames.dtype)


class WienerNet(nn.Module):
    """The default resnet, refining a Wiener base it also sees (pixel-unshuffled)."""

    def __init__(self, factor, features, stages, weights, photons):
        super().__init__()
        self.factor, self.weights, self.photons = factor, np.asarray(weights), photons
        self.head = nn.Conv2d(1 + factor**2, features, 3, padding=1)
        self.body = nn.Sequential(*(ResBlock(features) for _ in range(stages)))
        self.tail = nn.Sequential(
            nn.Conv2d(features, factor**2, 3, padding=1), nn.PixelShuffle(factor)
        )
        nn.init.zeros_(self.tail[0].weight)  # starts as the Wiener filter alone
        nn.init.zeros_(self.tail[0].bias)

    def forward(self, frames, psf):
        base = wiener_upsample(frames, psf, self.weights, self.photons)
        x = self.head(torch.cat([frames, F.pixel_unshuffle(base, self.factor)], 1))
        return base + self.tail(x + self.body(x))


def use_wiener_base():
    """Make psf_learn.train's camera build a WienerNet and hand it the current PSF."""
    plain_init = training.CodedCamera.__init__

    def init(self, psf_init, sensor, config):
        plain_init(self, psf_init, sensor, config)
        weights = sensor.weights
        self.net = WienerNet(sensor.factor, config.features, config.stages, weights, sensor.photons)

    def forward(self, scenes, seeds):
        psf = self.psf()
        frames = simulate_capture(scenes, psf, self.sensor, padding="valid", seeds=seeds)
        return self.net(frames, psf)

    training.CodedCamera.__init__, training.CodedCamera.forward = init, forward


def alternate_psf_steps(every):
    """Make psf_learn.train step the PSF on one step in ``every`` (the network on all)."""
    plain_step = training._step

    def step(camera, model, opt, batch, index, device, fine_tuning, psf_learns=True):
        learns = psf_learns and index % every == every - 1
        return plain_step(camera, model, opt, batch, index, device, fine_tuning, learns)

    training._step = step


class _ToldThePSF(nn.Module):
    """A WienerNet called as evaluate calls a network, net(frame), with its PSF bound."""

    def __init__(self, net, psf):
        super().__init__()
        self.net, self.psf = net, torch.from_numpy(psf)

    def forward(self, frames):
        return self.net(frames, self.psf)


def score(camera, folder, wiener):
    """Return ``psf_learn.evaluate.evaluate``'s mean scores of a trained camera on a folder."""
    names, images = imgio.read_folder(folder)
    psf = camera.psf.numpy()
    net = _ToldThePSF(camera.net, psf) if wiener else camera.net
    return evaluate(SRModel(net, psf, camera.sensor, None), names, images)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--psf", nargs="+", default=["box", "gaussian:1.5", "learned"])
    p.add_argument("--base", choices=("bicubic", "wiener"), default="wiener")
    p.add_argument("--area", action="store_true", help="integrate the disc over 4 sub-pixels")
    p.add_argument("--alternate", type=int, default=1, help="the PSF steps on 1 step in N")
    p.add_argument("--steps", type=int, default=6000)
    p.add_argument("--data", default=str(DATA), help="folder holding set5/, set14/, sun_hays80/")
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    from doe.design import load_design

    sensor = sensor_from_design(load_design())
    if args.area:  # the centred disc's centre is the corner of cells (1, 1) .. (2, 2)
        w = np.zeros((4, 4))
        w[1:3, 1:3] = 0.25
        sensor = SensorModel(tuple(map(tuple, w)), sensor.photons)
    wiener = args.base == "wiener"
    if wiener:
        use_wiener_base()
    if args.alternate > 1:
        alternate_psf_steps(args.alternate)
    data = Path(args.data)
    _, images = imgio.read_folder(data / "sun_hays80")
    scenes = training.augment_scales(images, 64 + 10)
    sampling = "area" if args.area else "point"
    every = f"PSF on 1 step in {args.alternate}"
    print(f"base {args.base}, {sampling} sampling, {every}, {args.steps} steps")
    for spec in args.psf:
        head, _, start = spec.partition("@")  # learned@START: learned from START
        learned = head == "learned"
        if not learned:
            psf0 = baseline_psf(spec, 11, sensor.weights)
        else:
            psf0 = starting_psf(start, 11, sensor.weights) if start else gaussian_psf(11)
        config = training.TrainConfig(steps=args.steps, minutes=0.0, patch=64, learn_psf=learned)
        t0 = time.perf_counter()
        camera = training.train(config, scenes, sensor, psf0, progress=False).camera
        s5, s14 = (score(camera, data / s, wiener)["psnr_y"] for s in ("set5", "set14"))
        print(
            f"{spec:14s} Set5 {s5:.3f}  Set14 {s14:.3f}  PSNR-Y  ({time.perf_counter() - t0:.0f} s)"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
