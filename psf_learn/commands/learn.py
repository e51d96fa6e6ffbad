"""``doefab learn``, ``doefab evaluate`` and ``doefab sr`` (torch is imported inside handlers)."""

import json
import math
import os
import platform
import sys
import tempfile
from pathlib import Path

from doe.infra.errors import InputError

PSF_CHOICES = ("learned", "delta", "box", "gaussian")
OUTPUTS = ("psf.npy", "model.pt", "learn.json")
# sr notes a frame whose 99th-percentile counts pass this many times its white level.
OVER_WHITE = 2.0


def register(sub):
    p = sub.add_parser("learn", help="train a PSF and a super-resolution network end to end")
    p.add_argument("--out", required=True, help="output folder (psf.npy, model.pt, learn.json)")
    p.add_argument(
        "--images",
        help="folder of training images (PNG/JPEG/TIFF, grayscale); "
        "default: embedded natural + dead-leaves images",
    )
    p.add_argument(
        "--psf",
        default="learned",
        help="learned (default), delta (low fill factor), box (full fill factor), "
        "gaussian (sigma 0.459 sub-pixel), gaussian:SIGMA (sub-pixels), or a psf.npy file "
        "(fixed)",
    )
    budget = p.add_mutually_exclusive_group()
    budget.add_argument(
        "--minutes", type=float, help="wall-clock budget (default: the design's [learning] minutes)"
    )
    budget.add_argument(
        "--steps", type=int, help="number of steps (resumable; deterministic on the CPU)"
    )
    p.add_argument("--seed", type=int, help="random seed (default: the design's)")
    p.add_argument("--config", help="design TOML file or preset name")
    p.add_argument("--init", metavar="MODEL_DIR", help="start from a trained model (fine-tune)")
    p.add_argument("--freeze-psf", action="store_true", help="keep the PSF fixed")
    p.add_argument("--features", type=int, help="network feature channels (default 24)")
    p.add_argument("--stages", type=int, help="residual blocks / projection stages (default 4)")
    p.add_argument("--arch", choices=("resnet", "dbpn"), help="network design (default resnet)")
    p.add_argument("--batch", type=int, help="patches per step (default 16)")
    p.add_argument(
        "--patch",
        type=int,
        help="patch size in sub-pixels, a multiple of the factor (default: the largest up to 64)",
    )
    p.add_argument("--lr", type=float, help="network learning rate (default 2e-3)")
    p.add_argument("--psf-lr", type=float, help="PSF logit learning rate (default 0.05)")
    p.add_argument(
        "--photons",
        type=float,
        help="counts of a white pixel (default: the design's photons_per_pixel); 0 = no noise",
    )
    p.add_argument("--dark-counts", type=float, default=0.0, help="dark counts per pixel")
    p.add_argument(
        "--threads",
        type=int,
        help="CPU threads (default: 1 with --steps, whose result then depends on neither the "
        "machine's cores nor its load; else the idle cores, from the load average: 1 on a busy "
        "machine, where one thread runs far faster than two fighting for cores)",
    )
    p.add_argument(
        "--device",
        choices=("auto", "cpu", "cuda"),
        default="auto",
        help="where to train (default auto: the GPU if torch sees one); "
        "only CPU runs repeat bit for bit",
    )
    p.add_argument("--restart", action="store_true", help="ignore an existing checkpoint")
    p.add_argument("--force", action="store_true", help="overwrite existing outputs")
    p.set_defaults(func=_learn)

    p = sub.add_parser("evaluate", help="PSNR/SSIM of a learned model on an image folder")
    p.add_argument("model_dir", help="folder written by `doefab learn`")
    p.add_argument("--images", required=True, help="folder of grayscale test images")
    p.add_argument("--psf-file", help="evaluate with this PSF (e.g. the realised plate's)")
    p.add_argument("--seed", type=int, default=None, help="noise seed (default fixed)")
    p.add_argument("--out", help="write the results to this JSON file")
    p.add_argument("--force", action="store_true", help="overwrite the JSON file")
    p.set_defaults(func=_evaluate)

    p = sub.add_parser("sr", help="super-resolve raw SPAD frames (npy or images)")
    p.add_argument("model_dir", help="folder written by `doefab learn`")
    p.add_argument("raw", nargs="+", help="raw frames: .npy (H, W) or (T, H, W), or image files")
    p.add_argument(
        "--out", required=True, help="output folder (<name>_sr.npy, <name>_sr.png, <name>_sr.json)"
    )
    p.add_argument("--photons", type=float, help="counts of white (default: the model's)")
    p.add_argument("--force", action="store_true", help="overwrite existing outputs")
    p.set_defaults(func=_sr)


