"""Train a detection experiment: runs of one config (``--runs N`` seeds) in a run folder.

A run folder (:func:`train_runs` with one run) holds ``run.json`` (the key: the resolved
:class:`~radarpc.experiments.radial_detection.config.ExperimentConfig` and the data it was
trained on), ``config.yaml`` (the same config, readable and reusable), the checkpoints,
``best.safetensors`` and ``log.csv``. With ``runs = N > 1`` the folder holds ``run0 .. run{N-1}``
(seeds ``train.seed + k``) and ``summary.json`` / ``summary.md`` with the mean and standard
deviation of the best validation metrics. The loop is :func:`radarpc.training.loop.fit`.
"""
from __future__ import annotations

import functools
import json
import math
import os
import statistics
from pathlib import Path
from typing import Callable

from radarpc.config import save_yaml, to_dict
from radarpc.distributed import dist_env
from radarpc.experiments.radial_detection.config import ExperimentConfig, canonical_key, with_train
from radarpc.experiments.radial_detection.task import DataPaths, RadialDetectionTask, data_pairs
from radarpc.io import atomic_write
from radarpc.training.loop import FitResult, fit

__all__ = ["run_key", "train_runs", "run_folders", "CONFIG_YAML", "SUMMARY_METRICS", "write_summary"]

CONFIG_YAML = "config.yaml"
"""The resolved config a run folder keeps beside its key (``run.json``)."""

SUMMARY_METRICS = ("f1", "ap", "ar", "f1_fixed", "range_error_m", "azimuth_error_deg", "freespace_miou")
"""Metrics summarised over runs (mean and standard deviation)."""


def run_key(cfg: ExperimentConfig, data: DataPaths, points: DataPaths | None = None) -> dict:
    """What identifies a run: the whole config and the absolute paths of its data.

    One root (and store) is stored as a path, as runs always stored it; several as lists in the
    order given (:func:`~radarpc.experiments.radial_detection.task.data_pairs`).
    """
    pairs = data_pairs(data, points)
    roots = [str(r.resolve()) for r, _ in pairs]
    stores = None if points is None else [str(p.resolve()) for _, p in pairs]
    if len(pairs) == 1:
        return {"experiment": to_dict(cfg), "data": roots[0], "points": stores[0] if stores else None}
    return {"experiment": to_dict(cfg), "data": roots, "points": stores}


def run_folders(out: str | os.PathLike) -> list[Path]:
    """The run folders of ``out``: itself when it holds a run, else its ``run*`` sub-folders."""
    out = Path(out)
    if (out / "run.json").is_file():
        return [out]
    runs = sorted((p for p in out.glob("run*") if (p / "run.json").is_file()),
                  key=lambda p: int(p.name[3:]) if p.name[3:].isdigit() else -1)
    if not runs:
        raise FileNotFoundError(f"{out}: no training run here (no run.json, no run*/run.json)")
    return runs


def train_runs(cfg: ExperimentConfig, data: DataPaths, out: str | os.PathLike, *,
               points: DataPaths | None = None, runs: int = 1, device: str | None = None,
               overwrite: bool = False, progress: bool = True,
               log: Callable[[str], None] = print,
               on_step: Callable[[int], None] | None = None) -> list[FitResult]:
    """Train ``runs`` seeds of ``cfg`` into ``out`` (see the module docstring); resumable.

    ``data`` is a RADIal root or several, ``points`` their point stores (pillar models), one per
    root: the training and validation frames of every root are used together. ``on_step`` is
    given the global step after each optimizer step of every run (:func:`~radarpc.training.loop.fit`;
    a study stops a run at its time limit through it).
    """
    if runs < 1:
        raise ValueError(f"runs must be >= 1, got {runs}")
    out = Path(out)
    results = []
    for k in range(runs):
        run_cfg = with_train(cfg, seed=cfg.train.seed + k)
        folder = out if runs == 1 else out / f"run{k}"
        task = RadialDetectionTask(run_cfg, data, points)      # the run's seed also draws its mirrors
        if task.preloaded_bytes:
            log(f"{folder}: point frames preloaded in memory, {task.preloaded_bytes / 2**30:.2f} GiB")
        res = fit(task, run_cfg.train, folder, run_key(run_cfg, data, points), device=device,
                  overwrite=overwrite, progress=progress, log=log, extra_outputs=(CONFIG_YAML,), on_step=on_step,
                  canonical_key=functools.partial(canonical_key, num_workers=run_cfg.train.num_workers))
        if dist_env().rank == 0 and not (folder / CONFIG_YAML).is_file():   # under torchrun, rank 0 alone writes
            save_yaml(run_cfg, folder / CONFIG_YAML)
        results.append(res)
    if runs > 1:
        rows = [{"run": k, "best_epoch": r.best_epoch,
                 **{m: (r.best_row or {}).get(f"val_{m}", math.nan) for m in SUMMARY_METRICS}}
                for k, r in enumerate(results)]
        write_summary(out / "summary", rows, f"{cfg.name}: best validation epoch of {runs} runs")
    return results


def _mean_std(rows: list[dict], key: str) -> tuple[float, float]:
    v = [float(r[key]) for r in rows if key in r and not math.isnan(float(r[key]))]
    if not v:
        return math.nan, math.nan
    return statistics.fmean(v), (statistics.stdev(v) if len(v) > 1 else 0.0)


def write_summary(stem: Path, rows: list[dict], title: str) -> None:
    summary = {m: dict(zip(("mean", "std"), _mean_std(rows, m))) for m in SUMMARY_METRICS}
    with atomic_write(stem.with_suffix(".json"), "w") as f:
        json.dump({"runs": rows, "summary": summary}, f, indent=2)
    lines = [f"# {title}", "", "| metric | mean | std |", "|---|---|---|"]
    lines += [f"| {m} | {s['mean']:.4f} | {s['std']:.4f} |" for m, s in summary.items()]
    with atomic_write(stem.with_suffix(".md"), "w") as f:
        f.write("\n".join(lines) + "\n")
