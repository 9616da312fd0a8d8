"""Evaluate a detection run: its best weights scored on a split with RADIal's metrics.

:func:`evaluate_run` writes ``eval_{split}.json`` and ``eval_{split}.md`` into the run folder (for
a multi-run folder: every run, then the mean and standard deviation), with the parameter count and
the batch-1 inference frames/s on the evaluation device, and optionally BEV figures.
``precision="bf16"`` scores the same weights under bf16 autocast (fast where the CPU multiplies
bf16 natively, or on a GPU) and writes ``eval_{split}_bf16.json`` / ``.md`` beside the fp32 files,
so the two can be compared. :func:`evaluate_classical` scores the classical detector the same way.
"""
from __future__ import annotations

import dataclasses
import functools
import json
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

import torch
from torch.utils.data import DataLoader

from radarpc.config import save_yaml
from radarpc.data.augment import mirror_sectors
from radarpc.data.point_dataset import PointCloudDataset
from radarpc.eval.detection import FIXED_THRESHOLD, NEAR_MISS_M, DetectionMetrics
from radarpc.eval.detection_files import write_detections
from radarpc.experiments.radial_detection.config import ExperimentConfig, canonical_key, experiment_from_dict
from radarpc.experiments.radial_detection.task import (DataPaths, DetectionBatch, collate_detection, collate_points, data_pairs,
                                                       detection_dataset, evaluate_model, item_frames, point_datasets)
from radarpc.experiments.radial_detection.train import SUMMARY_METRICS, run_folders, write_summary
from radarpc.io import DataFileError, atomic_write
from radarpc.models.classical import ClassicalConfig, classical_detect
from radarpc.models.mirror import MirrorAveraged
from radarpc.boxes import Detections
from radarpc.models.targets import TargetConfig, decode_detections
from radarpc.machine import check_device
from radarpc.models.complexity import Rate, frames_per_second
from radarpc.runs import check_writable, locked_output, read_json, remove_temp_files
from radarpc.training.checkpoint import load_model_state, load_weights
from radarpc.training.loop import BEST_WEIGHTS, LOG_CSV, autocast_context, training_status

__all__ = ["load_trained", "EvalResult", "evaluate_run", "evaluate_classical", "mirror_sectors_of",
           "EVAL_PRECISIONS"]

EVAL_PRECISIONS = ("fp32", "bf16")
"""Precisions :func:`evaluate_run` scores in (bf16: autocast; the weights stay fp32)."""


@dataclass
class EvalResult:
    """What :func:`evaluate_run` measured for one run."""

    run: Path
    split: str
    metrics: dict
    parameters: int
    fps: Rate
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
    """Scored and timed with :func:`~radarpc.models.fast.fast_inference`'s copy of the model."""
    easy: bool = False
    """Scored in RADIal's easy mode: ``Difficult`` labels dropped (:func:`evaluate_run`)."""
    empty_frames: bool = True
    """Frames without a vehicle to score were scored too (their false alarms count)."""
    training: dict | None = None
    """What the weights are (:func:`training_status`): their epoch and step, and whether the run
    had finished (None for the classical detector)."""

    @property
    def stem(self) -> str:
        """The name of the written files: ``eval_{split}``, then ``_on_{scored_on}`` for data not
        the run's own, ``_easy`` in RADIal's easy mode, ``_vehicle_frames`` without the frames that have no vehicle
        to score, ``_mirror`` when mirror-averaged, ``_fast``
        for the fast inference copy and ``_{precision}`` unless fp32."""
        return (f"eval_{self.split}" + (f"_on_{self.scored_on}" if self.scored_on else "")
                + ("_easy" if self.easy else "") + ("" if self.empty_frames else "_vehicle_frames")
                + ("_mirror" if self.mirror_average else "") + ("_fast" if self.fast else "")
                + ("" if self.precision == "fp32" else f"_{self.precision}"))


def _load_run(folder: Path) -> tuple[ExperimentConfig, dict]:
    key = read_json(folder / "run.json")
    if not isinstance(key, dict) or "experiment" not in key:
        raise DataFileError(folder / "run.json", "not a radarpc training run key (no 'experiment')")
    return experiment_from_dict(key["experiment"], where=str(folder / "run.json")), key


