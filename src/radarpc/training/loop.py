"""One training loop for every model: AdamW with a learning-rate schedule, AMP on CUDA, validation
per epoch or every N steps, best checkpoint by a metric to maximise or minimise, exact resume, DDP
under torchrun, frozen submodules.

What a model brings is a :class:`Task` (its datasets, collate, loss and validation); the loop
owns everything else:

* **optimisation** -- AdamW (weight decay ``weight_decay``) over the parameters that require a
  gradient, with gradient clipping (``grad_clip_norm``) over the same parameters, and a schedule
  (:func:`scheduled_lr`, equations there): ``"onecycle"`` (torch's ``OneCycleLR``: from
  ``lr_start`` up to ``lr_max``, then cosine-annealed down to ``lr_start / 1e4``), ``"cosine"``
  (linear warm-up from ``lr_start`` to ``lr_max``, then a cosine decay to ``lr_min``) or
  ``"constant"`` (the same warm-up, then ``lr_max``). The warm-up lasts ``warmup_steps`` steps, or
  the share ``warmup_fraction`` of the run when ``warmup_steps`` is 0;
* **run length** -- ``epochs`` epochs, or with ``max_steps`` > 0 (and ``epochs`` 0) exactly
  ``max_steps`` optimizer steps, the epochs going on as needed and the last one cut short;
* **precision** -- ``"auto"`` is bf16 autocast on CUDA devices that support it, else fp16
  autocast with gradient scaling; on CPUs it is fp32 unless the CPU multiplies bf16 natively
  (AMX or AVX512-BF16), where bf16 autocast keeps fp32 weights and optimizer state. The
  precision a run starts in is stored in its checkpoints and kept on a resume, so ``"auto"`` does
  not switch precision when a run moves to another machine;
* **data** -- the order of epoch ``e`` is a permutation drawn from ``(seed, e)`` alone; global
  batch ``b`` holds the same items whatever the number of ranks (rank ``r`` of ``W`` takes its
  ``batch_size / W`` share), loaded in ``num_workers`` worker processes;
* **validation** -- at each epoch's end (``validate_every`` 0), or every ``validate_every``
  optimizer steps; in both cases also at the end of the run. ``Task.evaluate`` scores the
  validation set with the global RNG seeded from ``seed`` alone, so a validation that draws noise
  (a diffusion loss) draws the same noise every time;
* **selection** -- the best ``select_metric`` (the highest with ``select_mode`` ``"max"``, the
  lowest with ``"min"``, e.g. a validation loss) gives ``best.safetensors`` (weights, the run key,
  the step and epoch, the metrics, the software);
* **checkpoints** -- every ``checkpoint_every`` steps, at each epoch end and after each
  validation the whole state (weights, optimizer, scheduler, scaler, running sums, history, best
  score) is written atomically to ``checkpoints/last.safetensors``, and every rank's RNG is
  reseeded from ``(seed, rank, step)``; a rerun resumes there and skips the batches already done,
  so a run killed at any moment ends with the same weights, optimizer state and log as an
  uninterrupted one;
* **frozen parts** -- a model whose attribute ``frozen_submodules`` (:data:`FROZEN_ATTR`) names
  submodules (``("autoencoder",)``, dotted names as ``named_modules`` gives them), e.g. the
  pretrained first stage of a latent diffusion model, has them frozen: their parameters get
  ``requires_grad = False`` (so they stay out of the optimizer and of clipping) and the
  submodules stay in eval mode while the rest trains, so their BatchNorm statistics and dropout
  do not move either (:func:`frozen_submodules`). Checkpoints and ``best.safetensors`` hold the
  whole ``state_dict``, frozen weights included: a best file loads alone into the model, and a
  resumed run goes on with the frozen weights it started with even if the file the task loaded
  them from has changed since (they cost disk, not optimizer state);
* **weight averaging** -- with ``ema_decay`` > 0 the loop keeps an exponential moving average of
  the weights and buffers, updated after every optimizer step (see :func:`ema_decay_at`); it is
  what validation scores and what ``best.safetensors`` holds, and checkpoints carry it;
* **compilation** -- with ``compile`` the training forward and backward run through
  ``torch.compile`` (Inductor); the first steps pay the compilation, validation and checkpoints
  use the plain module, whose parameters the compiled one shares;
* **run key** -- ``run.json`` holds the caller's key, compared on a rerun (optionally read through
  a ``canonical_key`` function, so that a run started before a config field existed resumes), and
  ``"software"`` (:func:`~radarpc.training.checkpoint.software_record`: radarpc version, git
  commit of its source tree when available, torch version), recorded but not compared; weights
  files and checkpoints carry the same record;
* **logs** -- ``log.csv`` (one row per validation: step, epoch, learning rate of the last step,
  training time and the means of the training loss terms since the previous row, validation
  metrics; rewritten whole from the history), TensorBoard events in ``tb/`` when the
  ``tensorboard`` package is installed, a tqdm bar on rank 0;
* **DDP** -- under ``torchrun`` the model is wrapped in ``DistributedDataParallel`` (NCCL on
  CUDA, gloo on CPU); rank 0 alone writes files and validates, the others wait at barriers.
"""
from __future__ import annotations