def _learn(args):
    import numpy as np
    import torch

    from doe.design import check_psf_grid, check_psf_kernel, design_summary, load_design
    from doe.infra import flags
    from doe.infra.files import read_psf, save_npy, sha256_file, staged_output, write_json
    from psf_learn import images as imgio
    from psf_learn import store
    from psf_learn.network import FEATURES_MAX, STAGES_MAX, check_arch
    from psf_learn.psf import baseline_psf, gaussian_psf
    from psf_learn.sensor import sensor_from_design
    from psf_learn.train import (
        TrainConfig,
        augment_scales,
        default_patch,
        device_name,
        pick_device,
        train,
        with_overrides,
    )

    for flag in ("steps", "minutes", "batch", "patch", "features", "stages", "threads"):
        flags.positive(f"--{flag}", getattr(args, flag))
    # Sizes past these exhaust a workstation's memory (a traceback, not a message).
    limits = (("batch", 1024), ("patch", 512), ("features", FEATURES_MAX), ("stages", STAGES_MAX))
    for flag, limit in limits:
        flags.at_most(f"--{flag}", getattr(args, flag), limit, "larger runs out of memory")
    flags.at_most("--minutes", args.minutes, flags.MINUTES_MAX, "two years")
    flags.at_most("--steps", args.steps, flags.STEPS_MAX, "years of training")
    flags.positive("--lr", args.lr)
    flags.positive("--psf-lr", args.psf_lr)
    for flag, value in (("--photons", args.photons), ("--dark-counts", args.dark_counts)):
        flags.at_most(flag, flags.non_negative(flag, value), flags.PHOTONS_MAX, "counts per pixel")
    flags.seed("--seed", args.seed)
    if args.device == "cuda" and not torch.cuda.is_available():
        raise InputError("--device cuda", "torch sees no CUDA device on this machine")
    # The thread count changes a run's last bits: a --steps run (deterministic,
    # resumable) takes a fixed one, not one read from the load of the moment.
    torch.set_num_threads(args.threads or (1 if args.steps else idle_cores()))
    design = load_design(args.config)
    k = design.kernel_size
    sensor = sensor_from_design(design, photons=args.photons, dark_counts=args.dark_counts)
    if sensor.photons <= 0 and sensor.dark_counts > 0:  # model.pt would record them all the same
        raise InputError("--dark-counts", "needs photon noise: --photons 0 simulates no counts")
    config = with_overrides(
        TrainConfig(minutes=design.learning.minutes, seed=design.learning.seed),
        steps=args.steps,
        minutes=None if args.steps else args.minutes,
        seed=args.seed,
        batch=args.batch,
        patch=args.patch or default_patch(sensor.factor),
        lr=args.lr,
        psf_lr=args.psf_lr,
        features=args.features,
        stages=args.stages,
        arch=args.arch,
    )
    if args.steps:
        config = with_overrides(config, minutes=0.0)
    try:
        check_arch(config.arch, sensor.factor)  # found now, not by a step of the training
    except ValueError as e:
        raise InputError("--arch", str(e)) from None
    if config.patch % sensor.factor:
        raise InputError("--patch", f"must be a multiple of {sensor.factor}, got {config.patch}")
    world = int(os.environ.get("WORLD_SIZE", "1"))  # torchrun's processes share each batch
    if config.batch % world:
        raise InputError(
            "--batch", f"{config.batch} does not split among the {world} processes of this job"
        )

    init_state = None
    init_psf = None
    if args.init:
        from psf_learn.sr import load_model

        base = load_model(args.init)
        init_psf = base.psf
        check_psf_grid(Path(args.init) / "psf.npy", design)  # as --psf FILE is
        init_state = base.net.state_dict()
        record, _, _ = store.load_model_dir(args.init)
        net = record["network"]
        if net["factor"] != sensor.factor:
            raise InputError(
                args.init,
                f"the model super-resolves by {net['factor']}, the design by {sensor.factor}; "
                "pass the design it was trained for with --config",
            )
        for key in ("features", "stages", "arch"):
            given = getattr(args, key)
            if given is not None and given != net[key]:
                raise InputError(
                    f"--{key}",
                    f"{given} differs from the --init model's {net[key]}; "
                    "fine-tuning keeps the network, drop the flag",
                )
        config = with_overrides(
            config, features=net["features"], stages=net["stages"], arch=net["arch"]
        )
    spec = args.psf
    if spec == "learned":
        psf0 = init_psf if init_psf is not None else gaussian_psf(k)
        learn_psf = not args.freeze_psf
    elif spec in PSF_CHOICES or spec.startswith("gaussian:"):
        try:
            psf0 = baseline_psf(spec, k, sensor.weights)
        except ValueError as e:
            raise InputError("--psf", str(e)) from None
        learn_psf = False
    else:
        if not Path(spec).exists():  # a misspelt name, or a file that is not there
            raise InputError(
                "--psf", f"{spec!r} is no file and none of {', '.join(PSF_CHOICES)}, gaussian:SIGMA"
            )
        psf0, learn_psf = read_psf(spec), False
        check_psf_grid(spec, design)
    learned_from = Path(args.init) / "psf.npy" if args.init else None
    check_psf_kernel(psf0, learned_from if spec == "learned" else spec, design)
    config = with_overrides(config, learn_psf=learn_psf)

    margin = psf0.shape[0] - 1
    need = config.patch + margin  # a patch blurred by the PSF without padding
    why = f"--patch {config.patch} plus the PSF's {margin}-pixel margin"
    if args.images:
        names, images = imgio.read_folder(args.images, need, f"{why}; a smaller --patch fits")
        source = str(args.images)
    else:
        names, images = imgio.default_images(seed=0)
        source = "embedded (scikit-image bundled photos + dead leaves)"
        smallest = min(min(img.shape) for img in images)
        if smallest < need:  # make_batch failed on the first too small image it drew
            fits = (smallest - margin) // sensor.factor * sensor.factor
            raise InputError(
                "--patch",
                f"{why} needs images of {need} pixels, the smallest embedded one has "
                f"{smallest}: use --patch {fits} or less, or --images",
            )
    images = augment_scales(images, config.patch + margin)

    out = Path(args.out)
    from doe.infra.files import _refuse_overwrite, check_out_folder

    check_out_folder(out)
    if not args.force:
        _refuse_overwrite(out, OUTPUTS)
    # The checkpoint goes there: a folder it cannot write to is refused now, not after
    # the training (a read-only --out once failed, with a traceback, at the end).
    created = not out.exists()
    try:
        out.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=out):
            pass
    except OSError as e:
        raise InputError(out, f"cannot write here ({e.strerror})") from None
    checkpoint = out / "checkpoint.pt"
    if args.restart:  # every rank of a torchrun job gets here before any reads it
        checkpoint.unlink(missing_ok=True)
    device = torch.device("cpu") if args.device == "cpu" else pick_device()
    if args.steps and device.type == "cuda" and os.environ.get("RANK", "0") == "0":
        print(
            f"note: training on {device_name(device)}: two runs of this command will differ "
            "(GPU gradients sum in a varying order; on an H100, PSFs 4e-4 apart after 150 "
            "steps); --device cpu repeats bit for bit",
            file=sys.stderr,
        )
    try:
        result = train(
            config,
            images,
            sensor,
            psf0,
            init_state=init_state,
            checkpoint=checkpoint,
            device=device,
        )
    except BaseException:
        if created and not any(out.iterdir()):  # a first run that diverged leaves no folder
            out.rmdir()
        raise
    if torch.distributed.is_available() and torch.distributed.is_initialized():
        rank = torch.distributed.get_rank()
        torch.distributed.barrier()
        torch.distributed.destroy_process_group()
        if rank != 0:
            return 0
    # A fixed PSF is written as given (through float32 logits it came back 4e-7 off).
    psf = result.camera.psf.numpy() if learn_psf else np.asarray(psf0, dtype=np.float64)
    info = {
        "config": {
            **config.identity(),
            "psf": spec,
            "kernel_size": int(psf.shape[0]),
            "photons_per_pixel": sensor.photons,
            "dark_counts": sensor.dark_counts,
            "sample_cell": list(sensor.sample_cell),
            "design": design.name,
            "init": str(args.init) if args.init else None,
        },
        "design": design_summary(design),
        "images": {"source": source, "count": len(names)},
        "steps": result.steps,
        "seconds": round(result.seconds, 3),
        "final_loss": result.loss,
        "final_psnr_db": result.psnr,
        "seed": config.seed,
        "device": device_name(device),
        "versions": {
            "torch": torch.__version__,
            "numpy": np.__version__,
            "python": platform.python_version(),
            "doefab": _version(),
        },
    }
    with staged_output(out, force=args.force, names=OUTPUTS) as stage:
        save_npy(stage / "psf.npy", psf)
        record = store.model_record(result.camera.net, result.camera.net_config, sensor)
        store.save_model(stage / "model.pt", record)
        # so that a model.pt or psf.npy from another run is not taken for this one's
        info["files"] = {n: sha256_file(stage / n) for n in ("model.pt", "psf.npy")}
        write_json(stage / "learn.json", info)
    checkpoint.unlink(missing_ok=True)
    print(
        f"trained the model for PSF {spec}: {result.steps} steps in {result.seconds:.0f} s, "
        f"training PSNR {result.psnr:.2f} dB -> {out}"
    )
    return 0


