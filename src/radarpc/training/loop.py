"""One training loop for every model: AdamW + OneCycle, AMP on CUDA, validation every epoch,
best checkpoint, exact resume, DDP under torchrun.

What a model brings is a :class:`Task` (its datasets, collate, loss and validation); the loop
owns everything else:

* **optimisation** -- AdamW (weight decay ``weight_decay``) and a OneCycle schedule from
  ``lr_start`` up to ``lr_max`` and cosine-annealed down over all steps;
* **precision** -- ``"auto"`` is bf16 autocast on CUDA devices that support it, else fp16
  autocast with gradient scaling; on CPUs it is fp32 unless the CPU multiplies bf16 natively
  (AMX or AVX512-BF16), where bf16 autocast keeps fp32 weights and optimizer state. The
  precision a run starts in is stored in its checkpoints and kept on a resume, so ``"auto"`` does
  not switch precision when a run moves to another machine;
* **data** -- the order of epoch ``e`` is a permutation drawn from ``(seed, e)`` alone; global
  batch ``b`` holds the same items whatever the number of ranks (rank ``r`` of ``W`` takes its
  ``batch_size / W`` share), loaded in ``num_workers`` worker processes;
* **checkpoints** -- every ``checkpoint_every`` steps and at each epoch end the whole state
  (weights, optimizer, scheduler, scaler, running sums, history) is written atomically to
  ``checkpoints/last.safetensors``, and every rank's RNG is reseeded from ``(seed, rank, step)``;
  a rerun resumes there and skips the batches already done, so a run killed at any moment ends
  with the same weights as an uninterrupted one;
* **weight averaging** -- with ``ema_decay`` > 0 the loop keeps an exponential moving average of
  the weights and buffers, updated after every optimizer step (see :func:`ema_decay_at`); it is
  what validation scores and what ``best.safetensors`` holds, and checkpoints carry it;
* **compilation** -- with ``compile`` the training forward and backward run through
  ``torch.compile`` (Inductor); the first steps pay the compilation, validation and checkpoints
  use the plain module, whose parameters the compiled one shares;
* **selection** -- after each epoch ``Task.evaluate`` scores the validation set; the best
  ``select_metric`` gives ``best.safetensors`` (weights and the resolved config);
* **logs** -- ``log.csv`` (one row per epoch, rewritten whole from the history), TensorBoard
  events in ``tb/`` when the ``tensorboard`` package is installed, a tqdm bar on rank 0;
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
from radarpc.training.checkpoint import TrainingState, load_state, save_state, save_weights

__all__ = ["PRECISIONS", "TrainConfig", "Task", "FitResult", "epoch_batches", "resolve_precision",
           "autocast_context", "ema_decay_at", "fit", "LAST_CHECKPOINT", "BEST_WEIGHTS", "LOG_CSV"]

PRECISIONS: tuple[str, ...] = ("auto", "fp32", "bf16", "fp16")
LAST_CHECKPOINT = Path("checkpoints") / "last.safetensors"
BEST_WEIGHTS = Path("best.safetensors")
LOG_CSV = Path("log.csv")


@dataclass(frozen=True)
class TrainConfig:
    """Optimisation and run settings shared by every model.

    ``batch_size`` is global: each of ``W`` torchrun ranks takes ``batch_size / W`` items.
    """

    epochs: int = 30
    batch_size: int = 4
    eval_batch_size: int = 4
    lr_start: float = 2.5e-4                 # OneCycle: from here ...
    lr_max: float = 2.5e-3                   # ... up to here, then cosine down
    warmup_fraction: float = 0.3             # share of the steps spent rising to lr_max
    weight_decay: float = 0.01
    grad_clip_norm: float = 0.0              # 0 = no clipping
    precision: str = "auto"                  # one of PRECISIONS
    seed: int = 0
    num_workers: int = 2                     # data-loading worker processes (0 = in the main process)
    checkpoint_every: int = 50               # steps between mid-epoch checkpoints
    select_metric: str = "f1"                # validation metric of the best checkpoint (higher is better)
    ema_decay: float = 0.0                   # weight averaging: 0 = off, else its decay (e.g. 0.999)
    compile: bool = False                    # torch.compile the training model (Inductor)

    def __post_init__(self) -> None:
        for name in ("epochs", "batch_size", "eval_batch_size", "checkpoint_every"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"train.{name} must be >= 1, got {getattr(self, name)}")
        if not 0 < self.lr_start <= self.lr_max:
            raise ValueError(f"train: need 0 < lr_start <= lr_max, got {self.lr_start}, {self.lr_max}")
        if not 0.0 < self.warmup_fraction < 1.0:
            raise ValueError(f"train.warmup_fraction must be in (0, 1), got {self.warmup_fraction}")
        if self.weight_decay < 0 or self.grad_clip_norm < 0 or self.num_workers < 0 or self.seed < 0:
            raise ValueError("train: weight_decay, grad_clip_norm, num_workers and seed must be >= 0")
        if not 0.0 <= self.ema_decay < 1.0:
            raise ValueError(f"train.ema_decay must be in [0, 1) (0 = no weight averaging), got {self.ema_decay}")
        if self.precision not in PRECISIONS:
            raise ValueError(f"train.precision must be one of {PRECISIONS}, got {self.precision!r}")


class Task(Protocol):
    """What a model family gives the loop.

    ``loss`` runs the (possibly DDP-wrapped) model on a collated batch already on the device and
    returns the total loss and its named parts (floats, for the logs); ``evaluate`` scores the
    unwrapped model on validation batches and returns named metrics (``select_metric`` among
    them). ``to_device`` moves a collated batch. A ``train_set`` whose items depend on the epoch
    (random augmentation) has a ``set_epoch(epoch)`` method, called before each epoch's loader is
    built, as ``DistributedSampler.set_epoch``.
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
    """The outcome of :func:`fit`: where the run is, its best validation score and epoch history."""

    out: Path
    best_score: float
    best_epoch: int
    history: list[dict[str, float]] = field(default_factory=list)
    resumed_from_step: int = 0


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
        on_step: Callable[[int], None] | None = None) -> FitResult:
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
        ``run.json``, compared on a rerun, and written into every weights file.
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

    Returns
    -------
    FitResult
    """
    env = dist_env()
    device = rank_device(device, env)
    out = Path(out)
    precision = resolve_precision(cfg.precision, device)
    if env.world_size > 1 and not torch_dist.is_initialized():
        torch_dist.init_process_group(backend="nccl" if device.type == "cuda" else "gloo")
    if device.type == "cuda":
        torch.cuda.set_device(device)

    run = None
    if env.rank == 0:
        # evaluations of the weights (radarpc evaluate's eval_* and figures) go with them
        run = RunFolder(out, {"run.json": run_key}, what="training run", indent=2,
                        owned=("run.json", "checkpoints", str(BEST_WEIGHTS), str(LOG_CSV), "tb",
                               "eval_*", "figures", *extra_outputs))
        run.start(overwrite=overwrite, resume=not overwrite)
    _barrier(env)
    try:
        return _fit(task, cfg, out, run_key, env, device, precision, progress, log, on_step)
    finally:
        if run is not None:
            run.close()


def _fit(task: Task, cfg: TrainConfig, out: Path, run_key: dict, env: DistEnv, device: torch.device,
         precision: str, progress: bool, log: Callable[[str], None],
         on_step: Callable[[int], None] | None) -> FitResult:
    torch.manual_seed(cfg.seed)
    model = task.build_model().to(device)
    n_train = len(task.train_set)
    steps_per_epoch = len(epoch_batches(n_train, cfg.batch_size, cfg.seed, 0, env))
    total_steps = cfg.epochs * steps_per_epoch
    optimizer = torch.optim.AdamW(model.parameters(), lr=cfg.lr_max, weight_decay=cfg.weight_decay)
    scheduler = torch.optim.lr_scheduler.OneCycleLR(
        optimizer, max_lr=cfg.lr_max, total_steps=total_steps, pct_start=cfg.warmup_fraction,
        anneal_strategy="cos", div_factor=cfg.lr_max / cfg.lr_start, cycle_momentum=False)

    info: dict[str, Any] = {"epoch": 0, "batch_in_epoch": 0, "step": 0, "sums": {}, "n_sums": 0,
                            "history": [], "best_score": -math.inf, "best_epoch": -1, "finished": False,
                            "precision": precision}
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
        model.load_state_dict(state.model)
        if average is not None:
            if state.ema is None:
                raise ValueError(f"{last}: the checkpoint holds no weight average, but train.ema_decay is "
                                 f"{cfg.ema_decay}; resume with the config the run started with")
            average.load_state_dict(state.ema)
        optimizer.load_state_dict(state.optimizer)
        scheduler.load_state_dict(state.scheduler)
        if scaler is not None and state.scaler:
            scaler.load_state_dict(state.scaler)
        info = state.info
        if env.rank == 0:
            log(f"{out}: resuming at epoch {info['epoch']}, step {info['step']} of {total_steps}")
    elif env.rank == 0:
        log(f"{out}: {total_steps} steps on {device}, precision {precision}"
            + (f" (train.precision {cfg.precision!r})" if cfg.precision != precision else ""))
    resumed_from = int(info["step"])
    _reseed(cfg.seed, env.rank, info["step"])
    if info["finished"]:
        if env.rank == 0:
            log(f"{out}: already finished (best {cfg.select_metric} {info['best_score']:.4f} "
                f"at epoch {info['best_epoch']})")
        return FitResult(out, info["best_score"], info["best_epoch"], info["history"], resumed_from)

    net: nn.Module = model
    if env.world_size > 1:
        net = nn.parallel.DistributedDataParallel(
            model, device_ids=[device.index] if device.type == "cuda" else None)
    if cfg.compile:
        net = torch.compile(net)        # DDP first: Dynamo then splits the graph at DDP's gradient buckets

    def checkpoint() -> None:
        if env.rank == 0:
            save_state(last, TrainingState(
                model=model.state_dict(), optimizer=optimizer.state_dict(), scheduler=scheduler.state_dict(),
                scaler=scaler.state_dict() if scaler is not None else None, info=info,
                ema=average.state_dict() if average is not None else None))
        _barrier(env)
        _reseed(cfg.seed, env.rank, info["step"])

    tb = _tensorboard(out, info["step"]) if env.rank == 0 else None
    # loaders get their own generator: creating one must not draw from the global RNG, whose
    # state a checkpoint restores (dropout and the like use it)
    val_loader = DataLoader(task.val_set, batch_size=cfg.eval_batch_size, shuffle=False,
                            collate_fn=task.collate, num_workers=cfg.num_workers,
                            generator=torch.Generator().manual_seed(cfg.seed))
    bar = tqdm(total=total_steps, initial=info["step"], desc=f"train {out.name}", unit="step",
               disable=not progress or env.rank != 0)
    try:
        while info["epoch"] < cfg.epochs:
            epoch = info["epoch"]
            batches = epoch_batches(n_train, cfg.batch_size, cfg.seed, epoch, env)[info["batch_in_epoch"]:]
            if hasattr(task.train_set, "set_epoch"):
                task.train_set.set_epoch(epoch)
            loader = DataLoader(task.train_set, batch_sampler=batches, collate_fn=task.collate,
                                num_workers=cfg.num_workers,
                                generator=torch.Generator().manual_seed(cfg.seed + epoch))
            net.train()
            t0 = time.perf_counter()
            lr_used = math.nan
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
                    nn.utils.clip_grad_norm_(model.parameters(), cfg.grad_clip_norm)
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
                if info["step"] % cfg.checkpoint_every == 0 and info["batch_in_epoch"] < steps_per_epoch:
                    checkpoint()

            train_means = _all_reduce_mean({k: v / max(info["n_sums"], 1) for k, v in info["sums"].items()},
                                           env, device)
            # the learning rate of the epoch's last step (after the last step of the run the
            # scheduler points past the end of its schedule)
            row: dict[str, Any] = {"epoch": epoch, "step": info["step"], "lr": lr_used,
                                   "train_time_s": time.perf_counter() - t0}
            row.update({f"train_{k}": v for k, v in train_means.items()})
            if env.rank == 0:
                scored = model if average is None else average
                scored.eval()
                with torch.no_grad(), autocast_context(precision, device):
                    metrics = task.evaluate(scored, val_loader, device)
                if cfg.select_metric not in metrics:
                    raise KeyError(f"validation gave {sorted(metrics)}, no train.select_metric "
                                   f"{cfg.select_metric!r}")
                row.update({f"val_{k}": float(v) for k, v in metrics.items()})
                score = float(metrics[cfg.select_metric])
                if score > info["best_score"]:
                    info["best_score"], info["best_epoch"] = score, epoch
                    save_weights(out / BEST_WEIGHTS, scored.state_dict(),
                                 {"run": run_key, "epoch": epoch, "precision": precision,
                                  "weights": "model" if average is None else "ema",
                                  "metrics": {k: float(v) for k, v in metrics.items()}})
                if tb is not None:
                    for k, v in row.items():
                        if k not in ("epoch", "step"):
                            tb.add_scalar(f"epoch/{k}", v, info["step"])
                log(f"epoch {epoch}: loss {row['train_loss']:.4f}, val {cfg.select_metric} {score:.4f} "
                    f"(best {info['best_score']:.4f} at epoch {info['best_epoch']})")
            info["history"].append(row)
            info.update(epoch=epoch + 1, batch_in_epoch=0, sums={}, n_sums=0,
                        finished=epoch + 1 == cfg.epochs)
            if env.rank == 0:
                # the best score lives on rank 0; the others learn it from the checkpoint on a resume
                _write_log(out / LOG_CSV, info["history"])
            checkpoint()
    finally:
        bar.close()
        if tb is not None:
            tb.close()
    return FitResult(out, info["best_score"], info["best_epoch"], info["history"], resumed_from)
