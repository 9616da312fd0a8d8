"""RADIal detection and freespace: the datasets of an experiment and the task the loop trains.

:class:`RadialDetectionTask` gives the loop (:mod:`radarpc.training.loop`) its datasets
(:class:`~radarpc.data.radial.RADIal` for cubes, :class:`~radarpc.data.point_dataset.PointCloudDataset`
for points), a collate that encodes the target maps in the loader's workers, the weighted RADIal
loss, and validation by RADIal's metrics (:mod:`radarpc.eval.detection`). What it trains is an
:class:`~radarpc.experiments.radial_detection.config.ExperimentConfig`.
"""
from __future__ import annotations

import os
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterable, Sequence

import torch
from torch import nn

from radarpc.data.augment import MirroredFrames, RotatedFrames, SuperposedFrames
from radarpc.data.point_dataset import PointCloudDataset, PointFrameBatch, collate_point_frames
from radarpc.data.radial import LabelTable, RADIal, label_problems, label_reach_m, read_labels, root_sensor
from radarpc.data.radial_format import SPARSE_RD_MANIFEST
from radarpc.eval.detection import DetectionMetrics, FreespaceMetrics
from radarpc.io import DataFileError
from radarpc.machine import physical_memory_bytes
from radarpc.experiments.radial_detection.config import ExperimentConfig
from radarpc.models.fftradnet import FFTRadNet, input_statistics
from radarpc.models.heads import HeadOutput
from radarpc.models.losses import detection_loss
from radarpc.boxes import Detections
from radarpc.models.targets import TargetConfig, decode_detections, encode_batch
from radarpc.points import PointCloudBatch

__all__ = ["DetectionBatch", "RadialDetectionTask", "collate_cubes", "collate_points",
           "collate_detection", "detection_dataset", "data_pairs", "ConcatFrames", "DataPaths",
           "evaluate_model", "check_root", "item_frames", "frames_without_vehicles", "point_datasets", "recorded_datasets", "preload_point_frames", "preload_budget_bytes", "DECODE_THRESHOLD", "MAX_CANDIDATES"]

DataPaths = str | os.PathLike | Sequence[str | os.PathLike]
"""One path, or several in order (dataset roots, or their point stores)."""

DECODE_THRESHOLD = 0.05
"""RADIal's decoding threshold: cells with probability >= 0.05 become candidates before NMS."""
MAX_CANDIDATES = 512
"""At most this many of the most probable cells per frame enter NMS during validation: an
untrained model puts most of the 28,672 cells above 0.05, and greedy NMS is sequential."""


@dataclass
class DetectionBatch:
    """A collated batch: model input, offset-batched labels, freespace and encoded targets.

    Attributes
    ----------
    inputs : complex Tensor ``(B, Nr, Nd, Nrx)`` or PointCloudBatch
    labels : float32 ``(M, 14)``, frame ``b`` rows ``label_offset[b-1]:label_offset[b]``
    label_offset : LongTensor ``(B,)``
    freespace : bool ``(B, 256, 224)``
    target : float32 ``(B, 3, 128, 224)``
    """

    inputs: torch.Tensor | PointCloudBatch
    labels: torch.Tensor
    label_offset: torch.Tensor
    freespace: torch.Tensor
    target: torch.Tensor

    def to(self, device: torch.device) -> "DetectionBatch":
        return DetectionBatch(self.inputs.to(device), self.labels.to(device), self.label_offset.to(device),
                              self.freespace.to(device), self.target.to(device))


def collate_cubes(items: list, targets: TargetConfig) -> DetectionBatch:
    """Collate ``RADIal`` items ``(rd, labels, freespace)`` and encode their targets."""
    labels = [it[1] for it in items]
    offset = torch.cumsum(torch.tensor([len(x) for x in labels], dtype=torch.int64), 0)
    lab = torch.cat(labels) if labels else torch.zeros(0, 14)
    return DetectionBatch(torch.stack([it[0] for it in items]), lab, offset,
                          torch.stack([it[2] for it in items]), encode_batch(lab, offset, targets))


