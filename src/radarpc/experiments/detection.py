"""Detection experiments: train runs of one config (``--runs N`` seeds), evaluate a run folder.

A run folder (:func:`train_runs` with one run) holds ``run.json`` (the key: the resolved
:class:`~radarpc.training.radial.ExperimentConfig` and the data it was trained on),
``config.yaml`` (the same config, readable and reusable), the checkpoints, ``best.safetensors``
and ``log.csv``. With ``runs = N > 1`` the folder holds ``run0 .. run{N-1}`` (seeds
``train.seed + k``) and ``summary.json`` / ``summary.md`` with the mean and standard deviation of
the best validation metrics.

:func:`evaluate_run` scores a run's best weights on a split with RADIal's metrics and writes
``eval_{split}.json`` and ``eval_{split}.md`` into the run folder (for a multi-run folder: every
run, then the mean and standard deviation), with the parameter count and the batch-1 inference
frames/s on the evaluation device, and optionally BEV figures. ``precision="bf16"`` scores the
same weights under bf16 autocast (fast where the CPU multiplies bf16 natively, or on a GPU) and
writes ``eval_{split}_bf16.json`` / ``.md`` beside the fp32 files, so the two can be compared.
"""
from __future__ import annotations

import dataclasses
import functools
import json
import math
import os
import statistics
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import torch
from torch.utils.data import DataLoader

from radarpc.boxes import Detections
from radarpc.config import from_dict, load_yaml, save_yaml, to_dict
from radarpc.io import DataFileError, atomic_write
from radarpc.runs import read_json
from radarpc.training.checkpoint import load_weights
from radarpc.training.loop import BEST_WEIGHTS, LOG_CSV, FitResult, autocast_context, fit
from radarpc.data.point_dataset import PointCloudDataset
from radarpc.eval.detection import FIXED_THRESHOLD, NEAR_MISS_M, DetectionMetrics
from radarpc.data.augment import mirror_sectors
from radarpc.models.classical import ClassicalConfig, classical_detect
from radarpc.models.mirror import MirrorAveraged
from radarpc.models.targets import TargetConfig, decode_detections
from radarpc.training.radial import (DetectionBatch, ExperimentConfig, RadialDetectionTask, collate_points,
                                     build_model, collate_detection, data_pairs, detection_dataset,
                                     evaluate_model, point_datasets, DataPaths)

__all__ = ["load_experiment", "run_key", "train_runs", "load_trained", "EvalResult", "evaluate_run",
           "evaluate_classical", "mirror_sectors_of", "run_folders", "CONFIG_YAML", "EVAL_PRECISIONS",
           "SUMMARY_METRICS"]

EVAL_PRECISIONS = ("fp32", "bf16")
"""Precisions :func:`evaluate_run` scores in (bf16: autocast; the weights stay fp32)."""

CONFIG_YAML = "config.yaml"
"""The resolved config a run folder keeps beside its key (``run.json``)."""

SUMMARY_METRICS = ("f1", "ap", "ar", "f1_fixed", "range_error_m", "azimuth_error_deg", "freespace_miou")
"""Metrics summarised over runs (mean and standard deviation)."""


def load_experiment(path: str | os.PathLike) -> ExperimentConfig:
    """Read an experiment YAML (safe loading; unknown keys and bad values name the file)."""
    return load_yaml(ExperimentConfig, path)


def run_key(cfg: ExperimentConfig, data: DataPaths, points: DataPaths | None = None) -> dict:
    """What identifies a run: the whole config and the absolute paths of its data.

    One root (and store) is stored as a path, as runs always stored it; several as lists in the
    order given (:func:`~radarpc.training.radial.data_pairs`).
    """
    pairs = data_pairs(data, points)
    roots = [str(r.resolve()) for r, _ in pairs]
    stores = None if points is None else [str(p.resolve()) for _, p in pairs]
    if len(pairs) == 1:
        return {"experiment": to_dict(cfg), "data": roots[0], "points": stores[0] if stores else None}
    return {"experiment": to_dict(cfg), "data": roots, "points": stores}