def load_trained(folder: str | os.PathLike, device: torch.device | str = "cpu"
                 ) -> tuple[ExperimentConfig, torch.nn.Module, dict]:
    """The config, model with its best weights (in eval mode, on ``device``) and run key of the
    training run folder ``folder``.

    Raises
    ------
    DataFileError
        ``run.json`` is missing or is not a training run's; ``best.safetensors`` is not a weights
        file, was written under another run key (copied in from another run), holds non-finite
        values, or does not fit the model of the run's config.
    FileNotFoundError
        The run has no best weights yet.
    """
    folder = Path(folder)
    cfg, key = _load_run(folder)
    best = folder / BEST_WEIGHTS
    if best.is_dir():
        raise DataFileError(best, "is a folder; expected the run's best weights (a safetensors file)")
    if not best.is_file():
        raise FileNotFoundError(f"{folder}: no {BEST_WEIGHTS} yet (the run has not finished an epoch)")
    state, info = load_weights(best)
    if "run" in info and _comparable(info["run"]) != _comparable(key):
        raise DataFileError(best, f"these weights were trained under another run key than {folder / 'run.json'} "
                                  f"(another run's weights copied in?); evaluate them in their own run folder")
    model = cfg.build_model()
    load_model_state(model, state, best, f"model {cfg.model.variant!r} of {folder / 'run.json'}")
    return cfg, model.to(device).eval(), key


def _comparable(key: object) -> object:
    """A run key as two copies of one run compare it: read through the config types, without
    the software record."""
    if not isinstance(key, dict):
        return key
    return {k: v for k, v in canonical_key(key, num_workers=0).items() if k != "software"}


def evaluate_run(run: str | os.PathLike, split: str = "test", *, data: DataPaths | None = None,
                 points: DataPaths | None = None, device: str | None = None, show: int = 0,
                 fps_frames: int = 20, batch_size: int = 4, precision: str = "fp32", mirror_average: bool = False,
                 fast: bool = False, easy: bool | None = None, empty_frames: bool = True, progress: bool = True,
                 log: Callable[[str], None] = print, timed: bool = True,
                 show_frames: Sequence[int] = ()) -> list[EvalResult]:
    """Score the best weights of every run in ``run`` on ``split`` (see the module docstring).

    ``data`` / ``points`` override the roots and stores stored with the run (a moved dataset, or
    one root of a run trained on several). Scores on other data than the run's own go to files of
    their own, ``eval_{split}_on_{names}``, so they do not replace the run's own scores
    (:func:`_scored_on` gives the names).
    ``precision`` is one of :data:`EVAL_PRECISIONS`. ``mirror_average`` scores a pillar model
    averaged over each frame and its mirror image (:class:`~radarpc.models.mirror.MirrorAveraged`;
    two forward passes a frame) into ``eval_{split}[_on_...]_mirror.*``. ``fast`` scores and times
    :func:`~radarpc.models.fast.fast_inference`'s copy of the model (exact rewrites; fp32
    only; its first passes compile kernels, before the timing) into ``eval_{split}[...]_fast.*``.
    ``easy`` scores RADIal's easy mode, what its ``2-Test.py`` and ``3-Evaluation.py`` score unless
    given ``--difficult``: label rows with ``Difficult == 1`` dropped, and the frames all of whose
    vehicles are difficult (:class:`~radarpc.data.radial.RADIal` with ``difficult=False``), into
    ``eval_{split}[...]_easy.*``. Frames without vehicles stay in (RADIal's loader drops them with
    its easy rows), so their false alarms still count. ``easy=False`` scores every label. ``None``
    (the default) follows the run's config: every label, or easy mode for a run trained with
    ``difficult: false``. ``empty_frames=False`` also leaves out the frames without a vehicle to
    score, as RADIal's loader does in its easy mode (what its ``3-Evaluation.py`` scores by
    default), into ``eval_{split}[...]_vehicle_frames.*``. ``timed=False`` skips the frames/s timing
    (the result's rate is NaN): the scores alone, when the time of ``fps_frames`` timed sweeps matters.
    ``show_frames`` draws these frames (RADIal numSample) of the split besides the ``show`` spread
    over it, as :func:`_shown` draws them (``figures/{stem}_frame{numSample:06d}.png``).
    """
    if precision not in EVAL_PRECISIONS:
        raise ValueError(f"precision must be one of {EVAL_PRECISIONS}, got {precision!r}")
    if fast and precision != "fp32":
        raise ValueError(f"fast inference is float32 only (the Winograd transforms and the products per frequency "
                         f"need its precision), got {precision!r}")
    for name, value, low in (("fps_frames", fps_frames, 1), ("batch_size", batch_size, 1), ("show", show, 0),
                             *(("show_frames", n, 0) for n in show_frames)):
        if isinstance(value, bool) or not isinstance(value, int) or value < low:
            raise ValueError(f"{name.replace('_', '-')} must be an integer >= {low}, got {value!r}")
    dev = check_device(device, "--device") if device else torch.device("cuda" if torch.cuda.is_available() else "cpu")
    folders = run_folders(run)
    for folder in folders:
        # before the evaluation, not after it: its outputs go into the run folder
        check_writable(folder, "run folder")
    results = []
    for folder in folders:
        with locked_output(folder, "run folder"):       # not while the run trains or another evaluation writes
            remove_temp_files(folder, recursive=False)  # what a killed evaluation left half-written
            results.append(_evaluate_folder(folder, split, data, points, dev, show, fps_frames if timed else 0,
                                            batch_size, precision, mirror_average, fast, easy, empty_frames, log,
                                            tuple(show_frames)))
    if len(results) > 1:
        rows = [{"run": k, **{m: (r.metrics.get(m) if r.metrics.get(m) is not None else math.nan)
                              for m in SUMMARY_METRICS}} for k, r in enumerate(results)]
        write_summary(Path(run) / f"{results[0].stem}_summary", rows,
                       f"{split}: {len(results)} runs" + ("" if precision == "fp32" else f", {precision}")
                       + (", mirror-averaged" if mirror_average else ""))
    return results