def collate_points(items: list, targets: TargetConfig) -> DetectionBatch:
    """Collate ``PointCloudDataset`` items and encode their targets."""
    b: PointFrameBatch = collate_point_frames(items)
    return DetectionBatch(b.points, b.labels, b.label_offset, b.freespace,
                          encode_batch(b.labels, b.label_offset, targets))


def collate_detection(items: list, cfg: ExperimentConfig) -> DetectionBatch:
    """Collate items of :func:`detection_dataset` and encode their target maps."""
    if cfg.input_kind == "rd":
        return collate_cubes(items, cfg.targets)
    return collate_points(items, cfg.targets)


def data_pairs(data: DataPaths, points: DataPaths | None = None) -> list[tuple[Path, Path | None]]:
    """Pair the RADIal roots ``data`` with their point stores ``points``, in order.

    ``data`` is one root or a sequence of roots; ``points`` is None (RD cubes), one store or a
    sequence of stores, one per root.

    Raises
    ------
    ValueError
        No root, a root or store given twice (its frames would count twice), or a number of stores
        that is not the number of roots.
    """
    def paths(given: DataPaths) -> list[Path]:
        return [Path(given)] if isinstance(given, (str, os.PathLike)) else [Path(g) for g in given]

    roots = paths(data)
    if not roots:
        raise ValueError("no dataset root given (--data ROOT [ROOT ...])")
    stores = None if points is None else paths(points)
    for what, given in (("dataset root", roots), ("point store", stores or [])):
        seen: dict[Path, Path] = {}
        for p in given:
            same = seen.setdefault(p.resolve(), p)
            if same is not p:
                raise ValueError(f"{p}: the same {what} is given twice ({same} and {p}); its frames would count "
                                 f"twice")
    if stores is None:
        return [(r, None) for r in roots]
    if len(stores) != len(roots):
        raise ValueError(f"{len(roots)} dataset roots ({', '.join(map(str, roots))}) but {len(stores)} point "
                         f"stores ({', '.join(map(str, stores))}): give one store per root, in the same order")
    return list(zip(roots, stores))


class ConcatFrames(torch.utils.data.ConcatDataset):
    """The frames of several roots, one after another (``torch.utils.data.ConcatDataset``) that
    passes :meth:`set_epoch` on to the datasets that draw per epoch (mirroring, rotation)."""

    def set_epoch(self, epoch: int) -> None:
        for ds in self.datasets:
            if hasattr(ds, "set_epoch"):
                ds.set_epoch(epoch)


def check_root(root: Path) -> None:
    """Refuse, naming it, a dataset root that is missing, a file or an empty folder."""
    if not root.exists():
        raise DataFileError(root, "dataset root does not exist")
    if not root.is_dir():
        raise DataFileError(root, "is a file; expected a RADIal-layout root folder (labels.csv, radar_FFT/, ...)")
    if not any(root.iterdir()):
        raise DataFileError(root, "is an empty folder; expected a RADIal-layout root (labels.csv, radar_FFT/, ...)")


def frames_without_vehicles(labels: LabelTable, difficult: bool) -> list[int]:
    """RADIal frame numbers with no vehicle to score: no vehicle row at all, or (with ``difficult``
    False) only ``Difficult`` ones. RADIal's own loader drops them in its easy mode."""
    scored = labels.has_vehicle & ((labels.difficult == 0) | difficult)
    return sorted(set(labels.num_sample.tolist()) - set(labels.num_sample[scored].tolist()))


