"""An offline trainer for forecasters: loss modules + optimizer + hooks, resumable exactly.

torchrl's ``Trainer`` is built around a data *collector* (frame counting, policy-weight updates,
collector shutdown); training here iterates a fixed dataset, so this trainer keeps torchrl's
vocabulary (``register_op`` with ``batch_process``, ``post_loss``, ``post_optim``,
``post_steps``, ``post_steps_log``) over a batch loader instead.

The loader must be re-iterable, yield one epoch per iteration and be deterministic given
``set_epoch(epoch)`` (:class:`mmf_rl.datasets.windows.WindowLoader` is). With the RNG states,
optimizer, scheduler and loss buffers stored in the checkpoint, a resumed run replays exactly
the batches and random draws of an uninterrupted one.
"""

from __future__ import annotations

import logging
import math
import random
import time
from collections import defaultdict
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
import torch.distributed as dist
from tensordict import TensorDictBase
from torch.nn.parallel import DistributedDataParallel
from tqdm.auto import tqdm

from mmf_rl.checkpoint import load_checkpoint, load_model_state, save_checkpoint
from mmf_rl.configuration import reject_unknown_keys
from mmf_rl.datasets.prefetch import BATCH_MAKING, Prefetcher

logger = logging.getLogger(__name__)

OPS = ("batch_process", "post_loss", "post_optim", "post_steps", "post_steps_log")
PRECISIONS = {"fp32": None, "bf16": torch.bfloat16, "fp16": torch.float16}
PREFETCH = (True, False, "auto")  # `TrainerConfig.prefetch`


class TrainingStopped(RuntimeError):
    """Training cannot go on (non-finite or exploding loss); the message says where and what to do."""


