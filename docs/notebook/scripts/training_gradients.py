"""Check: do bf16 autocast and ``torch.compile`` train a detection model as eager fp32 does?

The training loop offers bf16 autocast (``train.precision``) and Inductor (``train.compile``). A
wrong gradient in either does not fail a step; it only makes training slower or worse, which one
run cannot tell from seed noise. This script builds an experiment config's model as
``radarpc train`` does (its seed, the training split's input statistics), takes real training
frames, and from the same initial weights computes the loss gradients in each mode:

* ``eager_fp32`` (the reference), ``eager_bf16``, ``compiled_bf16``, ``compiled_fp32``
  (``--modes`` picks; bf16 modes need a device that runs bf16 autocast).

It prints one JSON object with, per mode, the loss of the batch, the median over weight tensors
of ``|g - g_ref| / |g_ref|`` and the five weight tensors with the lowest cosine to the reference
(:func:`radarpc.training.gradients.compare_gradients`).
Only tensors of two or more dimensions are compared: a convolution's bias that a BatchNorm follows
has a zero gradient in exact arithmetic, so rounding is all its gradient holds. bf16 rounding
gives eager bf16 some spread (every activation carries 2^-9 relative error); a mode whose
cosines fall far below eager bf16's computes something else.

With ``--steps N`` each mode also trains N steps on the same batches (AdamW, weight decay 0.01,
constant ``--lr``, no schedule) and the JSON gains the
mean training loss of each window of 50 steps, and the wall time (the first compiled step
includes the compilation).

Usage::

    python docs/notebook/scripts/training_gradients.py configs/fftradnet-s.yaml --data ROOT [--points STORE]
        [--batch-size 8] [--steps 250] [--modes eager_fp32 eager_bf16 compiled_bf16] [--device cpu]
"""
from __future__ import annotations

import argparse
import contextlib
import copy
import json
import platform
import statistics
import time

import torch

from radarpc.config import load_yaml
from radarpc.machine import cpu_model
from radarpc.training.gradients import compare_gradients
from radarpc.experiments.radial_detection.config import ExperimentConfig
from radarpc.experiments.radial_detection.task import RadialDetectionTask

MODES = ("eager_fp32", "eager_bf16", "compiled_bf16", "compiled_fp32")
WINDOW = 50


def autocast(mode: str, device: torch.device):
    """bf16 autocast for the ``*_bf16`` modes, else nothing."""
    if mode.endswith("bf16"):
        return torch.autocast(device.type, dtype=torch.bfloat16)
    return contextlib.nullcontext()


def run_mode(task: RadialDetectionTask, model: torch.nn.Module, mode: str, batches: list, lr: float,
             device: torch.device) -> tuple[float, dict[str, torch.Tensor], list[float], float]:
    """Train a copy of ``model`` one step per batch in ``mode`` (AdamW at a constant ``lr``).

    Returns the first batch's loss and every parameter's gradient there (from ``model``'s
    weights), the loss of every step, and the wall time of all steps.
    """
    m = copy.deepcopy(model)
    net = torch.compile(m) if mode.startswith("compiled") else m
    opt = torch.optim.AdamW(m.parameters(), lr=lr, weight_decay=0.01)
    losses, first_grads, t0 = [], {}, time.perf_counter()
    for batch in batches:
        with autocast(mode, device):
            loss, _ = task.loss(net, batch)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        if not losses:
            first_grads = {k: p.grad.detach().float().clone() for k, p in m.named_parameters()
                           if p.grad is not None}
        opt.step()
        losses.append(float(loss.detach()))
    return losses[0], first_grads, losses, time.perf_counter() - t0


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("config", help="an experiment config (configs/*.yaml or a run's config.yaml)")
    p.add_argument("--data", nargs="+", required=True, help="RADIal-layout root(s), as for radarpc train")
    p.add_argument("--points", nargs="+", help="point store(s) of the roots (pillar models)")
    p.add_argument("--batch-size", type=int, help="default: the config's train.batch_size")
    p.add_argument("--steps", type=int, default=0, help="also train each mode this many steps (0: gradients only)")
    p.add_argument("--lr", type=float, default=1e-3)
    p.add_argument("--modes", nargs="+", choices=MODES, default=list(MODES))
    p.add_argument("--device", default="cpu")
    p.add_argument("--threads", type=int, default=torch.get_num_threads())
    args = p.parse_args()
    if args.steps < 0:
        p.error("--steps must be >= 0")
    torch.set_num_threads(args.threads)
    device = torch.device(args.device)

    cfg = load_yaml(ExperimentConfig, args.config)
    task = RadialDetectionTask(cfg, args.data, args.points, preload=False)
    torch.manual_seed(cfg.train.seed)
    model = task.build_model().to(device).train()
    bs = args.batch_size or cfg.train.batch_size
    n = len(task.train_set)
    order = torch.randperm(n, generator=torch.Generator().manual_seed(cfg.train.seed)).tolist()

    def batch(step: int):
        items = [task.train_set[order[(step * bs + i) % n]] for i in range(bs)]
        return task.to_device(task.collate(items), device)

    batches = [batch(s) for s in range(max(args.steps, 1))]
    result = {"config": args.config, "data": args.data, "batch_size": bs, "device": str(device),
              "cpu": cpu_model(), "threads": args.threads, "torch": torch.__version__,
              "python": platform.python_version(), "modes": {}}
    modes = [m for m in MODES if m in args.modes]          # the eager_fp32 reference first
    ref = None
    for mode in modes:
        loss, g, losses, wall = run_mode(task, model, mode, batches, args.lr, device)
        row = {"loss": loss}
        if mode == "eager_fp32":
            ref = g
        elif ref is not None:
            row |= compare_gradients(g, ref)
        if args.steps:
            row["training"] = {"steps": len(losses), "wall_s": wall, "window": WINDOW,
                               "mean_loss_per_window": [statistics.fmean(losses[i:i + WINDOW])
                                                        for i in range(0, len(losses), WINDOW)]}
        result["modes"][mode] = row
    print(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