def _seeded(cfg: ExperimentConfig, k: int) -> ExperimentConfig:
    return dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, seed=cfg.train.seed + k))


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
               log: Callable[[str], None] = print) -> list[FitResult]:
    """Train ``runs`` seeds of ``cfg`` into ``out`` (see the module docstring); resumable.

    ``data`` is a RADIal root or several, ``points`` their point stores (pillar models), one per
    root: the training and validation frames of every root are used together.
    """
    if runs < 1:
        raise ValueError(f"runs must be >= 1, got {runs}")
    out = Path(out)
    results = []
    for k in range(runs):
        run_cfg = _seeded(cfg, k)
        folder = out if runs == 1 else out / f"run{k}"
        task = RadialDetectionTask(run_cfg, data, points)      # the run's seed also draws its mirrors
        if task.preloaded_bytes:
            log(f"{folder}: point frames preloaded in memory, {task.preloaded_bytes / 2**30:.2f} GiB")
        res = fit(task, run_cfg.train, folder, run_key(run_cfg, data, points), device=device,
                  overwrite=overwrite, progress=progress, log=log, extra_outputs=(CONFIG_YAML,))
        if not (folder / CONFIG_YAML).is_file():
            save_yaml(run_cfg, folder / CONFIG_YAML)
        results.append(res)
    if runs > 1:
        rows = [{"run": k, "best_epoch": r.best_epoch,
                 **{m: r.history[r.best_epoch].get(f"val_{m}", math.nan) for m in SUMMARY_METRICS}}
                for k, r in enumerate(results)]
        _write_summary(out / "summary", rows, f"{cfg.name}: best validation epoch of {runs} runs")
    return results


def _mean_std(rows: list[dict], key: str) -> tuple[float, float]:
    v = [float(r[key]) for r in rows if key in r and not math.isnan(float(r[key]))]
    if not v:
        return math.nan, math.nan
    return statistics.fmean(v), (statistics.stdev(v) if len(v) > 1 else 0.0)


def _write_summary(stem: Path, rows: list[dict], title: str) -> None:
    summary = {m: dict(zip(("mean", "std"), _mean_std(rows, m))) for m in SUMMARY_METRICS}
    with atomic_write(stem.with_suffix(".json"), "w") as f:
        json.dump({"runs": rows, "summary": summary}, f, indent=2)
    lines = [f"# {title}", "", "| metric | mean | std |", "|---|---|---|"]
    lines += [f"| {m} | {s['mean']:.4f} | {s['std']:.4f} |" for m, s in summary.items()]
    with atomic_write(stem.with_suffix(".md"), "w") as f:
        f.write("\n".join(lines) + "\n")


@dataclass
class EvalResult:
    """What :func:`evaluate_run` measured for one run."""

    run: Path
    split: str
    metrics: dict
    parameters: int
    fps: float
    device: str
    threads: int
    precision: str = "fp32"
    data: tuple[str, ...] = ()
    """The roots scored (absolute paths)."""
    points: tuple[str, ...] | None = None
    """Their point stores (point models)."""
    scored_on: str = ""
    """Names the data when it is not the run's own (:func:`evaluate_run`), else empty."""
    mirror_average: bool = False
    """Scored with :class:`~radarpc.models.mirror.MirrorAveraged` (the frame and its mirror image)."""
    fast: bool = False
    """Scored and timed with :func:`~radarpc.models.fast_inference.fast_inference`'s copy of the model."""
    easy: bool = False
    """Scored in RADIal's easy mode: ``Difficult`` labels dropped (:func:`evaluate_run`)."""

    @property
    def stem(self) -> str:
        """The name of the written files: ``eval_{split}``, then ``_on_{scored_on}`` for data not
        the run's own, ``_easy`` in RADIal's easy mode, ``_mirror`` when mirror-averaged, ``_fast``
        for the fast inference copy and ``_{precision}`` unless fp32."""
        return (f"eval_{self.split}" + (f"_on_{self.scored_on}" if self.scored_on else "")
                + ("_easy" if self.easy else "")
                + ("_mirror" if self.mirror_average else "") + ("_fast" if self.fast else "")
                + ("" if self.precision == "fp32" else f"_{self.precision}"))