@dataclass
class TrainerConfig:
    """Optimisation and bookkeeping of one run.

    Args:
        total_steps (int, optional): optimizer updates of the run. Defaults to ``1000``.
        batch_size (int, optional): windows per update, per rank (used by whoever builds the loader).
            Defaults to ``128``.
        lr (float, optional): AdamW's peak learning rate. Defaults to ``1e-3``.
        weight_decay (float, optional): AdamW's decoupled weight decay. Defaults to ``0``.
        lr_schedule (str, optional): ``"cosine"`` (default: decay to zero over the run after the warmup)
            or ``"constant"``.
        warmup_steps (int, optional): updates of linear warmup to ``lr``, so the first steps of a fresh
            model do not take full-size updates. Defaults to ``50``.
        grad_clip_norm (float, optional): the gradients' global norm is clipped to this (``None``: no
            clipping). Defaults to ``1.0``.
        log_every (int, optional): updates between two logged lines of the losses. Defaults to ``25``.
        eval_every (int, optional): updates between two evaluations (and at the end of the run).
            Defaults to ``250``.
        checkpoint_every (int, optional): updates between two checkpoints (and at the end of the run).
            Defaults to ``250``.
        keep_checkpoints (int, optional): the newest checkpoints kept; older ones are pruned. Defaults to
            ``2``.
        early_stopping_patience (int, optional): stop after this many evaluations in a row without a lower
            ``early_stopping_metric`` (``None``: never).
        early_stopping_metric (str, optional): the metric that decides it; one of those the evaluation
            returns.
        max_nonfinite_steps (int, optional): a step whose loss is NaN/Inf is skipped (no update) and counted;
            more than this many in a row stop the run.
        loss_explosion_threshold (float, optional): a finite total loss above it stops the run, naming the
            last good checkpoint.
        seed (int, optional): seeds the initial weights, the loader's order and the latent draws.
        progress_bar (bool, optional): show tqdm's bar on rank 0.
        precision (str, optional): ``"fp32"``, or ``"bf16"``/``"fp16"`` autocast of the model's forward (the
            losses stay fp32; ``"fp16"`` is CUDA-only and scales the loss with a ``GradScaler``).
        compile (bool, optional): ``torch.compile`` the training forward.
        fused_optimizer (bool, optional): AdamW's fused kernel (one kernel for all parameters instead of a
            loop of small ops per parameter): a faster step at small batches, but its rounding differs from
            the loop's, and data-parallel ranks then drift apart from a one-process run by more than the loop
            lets them. ``False`` (default): torch's own choice (the per-parameter loop on CPU, its
            multi-tensor ``foreach`` form on CUDA).
        prefetch (bool | str, optional): make the next batch (and copy it to the device) on a background
            thread while the current step runs; the batches and results are the same either way. ``"auto"``
            (default): on CUDA, and on CPU when worker processes make the batches (image augmentation with
            ``augment.workers``: the thread mostly waits on them). Otherwise on CPU the step's own threads
            already use every core, so a batch made beside it competes with the step instead of overlapping it
            (docs/results.md has the measured cost); ``True`` prefetches on CPU too (cores to spare),
            ``False`` never.

    Raises:
        ValueError: an unknown ``precision``, ``prefetch`` or ``lr_schedule``, a count below 1 or a
            negative rate, norm or patience (the message names the ``trainer.`` key).
    """

    total_steps: int = 1000
    batch_size: int = 128
    lr: float = 1e-3
    weight_decay: float = 0.0
    lr_schedule: str = "cosine"
    warmup_steps: int = 50
    grad_clip_norm: float | None = 1.0
    log_every: int = 25
    eval_every: int = 250
    checkpoint_every: int = 250
    keep_checkpoints: int = 2
    early_stopping_patience: int | None = None
    early_stopping_metric: str = "val/mse"
    max_nonfinite_steps: int = 10
    loss_explosion_threshold: float = 1e6
    seed: int = 0
    progress_bar: bool = True
    precision: str = "fp32"
    compile: bool = False
    fused_optimizer: bool = False
    prefetch: bool | str = "auto"

    def __post_init__(self):
        if self.precision not in PRECISIONS:
            raise ValueError(f"trainer.precision must be one of {list(PRECISIONS)}, found {self.precision!r}")
        if self.prefetch not in PREFETCH:
            raise ValueError(f"trainer.prefetch must be true, false or 'auto', found {self.prefetch!r}")
        if self.lr_schedule not in ("constant", "cosine"):
            raise ValueError(
                f"trainer.lr_schedule must be 'constant' or 'cosine', found {self.lr_schedule!r}"
            )
        for name in (
            "total_steps",
            "batch_size",
            "log_every",
            "eval_every",
            "checkpoint_every",
            "keep_checkpoints",
        ):
            if getattr(self, name) < 1:
                raise ValueError(f"trainer.{name} must be >= 1, found {getattr(self, name)}")
        # A negative clip norm would flip every gradient's sign instead of failing.
        for name in (
            "lr",
            "weight_decay",
            "warmup_steps",
            "grad_clip_norm",
            "max_nonfinite_steps",
            "early_stopping_patience",
        ):
            value = getattr(self, name)
            if value is not None and value < 0:
                raise ValueError(f"trainer.{name} must be >= 0, found {value}")

    @classmethod
    def from_dict(cls, d: dict) -> TrainerConfig:
        """Build from plain data (the Hydra ``trainer`` config).

        Args:
            d (dict): the settings.

        Returns:
            The config.

        Raises:
            ValueError: an unknown key or an invalid value.
        """
        reject_unknown_keys(cls, d, "trainer config")
        return cls(**d)


def seed_everything(seed: int) -> None:
    """Seed Python's, NumPy's and torch's global generators.

    Args:
        seed (int): the seed (NumPy gets it modulo ``2**32``).
    """
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)


def rng_state() -> dict:
    mt, keys_, pos, has_gauss, cached = np.random.get_state()
    return {
        "torch": torch.get_rng_state(),
        "numpy": {
            "keys": torch.from_numpy(keys_.astype(np.int64)),
            "pos": pos,
            "has_gauss": has_gauss,
            "cached": cached,
        },
        "python": random.getstate(),
    }


def set_rng_state(state: dict) -> None:
    torch.set_rng_state(state["torch"])
    n = state["numpy"]
    np.random.set_state(
        ("MT19937", n["keys"].numpy().astype(np.uint32), n["pos"], n["has_gauss"], n["cached"])
    )
    python = state["python"]
    random.setstate((python[0], tuple(python[1]), python[2]))