def _evaluate_folder(folder: Path, split: str, data, points, dev: torch.device, show: int, fps_frames: int,
                     batch_size: int, precision: str, mirror_average: bool, fast: bool, easy: bool | None,
                     empty_frames: bool, log: Callable[[str], None], show_frames: tuple[int, ...] = ()) -> EvalResult:
    """:func:`evaluate_run` for one run folder (its lock held)."""
    from radarpc.viz import plot_detection_frame, plot_learning_curves

    if mirror_average:
        stored, _ = _load_run(folder)
        if stored.input_kind != "points":
            raise ValueError(f"{folder}: mirror averaging applies to point models; {stored.name!r} takes RD "
                             f"cubes (mirroring a cube would need the array's geometry)")
    cfg, model, key = load_trained(folder, dev)
    status = training_status(folder)
    if status["finished"] is False:
        log(f"{folder}: warning: the run has not finished (its last checkpoint is at epoch {status['epochs_done']}, "
            f"step {status['steps_done']}); scoring its best weights so far, from epoch {status['weights_epoch']}")
    if points is not None and cfg.input_kind != "points":
        raise ValueError(f"{folder}: model {cfg.model.variant!r} reads RD cubes, not point stores; drop --points")
    n_params = sum(p.numel() for p in model.parameters())
    if fast:
        from radarpc.models.fast import fast_inference

        model = fast_inference(model)
    roots = data or key["data"]
    stores = (points or key.get("points")) if cfg.input_kind == "points" else None
    run_easy = (not cfg.difficult) if easy is None else easy   # by default as the run was trained
    ds = detection_dataset(dataclasses.replace(cfg, difficult=not run_easy), roots, stores, split,
                           empty_frames=empty_frames)
    frames_of_items = item_frames(ds)
    drawn = _frame_items(frames_of_items, show_frames, split)     # a frame not in the split fails before scoring
    if mirror_average:
        model = MirrorAveraged(model, cfg.targets, sectors=mirror_sectors_of(ds))
    scored = _resolved(data_pairs(roots, stores))
    own = _resolved(data_pairs(key["data"], key.get("points") if stores is not None else None))
    collate = functools.partial(collate_detection, cfg=cfg)
    loader = DataLoader(ds, batch_size=batch_size, shuffle=False, collate_fn=collate)
    found: list[Detections] = []
    with torch.inference_mode(), autocast_context(precision, dev):
        report, miou = evaluate_model(model, loader, dev, cfg.targets, max_candidates=None,
                                      on_detections=found.append)
    metrics = report.to_dict()
    metrics["freespace_miou"] = miou
    if metrics["n_labels"] == 0:
        log(f"{folder}: warning: the {split} split of {', '.join(str(r) for r, _ in scored)} holds no labels "
            f"(in this mode): recall and F1 mean nothing here")
    single = DataLoader(ds, batch_size=1, shuffle=False, collate_fn=collate)
    frames = []
    for b in single if fps_frames > 0 else ():          # 0: not timed
        frames.append(b.to(dev))
        if len(frames) >= fps_frames:
            break
    with torch.inference_mode(), autocast_context(precision, dev):
        fps = frames_per_second(lambda b: model(b.inputs), frames, dev)
    res = EvalResult(folder, split, metrics, n_params, fps, str(dev), torch.get_num_threads(), precision,
                     data=tuple(str(r) for r, _ in scored),
                     points=None if stores is None else tuple(str(p) for _, p in scored),
                     scored_on=_scored_on(scored, own), mirror_average=mirror_average, fast=fast, easy=run_easy,
                     empty_frames=empty_frames, training=status)
    _write_eval(folder, res, cfg.name, frames_of_items)
    _write_detections(folder / f"{res.stem}_detections.csv", frames_of_items, found)
    curve = folder / "figures" / "learning_curve.png"
    if (folder / LOG_CSV).is_file() and not _newer(curve, folder / LOG_CSV):     # drawn once per log, not per evaluation
        plot_learning_curves({cfg.name: folder / LOG_CSV}, curve)
    shown = _shown(ds, show, collate) + [(i, collate([ds[i]])) for i in drawn]
    if shown:
        with torch.inference_mode(), autocast_context(precision, dev):
            names = _frame_names(frames_of_items)
            for k, b in shown:
                b = b.to(dev)
                out = model(b.inputs)
                dets = decode_detections(out.detection.float(), cfg.targets, threshold=FIXED_THRESHOLD)
                plot_detection_frame(b.to(torch.device("cpu")), dets.to("cpu"), out.detection[0, 0].float().cpu(),
                                     folder / "figures" / f"{res.stem}_{names[k]}.png",
                                     title=f"{cfg.name} {split} {names[k]} ({len(b.labels)} labels)")
    log(f"{folder}: {split} F1 {metrics['f1']:.4f} (AP {metrics['ap']:.4f}, AR {metrics['ar']:.4f}), "
        f"F1@0.2 {metrics['f1_fixed']:.4f}, freespace mIoU {miou if miou is not None else float('nan'):.4f}, "
        f"{n_params:,} parameters, {fps.text()} at batch 1 on {dev}, {precision}"
        + (", mirror-averaged" if mirror_average else "") + (", fast inference copy" if fast else ""))
    return res


