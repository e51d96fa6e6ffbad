"""The front page's learning rows: what the plate buys on held-back images.

From ``learn.json``'s ``heldout`` (:mod:`doe.records.learn`): the trained model
and the no-plate model (``delta`` PSF, trained the same way) scored on images the
training never saw, and the difference, in both conventions (full-range grey,
and the SR papers' MATLAB Y). The training-batch PSNR stays in learn.json.
"""

from pathlib import Path

from doe.infra.errors import InputError
from doe.records.learn import LEARN_JSON, read_learn


def learn_rows(run_dir):
    """Return the Summary rows (label, value shown) of the run's learn stage; [] without one."""
    path = Path(run_dir) / "learn" / LEARN_JSON
    try:
        record = read_learn(path)
    except InputError:
        return []
    held = record.heldout or {}
    model = held.get("model")
    if not isinstance(model, dict):
        return []
    names = (held.get("images") or {}).get("names") or []
    where = f"{len(names)} held-back images ({', '.join(map(str, names))})"
    gain = record.plate_gain()
    if gain is None:
        return [
            (
                f"PSNR on {where}, PSNR-Y in brackets (dB)",
                f"{_db(model, 'psnr')} ({_db(model, 'psnr_y')}); no no-plate model (--no-baseline)",
            )
        ]
    model, base, diff = gain
    return [
        (
            f"PSNR on {where} (dB): with the plate / no plate (delta PSF) / what the plate buys",
            f"{_db(model, 'psnr')} / {_db(base, 'psnr')} / {_db(diff, 'psnr', sign=True)}",
        ),
        (
            "same, PSNR-Y (MATLAB Y 16-235, the SR papers' convention)",
            f"{_db(model, 'psnr_y')} / {_db(base, 'psnr_y')} / {_db(diff, 'psnr_y', sign=True)}",
        ),
    ]


def _db(scores, key, sign=False):
    """Return a score in dB with 2 decimals, '?' where the record lacks it."""
    value = scores.get(key)
    if not isinstance(value, (int, float)) or isinstance(value, bool):
        return "?"
    return f"{value:+.2f}" if sign else f"{value:.2f}"