def _load_run(folder: Path) -> tuple[ExperimentConfig, dict]:
    key = read_json(folder / "run.json")
    if not isinstance(key, dict) or "experiment" not in key:
        raise DataFileError(folder / "run.json", "not a radarpc training run key (no 'experiment')")
    return from_dict(ExperimentConfig, key["experiment"], where=str(folder / "run.json")), key


def load_trained(folder: str | os.PathLike, device: torch.device | str = "cpu"
                 ) -> tuple[ExperimentConfig, torch.nn.Module, dict]:
    """The config, model with its best weights (in eval mode, on ``device``) and run key of the
    training run folder ``folder``.

    Raises
    ------
    DataFileError
        ``run.json`` is missing or is not a training run's.
    FileNotFoundError
        The run has no best weights yet.
    """
    folder = Path(folder)
    cfg, key = _load_run(folder)
    best = folder / BEST_WEIGHTS
    if not best.is_file():
        raise FileNotFoundError(f"{folder}: no {BEST_WEIGHTS} yet (the run has not finished an epoch)")
    state, _ = load_weights(best)
    model = build_model(cfg)
    model.load_state_dict(state)
    return cfg, model.to(device).eval(), key


def _fps(model: torch.nn.Module, batches: list[DetectionBatch], device: torch.device, repeats: int = 3,
         precision: str = "fp32") -> float:
    """Batch-1 forward passes per second (after one warm-up pass), median of ``repeats`` sweeps."""
    if not batches:
        return math.nan
    rates = []
    with torch.inference_mode(), autocast_context(precision, device):
        model(batches[0].inputs)
        for _ in range(repeats):
            if device.type == "cuda":
                torch.cuda.synchronize(device)
            t0 = time.perf_counter()
            for b in batches:
                model(b.inputs)
            if device.type == "cuda":
                torch.cuda.synchronize(device)
            rates.append(len(batches) / (time.perf_counter() - t0))
    return float(statistics.median(rates))


