"""`mmf-rl train [overrides]`: a LeRobot dataset in, a trained missing-modality forecaster out.

    mmf-rl train data=so101 trainer.total_steps=500 run_dir=runs/so101
    mmf-rl train data=/path/to/mine.yaml run_dir=runs/mine     # a data config of your own (`mmf-rl inspect`)
    mmf-rl train --cfg data=so101 model=lf_lstm                # print the composed config, do not train
    torchrun --nproc_per_node=2 -m mmf_rl.cli train ...     # data parallel (gloo on CPU, NCCL on GPU)

Top to bottom (:func:`mmf_rl.trainers.training.train`, ``mmf_rl.train`` from Python): compose the
config, set up devices and processes, open the window cache, build the model and its losses, train
with checkpoints, logs and validation, then save the final weights. ``resume=true`` continues the
run in ``run_dir`` exactly where its last checkpoint was; ``init_from=RUN_OR_CHECKPOINT``
fine-tunes: a new run starting from another run's (or a ``save_pretrained`` directory's) weights,
with a new optimizer and schedule, at step 0, and the normalisation statistics of this run's data.
With ``calibrate=true`` (the default) the trained model's forecast scale is then recalibrated per
presence pattern on the val split (what ``mmf-rl calibrate`` does) and the last checkpoint re-saved
with the factors. A model with a learned sampler (``model.learned_samples=K``) has it trained first,
for ``sampler.steps``, on the frozen forecaster (:mod:`mmf_rl.trainers.latent_sampler`). The final
model is also written with ``save_pretrained`` to ``run_dir/model`` (weights, config, statistics,
data config, and the calibration's fit).
"""

from __future__ import annotations

import os
from pathlib import Path

from omegaconf import DictConfig

from mmf_rl.checkpoint import CheckpointError, list_checkpoints
from mmf_rl.configuration import ConfigError, run_config_command
from mmf_rl.trainers.trainer import TrainingStopped
from mmf_rl.trainers.training import train

EXAMPLES = [
    "mmf-rl train data=so101 trainer.total_steps=500 run_dir=runs/so101",
    "mmf-rl train data=/path/to/mine.yaml run_dir=runs/mine      # your own data config (mmf-rl inspect "
    "writes one)",
    "mmf-rl train --cfg data.root=/data/mine data.modalities='{cam: observation.images.top}' "
    "data.target=observation.state   # print the composed config only",
]
ERRORS = (ConfigError, CheckpointError, TrainingStopped, OSError, ValueError, KeyError)


class PeerFailure(Exception):
    """A rank's training broken under DDP, most likely by a peer that died or hung."""


def distributed_failure(error: RuntimeError, run_dir: Path) -> str:
    """One line for a rank whose training broke under DDP: usually a peer died or hung."""
    checkpoints = list_checkpoints(run_dir / "checkpoints")
    resume = (
        f"continue from {checkpoints[-1]} with resume=true"
        if checkpoints
        else "nothing was checkpointed yet; start again"
    )
    cause = " ".join(str(error).split())[:300]
    return (
        f"rank {os.environ.get('RANK', '?')} of {os.environ['WORLD_SIZE']} stopped ({type(error).__name__}: "
        f"{cause}); if another rank died or hung, torchrun's report names it; {resume}"
    )


def train_naming_peer_failures(cfg: DictConfig) -> Path:
    """:func:`~mmf_rl.trainers.training.train`; under DDP a dead or hung peer surfaces as a RuntimeError
    from a collective (gloo's "Connection reset by peer", a timeout after MMF_RL_DIST_TIMEOUT seconds):
    it becomes a :class:`PeerFailure`, one line instead of one traceback per surviving rank."""
    try:
        return train(cfg)
    except RuntimeError as err:
        alone = int(os.environ.get("WORLD_SIZE", "1")) == 1
        if isinstance(err, ERRORS) or alone or os.environ.get("MMF_RL_DEBUG"):
            raise
        raise PeerFailure(distributed_failure(err, Path(cfg.run_dir).resolve())) from err


def main(argv: list[str]) -> int:
    return run_config_command(
        argv,
        "train",
        "Train a missing-modality forecaster on a LeRobot dataset (configs/train.yaml composed with your "
        "overrides).",
        EXAMPLES,
        train_naming_peer_failures,
        (*ERRORS, PeerFailure),
    )
