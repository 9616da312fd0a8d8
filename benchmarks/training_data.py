"""Benchmark: what the training data path costs per batch, read from the point stores or preloaded.

A point store is compressed in row groups of many frames (64 for `radarpc pointcloud`), and a
frame read from the file decodes its whole row group; training reads the frames in random order.
:func:`radarpc.experiments.radial_detection.task.preload_point_frames` holds them in memory instead. This script
builds the training split of a run (``--config``, ``--data`` roots, ``--points`` stores), takes
the first ``--batches`` batches of epoch 0 in the loop's order (:func:`radarpc.training.loop.epoch_batches`)
and times, in this one process, item reading plus the collate (target encoding included):

* ``file``: the frames read from the stores;
* ``preloaded``: the same frames after preloading (the preload itself is timed apart);
* ``step``: one training step of the config's model on those batches, at ``--precision``, to put
  the data cost beside the compute it competes with for the cores (the loop's loader workers run
  beside the step).

Both data paths give the same batches (checked). Prints one JSON object: seconds per batch of
each, their ratio, the preload's seconds and GiB, the step's seconds, threads, CPU and load
average. Timings are only meaningful on a quiet machine.

Usage::

    python benchmarks/training_data.py spectralpillars-s.yaml --data sim_r4 --points pc_r4_057.parquet --batches 40
"""
from __future__ import annotations

import argparse
import os


def _parse() -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("config", help="experiment config (YAML) of a point model")
    p.add_argument("--data", nargs="+", required=True, help="RADIal-layout roots")
    p.add_argument("--points", nargs="+", required=True, help="their point stores, one per root")
    p.add_argument("--batches", type=int, default=40, help="batches timed (the first of epoch 0)")
    p.add_argument("--threads", type=int, default=2, help="torch / BLAS threads of the step")
    p.add_argument("--precision", choices=("fp32", "bf16"), default="bf16", help="autocast of the step")
    return p.parse_args()


ARGS = _parse() if __name__ == "__main__" else None
if ARGS is not None:  # BLAS threads must be fixed before numpy/torch load their thread pools
    os.environ.setdefault("OMP_NUM_THREADS", str(ARGS.threads))

import dataclasses  # noqa: E402
import json  # noqa: E402
import time  # noqa: E402

import torch  # noqa: E402

from radarpc.experiments.radial_detection.config import load_experiment  # noqa: E402
from radarpc.machine import cpu_model  # noqa: E402
from radarpc.training.loop import autocast_context, epoch_batches  # noqa: E402
from radarpc.experiments.radial_detection.task import RadialDetectionTask, preload_point_frames  # noqa: E402


def _read(task: RadialDetectionTask, batches: list[list[int]]) -> tuple[float, list]:
    t = time.perf_counter()
    out = [task.collate([task.train_set[i] for i in b]) for b in batches]
    return (time.perf_counter() - t) / len(batches), out


def _same(a, b) -> bool:
    fields = [f.name for f in dataclasses.fields(a.inputs)]
    return all(torch.equal(getattr(a.inputs, f), getattr(b.inputs, f)) for f in fields
               if isinstance(getattr(a.inputs, f), torch.Tensor)) and torch.equal(a.target, b.target) \
        and torch.equal(a.freespace, b.freespace) and torch.equal(a.labels, b.labels)


def main(a: argparse.Namespace) -> dict:
    torch.set_num_threads(a.threads)
    cfg = load_experiment(a.config)
    if cfg.input_kind != "points":
        raise SystemExit(f"{a.config}: {cfg.name} reads RD cubes; this benchmark times point stores")
    load_before = os.getloadavg()[0]
    task = RadialDetectionTask(cfg, a.data, a.points, preload=False)
    batches = epoch_batches(len(task.train_set), cfg.train.batch_size, cfg.train.seed, 0)[:a.batches]
    file_s, from_file = _read(task, batches)
    t = time.perf_counter()
    held = preload_point_frames([task.train_set], budget_bytes=2**62)
    preload_s = time.perf_counter() - t
    mem_s, from_memory = _read(task, batches)
    if not all(_same(x, y) for x, y in zip(from_file, from_memory)):
        raise SystemExit("preloaded batches differ from the batches read from the stores")

    torch.manual_seed(cfg.train.seed)
    model = task.build_model()
    model.train()
    opt = torch.optim.AdamW(model.parameters(), lr=cfg.train.lr_start)
    device = torch.device("cpu")
    warm = min(3, len(from_memory) - 1)
    for k, batch in enumerate(from_memory):
        if k == warm:
            t = time.perf_counter()
        with autocast_context(a.precision, device):
            loss, _ = task.loss(model, batch)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
    step_s = (time.perf_counter() - t) / (len(from_memory) - warm)
    return {"config": a.config, "data": a.data, "points": a.points, "train_frames": len(task.train_set),
            "batch_size": cfg.train.batch_size, "batches": len(batches),
            "file_s_per_batch": file_s, "preloaded_s_per_batch": mem_s, "file_over_preloaded": file_s / mem_s,
            "preload_s": preload_s, "preloaded_gib": held / 2**30,
            "step_s": step_s, "step_precision": a.precision, "file_over_step": file_s / step_s,
            "threads": torch.get_num_threads(), "cpu": cpu_model(),
            "load_avg_1min": [load_before, os.getloadavg()[0]]}


if __name__ == "__main__":
    print(json.dumps(main(ARGS), indent=2))