def _write_detections(path: Path, frames: list[tuple[Path, int]], found: list[Detections]) -> None:
    per_frame = [d.frame(b).rows().double().numpy() for d in found for b in range(len(d))]
    if len(per_frame) != len(frames):
        raise RuntimeError(f"{len(per_frame)} frames of detections for {len(frames)} items")
    write_detections(path, [(root.name, num) for root, num in frames], per_frame)


def _frame_names(frames: list[tuple[Path, int]]) -> list[str]:
    """Figure names of items: ``frame000123`` (RADIal's numSample), prefixed by the root's folder
    name when several roots are scored."""
    several = len({root for root, _ in frames}) > 1
    return [(f"{root.name}_" if several else "") + f"frame{num:06d}" for root, num in frames]


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


def _newer(path: Path, than: Path) -> bool:
    """Whether ``path`` exists and was written after ``than`` (at the same instant counts as not newer)."""
    return path.is_file() and path.stat().st_mtime_ns > than.stat().st_mtime_ns


def _shown(ds, k: int, collate) -> list[tuple[int, DetectionBatch]]:
    """``k`` items spread evenly over ``ds`` (first and last included), each a batch of one: the
    figures of ``--show`` (the first items of a split are often one sequence's empty frames)."""
    n = len(ds)
    k = min(k, n)                                   # more asked than there are: each item once
    picks = sorted({round(i * (n - 1) / max(k - 1, 1)) for i in range(k)})
    return [(i, collate([ds[i]])) for i in picks]


