"""What the plate buys: the trained model and a no-plate model scored on held-back images.

``doefab learn`` trains, beside its model, the no-plate model: the same network
trained the same way (same steps or minutes, seed, images, starting network)
for the ``delta`` PSF, i.e. the bare low fill-factor SPAD. Both are evaluated
(:func:`psf_learn.evaluate.evaluate`, both conventions) on images the training
never saw: the embedded set's held-out photos (:func:`psf_learn.images.held_out_images`)
or ``--eval-images``. The difference is what the plate buys, in dB.

``--no-baseline`` (or ``--psf delta``, whose model is the no-plate one) leaves
the second training out; the model is scored all the same.
"""

import numpy as np

from psf_learn.evaluate import evaluate
from psf_learn.psf import baseline_psf
from psf_learn.scores import SCORE_KEYS
from psf_learn.sr import SRModel
from psf_learn.train import train, with_overrides

BASELINE_PSF = "delta"
BASELINE_CHECKPOINT = "checkpoint_delta.pt"


def wants_baseline(opts):
    """Return whether a training with these options trains the no-plate model too."""
    return not opts.no_baseline and opts.psf != BASELINE_PSF


def train_baseline(plan, progress):
    """Train the no-plate (``delta``) model as ``plan`` trains its own; return the TrainResult.

    Its checkpoint (``checkpoint_delta.pt`` in the output folder) resumes it as the
    model's own does.
    """
    psf0 = baseline_psf(BASELINE_PSF, plan.psf0.shape[0], plan.sensor.weights)
    return train(
        with_overrides(plan.config, learn_psf=False),
        plan.scenes,
        plan.sensor,
        psf0,
        init_state=plan.init_state,
        checkpoint=plan.checkpoint.with_name(BASELINE_CHECKPOINT),
        progress=progress,
        device=plan.device,
    )


def score(camera, psf, plan):
    """Return the evaluation (both conventions, per image and mean) of a trained camera."""
    model = SRModel(camera.net.eval(), np.asarray(psf, dtype=np.float64), plan.sensor, None)
    return evaluate(model, plan.eval_names, plan.eval_scenes)


def heldout_record(plan, model_scores, baseline_scores):
    """Return the ``heldout`` entry of learn.json: both models' scores and their difference.

    ``baseline_scores`` is None when no no-plate model was trained; for ``--psf delta``
    the model is the no-plate one, and the difference is zero.
    """
    if plan.opts.psf == BASELINE_PSF:
        baseline_scores = model_scores
    gain = None
    if baseline_scores is not None:
        gain = {k: model_scores[k] - baseline_scores[k] for k in SCORE_KEYS if "psnr" in k}
    return {
        "images": {"source": plan.eval_source, "names": list(plan.eval_names)},
        "model": model_scores,
        "no_plate": baseline_scores,
        "plate_gain_db": gain,
    }