import copy
import csv
import io
import math
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Protocol, Sequence

import numpy as np
import torch
import torch.distributed as torch_dist
from torch import nn
from torch.utils.data import DataLoader, Dataset
from tqdm import tqdm

from radarpc.distributed import DistEnv, dist_env, rank_device
from radarpc.io import atomic_write
from radarpc.machine import cpu_has_native_bf16
from radarpc.runs import RunFolder
from radarpc.training.checkpoint import (TrainingState, load_model_state, load_state, read_info, save_state,
                                         save_weights, software_record)

__all__ = ["PRECISIONS", "SCHEDULES", "SELECT_MODES", "FROZEN_ATTR", "TrainConfig", "Task", "FitResult",
           "epoch_batches", "resolve_precision", "autocast_context", "ema_decay_at", "scheduled_lr",
           "frozen_submodules", "fit", "training_status", "LAST_CHECKPOINT", "BEST_WEIGHTS", "LOG_CSV"]

PRECISIONS: tuple[str, ...] = ("auto", "fp32", "bf16", "fp16")
SCHEDULES: tuple[str, ...] = ("onecycle", "cosine", "constant")
SELECT_MODES: tuple[str, ...] = ("max", "min")
FROZEN_ATTR = "frozen_submodules"
"""The model attribute that names its frozen submodules (a sequence of ``named_modules`` names)."""
LAST_CHECKPOINT = Path("checkpoints") / "last.safetensors"
BEST_WEIGHTS = Path("best.safetensors")
LOG_CSV = Path("log.csv")
MAX_WORKERS = 256
"""The most loader processes a config may ask for (a million of them hung torch)."""
ONECYCLE_FINAL_DIV = 1e4
"""``OneCycleLR``'s ``final_div_factor``: the one-cycle schedule ends at ``lr_start / 1e4``."""


@dataclass(frozen=True)
class TrainConfig:
    """Optimisation and run settings shared by every model.

    ``batch_size`` is global: each of ``W`` torchrun ranks takes ``batch_size / W`` items. A run
    lasts ``epochs`` epochs, or, with ``max_steps`` > 0, exactly ``max_steps`` optimizer steps; then
    ``epochs`` must be 0, so that a config never holds a length it does not use.
    """

    epochs: int = 30                         # 0 when max_steps counts the run
    max_steps: int = 0                       # > 0: the run is this many optimizer steps (epochs 0)
    batch_size: int = 4
    eval_batch_size: int = 4
    schedule: str = "onecycle"               # one of SCHEDULES (see scheduled_lr)
    lr_start: float = 2.5e-4                 # warm-up: from here ...
    lr_max: float = 2.5e-3                   # ... up to here, then down (onecycle, cosine) or flat
    lr_min: float = 0.0                      # where "cosine" ends (the other schedules: 0)
    warmup_fraction: float = 0.3             # share of the steps spent rising to lr_max ...
    warmup_steps: int = 0                    # ... or, when > 0, that many steps
    weight_decay: float = 0.01
    grad_clip_norm: float = 0.0              # 0 = no clipping
    precision: str = "auto"                  # one of PRECISIONS
    seed: int = 0
    num_workers: int = 2                     # data-loading worker processes (0 = in the main process)
    checkpoint_every: int = 50               # steps between mid-epoch checkpoints
    validate_every: int = 0                  # 0 = validate at each epoch end; N = every N steps
    select_metric: str = "f1"                # validation metric of the best checkpoint ...
    select_mode: str = "max"                 # ... the highest ("max") or the lowest ("min")
    ema_decay: float = 0.0                   # weight averaging: 0 = off, else its decay (e.g. 0.999)
    compile: bool = False                    # torch.compile the training model (Inductor)

    def __post_init__(self) -> None:
        if int(self.max_steps) < 0:
            raise ValueError(f"train.max_steps must be >= 0 (0 = epochs count the run), got {self.max_steps}")
        if self.max_steps > 0 and self.epochs != 0:
            raise ValueError(f"train.max_steps={self.max_steps} counts the run in optimizer steps: set "
                             f"train.epochs to 0 (got {self.epochs}), or max_steps to 0 to count it in epochs")
        if self.max_steps == 0 and int(self.epochs) < 1:
            raise ValueError(f"train.epochs must be >= 1 (or 0 with train.max_steps > 0), got {self.epochs}")
        for name in ("batch_size", "eval_batch_size", "checkpoint_every"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"train.{name} must be >= 1, got {getattr(self, name)}")
        if int(self.validate_every) < 0:
            raise ValueError(f"train.validate_every must be >= 0 (0 = at each epoch end), got {self.validate_every}")
        if self.schedule not in SCHEDULES:
            raise ValueError(f"train.schedule must be one of {SCHEDULES}, got {self.schedule!r}")
        if self.select_mode not in SELECT_MODES:
            raise ValueError(f"train.select_mode must be one of {SELECT_MODES}, got {self.select_mode!r}")
        if not 0 < self.lr_start <= self.lr_max:
            raise ValueError(f"train: need 0 < lr_start <= lr_max, got {self.lr_start}, {self.lr_max}")
        if not 0 <= self.lr_min <= self.lr_max:
            raise ValueError(f"train: need 0 <= lr_min <= lr_max, got {self.lr_min}, {self.lr_max}")
        if self.lr_min > 0 and self.schedule != "cosine":
            raise ValueError(f"train.lr_min={self.lr_min} is where the 'cosine' schedule ends; "
                             f"schedule {self.schedule!r} does not use it (leave it 0)")
        if not 0.0 < self.warmup_fraction < 1.0:
            raise ValueError(f"train.warmup_fraction must be in (0, 1), got {self.warmup_fraction}")
        if int(self.warmup_steps) < 0:
            raise ValueError(f"train.warmup_steps must be >= 0 (0 = use warmup_fraction), got {self.warmup_steps}")
        if self.max_steps > 0 and self.warmup_steps >= self.max_steps:
            raise ValueError(f"train.warmup_steps={self.warmup_steps} must be below train.max_steps={self.max_steps}")
        if self.weight_decay < 0 or self.grad_clip_norm < 0 or self.num_workers < 0 or self.seed < 0:
            raise ValueError("train: weight_decay, grad_clip_norm, num_workers and seed must be >= 0")
        if self.num_workers > MAX_WORKERS:
            raise ValueError(f"train.num_workers={self.num_workers}: at most {MAX_WORKERS} loader processes "
                             f"(each holds a copy of the dataset object)")
        if not 0.0 <= self.ema_decay < 1.0:
            raise ValueError(f"train.ema_decay must be in [0, 1) (0 = no weight averaging), got {self.ema_decay}")
        if self.precision not in PRECISIONS:
            raise ValueError(f"train.precision must be one of {PRECISIONS}, got {self.precision!r}")

    def total_steps(self, steps_per_epoch: int) -> int:
        """Optimizer steps of the run, for an epoch of ``steps_per_epoch`` steps."""
        return self.max_steps if self.max_steps > 0 else self.epochs * steps_per_epoch

    def warmup(self, total_steps: int) -> float:
        """Warm-up length in steps of a run of ``total_steps``: ``warmup_steps``, or when it is 0
        ``warmup_fraction * total_steps`` (not rounded, as ``OneCycleLR`` takes it)."""
        if self.warmup_steps >= total_steps > 0:
            raise ValueError(f"train.warmup_steps={self.warmup_steps} must be below the run's {total_steps} steps")
        return float(self.warmup_steps) if self.warmup_steps > 0 else self.warmup_fraction * total_steps