def make_optimizer(params, config: TrainerConfig) -> torch.optim.Optimizer:
    # At small batches the per-parameter loop of small ops is a large share of a CPU step; the fused
    # kernel runs on CPU and CUDA for floating-point parameters.
    fused = {"fused": True} if config.fused_optimizer else {}
    return torch.optim.AdamW(params, lr=config.lr, weight_decay=config.weight_decay, **fused)


def make_scheduler(
    optimizer: torch.optim.Optimizer, config: TrainerConfig
) -> torch.optim.lr_scheduler.LRScheduler:
    """Linear warm-up, then constant or cosine decay to 0 at ``total_steps``."""
    warmup, total, cosine = config.warmup_steps, config.total_steps, config.lr_schedule == "cosine"

    def factor(step: int) -> float:
        if step < warmup:
            return (step + 1) / warmup
        if not cosine:
            return 1.0
        progress = (step - warmup) / max(1, total - warmup)
        return 0.5 * (1 + math.cos(math.pi * min(1.0, progress)))

    return torch.optim.lr_scheduler.LambdaLR(optimizer, factor)


class _LossStep(torch.nn.Module):
    """One training forward as a module: ``batch -> (summed loss_* tensor, detached loss TensorDict)``.

    ``DistributedDataParallel`` wraps this rather than the forecaster: with
    ``find_unused_parameters`` it learns which parameters a rank used by walking the autograd
    graph back from the tensors it finds in the forward's output (tensors, tuples, dicts; not a
    TensorDict's entries). The summed loss is the one tensor every gradient flows from. The model
    is registered next to the loss so that every weight it checkpoints is reduced.

    With ``dtype`` (bf16/fp16) the forward runs under ``torch.autocast``; the trainer casts the
    model's outputs back to fp32 (:func:`outputs_to_fp32`), so the Gaussian NLL and KL terms,
    elementwise ops that autocast leaves in their inputs' dtype, are computed in fp32.
    """

    def __init__(
        self,
        model: torch.nn.Module,
        loss_module: torch.nn.Module,
        device_type: str = "cpu",
        dtype: torch.dtype | None = None,
    ):
        super().__init__()
        self.model, self.loss_module = model, loss_module
        self.device_type, self.dtype = device_type, dtype

    def forward(self, batch: TensorDictBase) -> tuple[torch.Tensor, TensorDictBase]:
        with torch.autocast(self.device_type, dtype=self.dtype, enabled=self.dtype is not None):
            losses = self.loss_module(batch)
        return sum(v for k, v in losses.items() if k.startswith("loss_")), losses.detach()


def outputs_to_fp32(module: torch.nn.Module, args, output):
    """Forward hook: the model's autocast (bf16/fp16) outputs (a tensor or TensorDict) as fp32."""

    def cast(t: torch.Tensor) -> torch.Tensor:
        return t.float() if t.dtype in (torch.bfloat16, torch.float16) else t

    return cast(output) if isinstance(output, torch.Tensor) else output.apply(cast)


def check_precision(precision: str, device: torch.device) -> None:
    if precision == "fp16" and device.type != "cuda":
        raise ValueError(
            f"trainer.precision=fp16 needs a CUDA device (loss scaling with torch.amp.GradScaler), "
            f"found device={device}; use trainer.precision=bf16 or fp32 on the CPU"
        )
    if precision == "bf16" and device.type == "cuda" and not torch.cuda.is_bf16_supported():
        raise ValueError(
            f"trainer.precision=bf16 is not supported by {torch.cuda.get_device_name(device)}; "
            "use trainer.precision=fp16 (with loss scaling) or fp32"
        )


