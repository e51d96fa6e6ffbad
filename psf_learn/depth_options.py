"""The flags that choose a gated SPAD's temporal response, shared by the depth commands.

The gate model's flags (``--gate-width-ps`` ...), ``--irf`` / ``--irf-t0-ps`` and
``--scan``, and the response they give (:mod:`psf_learn.depth_response`).
Malformed values raise :class:`doe.infra.errors.InputError` (exit 2). numpy
only: this module must not import torch.
"""

import numpy as np

from doe.infra import flags
from doe.infra.errors import InputError

# An IRF cut above this share of its peak is extended over much of its shape (the
# extension is good to ~0.01 of the peak for a cut at half the peak).
IRF_CUT_WARN = 0.5
GATE_FLAGS = {  # flag attribute -> (default, GateModel field, help)
    "gate_width_ps": (200.0, "width", "length of the undistorted gate rectangle [0, width]"),
    "rise_ps": (40.0, "rise", "RC rise constant inside the gate, 1 - exp(-t / rise)"),
    "fall_ps": (60.0, "fall", "RC decay constant after the gate"),
    "band_sigma_ps": (100.0, "band_sigma", "std of the Gaussian band limit of the gate"),
    "pulse_fwhm_ps": (80.0, "pulse_fwhm", "FWHM of the Gaussian laser pulse"),
}


def add_gate_flags(p):
    """The gate model's flags and --irf, shared by depth and depth-calibrate."""
    g = p.add_argument_group("gate model (in ps; not together with --irf)")
    for attr, (default, _, text) in GATE_FLAGS.items():
        g.add_argument(
            "--" + attr.replace("_", "-"),
            dest=attr,
            type=float,
            default=None,
            help=f"{text} (default {default:g})",
        )
    g.add_argument(
        "--pulse",
        choices=("gaussian", "emg"),
        default=None,
        help="laser pulse shape (default gaussian)",
    )
    g.add_argument("--tau-ps", type=float, default=None, help="exponential tail of an 'emg' pulse")
    p.add_argument(
        "--irf",
        help="measured instrument response (.npy, 1-D) on the scan axis, "
        "from a reference target at --irf-t0-ps; replaces the gate model",
    )
    p.add_argument(
        "--irf-t0-ps",
        type=float,
        help="arrival time of the IRF's reference target (default 0)",
    )


def add_scan_flag(p):
    """The --scan flag of depth, transient and depth-calibrate."""
    p.add_argument(
        "--scan",
        choices=("gate", "laser", "auto"),
        default="auto",
        help="scan direction: gate (the gate delayed, h = G correlated with Pi), laser "
        "(time-reversed, h = G * Pi) or auto (fit both, keep the likelier; default)",
    )


def responses_from_flags(args):
    """{direction: response} for --scan (both for auto; "irf" for --irf) and the summary."""
    if args.irf:
        if args.scan != "auto":
            raise InputError(
                "--scan",
                "a measured IRF, taken in the same scan, fixes the direction by itself; "
                "drop --scan",
            )
        response, summary = response_from_flags(args)
        return {"irf": response}, summary
    scans = ("gate", "laser") if args.scan == "auto" else (args.scan,)
    parts = [response_from_flags(args, scan) for scan in scans]
    return {scan: r for scan, (r, _) in zip(scans, parts, strict=True)}, parts[0][1]


def response_from_flags(args, scan="gate"):
    """The temporal response from the gate flags (in direction ``scan``) or from --irf."""
    from psf_learn.cubes import read_irf
    from psf_learn.depth_response import GateModel, gate_response, response_from_irf

    shift = flags.positive("--shift-ps", args.shift_ps) * 1e-12
    if args.irf:
        given = [a for a in [*GATE_FLAGS, "pulse", "tau_ps"] if getattr(args, a) is not None]
        if given:
            raise InputError(
                "--irf",
                "replaces the gate model; drop "
                + ", ".join("--" + a.replace("_", "-") for a in given),
            )
        irf = read_irf(args.irf)
        t0 = 0.0 if args.irf_t0_ps is None else args.irf_t0_ps
        if not np.isfinite(t0):
            raise InputError("--irf-t0-ps", "must be a finite number")
        summary = {"irf": str(args.irf), "irf_t0_ps": t0, "warnings": irf_warnings(irf)}
        try:
            return response_from_irf(irf, shift, t0 * 1e-12), summary
        except ValueError as e:
            raise InputError(args.irf, str(e)) from None
    if args.irf_t0_ps is not None:
        raise InputError("--irf-t0-ps", "only applies with --irf")
    params = {}
    for attr, (default, name, _) in GATE_FLAGS.items():
        value = default if getattr(args, attr) is None else getattr(args, attr)
        flag = "--" + attr.replace("_", "-")
        check = flags.positive if name in ("width", "pulse_fwhm") else flags.non_negative
        check(flag, value)
        params[name] = value * 1e-12
    pulse = args.pulse or "gaussian"
    tau = 0.0 if args.tau_ps is None else args.tau_ps
    if pulse == "emg":
        flags.positive("--tau-ps", tau)
    elif args.tau_ps is not None:
        raise InputError("--tau-ps", "only applies with --pulse emg")
    model = GateModel(pulse=pulse, tau=tau * 1e-12, **params)
    summary = {f"{k}_ps": v / 1e-12 for k, v in params.items()}
    summary.update(pulse=pulse, tau_ps=tau)
    try:
        return gate_response(model, scan=scan), summary
    except ValueError as e:
        raise InputError("gate model", f"{e}; check the gate flags (ps)") from None


def irf_warnings(irf):
    """Say when the reference's profile is cut high up at an end of the scan."""
    y = np.clip(np.asarray(irf, dtype=np.float64), 0.0, None)
    y = y / y.max()
    return [
        f"the IRF is cut at {value:.2f} of its peak at the {end} of the scan: beyond it "
        "h is extrapolated (a few ps of timing bias); place the reference so that its "
        "whole profile lies in the scan"
        for end, value in (("start", y[0]), ("end", y[-1]))
        if value > IRF_CUT_WARN
    ]