class Task(Protocol):
    """What a model family gives the loop.

    ``loss`` runs the (possibly DDP-wrapped) model on a collated batch already on the device and
    returns the total loss and its named parts (floats, for the logs); ``evaluate`` scores the
    unwrapped model on validation batches and returns named metrics (``select_metric`` among
    them). ``to_device`` moves a collated batch. A ``train_set`` whose items depend on the epoch
    (random augmentation) has a ``set_epoch(epoch)`` method, called before each epoch's loader is
    built, as ``DistributedSampler.set_epoch``. The model ``build_model`` returns may name frozen
    submodules in its attribute ``frozen_submodules`` (see the module docstring).
    """

    train_set: Dataset
    val_set: Dataset

    def build_model(self) -> nn.Module: ...
    def collate(self, items: list) -> Any: ...
    def to_device(self, batch: Any, device: torch.device) -> Any: ...
    def loss(self, model: nn.Module, batch: Any) -> tuple[torch.Tensor, dict[str, float]]: ...
    def evaluate(self, model: nn.Module, batches: Iterable, device: torch.device) -> dict[str, float]: ...


@dataclass
class FitResult:
    """The outcome of :func:`fit`: where the run is, its best validation score, where that was
    (epoch and optimizer step), and the validation history (the rows of ``log.csv``)."""

    out: Path
    best_score: float
    best_epoch: int
    history: list[dict[str, float]] = field(default_factory=list)
    resumed_from_step: int = 0
    best_step: int = -1

    @property
    def best_row(self) -> dict[str, float] | None:
        """The history row of the best validation (None before any)."""
        return next((r for r in self.history if r["step"] == self.best_step), None)