class Trainer:
    """Trains ``model`` by summing the ``loss_*`` entries of ``loss_module`` over ``loader`` batches.

    Args:
        model (torch.nn.Module): the module whose weights are checkpointed (the loss module's
            forecaster).
        loss_module (torch.nn.Module): a torchrl ``LossModule`` returning ``loss_*`` entries.
        loader (Iterable[TensorDictBase]): re-iterable, one epoch per iteration, with ``set_epoch(epoch)``
            and deterministic given it (a :class:`~mmf_rl.datasets.WindowLoader`). If it has them,
            its ``batch_making`` (one of :data:`~mmf_rl.datasets.prefetch.BATCH_MAKING`; default
            ``"thread_safe"``) says where a batch may be made ahead, and its ``close()`` is called when
            training ends (it may own worker processes).
        config (TrainerConfig): the optimisation and bookkeeping.

    Keyword Args:
        run_dir (str | Path, optional): where ``checkpoints/`` go (only rank 0 writes); ``None``: no
            checkpoints.
        logger (torchrl.record.loggers.Logger, optional): where rank 0 logs; ``None``: nowhere.
        evaluate (Callable[[torch.nn.Module], dict[str, float]], optional): ``evaluate(model) ->
            {name: value}``, called every ``eval_every`` steps and at the end; its values are logged
            as ``name`` and can drive early stopping.
        checkpoint_meta (dict, optional): stored with every checkpoint (the config, the data's
            fingerprint).
        checkpoint_tensors (dict[str, torch.Tensor], optional): tensors stored with every checkpoint
            (the normalisation statistics).
        rank (int, optional): this process's data-parallel rank. Defaults to ``0``.
        world_size (int, optional): data-parallel processes (``torch.distributed`` must be initialised
            when ``> 1``). Defaults to ``1``.

    Batches are moved to the model's device (pinned, ``non_blocking``, on CUDA).

    Raises:
        ValueError: a loader with an unknown ``batch_making``, or a ``precision`` the device cannot
            run.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from mmf_rl.keys import ModalitySpec
        >>> from mmf_rl.models import ForecasterConfig, MultimodalForecaster
        >>> from mmf_rl.objectives import ELBOLoss
        >>> from mmf_rl.trainers import Trainer, TrainerConfig
        >>> model = MultimodalForecaster(ForecasterConfig(
        ...     modalities=[ModalitySpec("force", "sequence", (6,))],
        ...     history=4, horizon=5, d_model=16, d_latent=4, num_heads=2,
        ... ))
        >>> batch = TensorDict({
        ...     ("obs", "force"): torch.randn(8, 4, 6), ("present", "force"): torch.ones(8, dtype=torch.bool),
        ...     "target": torch.randn(8, 5, 2),
        ... }, batch_size=[8])
        >>> class Batches(list):  # a WindowLoader would also draw a new order per epoch
        ...     def set_epoch(self, epoch):
        ...         pass
        >>> trainer = Trainer(
        ...     model,
        ...     ELBOLoss(model),
        ...     Batches([batch, batch]),
        ...     TrainerConfig(total_steps=6, warmup_steps=0, progress_bar=False),
        ...     evaluate=lambda model: {"val/loss": 0.0},
        ... )
        >>> trainer.train()
        {'val/loss': 0.0}
        >>> trainer.step
        6
    """

    def __init__(
        self,
        model: torch.nn.Module,
        loss_module: torch.nn.Module,
        loader,
        config: TrainerConfig,
        *,
        run_dir: str | Path | None = None,
        logger=None,
        evaluate: Callable[[torch.nn.Module], dict[str, float]] | None = None,
        checkpoint_meta: dict | None = None,
        checkpoint_tensors: dict[str, torch.Tensor] | None = None,
        rank: int = 0,
        world_size: int = 1,
    ):
        self.model, self.loss_module, self.loader, self.config = model, loss_module, loader, config
        self.run_dir = Path(run_dir) if run_dir is not None else None
        self.logger = logger if rank == 0 else None
        self.evaluate = evaluate
        self.checkpoint_meta = dict(checkpoint_meta or {})
        self.checkpoint_tensors = dict(checkpoint_tensors or {})
        self.rank, self.world_size = rank, world_size
        self.device = next(model.parameters()).device
        self.batch_making = getattr(loader, "batch_making", "thread_safe")
        if self.batch_making not in BATCH_MAKING:
            raise ValueError(
                f"the loader's batch_making must be one of {list(BATCH_MAKING)}, found {self.batch_making!r}"
            )
        check_precision(config.precision, self.device)
        self.optimizer = make_optimizer(model.parameters(), config)
        self.scheduler = make_scheduler(self.optimizer, config)
        self.ops: dict[str, list[Callable]] = {name: [] for name in OPS}
        self.step = 0
        self.epoch = 0
        self.batch_in_epoch = 0
        self.nonfinite_in_a_row = 0
        self.nonfinite_total = 0
        self.best_metric = math.inf
        self.evals_without_improvement = 0
        self.last_checkpoint: Path | None = None
        self.history: list[dict[str, float]] = []
        if config.grad_clip_norm:
            self.register_op("post_loss", self._clip_gradients)
        # Disabled (fp32, bf16) it passes the loss and the optimizer step through unchanged.
        self.scaler = torch.amp.GradScaler(self.device.type, enabled=config.precision == "fp16")
        self.loss_step: torch.nn.Module = _LossStep(
            model, loss_module, self.device.type, PRECISIONS[config.precision]
        )
        if world_size > 1:
            # DDP starts every rank from rank 0's weights and averages gradients in backward. An
            # encoder whose modality is absent from a rank's batch gets no gradient there
            # (find_unused_parameters): it counts as zero in the average, and keeps no gradient
            # (no optimizer update) when absent on every rank, as in one process.
            self.loss_step = DistributedDataParallel(self.loss_step, find_unused_parameters=True)
        if config.compile:
            self.loss_step = torch.compile(self.loss_step)

    # -- hooks ------------------------------------------------------------------------------------

    def register_op(self, dest: str, op: Callable) -> None:
        """Call ``op`` at ``dest``, as torchrl's ``Trainer`` hooks.

        Args:
            dest (str): ``"batch_process"`` (``op(batch) -> batch``), ``"post_loss"``,
                ``"post_optim"``, ``"post_steps"`` (``op(trainer)``) or ``"post_steps_log"``
                (``op(trainer, logs)``).
            op (Callable): the hook.

        Raises:
            ValueError: an unknown ``dest``.
        """
        if dest not in self.ops:
            raise ValueError(f"unknown hook point {dest!r}; expected one of {list(OPS)}")
        self.ops[dest].append(op)

    def _clip_gradients(self, trainer: Trainer) -> None:
        torch.nn.utils.clip_grad_norm_(self.model.parameters(), self.config.grad_clip_norm)

    # -- state ------------------------------------------------------------------------------------

    def _loss_buffers(self) -> dict[str, torch.Tensor]:
        # The loss module's own state (e.g. the KL warm-up counter), not the model weights it wraps.
        model_tensors = {id(t) for t in self.model.state_dict(keep_vars=True).values()}
        return {
            k: v for k, v in self.loss_module.state_dict(keep_vars=True).items() if id(v) not in model_tensors
        }

    def state_dict(self) -> dict:
        epoch, batch_in_epoch = self.epoch, self.batch_in_epoch
        if batch_in_epoch >= len(self.loader):  # the epoch is finished: resume at the next one
            epoch, batch_in_epoch = epoch + 1, 0
        return {
            "step": self.step,
            "epoch": epoch,
            "batch_in_epoch": batch_in_epoch,
            "optimizer": self.optimizer.state_dict(),
            "scheduler": self.scheduler.state_dict(),
            "loss_buffers": {k: v.detach().clone() for k, v in self._loss_buffers().items()},
            "rng": self._rng_states(),
            "nonfinite_total": self.nonfinite_total,
            "best_metric": self.best_metric,
            "evals_without_improvement": self.evals_without_improvement,
            **({"grad_scaler": self.scaler.state_dict()} if self.scaler.is_enabled() else {}),
        }

    def _rng_states(self) -> list[dict]:
        """Every rank's RNG state (a collective call under DDP): each rank draws its own latents."""
        if self.world_size == 1:
            return [rng_state()]
        states: list = [None] * self.world_size
        dist.all_gather_object(states, rng_state())
        return states

    def load_state_dict(self, state: dict) -> None:
        self.step, self.epoch, self.batch_in_epoch = state["step"], state["epoch"], state["batch_in_epoch"]
        self.optimizer.load_state_dict(state["optimizer"])
        self.scheduler.load_state_dict(state["scheduler"])
        self.loss_module.load_state_dict(state["loss_buffers"], strict=False)
        rngs = state["rng"]
        if len(rngs) != self.world_size:
            raise RuntimeError(
                f"the checkpoint was written by {len(rngs)} rank(s) and this run has "
                f"{self.world_size}; resume with the same number of processes"
            )
        set_rng_state(rngs[self.rank])
        self.nonfinite_total = state["nonfinite_total"]
        self.best_metric = state["best_metric"]
        self.evals_without_improvement = state["evals_without_improvement"]
        if self.scaler.is_enabled() and "grad_scaler" in state:
            self.scaler.load_state_dict(state["grad_scaler"])

    def save(self) -> Path | None:
        """Checkpoint (rank 0 writes; under DDP every rank must call it: the RNG states are gathered)."""
        if self.run_dir is None:
            return None
        state = self.state_dict()
        if self.rank == 0:
            self.last_checkpoint = save_checkpoint(
                self.run_dir / "checkpoints",
                self.step,
                self.model.state_dict(),
                meta={**self.checkpoint_meta, "trainer": asdict(self.config)},
                tensors=self.checkpoint_tensors,
                trainer_state=state,
                keep_last=self.config.keep_checkpoints,
            )
        if self.world_size > 1:
            dist.barrier()  # no rank runs ahead of a checkpoint it may be asked to resume from
        return self.last_checkpoint

    def resume(self, path: str | Path) -> None:
        """Continue from a checkpoint (or a directory's ``last`` one): weights and trainer state.

        Args:
            path (str | Path): a checkpoint, or a ``checkpoints/`` directory.

        Raises:
            RuntimeError: the checkpoint holds weights only, or was written by another number of
                ranks.
        """
        checkpoint = load_checkpoint(path)
        load_model_state(self.model, checkpoint)
        if checkpoint.trainer_state is None:
            raise RuntimeError(
                f"{checkpoint.path} holds weights only (no trainer state); it cannot be resumed"
            )
        self.load_state_dict(checkpoint.trainer_state)
        self.last_checkpoint = checkpoint.path

    # -- loop -------------------------------------------------------------------------------------

    def _batches(self):
        """Batches from the trainer's position on. It keeps its own position (it may run ahead on
        the prefetch thread); the trainer's advances as batches are taken (:meth:`_advance`)."""
        if len(self.loader) == 0:
            raise ValueError(
                "the training loader yields no batch: the training split has fewer windows than "
                "one batch per rank; lower the batch size or record more episodes"
            )
        epoch, skip = self.epoch, self.batch_in_epoch
        while True:
            self.loader.set_epoch(epoch)
            for index, batch in enumerate(self.loader):
                if index >= skip:  # resuming inside an epoch: replay up to where we were
                    yield batch
            epoch, skip = epoch + 1, 0

    @property
    def prefetching(self) -> bool:
        """Whether batches are made one step ahead (``config.prefetch``; ``"auto"``: on CUDA, or
        when worker processes make them)."""
        if self.config.prefetch == "auto":
            return self.device.type == "cuda" or self.batch_making == "in_workers"
        return bool(self.config.prefetch)

    def _advance(self) -> None:
        if self.batch_in_epoch >= len(self.loader):
            self.epoch, self.batch_in_epoch = self.epoch + 1, 0
        self.batch_in_epoch += 1

    def _batch_stream(self):
        if self.prefetching:
            return Prefetcher(self._batches(), self.device, threaded=self.batch_making != "global_rng")
        if self.device.type == "cpu":
            return self._batches()
        return (batch.to(self.device) for batch in self._batches())

    def _train_step(self, batch: TensorDictBase) -> dict[str, float] | None:
        """One update from ``batch``: its logged values, or ``None`` when its loss was non-finite
        (no update)."""
        total, losses = self.loss_step(batch)
        total_value = float(total.detach())
        any_nonfinite, worst = self._loss_over_ranks(total_value)
        if any_nonfinite:
            self._skip_nonfinite_step(losses)
            return None
        self._check_not_exploded(worst)
        self.nonfinite_in_a_row = 0
        self._update(total)
        logs = {k: float(v) for k, v in losses.items() if v.numel() == 1}
        logs["loss"] = total_value
        return logs

    def _loss_over_ranks(self, total_value: float) -> tuple[bool, float]:
        """(some rank's loss is non-finite, the largest finite loss of all ranks).

        Under DDP every rank must take the same decision (skip, stop or step) before backward, or
        the gradient all-reduce inside backward would wait forever. (A DDP forward without backward
        is fine: the next forward starts a new reduction.)"""
        finite = math.isfinite(total_value)
        status = torch.tensor([0.0 if finite else 1.0, total_value if finite else -math.inf])
        if self.world_size > 1:
            dist.all_reduce(status, op=dist.ReduceOp.MAX)
        return bool(status[0] > 0), float(status[1])

    def _skip_nonfinite_step(self, losses: TensorDictBase) -> None:
        """Count a step skipped for its non-finite loss; too many in a row stop the run."""
        self.nonfinite_in_a_row += 1
        self.nonfinite_total += 1
        if self.nonfinite_in_a_row <= self.config.max_nonfinite_steps:
            return
        bad = [k for k, v in losses.items() if k.startswith("loss_") and not torch.isfinite(v)]
        raise TrainingStopped(
            f"{self.nonfinite_in_a_row} steps in a row had a non-finite loss "
            f"({bad or 'on another rank'}); last at step {self.step}, epoch {self.epoch}, batch "
            f"{self.batch_in_epoch - 1}. Check that batch for NaN/Inf inputs, or lower trainer.lr. "
            f"Last good checkpoint: {self.last_checkpoint}"
        )

    def _check_not_exploded(self, worst: float) -> None:
        if worst > self.config.loss_explosion_threshold:
            raise TrainingStopped(
                f"loss exploded to {worst:.3g} at step {self.step} (threshold "
                f"trainer.loss_explosion_threshold={self.config.loss_explosion_threshold:g}); lower "
                f"trainer.lr or enable gradient clipping. Last good checkpoint: {self.last_checkpoint}"
            )

    def _update(self, total: torch.Tensor) -> None:
        """Backward, the post_loss hooks (gradient clipping among them), the optimizer and
        scheduler steps, the post_optim hooks."""
        self.optimizer.zero_grad(set_to_none=True)
        self.scaler.scale(total).backward()
        self.scaler.unscale_(self.optimizer)  # clipping and post_loss hooks see the true gradients
        for op in self.ops["post_loss"]:
            op(self)
        self.scaler.step(self.optimizer)
        self.scaler.update()
        self.scheduler.step()
        for op in self.ops["post_optim"]:
            op(self)

    def _evaluate(self) -> dict[str, float]:
        if self.evaluate is None:
            return {}
        was_training = self.model.training
        self.model.eval()
        with torch.no_grad():
            metrics = self.evaluate(self.model)
        self.model.train(was_training)
        name = self.config.early_stopping_metric
        if name not in metrics:
            if self.config.early_stopping_patience is not None:
                # Skipping it would silently train without early stopping.
                raise ValueError(
                    f"trainer.early_stopping_metric={name!r} is not among the evaluation's metrics "
                    f"{sorted(metrics)}; set it to one of them"
                )
            return metrics
        if metrics[name] < self.best_metric:
            self.best_metric, self.evals_without_improvement = metrics[name], 0
        else:
            self.evals_without_improvement += 1
        return metrics

    def _log(self, values: dict[str, float]) -> None:
        if self.logger is not None:
            for name, value in values.items():
                self.logger.log_scalar(name, value, step=self.step)

    def _log_window(self, window: dict[str, list[float]], rate: float, bar) -> None:
        """Log the averages of the steps since the last log, then start a new window."""
        averaged = {f"train/{k}": sum(v) / len(v) for k, v in window.items()}
        averaged["train/samples_per_s"] = rate
        averaged["train/lr"] = self.scheduler.get_last_lr()[0]
        self._log(averaged)
        self.history.append({"step": self.step, **averaged})
        for op in self.ops["post_steps_log"]:
            op(self, averaged)
        bar.set_postfix(loss=f"{averaged['train/loss']:.3f}", samples_s=f"{rate:.0f}")
        window.clear()

    def _stops_early(self) -> bool:
        cfg = self.config
        if (
            cfg.early_stopping_patience is None
            or self.evals_without_improvement <= cfg.early_stopping_patience
        ):
            return False
        logger.info(
            "early stopping at step %d: %s has not improved for %d evaluations (best %.4g)",
            self.step,
            cfg.early_stopping_metric,
            self.evals_without_improvement,
            self.best_metric,
        )
        return True

    def train(self) -> dict[str, float]:
        """Run until ``total_steps`` (or early stopping).

        Returns:
            The last evaluation's metrics (``{}`` without ``evaluate``).

        Raises:
            TrainingStopped: too many non-finite losses in a row, or an exploding loss.
            ValueError: early stopping on a metric ``evaluate`` does not return.
        """
        cfg = self.config
        self.model.train()
        self.loss_module.train()
        batches = self._batch_stream()
        # Outside autocast (evaluation, fp32) the hook leaves the outputs as they are.
        fp32_outputs = self.model.register_forward_hook(outputs_to_fp32) if cfg.precision != "fp32" else None
        window: dict[str, list[float]] = defaultdict(list)
        samples, started = 0, time.perf_counter()
        bar = tqdm(
            total=cfg.total_steps,
            initial=self.step,
            disable=not cfg.progress_bar or self.rank != 0,
            desc="train",
            unit="step",
            dynamic_ncols=True,
        )
        metrics: dict[str, float] = {}
        try:
            while self.step < cfg.total_steps:
                batch = next(batches)
                self._advance()
                for op in self.ops["batch_process"]:
                    batch = op(batch)
                logs = self._train_step(batch)
                if logs is None:
                    self._log({"train/nonfinite_steps": float(self.nonfinite_total)})
                    continue
                self.step += 1
                bar.update(1)
                samples += batch.shape[0] * self.world_size
                for k, v in logs.items():
                    window[k].append(v)
                for op in self.ops["post_steps"]:
                    op(self)
                if self.step % cfg.log_every == 0 or self.step == cfg.total_steps:
                    self._log_window(window, samples / max(time.perf_counter() - started, 1e-9), bar)
                last = self.step == cfg.total_steps
                if self.step % cfg.eval_every == 0 or last:
                    metrics = self._evaluate()
                    self._log(metrics)
                    if self._stops_early():
                        self.save()
                        break
                if self.step % cfg.checkpoint_every == 0 or last:
                    self.save()
        finally:
            bar.close()
            if isinstance(batches, Prefetcher):
                batches.close()  # first: its thread may be waiting on the loader's workers
            if hasattr(self.loader, "close"):
                self.loader.close()
            if fp32_outputs is not None:
                fp32_outputs.remove()
        if self.world_size > 1:
            self.check_replicas_agree()
        return metrics

    def check_replicas_agree(self, tolerance: float = 1e-6) -> float:
        """Every rank must hold rank 0's weights after data-parallel training; raise if not."""
        flat = torch.cat([p.detach().reshape(-1) for p in self.model.parameters()])
        reference = flat.clone()
        dist.broadcast(reference, src=0)
        gap = (flat - reference).abs().max()
        dist.all_reduce(gap, op=dist.ReduceOp.MAX)
        if gap > tolerance:
            raise RuntimeError(
                f"data-parallel ranks diverged: max weight difference {float(gap):.3g} after "
                f"{self.step} steps"
            )
        if self.rank == 0:
            logger.info(
                "data parallel: %d ranks agree after %d steps (max weight difference %.1e)",
                self.world_size,
                self.step,
                float(gap),
            )
        return float(gap)
