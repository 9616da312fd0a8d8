"""The learned baseline as a task of the training loop: frames, collate, loss and validation.

It reads a ColoRadar-layout root (:class:`radarpc.data.coloradar.ColoRadar`: real or simulated)
split by runs. Per frame:

* the input: the radar cube (:meth:`radarpc.data.coloradar.ColoRadar.cube`) as RaLD normalises it
  for its diffusion model, intensity clipped to ``[0, radar.max_intensity_db]`` dB, divided by it,
  then upsampled to the model's ``radar_shape`` (:func:`radarpc.data.coloradar.rald_intensity`);
* the target: the occupancy of the target grid (:meth:`OccupancyTarget.grid` over the root's field
  of view) by the frame's LiDAR points in the radar frame, cropped to the field of view: a cell is
  occupied when at least one point falls in it (:func:`radarpc.rald.frustum.voxelize`, RaLD's
  Eq. 7), as a dense ``(n_r, n_az, n_el)`` float tensor of 0 and 1;
* the loss: the weighted binary cross-entropy of :class:`~.config.OccupancyTarget` (mean over the
  cells and frames of the batch, occupied cells weighted by ``occupied_weight``);
* validation: per frame the same loss and, with the logits thresholded at 0 (probability 0.5, the
  cloud's default threshold), the IoU of the predicted and true occupied cells, the precision, the
  recall and their F1; each averaged over the frames (:data:`~.config.METRICS`).

Items draw nothing at random: a frame's input and target are functions of the frame, so a resumed
run reads what an uninterrupted one does.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable

import torch
import torch.nn.functional as F
from torch import nn
from torch.utils.data import Dataset

from radarpc.data.coloradar import ColoRadar, rald_intensity
from radarpc.experiments.rpdnet.config import OccupancyExperiment, OccupancyTarget
from radarpc.rald.frustum import FrustumGrid, voxelize

__all__ = ["OccupancyBatch", "OccupancyFrames", "occupancy_target", "weighted_bce", "occupancy_metrics",
           "evaluate_occupancy", "OccupancyTask"]


@dataclass
class OccupancyBatch:
    """A collated batch: normalised radar cubes ``(B, R, A, E)`` and target occupancies
    ``(B, n_r, n_az, n_el)`` (float, 0 or 1)."""

    radar: torch.Tensor
    occupied: torch.Tensor

    def to(self, device: torch.device) -> "OccupancyBatch":
        return OccupancyBatch(self.radar.to(device), self.occupied.to(device))


def occupancy_target(grid: FrustumGrid, xyz) -> torch.Tensor:
    """The dense occupancy ``(n_r, n_az, n_el)`` (float32, 0 or 1) of ``grid`` by the points ``xyz``
    ``(N, 3)`` (radar frame, metres; points outside the grid are dropped)."""
    return voxelize(grid, torch.as_tensor(xyz)).dense().to(torch.float32)


def weighted_bce(logits: torch.Tensor, occupied: torch.Tensor, occupied_weight: float) -> torch.Tensor:
    """``(1/N) sum_c [w y_c (-log sigma(s_c)) + (1 - y_c) (-log(1 - sigma(s_c)))]`` over all ``N``
    entries of ``logits`` and ``occupied`` (same shape), ``w = occupied_weight``."""
    return F.binary_cross_entropy_with_logits(logits, occupied, pos_weight=logits.new_tensor(occupied_weight))


class OccupancyFrames(Dataset):
    """``(radar (R, A, E), occupied (n_r, n_az, n_el))`` of each paired frame of a split."""

    def __init__(self, root: str | os.PathLike, split: str, target: OccupancyTarget,
                 radar_shape: tuple[int, int, int], max_intensity_db: float):
        self.frames = ColoRadar(root, split, cube_size=None)
        if len(self.frames) == 0:
            raise ValueError(f"{root}: split {split!r} has no paired radar / LiDAR frame (runs of this split: "
                             f"{', '.join(r.name for r in self.frames.runs) or 'none'})")
        self.grid = target.grid(self.frames.fov)
        self.radar_shape = tuple(radar_shape)
        self.max_intensity_db = float(max_intensity_db)

    def __len__(self) -> int:
        return len(self.frames)

    def __getitem__(self, i: int) -> tuple[torch.Tensor, torch.Tensor]:
        radar = rald_intensity(self.frames.cube(i), self.radar_shape, max_db=self.max_intensity_db)   # (R, A, E)
        return radar, occupancy_target(self.grid, self.frames.lidar_points(i))                        # (n_r, n_az, n_el)


def _collate(items: list) -> OccupancyBatch:
    return OccupancyBatch(*(torch.stack(t) for t in zip(*items)))


def occupancy_metrics(logits: torch.Tensor, occupied: torch.Tensor) -> dict[str, torch.Tensor]:
    """Per-frame scores ``(B,)`` of logits ``(B, ...)`` thresholded at 0 against the truth ``(B, ...)``:
    with ``P`` the predicted and ``O`` the occupied cells, ``iou = |P & O| / |P | O|``,
    ``precision = |P & O| / |P|``, ``recall = |P & O| / |O|``, ``f1`` their harmonic mean
    ``2 |P & O| / (|P| + |O|)``; each 1 where its denominator is 0 (nothing to get wrong)."""
    pred = (logits > 0).flatten(1)
    occ = occupied.flatten(1) > 0.5
    # counts of at most a grid's cells (< 2^24) are exact in float32, which every device has (MPS no float64)
    inter = (pred & occ).sum(1).float()
    n_pred, n_occ = pred.sum(1).float(), occ.sum(1).float()
    union = n_pred + n_occ - inter

    def ratio(num, den):
        return torch.where(den > 0, num / den.clamp_min(1), torch.ones_like(num))

    return {"iou": ratio(inter, union), "precision": ratio(inter, n_pred), "recall": ratio(inter, n_occ),
            "f1": ratio(2 * inter, n_pred + n_occ)}


@torch.no_grad()
def evaluate_occupancy(model: nn.Module, batches: Iterable[OccupancyBatch], device: torch.device,
                       occupied_weight: float) -> dict[str, float]:
    """The validation metrics (:data:`~.config.METRICS`), each the mean over frames of its
    per-frame value."""
    sums: dict[str, float] = {}
    n = 0
    for batch in batches:
        batch = batch.to(device)
        logits = model(batch.radar).float()                                   # (B, n_r, n_az, n_el)
        loss = torch.stack([weighted_bce(logits[b], batch.occupied[b], occupied_weight)
                            for b in range(logits.shape[0])])                 # (B,)
        for k, v in {"loss": loss, **occupancy_metrics(logits, batch.occupied)}.items():
            sums[k] = sums.get(k, 0.0) + float(v.detach().cpu().double().sum())
        n += logits.shape[0]
    return {k: v / max(n, 1) for k, v in sums.items()}


class OccupancyTask:
    """The loop's :class:`~radarpc.training.loop.Task` for the learned baseline.

    Parameters
    ----------
    cfg : OccupancyExperiment
    data : path-like
        A ColoRadar-layout root.
    splits : (str, str)
        Training and validation splits (:func:`radarpc.data.coloradar.split_runs`).

    Raises
    ------
    ValueError
        A split without paired frames; a root whose field of view cuts the target grid into
        another shape than the model writes.
    """

    def __init__(self, cfg: OccupancyExperiment, data: str | os.PathLike,
                 splits: tuple[str, str] = ("train", "val")) -> None:
        self.cfg = cfg
        self.root = Path(data)
        kw = dict(target=cfg.target, radar_shape=cfg.model.config.radar_shape,
                  max_intensity_db=cfg.radar.max_intensity_db)
        self.train_set = OccupancyFrames(data, splits[0], **kw)
        self.val_set = OccupancyFrames(data, splits[1], **kw)
        if self.train_set.grid.shape != cfg.model.config.out_shape:
            raise ValueError(f"{data}: its field of view cut into target.cell {list(cfg.target.cell)} gives "
                             f"{self.train_set.grid.shape} cells, but model {cfg.model.variant!r} writes "
                             f"{cfg.model.config.out_shape}")

    def build_model(self) -> nn.Module:
        return self.cfg.build_model()

    def collate(self, items: list) -> OccupancyBatch:
        return _collate(items)

    def to_device(self, batch: OccupancyBatch, device: torch.device) -> OccupancyBatch:
        return batch.to(device)

    def loss(self, model: nn.Module, batch: OccupancyBatch) -> tuple[torch.Tensor, dict[str, float]]:
        logits = model(batch.radar).float()                                   # (B, n_r, n_az, n_el)
        return weighted_bce(logits, batch.occupied, self.cfg.target.occupied_weight), {}

    def evaluate(self, model: nn.Module, batches: Iterable, device: torch.device) -> dict[str, float]:
        return evaluate_occupancy(model, batches, device, self.cfg.target.occupied_weight)