def _root_dataset(cfg: ExperimentConfig, data: Path, points: Path | None, split: str, empty_frames: bool = True):
    check_root(data)
    labels = read_labels(data / "labels.csv")
    problems = label_problems(labels, label_reach_m(root_sensor(data)[0]))
    if problems:
        more = f"; {len(problems) - 3} more" if len(problems) > 3 else ""
        raise DataFileError(labels.path, f"labels no radar could have measured: {'; '.join(problems[:3])}{more} "
                                         f"(`radarpc info {data} --check` lists them all)")
    skip = None if empty_frames else frames_without_vehicles(labels, cfg.difficult)
    if cfg.input_kind == "rd":
        ds = RADIal(data, split=split, difficult=cfg.difficult, skip=skip)
        fc = cfg.model.config
        if ds.sensor.rd_shape != (fc.n_range, fc.n_doppler, fc.n_rx):
            raise ValueError(f"{data}: cubes of sensor {ds.sensor.name!r} are {ds.sensor.rd_shape}, the "
                             f"model takes ({fc.n_range}, {fc.n_doppler}, {fc.n_rx}); pick the config of "
                             f"this sensor (e.g. fftradnet-s for radial-s)")
        return ds
    if points is None:
        raise ValueError(f"experiment {cfg.name!r} trains on point clouds: give the point store "
                         f"(--points FILE.parquet, made by `radarpc pointcloud {data}`)")
    return PointCloudDataset(points, data, split=split, difficult=cfg.difficult, skip=skip)


def detection_dataset(cfg: ExperimentConfig, data: DataPaths, points: DataPaths | None = None,
                      split: str = "train", *,
                      augment_seed: int | None = None, empty_frames: bool = True):
    """The dataset of ``split`` for ``cfg``'s input: RD cubes of ``data``, or the point store
    ``points`` joined with ``data``'s labels.

    Parameters
    ----------
    cfg : ExperimentConfig
    data : path-like or sequence of path-like
        One RADIal root, or several whose frames are used one after another (:class:`ConcatFrames`),
        each root with its own split.
    points : path-like or sequence of path-like, optional
        The point store of each root (pillar models); ignored by FFTRadNet.
    split : {"train", "val", "test", "all"}
    empty_frames : bool
        Keep the frames without a vehicle to score (their false alarms count; radarpc's default).
        False leaves them out (:func:`frames_without_vehicles`), as RADIal's loader does in its
        easy mode.
    augment_seed : int, optional
        Mirror ``cfg.mirror_probability`` of the items (:class:`MirroredFrames`), rotate them by up
        to ``cfg.rotation_max_deg`` (:class:`RotatedFrames`) and superpose ``cfg.superpose_probability``
        of the RD items (:class:`SuperposedFrames`) at random, drawn from this seed (and the
        root's position, so roots draw independently). None: the frames as they are.

    Raises
    ------
    ValueError
        Roots and stores do not pair up (:func:`data_pairs`), a root's cubes do not fit the model,
        superposition asked of a sparse-RD root,
        a pillar model without stores, or stores of different point features (enrichments).
    """
    if cfg.input_kind == "rd" and points is not None:
        raise ValueError(f"experiment {cfg.name!r}: model {cfg.model.variant!r} reads RD cubes, not point stores; "
                         f"drop --points (give a sparse-RD root as --data for the sparse-RD baseline)")
    pairs = data_pairs(data, points if cfg.input_kind == "points" else None)
    parts = []
    for k, (root, store) in enumerate(pairs):
        if augment_seed is not None and cfg.superpose_probability > 0 and (Path(root) / SPARSE_RD_MANIFEST).exists():
            raise ValueError(f"{root} is a sparse-RD root: the sum of two sparse cubes is not the sparse RD of "
                             f"both scenes (its mask is a CFAR decision); set superpose_probability to 0")
        ds = _root_dataset(cfg, root, store, split, empty_frames)
        if parts and cfg.input_kind == "points" and ds.store.metadata.enrich != parts[0].store.metadata.enrich:
            raise ValueError(f"point stores of different features cannot train one model: {store} has the "
                             f"enrichments {list(ds.store.metadata.enrich)}, {parts[0].store.path} has "
                             f"{list(parts[0].store.metadata.enrich)}")
        parts.append(ds)
    if augment_seed is not None and cfg.mirror_probability > 0:
        parts = [MirroredFrames(ds, cfg.mirror_probability, augment_seed, stream=k) for k, ds in enumerate(parts)]
    if augment_seed is not None and cfg.rotation_max_deg > 0:
        parts = [RotatedFrames(ds, cfg.rotation_max_deg, augment_seed, stream=k) for k, ds in enumerate(parts)]
    if augment_seed is not None and cfg.superpose_probability > 0:
        parts = [SuperposedFrames(ds, cfg.superpose_probability, augment_seed, stream=k) for k, ds in enumerate(parts)]
    return parts[0] if len(parts) == 1 else ConcatFrames(parts)