def idle_cores():
    """Return the CPU threads to use: OMP_NUM_THREADS if set, else the cores not busy now."""
    if os.environ.get("OMP_NUM_THREADS", "").isdigit():
        return max(1, int(os.environ["OMP_NUM_THREADS"]))
    cores = os.cpu_count() or 1
    try:
        busy = os.getloadavg()[0]
    except OSError:
        busy = 0.0
    return max(1, min(cores, int(cores - busy)))


def _version():
    try:
        from importlib.metadata import version

        return version("doefab")
    except Exception:
        return "unknown"


def _evaluate(args):
    import torch

    from doe.design import check_measured_psf, psf_grid_problem
    from doe.infra import flags
    from doe.infra.files import read_psf, write_json
    from psf_learn import images as imgio
    from psf_learn.evaluate import EVAL_SEED, evaluate
    from psf_learn.sr import load_model

    flags.seed("--seed", args.seed)
    torch.set_num_threads(1)
    out = Path(args.out) if args.out else None
    if out is not None and out.is_dir():
        raise InputError(out, "is a folder; --out names the JSON file to write")
    if out is not None and (out.exists() or out.is_symlink()) and not args.force:
        raise InputError(out, "exists; use --force or another --out")
    parent = next((q for q in (out.parents if out else ()) if q.exists()), None)
    if parent is not None and not parent.is_dir():  # found now, not after the evaluation
        raise InputError(parent, f"is a file, so {out.name} cannot be written inside it")
    model = load_model(args.model_dir)
    psf = None
    if args.psf_file:
        psf = read_psf(args.psf_file)
        check_measured_psf(args.psf_file)
        summary = (model.learn or {}).get("design")  # a model without it is not compared
        problem = psf_grid_problem(args.psf_file, summary, "the model")
        if problem:
            path, text = problem
            raise InputError(path, f"{text}; --psf-file must be made for the model's grid")
    # The capture mirrors each image by K // 2 at its borders: narrower ones cannot be.
    k = (model.psf if psf is None else psf).shape[0]
    psf_path = args.psf_file or Path(args.model_dir) / "psf.npy"
    names, images = imgio.read_folder(
        args.images,
        min_size=max(4 * model.sensor.factor, k),
        why=f"the {k}x{k} PSF of {psf_path} needs {k} pixels"
        if k > 4 * model.sensor.factor
        else "",
    )
    seed = EVAL_SEED if args.seed is None else args.seed
    res = evaluate(model, names, images, psf, seed, progress=sys.stderr.isatty())
    if not math.isfinite(res["psnr"]):  # images in [0, 1]: the weights overflowed float32
        raise InputError(Path(args.model_dir) / "model.pt", "gives non-finite estimates")
    for name, v in res["images"].items():
        print(f"{name:32s} PSNR {v['psnr']:6.2f} dB  SSIM {v['ssim']:.4f}")
    print(f"{'mean':32s} PSNR {res['psnr']:6.2f} dB  SSIM {res['ssim']:.4f}")
    if out is not None:
        out.parent.mkdir(parents=True, exist_ok=True)
        write_json(
            out,
            {
                **res,
                "model": str(args.model_dir),
                "images_folder": args.images,
                "psf_file": args.psf_file,
            },
        )
    return 0


