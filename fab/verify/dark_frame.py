"""A dark frame that saw the light: files swapped, or a dark taken with the light on.

``refuse_a_dark_frame_with_dots`` runs when the dark-subtracted capture shows no dot
lattice. The dark frame is named only when it holds a dot lattice of its own (a pitch
measured from its dots, as for a capture) whose dots carry at least ``DARK_LIGHT_SHARE``
of the light of the capture's own dots as stored: a true dark frame's hot pixels and
noise never do, whatever the camera's pixel pitch, while a lattice too tight or too
faint in the capture to register then says nothing against its dark frame.
"""

from pathlib import Path

import numpy as np

from doe.infra.errors import InputError
from fab.verify.capture import read_raw_image
from fab.verify.lattice import DETECT_SIGMAS, pixel_noise
from fab.verify.pitch import measure_pitch

# The dark frame's dots must hold this share of the light of the capture's dots.
DARK_LIGHT_SHARE = 0.5


def refuse_a_dark_frame_with_dots(capture, dark):
    """Raise InputError naming ``dark`` when it holds the dots the subtraction took away.

    ``capture`` and ``dark`` are the files as given.
    """
    dark_raw = read_raw_image(dark)
    dark_img = dark_raw.data.astype(np.float32)
    if measure_pitch(dark_img, dark_raw.quantum) is None:
        return
    cap_raw = read_raw_image(capture)
    dark_light = dot_light(dark_img, dark_raw.quantum)
    cap_light = dot_light(cap_raw.data.astype(np.float32), cap_raw.quantum)
    if not dark_light >= DARK_LIGHT_SHARE * cap_light or dark_light == 0:
        return
    if cap_light >= DARK_LIGHT_SHARE * dark_light:
        raise InputError(
            dark,
            "the dark frame holds the capture's dot lattice, so none is left once it is "
            "subtracted; take the dark with the light blocked",
        )
    raise InputError(
        dark,
        f"the dark frame holds a dot lattice and the capture {Path(capture).name} "
        "none: are the capture and --dark swapped?",
    )


def dot_light(image, quantum=0.0):
    """Return the light (DN, above the frame's median) of the pixels standing
    ``DETECT_SIGMAS`` noise sigmas out: a frame's dots, or 0."""
    x = np.asarray(image, dtype=np.float32)
    x = x - np.float32(np.median(x[::4, ::4]))
    noise = pixel_noise(x[::4, ::4], quantum)
    return float(x[x > DETECT_SIGMAS * noise].sum(dtype=np.float64))
