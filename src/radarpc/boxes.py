"""RADIal's vehicle detections and their evaluation boxes: the geometry shared by the detection
models (which decode detections) and the metrics (which score them).

A detection is a point ``(R, A)``: ground range (m) and azimuth (deg, left positive) of the
vehicle's reference point, with a confidence score. :class:`Detections` holds the detections of
``B`` frames concatenated with a cumulative ``offset``, the convention of
:class:`radarpc.points.PointCloudBatch`.

RADIal's metric (``FFTRadNet/utils/metrics.py``; facts, not code, carried over) turns every point
into a fixed axis-aligned box in the frame ``x = R sin A`` (lateral), ``y = R cos A`` (forward),
:data:`BOX_WIDTH_M` wide and :data:`BOX_LENGTH_M` long, with its near edge centred on the point:
``[x - W/2, x + W/2] x [y, y + L]`` (:func:`ra_to_box_xy`). Two such boxes overlap by
``max(0, W - |dx|) max(0, L - |dy|)`` (:func:`box_iou`).

This module is a data contract: it imports nothing of radarpc but the contract :mod:`radarpc.points`,
so that the metrics (:mod:`radarpc.eval`) read detections without importing a model.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Sequence

import numpy as np
import torch

from radarpc.points import frame_span

__all__ = [
    "BOX_WIDTH_M",
    "BOX_LENGTH_M",
    "Detections",
    "ra_to_box_xy",
    "box_iou",
]

BOX_WIDTH_M = 1.8
"""Width (across, x here = lateral) of RADIal's fixed evaluation box."""
BOX_LENGTH_M = 4.0
"""Length (along the forward axis) of RADIal's fixed evaluation box."""


@dataclass
class Detections:
    """Point detections of ``B`` frames, concatenated; frame ``b`` holds rows
    ``offset[b-1]:offset[b]`` (``offset[-1] = K``), sorted by decreasing score within a frame.

    Attributes
    ----------
    score : float32 ``(K,)``         confidence in [0, 1]
    range_m : float32 ``(K,)``       ground range of the vehicle's reference point
    azimuth_deg : float32 ``(K,)``   azimuth, left positive
    offset : LongTensor ``(B,)``     cumulative end row of each frame
    """

    score: torch.Tensor
    range_m: torch.Tensor
    azimuth_deg: torch.Tensor
    offset: torch.Tensor

    def __len__(self) -> int:
        """Number of frames."""
        return int(self.offset.numel())

    @property
    def num_detections(self) -> int:
        return int(self.score.numel())

    def frame(self, b: int) -> "Detections":
        """The detections of frame ``b`` alone (a batch of one)."""
        _, start, end = frame_span(self.offset, b)
        return Detections(self.score[start:end], self.range_m[start:end], self.azimuth_deg[start:end],
                          self.offset.new_tensor([end - start]))

    def rows(self) -> torch.Tensor:
        """``(K, 3)`` columns ``(score, range_m, azimuth_deg)``."""
        return torch.stack([self.score, self.range_m, self.azimuth_deg], dim=1)

    def to(self, device: torch.device | str) -> "Detections":
        return Detections(**{f.name: getattr(self, f.name).to(device) for f in dataclasses.fields(self)})

    @staticmethod
    def from_frames(frames: Sequence[torch.Tensor], device: torch.device | str | None = None) -> "Detections":
        """Concatenate per-frame ``(K_b, 3)`` ``(score, range_m, azimuth_deg)`` tensors (any order
        within a frame; rows are sorted by decreasing score here)."""
        parts, counts = [], []
        for k, f in enumerate(frames):
            f = torch.as_tensor(f, dtype=torch.float32, device=device)
            if f.ndim != 2 or f.shape[1] != 3:
                raise ValueError(f"frame {k}: expected a (K, 3) (score, range_m, azimuth_deg) tensor, "
                                 f"got shape {tuple(f.shape)}")
            parts.append(f[torch.sort(f[:, 0], descending=True, stable=True).indices])
            counts.append(f.shape[0])
        dev = parts[0].device if parts else device
        rows = torch.cat(parts) if parts else torch.zeros(0, 3, device=dev)
        offset = torch.cumsum(torch.tensor(counts, dtype=torch.int64, device=dev), 0)
        return Detections(rows[:, 0].contiguous(), rows[:, 1].contiguous(), rows[:, 2].contiguous(), offset)


def ra_to_box_xy(range_m: torch.Tensor, azimuth_deg: torch.Tensor) -> torch.Tensor:
    """RADIal's evaluation box of each point: ``(..., 2)`` its near-edge centre ``(x, y)``.

    RADIal's metric uses ``x = R sin A`` (lateral) and ``y = R cos A`` (forward) and places an
    axis-aligned box ``[x - W/2, x + W/2] x [y, y + L]`` (``W`` = :data:`BOX_WIDTH_M`, ``L`` =
    :data:`BOX_LENGTH_M`) with its near edge centred on the point.

    On the CPU (without autograd) the box is computed in float64 by numpy and returned in the
    inputs' dtype: torch's CPU ``sin``/``cos`` run through MKL VML, whose first call on an OpenMP
    worker after an MKL GEMM came out of some processes at reduced accuracy (1e-4 relative in
    float32, 1e-8 in float64; torch 2.13, ``docs/notebook/scripts/vml_first_call.py``), and these positions
    decide NMS and true positives at IoU thresholds, so they must be the same in every process.
    """
    if range_m.device.type == azimuth_deg.device.type == "cpu" and not (range_m.requires_grad
                                                                        or azimuth_deg.requires_grad):
        r = range_m.detach().to(torch.float64).numpy()
        a = np.deg2rad(azimuth_deg.detach().to(torch.float64).numpy())
        dtype = torch.result_type(range_m, azimuth_deg)                        # as torch's sin would give
        dtype = dtype if dtype.is_floating_point else torch.get_default_dtype()
        return torch.from_numpy(np.stack([r * np.sin(a), r * np.cos(a)], axis=-1)).to(dtype)
    a = torch.deg2rad(azimuth_deg)
    return torch.stack([range_m * torch.sin(a), range_m * torch.cos(a)], dim=-1)


def box_iou(xy_a: torch.Tensor, xy_b: torch.Tensor) -> torch.Tensor:
    """Pairwise IoU ``(N, M)`` of RADIal's fixed boxes given by their near-edge centres
    ``(N, 2)``, ``(M, 2)`` (:func:`ra_to_box_xy`).

    All boxes are ``W x L`` and axis-aligned, so ``inter = max(0, W - |dx|) max(0, L - |dy|)`` and
    ``IoU = inter / (2 W L - inter)``: the polygon IoU of the official code, in closed form.
    """
    d = (xy_a[:, None, :] - xy_b[None, :, :]).abs()                        # (N, M, 2)
    inter = (BOX_WIDTH_M - d[..., 0]).clamp(min=0) * (BOX_LENGTH_M - d[..., 1]).clamp(min=0)
    return inter / (2 * BOX_WIDTH_M * BOX_LENGTH_M - inter)