def evaluate_run(run: str | os.PathLike, split: str = "test", *, data: DataPaths | None = None,
                 points: DataPaths | None = None, device: str | None = None, show: int = 0,
                 fps_frames: int = 20, batch_size: int = 4, precision: str = "fp32", mirror_average: bool = False,
                 fast: bool = False, easy: bool | None = None, progress: bool = True,
                 log: Callable[[str], None] = print) -> list[EvalResult]:
    """Score the best weights of every run in ``run`` on ``split`` (see the module docstring).

    ``data`` / ``points`` override the roots and stores stored with the run (a moved dataset, or
    one root of a run trained on several). Scores on other data than the run's own go to files of
    their own, ``eval_{split}_on_{names}``, so they do not replace the run's own scores
    (:func:`_scored_on` gives the names).
    ``precision`` is one of :data:`EVAL_PRECISIONS`. ``mirror_average`` scores a pillar model
    averaged over each frame and its mirror image (:class:`~radarpc.models.mirror.MirrorAveraged`;
    two forward passes a frame) into ``eval_{split}[_on_...]_mirror.*``. ``fast`` scores and times
    :func:`~radarpc.models.fast_inference.fast_inference`'s copy of the model (exact rewrites; fp32
    only; its first passes compile kernels, before the timing) into ``eval_{split}[...]_fast.*``.
    ``easy`` scores RADIal's easy mode, what its ``2-Test.py`` and ``3-Evaluation.py`` score unless
    given ``--difficult``: label rows with ``Difficult == 1`` dropped, and the frames all of whose
    vehicles are difficult (:class:`~radarpc.data.radial.RADIal` with ``difficult=False``), into
    ``eval_{split}[...]_easy.*``. Frames without vehicles stay in (RADIal's loader drops them with
    its easy rows), so their false alarms still count. ``easy=False`` scores every label. ``None``
    (the default) follows the run's config: every label, or easy mode for a run trained with
    ``difficult: false``.
    """
    from radarpc.viz import plot_detection_frame, plot_learning_curves

    if precision not in EVAL_PRECISIONS:
        raise ValueError(f"precision must be one of {EVAL_PRECISIONS}, got {precision!r}")
    if fast and precision != "fp32":
        raise ValueError(f"fast inference is float32 only (the Winograd transforms and the products per frequency "
                         f"need its precision), got {precision!r}")
    dev = torch.device(device) if device else torch.device("cuda" if torch.cuda.is_available() else "cpu")
    results = []
    for folder in run_folders(run):
        if mirror_average:
            stored, _ = _load_run(folder)
            if stored.input_kind != "points":
                raise ValueError(f"{folder}: mirror averaging applies to point models; {stored.name!r} takes RD "
                                 f"cubes (mirroring a cube would need the array's geometry)")
        cfg, model, key = load_trained(folder, dev)
        n_params = sum(p.numel() for p in model.parameters())
        if fast:
            from radarpc.models.fast_inference import fast_inference

            model = fast_inference(model)
        roots = data or key["data"]
        stores = (points or key.get("points")) if cfg.input_kind == "points" else None
        run_easy = (not cfg.difficult) if easy is None else easy   # by default as the run was trained
        ds = detection_dataset(dataclasses.replace(cfg, difficult=not run_easy), roots, stores, split)
        if mirror_average:
            model = MirrorAveraged(model, cfg.targets, sectors=mirror_sectors_of(ds))
        scored = _resolved(data_pairs(roots, stores))
        own = _resolved(data_pairs(key["data"], key.get("points") if stores is not None else None))
        collate = functools.partial(collate_detection, cfg=cfg)
        loader = DataLoader(ds, batch_size=batch_size, shuffle=False, collate_fn=collate)
        with torch.inference_mode(), autocast_context(precision, dev):
            report, miou = evaluate_model(model, loader, dev, cfg.targets, max_candidates=None)
        metrics = report.to_dict()
        metrics["freespace_miou"] = miou
        single = DataLoader(ds, batch_size=1, shuffle=False, collate_fn=collate)
        frames = []
        for b in single:
            frames.append(b.to(dev))
            if len(frames) >= fps_frames:
                break
        fps = _fps(model, frames, dev, precision=precision)
        res = EvalResult(folder, split, metrics, n_params, fps, str(dev), torch.get_num_threads(), precision,
                         data=tuple(str(r) for r, _ in scored),
                         points=None if stores is None else tuple(str(p) for _, p in scored),
                         scored_on=_scored_on(scored, own), mirror_average=mirror_average, fast=fast, easy=run_easy)
        _write_eval(folder, res, cfg.name)
        if (folder / LOG_CSV).is_file():
            plot_learning_curves({cfg.name: folder / LOG_CSV}, folder / "figures" / "learning_curve.png")
        if show:
            with torch.inference_mode(), autocast_context(precision, dev):
                for k, b in _shown(ds, show, collate):
                    b = b.to(dev)
                    out = model(b.inputs)
                    dets = decode_detections(out.detection.float(), cfg.targets, threshold=FIXED_THRESHOLD)
                    plot_detection_frame(b.to(torch.device("cpu")), dets.to("cpu"), out.detection[0, 0].float().cpu(),
                                         folder / "figures" / f"{res.stem}_{k}.png",
                                         title=f"{cfg.name} {split} item {k} ({len(b.labels)} labels)")
        log(f"{folder}: {split} F1 {metrics['f1']:.4f} (AP {metrics['ap']:.4f}, AR {metrics['ar']:.4f}), "
            f"F1@0.2 {metrics['f1_fixed']:.4f}, freespace mIoU {miou if miou is not None else float('nan'):.4f}, "
            f"{n_params:,} parameters, {fps:.1f} frames/s at batch 1 on {dev}, {precision}"
            + (", mirror-averaged" if mirror_average else "") + (", fast inference copy" if fast else ""))
        results.append(res)
    if len(results) > 1:
        rows = [{"run": k, **{m: (r.metrics.get(m) if r.metrics.get(m) is not None else math.nan)
                              for m in SUMMARY_METRICS}} for k, r in enumerate(results)]
        _write_summary(Path(run) / f"{results[0].stem}_summary", rows,
                       f"{split}: {len(results)} runs" + ("" if precision == "fp32" else f", {precision}")
                       + (", mirror-averaged" if mirror_average else ""))
    return results