# ---- pieces ---------------------------------------------------------------------------------------
def epoch_batches(n_items: int, batch_size: int, seed: int, epoch: int, env: DistEnv = DistEnv()
                  ) -> list[list[int]]:
    """This rank's index batches of epoch ``epoch``: a seeded permutation cut into global batches.

    Global batch ``b`` is ``perm[b B:(b+1) B]`` (``B = batch_size``, the incomplete tail dropped);
    rank ``r`` of ``W`` takes its ``r``-th slice of ``B / W`` items.
    """
    if batch_size % env.world_size:
        raise ValueError(f"train.batch_size={batch_size} must be a multiple of the number of ranks "
                         f"({env.world_size})")
    if n_items < batch_size:
        raise ValueError(f"the training set has {n_items} items, fewer than one batch of {batch_size}")
    g = torch.Generator().manual_seed(int(np.random.SeedSequence([seed, epoch]).generate_state(1)[0]))
    perm = torch.randperm(n_items, generator=g).tolist()
    per_rank = batch_size // env.world_size
    lo = env.rank * per_rank
    return [perm[b * batch_size + lo: b * batch_size + lo + per_rank] for b in range(n_items // batch_size)]


def resolve_precision(precision: str, device: torch.device) -> str:
    """The precision ``"auto"`` means on ``device`` (see the module docstring); others unchanged."""
    if precision != "auto":
        if precision == "fp16" and device.type != "cuda":
            raise ValueError("train.precision='fp16' needs a CUDA device (gradient scaling); use bf16 or fp32")
        return precision
    if device.type == "cuda":
        return "bf16" if torch.cuda.is_bf16_supported() else "fp16"
    return "bf16" if device.type == "cpu" and cpu_has_native_bf16() else "fp32"


def autocast_context(precision: str, device: torch.device):
    """The autocast context of a resolved ``precision`` on ``device`` (``"fp32"``: autocast off)."""
    if precision == "fp32":
        return torch.autocast(device.type, enabled=False)
    return torch.autocast(device.type, dtype=torch.bfloat16 if precision == "bf16" else torch.float16)


def ema_decay_at(step: int, ema_decay: float) -> float:
    r"""Decay of the weight average at optimizer step ``step`` (1-based).

    The average after step :math:`n` is

    .. math:: \bar\theta_n = \beta_n \bar\theta_{n-1} + (1 - \beta_n) \theta_n, \qquad
              \beta_n = \min\left(\beta, \frac{1 + n}{10 + n}\right),

    with :math:`\beta` = ``ema_decay``. The ramp keeps the first steps' weights, still near the
    random initialisation, from weighing on an average a short run reads after a few hundred
    steps (with a fixed 0.999, step 1 would still carry half the weight at step 700).
    """
    if step < 1:
        raise ValueError(f"step is 1-based, got {step}")
    return min(ema_decay, (1.0 + step) / (10.0 + step))


@torch.no_grad()
def _ema_update(average: nn.Module, model: nn.Module, beta: float) -> None:
    # buffers too: batch-norm statistics averaged with the weights they normalise
    current = model.state_dict()
    for name, a in average.state_dict().items():
        if a.is_floating_point():
            a.lerp_(current[name], 1.0 - beta)
        else:
            a.copy_(current[name])


def scheduled_lr(schedule: str, step: int, total_steps: int, warmup: float, lr_start: float, lr_max: float,
                 lr_min: float = 0.0) -> float:
    r"""Learning rate of the optimizer step that follows ``step`` steps (``step`` = 0: the first).

    With :math:`s` = ``step``, :math:`T` = ``total_steps``, :math:`W` = ``warmup`` (steps, may be
    fractional), :math:`\ell_0` = ``lr_start``, :math:`\ell_1` = ``lr_max``, :math:`\ell_2` = ``lr_min``
    and :math:`c(p) = \tfrac12 (1 + \cos \pi p)` (1 at :math:`p = 0`, 0 at :math:`p = 1`):

    ``"cosine"`` -- a linear warm-up, then a cosine decay that reaches :math:`\ell_2` at :math:`s = T`
    (one step after the last, so the last step is not wasted at :math:`\ell_2 = 0`):

    .. math:: \ell(s) = \begin{cases} \ell_0 + (\ell_1 - \ell_0)\, s / W & s < W \\
              \ell_2 + (\ell_1 - \ell_2)\, c\!\left(\min\left(1, \frac{s - W}{T - W}\right)\right) & s \ge W
              \end{cases}

    ``"constant"`` -- the same warm-up, then :math:`\ell(s) = \ell_1` for :math:`s \ge W`.

    ``"onecycle"`` -- torch's ``OneCycleLR`` with cosine annealing (``lr_min`` unused): it rises
    until step :math:`a = W - 1` and ends at :math:`\ell_e = \ell_0 / 10^4` on the last step
    :math:`s = T - 1`:

    .. math:: \ell(s) = \begin{cases} \ell_1 + (\ell_0 - \ell_1)\, c(s / a) & s \le a \\
              \ell_e + (\ell_1 - \ell_e)\, c\!\left(\frac{s - a}{T - 1 - a}\right) & s > a
              \end{cases}

    The loop drives ``"cosine"`` and ``"constant"`` through ``LambdaLR`` with the factor
    :math:`\ell(s) / \ell_1` (its state, a step count, resumes exactly) and ``"onecycle"`` through
    ``OneCycleLR`` itself, which this equation matches to rounding.
    """
    if schedule not in SCHEDULES:
        raise ValueError(f"schedule must be one of {SCHEDULES}, got {schedule!r}")
    if step < 0 or total_steps < 1:
        raise ValueError(f"need step >= 0 and total_steps >= 1, got {step}, {total_steps}")
    if not 0 <= warmup < total_steps:
        raise ValueError(f"the warm-up ({warmup} steps) must be in [0, total_steps={total_steps})")

    def c(p: float) -> float:
        return (math.cos(math.pi * p) + 1.0) / 2.0

    if schedule == "onecycle":
        a, end = warmup - 1.0, lr_start / ONECYCLE_FINAL_DIV
        if step <= a:
            return lr_max + (lr_start - lr_max) * c(step / a)
        return end + (lr_max - end) * c((step - a) / (total_steps - 1 - a))
    if step < warmup:
        return lr_start + (lr_max - lr_start) * step / warmup
    if schedule == "constant":
        return lr_max
    return lr_min + (lr_max - lr_min) * c(min(1.0, (step - warmup) / (total_steps - warmup)))


def _scheduler(optimizer: torch.optim.Optimizer, cfg: TrainConfig,
               total_steps: int) -> torch.optim.lr_scheduler.LRScheduler:
    """The scheduler of ``cfg.schedule`` over ``total_steps`` (the optimizer's lr is ``lr_max``)."""
    warmup = cfg.warmup(total_steps)
    if cfg.schedule == "onecycle":
        return torch.optim.lr_scheduler.OneCycleLR(
            optimizer, max_lr=cfg.lr_max, total_steps=total_steps,
            pct_start=cfg.warmup_fraction if cfg.warmup_steps == 0 else warmup / total_steps,
            anneal_strategy="cos", div_factor=cfg.lr_max / cfg.lr_start, cycle_momentum=False)
    return torch.optim.lr_scheduler.LambdaLR(optimizer, lambda s: scheduled_lr(
        cfg.schedule, s, total_steps, warmup, cfg.lr_start, cfg.lr_max, cfg.lr_min) / cfg.lr_max)


def frozen_submodules(model: nn.Module) -> list[nn.Module]:
    """Freeze and return the submodules ``model`` names in its ``frozen_submodules`` attribute.

    Their parameters get ``requires_grad = False``; the loop keeps the modules in eval mode while
    the rest of the model trains. A model without the attribute freezes nothing.

    Raises
    ------
    ValueError
        The attribute is a string rather than a sequence of names, names the model itself
        (``""``: nothing would train), or names no submodule.
    """
    names = getattr(model, FROZEN_ATTR, ())
    if isinstance(names, str):
        raise ValueError(f"{type(model).__name__}.{FROZEN_ATTR} must be a sequence of submodule names, "
                         f"got the string {names!r}")
    out = []
    for name in names:
        if not name:
            raise ValueError(f"{type(model).__name__}.{FROZEN_ATTR} names the model itself ({name!r}); "
                             "name the submodules to freeze")
        try:
            module = model.get_submodule(name)
        except AttributeError:
            raise ValueError(f"{type(model).__name__}.{FROZEN_ATTR} names {name!r}, which is not a submodule "
                             f"of the model") from None
        module.requires_grad_(False)
        out.append(module)
    return out


def _reseed(seed: int, rank: int, step: int) -> None:
    """Seed this rank's global RNGs (dropout and the like) from ``(seed, rank, step)``.

    Done at the start and at every checkpoint, in an uninterrupted run as in a resumed one, so
    the random stream after a checkpoint does not depend on what ran before it, on any number
    of ranks (each rank draws its own stream), and no RNG state needs saving.
    """
    torch.manual_seed(int(np.random.SeedSequence([seed, rank, step]).generate_state(1)[0]))


def _write_log(path: Path, history: list[dict[str, float]]) -> None:
    keys: list[str] = []
    for row in history:
        keys += [k for k in row if k not in keys]
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=keys, lineterminator="\n")
    w.writeheader()
    for row in history:
        w.writerow({k: repr(v) if isinstance(v, float) else v for k, v in row.items()})
    with atomic_write(path, "w") as f:
        f.write(buf.getvalue())


def _tensorboard(out: Path, purge_step: int):
    try:
        from torch.utils.tensorboard import SummaryWriter
    except ImportError:                    # optional: CSV logs are always written
        return None
    # purge_step drops events a killed run logged after its last checkpoint
    return SummaryWriter(str(out / "tb"), purge_step=purge_step)


def _barrier(env: DistEnv) -> None:
    if env.world_size > 1:
        torch_dist.barrier()


def _all_reduce_mean(values: dict[str, float], env: DistEnv, device: torch.device) -> dict[str, float]:
    if env.world_size == 1 or not values:
        return values
    keys = sorted(values)
    t = torch.tensor([values[k] for k in keys], dtype=torch.float64, device=device)
    torch_dist.all_reduce(t)
    return {k: float(v) / env.world_size for k, v in zip(keys, t.tolist())}


# ---- the loop -------------------------------------------------------------------------------------
def fit(task: Task, cfg: TrainConfig, out: str | os.PathLike, run_key: dict, *,
        device: torch.device | str | None = None, overwrite: bool = False, progress: bool = True,
        log: Callable[[str], None] = print, extra_outputs: Sequence[str] = (),
        on_step: Callable[[int], None] | None = None,
        canonical_key: Callable[[dict], dict] | None = None, locators: Sequence[str] = ()) -> FitResult:
    """Train ``task``'s model in the run folder ``out`` (resumed when it holds the same run).

    Parameters
    ----------
    task : Task
        Datasets, collate, loss and validation of the model.
    cfg : TrainConfig
    out : path-like
        Run folder. Without ``overwrite`` a non-empty folder must hold the same ``run_key``; the
        run then resumes from its last checkpoint (or returns at once if it finished).
    run_key : dict
        JSON-able settings that identify the run (the resolved experiment config): stored in
        ``run.json``, compared on a rerun, and written into every weights file. ``run.json`` also
        records ``"software"`` (not compared), a key ``run_key`` must not hold.
    device : torch.device or str, optional
        Default: ``cuda:LOCAL_RANK`` when CUDA is available, else the CPU.
    overwrite : bool
        Start over, deleting the run's own files.
    progress : bool
        tqdm bar on rank 0.
    log : callable
        Where rank 0's one-line messages go.
    extra_outputs : sequence of str
        Other files the caller writes into ``out`` (``overwrite`` removes them too).
    on_step : callable, optional
        Called with the global step after each optimizer step (tests use it to interrupt).
    canonical_key : callable, optional
        Reads a stored key (``run.json`` without ``"software"``) as this code writes it, e.g.
        through the config type so that fields added since the run started take their defaults;
        applied before the comparison (:class:`~radarpc.runs.RunFolder` ``canonical``). Without
        it the stored key is compared as it is, and a field it lacks reads as missing.
    locators : sequence of str
        Dotted keys of ``run_key`` that say where a run it refers to lives (``"ae.path"``): not
        compared, and updated in ``run.json`` when the run resumes (:class:`~radarpc.runs.RunFolder`).

    Returns
    -------
    FitResult
    """
    if "software" in run_key:
        raise ValueError("run_key holds 'software', which fit records itself in run.json")
    env = dist_env()
    device = rank_device(device, env)
    out = Path(out)
    precision = resolve_precision(cfg.precision, device)
    software = software_record()
    if env.world_size > 1 and not torch_dist.is_initialized():
        torch_dist.init_process_group(backend="nccl" if device.type == "cuda" else "gloo")
    if device.type == "cuda":
        torch.cuda.set_device(device)

    run = None
    if env.rank == 0:
        # evaluations of the weights (radarpc evaluate's eval_* and figures) go with them
        run = RunFolder(out, {"run.json": {**run_key, "software": software}}, what="training run", indent=2,
                        ignore_keys=("software",), locators=locators,
                        canonical=None if canonical_key is None else {"run.json": canonical_key},
                        owned=("run.json", "checkpoints", str(BEST_WEIGHTS), str(LOG_CSV), "tb",
                               "eval_*", "figures", *extra_outputs))
        run.start(overwrite=overwrite, resume=not overwrite)
    _barrier(env)
    try:
        return _fit(task, cfg, out, run_key, software, env, device, precision, progress, log, on_step)
    finally:
        if run is not None:
            run.close()


_VALIDATION_STREAM = 0x76616C            # "val": the RNG stream validations draw from


def _fit(task: Task, cfg: TrainConfig, out: Path, run_key: dict, software: dict, env: DistEnv,
         device: torch.device, precision: str, progress: bool, log: Callable[[str], None],
         on_step: Callable[[int], None] | None) -> FitResult:
    torch.manual_seed(cfg.seed)
    model = task.build_model().to(device)
    frozen = frozen_submodules(model)
    trainable = [p for p in model.parameters() if p.requires_grad]
    if not trainable:
        raise ValueError(f"{out}: the model has no parameter that requires a gradient; nothing to train")
    n_train = len(task.train_set)
    steps_per_epoch = len(epoch_batches(n_train, cfg.batch_size, cfg.seed, 0, env))
    total_steps = cfg.total_steps(steps_per_epoch)
    optimizer = torch.optim.AdamW(trainable, lr=cfg.lr_max, weight_decay=cfg.weight_decay)
    scheduler = _scheduler(optimizer, cfg, total_steps)
    minimize = cfg.select_mode == "min"
    by_step = cfg.validate_every > 0

    info: dict[str, Any] = {"epoch": 0, "batch_in_epoch": 0, "step": 0, "sums": {}, "n_sums": 0,
                            "history": [], "best_score": math.inf if minimize else -math.inf,
                            "best_epoch": -1, "best_step": -1, "finished": False, "precision": precision}
    last = out / LAST_CHECKPOINT
    state = load_state(last) if last.is_file() else None
    if state is not None:
        # "auto" resolves per machine (bf16 where the CPU has it, fp32 elsewhere); a resumed run
        # keeps the precision it started in, or its final weights would depend on where it ran
        started = state.info.setdefault("precision", precision)     # older checkpoints: as before
        if started != precision:
            try:
                precision = resolve_precision(started, device)
            except ValueError as e:
                raise ValueError(f"{out}: the run started in {started} and cannot resume on {device}: {e}") from None
            if env.rank == 0:
                log(f"{out}: resuming in {started}, the precision the run started in "
                    f"(train.precision {cfg.precision!r} on {device} alone would mean {info['precision']})")
    scaler = torch.amp.GradScaler(device.type) if precision == "fp16" else None
    average: nn.Module | None = None
    if cfg.ema_decay > 0:
        average = copy.deepcopy(model).requires_grad_(False).eval()
    if state is not None:
        load_model_state(model, state.model, last, "this run's model (another model's checkpoint? start over with "
                                                    "--overwrite, or train in another folder)")
        if average is not None:
            if state.ema is None:
                raise ValueError(f"{last}: the checkpoint holds no weight average, but train.ema_decay is "
                                 f"{cfg.ema_decay}; resume with the config the run started with")
            load_model_state(average, state.ema, last, "this run's model (its weight average)")
        optimizer.load_state_dict(state.optimizer)
        scheduler.load_state_dict(state.scheduler)
        if scaler is not None and state.scaler:
            scaler.load_state_dict(state.scaler)
        info = state.info
        if "best_step" not in info:          # checkpoints written before step-based validation
            info["best_step"] = next((r["step"] for r in info["history"] if r["epoch"] == info["best_epoch"]), -1)
        if env.rank == 0:
            log(f"{out}: resuming at epoch {info['epoch']}, step {info['step']} of {total_steps}")
    elif env.rank == 0:
        log(f"{out}: {total_steps} steps on {device}, precision {precision}"
            + (f" (train.precision {cfg.precision!r})" if cfg.precision != precision else ""))
        if frozen:
            n_frozen = sum(p.numel() for m in frozen for p in m.parameters())
            log(f"{out}: {', '.join(getattr(model, FROZEN_ATTR))} frozen ({n_frozen} parameters in eval "
                f"mode), {sum(p.numel() for p in trainable)} parameters trained")
    resumed_from = int(info["step"])
    _reseed(cfg.seed, env.rank, info["step"])

    def result() -> FitResult:
        return FitResult(out, info["best_score"], info["best_epoch"], info["history"], resumed_from,
                         info["best_step"])

    if info["finished"]:
        if env.rank == 0:
            where = f"step {info['best_step']}" if by_step else f"epoch {info['best_epoch']}"
            log(f"{out}: already finished (best {cfg.select_metric} {info['best_score']:.4f} at {where})")
        return result()

    net: nn.Module = model
    if env.world_size > 1:
        net = nn.parallel.DistributedDataParallel(
            model, device_ids=[device.index] if device.type == "cuda" else None)
    if cfg.compile:
        net = torch.compile(net)        # DDP first: Dynamo then splits the graph at DDP's gradient buckets

    def train_mode() -> None:
        net.train()
        for m in frozen:                # a frozen first stage: no BatchNorm statistics, no dropout
            m.eval()

    def checkpoint() -> None:
        if env.rank == 0:
            save_state(last, TrainingState(
                model=model.state_dict(), optimizer=optimizer.state_dict(), scheduler=scheduler.state_dict(),
                scaler=scaler.state_dict() if scaler is not None else None, info=info,
                ema=average.state_dict() if average is not None else None))
        _barrier(env)
        _reseed(cfg.seed, env.rank, info["step"])

    tb = _tensorboard(out, info["step"]) if env.rank == 0 else None

    def validate(epoch: int, lr_used: float, train_time: float) -> None:
        """One row of the history: the training means since the previous row and the validation
        metrics; the best weights when they improve. A checkpoint follows (and reseeds)."""
        train_means = _all_reduce_mean({k: v / max(info["n_sums"], 1) for k, v in info["sums"].items()},
                                       env, device)
        row: dict[str, Any] = {"epoch": epoch, "step": info["step"], "lr": lr_used, "train_time_s": train_time}
        row.update({f"train_{k}": v for k, v in train_means.items()})
        if env.rank == 0:
            scored = model if average is None else average
            scored.eval()
            # loaders get their own generator: creating one must not draw from the global RNG;
            # a fresh one each time, so that every validation loads alike
            val_loader = DataLoader(task.val_set, batch_size=cfg.eval_batch_size, shuffle=False,
                                    collate_fn=task.collate, num_workers=cfg.num_workers,
                                    generator=torch.Generator().manual_seed(cfg.seed))
            torch.manual_seed(int(np.random.SeedSequence([cfg.seed, _VALIDATION_STREAM]).generate_state(1)[0]))
            with torch.no_grad(), autocast_context(precision, device):
                metrics = task.evaluate(scored, val_loader, device)
            if cfg.select_metric not in metrics:
                raise KeyError(f"validation gave {sorted(metrics)}, no train.select_metric "
                               f"{cfg.select_metric!r}")
            row.update({f"val_{k}": float(v) for k, v in metrics.items()})
            score = float(metrics[cfg.select_metric])
            if (score < info["best_score"]) if minimize else (score > info["best_score"]):
                info["best_score"], info["best_epoch"], info["best_step"] = score, epoch, info["step"]
                save_weights(out / BEST_WEIGHTS, scored.state_dict(),
                             {"run": run_key, "epoch": epoch, "step": info["step"], "precision": precision,
                              "weights": "model" if average is None else "ema",
                              "metrics": {k: float(v) for k, v in metrics.items()}, "software": software})
            if tb is not None:
                for k, v in row.items():
                    if k not in ("epoch", "step"):
                        tb.add_scalar(f"{'validation' if by_step else 'epoch'}/{k}", v, info["step"])
            with tqdm.external_write_mode():     # on a line of its own, above the progress bar
                if by_step:
                    log(f"step {info['step']} (epoch {epoch}): loss {row['train_loss']:.4f}, val "
                        f"{cfg.select_metric} {score:.4f} (best {info['best_score']:.4f} at step {info['best_step']})")
                else:
                    log(f"epoch {epoch}: loss {row['train_loss']:.4f}, val {cfg.select_metric} {score:.4f} "
                        f"(best {info['best_score']:.4f} at epoch {info['best_epoch']})")
        info["history"].append(row)
        info.update(sums={}, n_sums=0)
        if env.rank == 0:
            # the best score lives on rank 0; the others learn it from the checkpoint on a resume
            _write_log(out / LOG_CSV, info["history"])

    bar = tqdm(total=total_steps, initial=info["step"], desc=f"train {out.name}", unit="step",
               disable=not progress or env.rank != 0)
    lr_used = math.nan                   # the learning rate of the last step (logged with a row)
    train_time = 0.0                     # training time since the last row, without validations
    try:
        while info["step"] < total_steps:
            epoch = info["epoch"]
            batches = epoch_batches(n_train, cfg.batch_size, cfg.seed, epoch, env)[info["batch_in_epoch"]:]
            batches = batches[:total_steps - info["step"]]          # a step-counted run ends inside an epoch
            if hasattr(task.train_set, "set_epoch"):
                task.train_set.set_epoch(epoch)
            loader = DataLoader(task.train_set, batch_sampler=batches, collate_fn=task.collate,
                                num_workers=cfg.num_workers,
                                generator=torch.Generator().manual_seed(cfg.seed + epoch))
            train_mode()
            t0 = time.perf_counter()
            for batch in loader:
                batch = task.to_device(batch, device)
                with autocast_context(precision, device):
                    loss, parts = task.loss(net, batch)
                if not torch.isfinite(loss):
                    raise FloatingPointError(f"{out}: non-finite training loss at step {info['step']} "
                                             f"(epoch {epoch}); lower train.lr_max or check the inputs")
                optimizer.zero_grad(set_to_none=True)
                if scaler is not None:
                    scaler.scale(loss).backward()
                    scaler.unscale_(optimizer)
                else:
                    loss.backward()
                if cfg.grad_clip_norm > 0:
                    nn.utils.clip_grad_norm_(trainable, cfg.grad_clip_norm)
                if scaler is not None:
                    scaler.step(optimizer)
                    scaler.update()
                else:
                    optimizer.step()
                lr_used = optimizer.param_groups[0]["lr"]
                scheduler.step()
                parts = {"loss": float(loss.detach()), **parts}
                for k, v in parts.items():
                    info["sums"][k] = info["sums"].get(k, 0.0) + float(v)
                info["n_sums"] += 1
                info["step"] += 1
                if average is not None:
                    _ema_update(average, model, ema_decay_at(info["step"], cfg.ema_decay))
                info["batch_in_epoch"] += 1
                bar.update(1)
                bar.set_postfix(loss=f"{parts['loss']:.4f}", epoch=epoch)
                if tb is not None:
                    tb.add_scalar("train/loss", parts["loss"], info["step"])
                    tb.add_scalar("train/lr", lr_used, info["step"])
                if on_step is not None:
                    on_step(info["step"])
                if info["batch_in_epoch"] == steps_per_epoch or info["step"] == total_steps:
                    continue             # the loader's last batch: the epoch's or the run's end, below
                if by_step and info["step"] % cfg.validate_every == 0:
                    validate(epoch, lr_used, train_time + time.perf_counter() - t0)
                    train_mode()
                    checkpoint()
                    train_time, t0 = 0.0, time.perf_counter()
                elif info["step"] % cfg.checkpoint_every == 0:
                    checkpoint()

            # the end of the epoch, or of the run inside its last epoch
            train_time += time.perf_counter() - t0
            finished = info["step"] == total_steps
            if not by_step or finished or info["step"] % cfg.validate_every == 0:
                validate(epoch, lr_used, train_time)
                train_time = 0.0
            if info["batch_in_epoch"] == steps_per_epoch:
                info.update(epoch=epoch + 1, batch_in_epoch=0)
            info["finished"] = finished
            checkpoint()
    finally:
        bar.close()
        if tb is not None:
            tb.close()
    return result()


def training_status(folder: str | os.PathLike) -> dict:
    """Where a run folder's best weights come from: ``{"weights_epoch", "weights_step", "finished",
    "epochs_done", "steps_done"}``. ``finished`` is None for weights not trained in this folder (no
    checkpoint: an imported run), False while the run's last checkpoint says it has steps left (a
    killed or running run)."""
    folder = Path(folder)
    _, best = read_info(folder / BEST_WEIGHTS)
    status = {"weights_epoch": best.get("epoch"), "weights_step": best.get("step"), "finished": None,
              "epochs_done": None, "steps_done": None}
    last = folder / LAST_CHECKPOINT
    if last.is_file():
        _, progress = read_info(last)
        status.update(finished=bool(progress.get("finished")), epochs_done=progress.get("epoch"),
                      steps_done=progress.get("step"))
    return status