def recorded_datasets(ds) -> list:
    """The datasets of recorded frames inside ``ds`` (a dataset of :func:`detection_dataset`), in
    root order, without the augmentation wrappers (mirror, rotation, superposition)."""
    while isinstance(ds, (MirroredFrames, RotatedFrames, SuperposedFrames)):
        ds = ds.frames
    return [r for d in ds.datasets for r in recorded_datasets(d)] if isinstance(ds, ConcatFrames) else [ds]


def item_frames(ds) -> list[tuple[Path, int]]:
    """``(root, numSample)`` of every item of ``ds`` (a dataset of :func:`detection_dataset`), in
    item order: RADIal's frame number of each item."""
    return [(Path(d.root), int(n)) for d in recorded_datasets(ds) for n in d.frame_ids]


def point_datasets(ds) -> list[PointCloudDataset]:
    """The point datasets inside ``ds`` (a dataset of :func:`detection_dataset`), in order; [] for RD cubes."""
    return [d for d in recorded_datasets(ds) if isinstance(d, PointCloudDataset)]


def preload_budget_bytes() -> int:
    """Memory the point frames of a training run may take when preloaded: a quarter of the
    machine's memory, shared by the ranks torchrun starts on it (``LOCAL_WORLD_SIZE``); 0 where
    the memory cannot be read."""
    total = physical_memory_bytes()
    ranks = max(int(os.environ.get("LOCAL_WORLD_SIZE", "1")), 1)
    return 0 if total is None else total // (4 * ranks)


def preload_point_frames(datasets: Iterable, budget_bytes: int | None = None) -> int:
    """Preload the point frames of ``datasets`` (:meth:`PointCloudDataset.preload`) if they fit.

    Training reads the frames in random order, and each read from a store decodes a row group
    of many frames; preloaded, a frame is a slice in memory, so the loader's workers take little
    of the cores the model needs.

    Parameters
    ----------
    datasets : iterable
        Datasets of :func:`detection_dataset`; those without point frames are skipped.
    budget_bytes : int, optional
        Preload nothing when the frames, decoded, would take more (a warning says so). Default
        :func:`preload_budget_bytes`.

    Returns
    -------
    int
        Bytes held.
    """
    found = [p for ds in datasets for p in point_datasets(ds)]
    if not found:
        return 0
    need = sum(p.decoded_bytes() for p in found)
    budget = preload_budget_bytes() if budget_bytes is None else int(budget_bytes)
    if need > budget:
        warnings.warn(f"the point frames of {', '.join(sorted({str(p.store.path) for p in found}))} would take "
                      f"{need / 2**30:.2f} GiB decoded, above the preload budget of {budget / 2**30:.2f} GiB; "
                      f"they are read from the stores, which is slower in random order", stacklevel=2)
        return 0
    return sum(p.preload() for p in found)