def _frame_items(frames: list[tuple[Path, int]], numbers: Sequence[int], split: str) -> list[int]:
    """The items whose numSample is one of ``numbers`` (``frames``: :func:`item_frames`), in the order
    given; every item of a number when several roots hold it.

    Raises
    ------
    ValueError
        A number is not a frame of the split.
    """
    picked = []
    for n in dict.fromkeys(numbers):
        items = [i for i, (_, num) in enumerate(frames) if num == n]
        if not items:
            raise ValueError(f"frame {n} (numSample) is not among the {len(frames)} frames of the {split} split "
                             f"scored here; choose one of them to draw")
        picked += items
    return picked


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
    found = []
    for batch in DataLoader(ds, batch_size=16, shuffle=False, collate_fn=collate):
        dets = classical_detect(batch.inputs, cfg)
        det.update(dets, batch.labels, batch.label_offset)
        found.append(dets.to("cpu"))
    metrics = det.compute().to_dict()
    metrics["freespace_miou"] = None
    frames = [b for _, b in zip(range(fps_frames), DataLoader(ds, batch_size=1, shuffle=False, collate_fn=collate))]
    fps = frames_per_second(lambda b: classical_detect(b.inputs, cfg), frames, torch.device("cpu"))
    res = EvalResult(out, split, metrics, 0, fps, "cpu",
                     torch.get_num_threads(), data=(str(Path(data).resolve()),), points=(str(Path(points).resolve()),),
                     easy=not difficult)
    frames_of_items = item_frames(ds)
    _write_eval(out, res, "classical (CFAR points, Doppler gating, BEV clusters)", frames_of_items)
    _write_detections(out / f"{res.stem}_detections.csv", frames_of_items, found)
    names = _frame_names(frames_of_items)
    for k, b in _shown(ds, show, collate):
        rows = classical_detect(b.inputs, cfg).rows()
        shown = Detections.from_frames([rows[rows[:, 0] >= FIXED_THRESHOLD]])
        plot_detection_frame(b, shown, None, out / "figures" / f"eval_{split}_{names[k]}.png",
                             title=f"classical {split} {names[k]} ({len(b.labels)} labels)")
    log(f"{out}: classical {split} F1 {metrics['f1']:.4f} (AP {metrics['ap']:.4f}, AR {metrics['ar']:.4f}), "
        f"F1@0.2 {metrics['f1_fixed']:.4f}, {fps.text()} at batch 1")
    return res


def _write_eval(folder: Path, res: EvalResult, name: str, frames: list[tuple[Path, int]]) -> None:
    """``{res.stem}.json`` / ``.md`` and ``figures/{res.stem}_labels.png`` (what became of the
    labels at each threshold, :func:`radarpc.viz.plot_label_outcomes`); the json lists ``frames``
    (root folder name, numSample), the frames of the detections file (:mod:`radarpc.eval.detection_files`)."""
    from radarpc.viz import plot_label_outcomes

    m = res.metrics
    doc = {"split": res.split, "data": list(res.data), "points": list(res.points) if res.points else None,
           "metrics": m, "parameters": res.parameters, "fps_batch1": res.fps.median,
           "fps_batch1_range": [res.fps.low, res.fps.high], "fps_sweeps": res.fps.repeats,
           "device": res.device, "threads": res.threads, "precision": res.precision,
           "mirror_average": res.mirror_average, "fast": res.fast, "easy": res.easy,
           "empty_frames": res.empty_frames, "training": res.training}
    doc["frames"] = {"root": [root.name for root, _ in frames], "numSample": [int(n) for _, n in frames]}
    with atomic_write(folder / f"{res.stem}.json", "w") as f:
        json.dump(doc, f, indent=2)
    thr = ", ".join(f"{t:.1f}" for t in m["thresholds"])
    lines = [
        f"# {name}: {res.split} split ({m['n_frames']} frames)"
        + ("" if res.precision == "fp32" else f", {res.precision} autocast")
        + (", RADIal's easy mode (Difficult labels dropped)" if res.easy else "")
        + ("" if res.empty_frames else ", frames without a vehicle to score left out (RADIal's loader)")
        + (f", UNFINISHED run: best weights so far, from epoch {res.training['weights_epoch']}"
           if res.training and res.training["finished"] is False else "")
        + (", averaged over each frame and its mirror image" if res.mirror_average else "")
        + (", fast inference copy (radarpc.models.fast)" if res.fast else ""), "",
        "| AP | AR | F1 | F1 @ 0.2 | range error (m) | azimuth error (deg) | freespace mIoU | parameters | frames/s (batch 1) |",
        "|---|---|---|---|---|---|---|---|---|",
        f"| {m['ap']:.4f} | {m['ar']:.4f} | {m['f1']:.4f} | {m['f1_fixed']:.4f} | {m['range_error_m']:.3f} | "
        f"{m['azimuth_error_deg']:.3f} | "
        f"{(m['freespace_miou'] if m['freespace_miou'] is not None else math.nan):.4f} | {res.parameters:,} | "
        f"{res.fps.median:.3g} ({res.fps.low:.3g}-{res.fps.high:.3g}; {res.device}, {res.threads} threads) |", "",
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