def mirror_sectors_of(ds) -> tuple[int, int] | None:
    """The sector layout :class:`~radarpc.models.mirror.MirrorAveraged` needs, every root checked
    to allow the mirror (:func:`~radarpc.data.augment.mirror_sectors`)."""
    sectors = [mirror_sectors(part) for part in point_datasets(ds)]   # the same layout: one model's stores
    return sectors[0]


def _resolved(pairs: list[tuple[Path, Path | None]]) -> list[tuple[Path, Path | None]]:
    return [(root.resolve(), None if store is None else store.resolve()) for root, store in pairs]


def _scored_on(scored: list[tuple[Path, Path | None]], own: list[tuple[Path, Path | None]]) -> str:
    """How the eval files name data other than the run's own, given both as resolved
    (root, store) pairs: the scored roots' folder names joined by ``+`` when they are not the
    run's roots, then the stores' file stems when a root of the run is scored with another store
    than its own (``sim_b`` for another root, ``pc200`` for the run's root with the store of
    another density); ``""`` for the run's own data."""
    own_store = dict(own)
    parts = []
    if [root for root, _ in scored] != [root for root, _ in own]:
        parts.append("+".join(root.name for root, _ in scored))
    if any(store is not None and own_store.get(root, store) != store for root, store in scored):
        parts.append("+".join(store.stem for _, store in scored))
    return "_".join(parts)


def _shown(ds, k: int, collate) -> list[tuple[int, DetectionBatch]]:
    """``k`` items spread evenly over ``ds`` (first and last included), each a batch of one: the
    figures of ``--show`` (the first items of a split are often one sequence's empty frames)."""
    n = len(ds)
    k = min(k, n)                                   # more asked than there are: each item once
    picks = sorted({round(i * (n - 1) / max(k - 1, 1)) for i in range(k)})
    return [(i, collate([ds[i]])) for i in picks]


def evaluate_classical(points: str | os.PathLike, data: str | os.PathLike, out: str | os.PathLike,
                       split: str = "test", *, cfg: ClassicalConfig = ClassicalConfig(), difficult: bool = True,
                       show: int = 0, fps_frames: int = 20, log: Callable[[str], None] = print) -> EvalResult:
    """Score the classical detector (:mod:`radarpc.models.classical`) on ``split`` of a point store
    with the learned models' metrics; writes ``out/eval_{split}.json`` / ``.md``
    (``eval_{split}_easy.*`` without the ``Difficult`` labels; as :func:`evaluate_run`, with 0
    parameters and the detector's batch-1 frames/s, point extraction excluded),
    ``out/classical.yaml`` and, with ``show``, figures of ``show`` frames spread over the split
    (:func:`_shown`)."""
    from radarpc.viz import plot_detection_frame

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    save_yaml(cfg, out / "classical.yaml")
    ds = PointCloudDataset(points, data, split=split, difficult=difficult)
    targets = TargetConfig()
    collate = functools.partial(collate_points, targets=targets)
    det = DetectionMetrics()
    for batch in DataLoader(ds, batch_size=16, shuffle=False, collate_fn=collate):
        det.update(classical_detect(batch.inputs, cfg), batch.labels, batch.label_offset)
    metrics = det.compute().to_dict()
    metrics["freespace_miou"] = None
    frames = [b for _, b in zip(range(fps_frames), DataLoader(ds, batch_size=1, shuffle=False, collate_fn=collate))]
    rates = []
    for _ in range(3):
        t0 = time.perf_counter()
        for b in frames:
            classical_detect(b.inputs, cfg)
        rates.append(len(frames) / max(time.perf_counter() - t0, 1e-12))
    res = EvalResult(out, split, metrics, 0, float(statistics.median(rates)) if frames else math.nan, "cpu",
                     torch.get_num_threads(), data=(str(Path(data).resolve()),), points=(str(Path(points).resolve()),),
                     easy=not difficult)
    _write_eval(out, res, "classical (CFAR points, Doppler gating, BEV clusters)")
    for k, b in _shown(ds, show, collate):
        rows = classical_detect(b.inputs, cfg).rows()
        shown = Detections.from_frames([rows[rows[:, 0] >= FIXED_THRESHOLD]])
        plot_detection_frame(b, shown, None, out / "figures" / f"eval_{split}_{k}.png",
                             title=f"classical {split} item {k} ({len(b.labels)} labels)")
    log(f"{out}: classical {split} F1 {metrics['f1']:.4f} (AP {metrics['ap']:.4f}, AR {metrics['ar']:.4f}), "
        f"F1@0.2 {metrics['f1_fixed']:.4f}, {res.fps:.1f} frames/s at batch 1")
    return res