def _sr(args):
    import numpy as np
    import torch
    from tqdm import tqdm

    from doe.infra import flags
    from doe.infra.files import save_npy, sha256_file, staged_output, write_json
    from psf_learn import images as imgio
    from psf_learn.sr import load_model, super_resolve, white_counts

    flags.positive("--photons", args.photons)
    flags.at_most("--photons", args.photons, flags.PHOTONS_MAX, "counts per pixel")
    torch.set_num_threads(1)
    model = load_model(args.model_dir)
    model_file = Path(args.model_dir) / "model.pt"
    stems = [Path(r).stem for r in args.raw]
    for i, stem in enumerate(stems):
        if stem in stems[:i]:
            first = args.raw[stems.index(stem)]
            raise InputError(
                args.raw[i], f"shares its name with {first}; their outputs would collide"
            )
    frames = [imgio.read_raw(r) for r in args.raw]
    # Each output has its own record, so that a folder can gather several batches.
    names = [f"{s}_sr{ext}" for s in stems for ext in (".npy", ".png", ".json")]
    record = {
        "model": str(args.model_dir),
        "model_sha256": sha256_file(model_file),
        "photons": white_counts(model, args.photons),
        "dark_counts": model.sensor.dark_counts,
        "doefab": _version(),
    }
    with staged_output(args.out, force=args.force, names=names) as stage:
        bar = tqdm(frames, desc="sr", unit="input", disable=None)
        for raw_path, stem, raw in zip(args.raw, stems, bar, strict=True):
            notes = _exposure_notes(raw, raw_path, record["photons"], model.sensor.dark_counts)
            for note in notes:
                print(f"doefab sr: {note}", file=sys.stderr)
            hr = super_resolve(model, raw, photons=args.photons)
            if not np.isfinite(hr).all():  # weights (or counts) past float32's range
                raise InputError(model_file, f"gives non-finite values on {raw_path}")
            made = (f"{stem}_sr.npy", f"{stem}_sr.png")
            save_npy(stage / made[0], hr)
            _write_preview(stage / made[1], hr if hr.ndim == 2 else hr.mean(axis=0))
            write_json(
                stage / f"{stem}_sr.json",
                {
                    **record,
                    "input": str(raw_path),
                    "input_sha256": sha256_file(raw_path),
                    "input_shape": list(raw.shape),
                    "output_shape": list(hr.shape),
                    "files": {n: sha256_file(stage / n) for n in made},
                    "notes": notes,
                },
            )
            print(f"{stem}: {raw.shape} -> {hr.shape}", file=sys.stderr)
    print(json.dumps({"outputs": names}))
    return 0


def _exposure_notes(raw, raw_path, white, dark_counts):
    """Return a note when a frame is far brighter than the white the network was trained on.

    A camera frame of 16-bit codes, or a SPAD exposed longer than the model's photon
    level, was super-resolved without a word: the network never saw a scene brighter
    than white, and its output then means little.
    """
    import numpy as np

    top = float(np.percentile(raw, 99)) - dark_counts
    if not top > OVER_WHITE * white:
        return []
    return [
        f"{raw_path}: 1 % of its counts exceed {top:.4g}, {top / white:.3g} times the white "
        f"level {white:g} the network was trained at: give --photons as the counts a white "
        "scene gives these frames"
    ]


def _write_preview(path, image):
    """Write an 8-bit PNG scaled to the image's 99.9th percentile (a viewing aid)."""
    import numpy as np
    from skimage import io

    top = float(np.percentile(image, 99.9)) or 1.0
    io.imsave(
        path, (np.clip(image / top, 0, 1) * 255).round().astype(np.uint8), check_contrast=False
    )