class RadialDetectionTask:
    """The loop's :class:`~radarpc.training.loop.Task` for RADIal detection + freespace.

    Parameters
    ----------
    cfg : ExperimentConfig
    data : path-like or sequence of path-like
        RADIal-layout root (labels, freespace; cubes for FFTRadNet), or several
        (:func:`detection_dataset`).
    points : path-like or sequence of path-like, optional
        Point store made from each root (required by the pillar models).
    splits : (str, str)
        Training and validation splits of every root.
    preload : bool
        Hold the point frames of both splits in memory when they fit (:func:`preload_point_frames`).

    Attributes
    ----------
    preloaded_bytes : int
        What the preloaded point frames take (0 when none are).
    """

    def __init__(self, cfg: ExperimentConfig, data: DataPaths, points: DataPaths | None = None,
                 splits: tuple[str, str] = ("train", "val"), *, preload: bool = True) -> None:
        self.cfg = cfg
        self.train_set = detection_dataset(cfg, data, points, splits[0], augment_seed=cfg.train.seed)
        self.val_set = detection_dataset(cfg, data, points, splits[1])
        self.preloaded_bytes = preload_point_frames([self.train_set, self.val_set]) if preload else 0

    # ---- the Task protocol --------------------------------------------------------------------
    def build_model(self) -> nn.Module:
        model = self.cfg.build_model()
        if isinstance(model, FFTRadNet):
            parts = recorded_datasets(self.train_set)         # never superposed: what inference sees
            recorded = parts[0] if len(parts) == 1 else torch.utils.data.ConcatDataset(parts)
            n = len(recorded)
            k = min(self.cfg.statistics_frames, n)
            picks = sorted({round(i * (n - 1) / max(k - 1, 1)) for i in range(k)})
            mean, std = input_statistics(recorded[i][0] for i in picks)
            model.set_input_statistics(mean, std)
        return model

    def collate(self, items: list) -> DetectionBatch:
        return collate_detection(items, self.cfg)

    def to_device(self, batch: DetectionBatch, device: torch.device) -> DetectionBatch:
        return batch.to(device)

    def loss(self, model: nn.Module, batch: DetectionBatch) -> tuple[torch.Tensor, dict[str, float]]:
        out: HeadOutput = model(batch.inputs)
        terms = detection_loss(out.detection, batch.target, self.cfg.loss, out.freespace,
                               batch.freespace if out.freespace is not None else None)
        return terms.total, {"classification": float(terms.classification.detach()),
                             "regression": float(terms.regression.detach()),
                             "freespace": float(terms.freespace.detach())}

    def evaluate(self, model: nn.Module, batches: Iterable, device: torch.device) -> dict[str, float]:
        report, miou = evaluate_model(model, batches, device, self.cfg.targets)
        out = {k: v for k, v in report.to_dict().items() if isinstance(v, float)}
        if miou is not None:
            out["freespace_miou"] = miou
        return out


def evaluate_model(model: nn.Module, batches: Iterable[DetectionBatch], device: torch.device,
                   targets: TargetConfig, *, max_candidates: int | None = MAX_CANDIDATES,
                   on_detections: Callable[[Detections], None] | None = None):
    """RADIal's detection report and the freespace mIoU (None without a freespace head).

    ``on_detections`` is given each batch's decoded detections (on the CPU), in batch order.
    """
    det = DetectionMetrics()
    fs = FreespaceMetrics()
    has_fs = False
    for batch in batches:
        batch = batch.to(device)
        out: HeadOutput = model(batch.inputs)
        maps = out.detection.float()
        if max_candidates is not None:
            maps = _keep_top_cells(maps, max_candidates)
        dets = decode_detections(maps, targets, threshold=DECODE_THRESHOLD)
        det.update(dets, batch.labels, batch.label_offset)
        if on_detections is not None:
            on_detections(dets.to("cpu"))
        if out.freespace is not None:
            has_fs = True
            fs.update(torch.sigmoid(out.freespace.float())[:, 0], batch.freespace)
    return det.compute(), (fs.compute() if has_fs else None)


def _keep_top_cells(maps: torch.Tensor, k: int) -> torch.Tensor:
    """``maps`` with the probability of all but each frame's ``k`` most probable cells set to 0."""
    prob = maps[:, 0].flatten(1)                                          # (B, H W)
    if prob.shape[1] <= k:
        return maps
    kth = torch.topk(prob, k, dim=1).values[:, -1:]                      # (B, 1)
    keep = (prob >= kth).view_as(maps[:, 0])
    out = maps.clone()
    out[:, 0] = torch.where(keep, maps[:, 0], torch.zeros_like(maps[:, 0]))
    return out