def _write_eval(folder: Path, res: EvalResult, name: str) -> None:
    """``{res.stem}.json`` / ``.md`` and ``figures/{res.stem}_labels.png`` (what became of the
    labels at each threshold, :func:`radarpc.viz.plot_label_outcomes`)."""
    from radarpc.viz import plot_label_outcomes

    m = res.metrics
    doc = {"split": res.split, "data": list(res.data), "points": list(res.points) if res.points else None,
           "metrics": m, "parameters": res.parameters, "fps_batch1": res.fps,
           "device": res.device, "threads": res.threads, "precision": res.precision,
           "mirror_average": res.mirror_average, "fast": res.fast, "easy": res.easy}
    with atomic_write(folder / f"{res.stem}.json", "w") as f:
        json.dump(doc, f, indent=2)
    thr = ", ".join(f"{t:.1f}" for t in m["thresholds"])
    lines = [
        f"# {name}: {res.split} split ({m['n_frames']} frames)"
        + ("" if res.precision == "fp32" else f", {res.precision} autocast")
        + (", RADIal's easy mode (Difficult labels dropped)" if res.easy else "")
        + (", averaged over each frame and its mirror image" if res.mirror_average else "")
        + (", fast inference copy (radarpc.models.fast_inference)" if res.fast else ""), "",
        "| AP | AR | F1 | F1 @ 0.2 | range error (m) | azimuth error (deg) | freespace mIoU | parameters | frames/s (batch 1) |",
        "|---|---|---|---|---|---|---|---|---|",
        f"| {m['ap']:.4f} | {m['ar']:.4f} | {m['f1']:.4f} | {m['f1_fixed']:.4f} | {m['range_error_m']:.3f} | "
        f"{m['azimuth_error_deg']:.3f} | "
        f"{(m['freespace_miou'] if m['freespace_miou'] is not None else math.nan):.4f} | {res.parameters:,} | "
        f"{res.fps:.1f} ({res.device}, {res.threads} threads) |", "",
        f"AP and AR: means over the confidence thresholds {thr} at IoU 0.5; F1 = 2 AP AR / (AP + AR). "
        f"F1 @ 0.2: precision and recall at confidence 0.2. Errors: mean absolute range and azimuth "
        f"differences of matched pairs at the sweep's thresholds.", "",
        f"At confidence 0.2: precision {m['precision_fixed']:.4f}, recall {m['recall_fixed']:.4f}; of the "
        f"{m['fn_fixed']} labels missed, {m['fn_near_fixed']} have a detection within {NEAR_MISS_M:g} m "
        f"(found, but the box is off by enough to fail IoU 0.5).",
    ]
    if res.data:
        stores = res.points or (None,) * len(res.data)
        lines += ["", "Scored on " + "; ".join(f"`{r}`" + (f" (points `{p}`)" if p else "")
                                               for r, p in zip(res.data, stores)) + "."]
    with atomic_write(folder / f"{res.stem}.md", "w") as f:
        f.write("\n".join(lines) + "\n")
    plot_label_outcomes(m, folder / "figures" / f"{res.stem}_labels.png",
                        title=f"{name}: {res.split} split")
