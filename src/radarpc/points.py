"""The point-cloud batch type shared by the DSP, the point store, the datasets and the models.

Point clouds of ``B`` frames are concatenated along the point axis and delimited by a cumulative
``offset`` vector (Pointcept's convention): frame ``b`` holds points ``offset[b-1]:offset[b]``
(``offset[-1] = N``). :func:`offset2batch` / :func:`batch2offset` convert between that vector and a
per-point frame index; :func:`collate_clouds` concatenates clouds into one batch (a DataLoader
``collate_fn``).

This module is a data contract: it imports nothing of radarpc, so that a model can take point
clouds without importing the DSP stage that makes them or the store that keeps them.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Sequence

import torch

__all__ = [
    "frame_span",
    "FLOAT_FIELDS",
    "INT_FIELDS",
    "BOOL_FIELDS",
    "LIST_FIELDS",
    "POINT_FIELDS",
    "PointCloudBatch",
    "offset2batch",
    "batch2offset",
    "collate_clouds",
    "mirror_points",
]

FLOAT_FIELDS: tuple[str, ...] = (
    "range_m", "azimuth_deg", "elevation_deg", "velocity_mps", "amplitude", "snr", "x", "y", "z")
"""Per-point float32 fields."""
INT_FIELDS: tuple[str, ...] = ("doppler_bin", "range_bin", "doppler_full")
"""Per-point integer fields (int64 tensors)."""
BOOL_FIELDS: tuple[str, ...] = ("is_neighbour",)
"""Per-point boolean fields."""
LIST_FIELDS: tuple[str, ...] = ("sector", "rd_patch")
"""Optional per-point enrichment fields, float32 ``(N, k)`` or None."""
POINT_FIELDS: tuple[str, ...] = FLOAT_FIELDS + INT_FIELDS + BOOL_FIELDS
"""Every per-point field that is always present."""


def offset2batch(offset: torch.Tensor) -> torch.Tensor:
    """Frame index of every point from the cumulative ``offset`` ``(B,)``: ``(N,)`` long."""
    counts = torch.diff(offset, prepend=offset.new_zeros(1))
    return torch.repeat_interleave(torch.arange(offset.numel(), device=offset.device), counts)


def frame_span(offset: torch.Tensor, b: int) -> tuple[int, int, int]:
    """``(b, start, end)``: frame ``b`` (negative counts from the end) of an offset-batched tensor
    holds rows ``start:end``.

    Raises
    ------
    IndexError
        ``b`` outside the ``len(offset)`` frames.
    """
    n = offset.numel()
    if not -n <= b < n:
        raise IndexError(f"frame {b} out of range for a batch of {n} frames")
    b = b % n
    return b, (int(offset[b - 1]) if b > 0 else 0), int(offset[b])


def batch2offset(batch: torch.Tensor, n_frames: int | None = None) -> torch.Tensor:
    """Cumulative ``offset`` ``(B,)`` from a sorted per-point frame index ``batch`` ``(N,)``.

    ``n_frames`` gives ``B`` when trailing frames may be empty (they cannot be seen in ``batch``).

    Raises
    ------
    ValueError
        ``batch`` is not 1-D, not sorted, negative, or has frames beyond ``n_frames``.
    """
    if batch.ndim != 1:
        raise ValueError(f"batch must be a 1-D frame index, got shape {tuple(batch.shape)}")
    if batch.numel() and (int(batch.min()) < 0 or bool((batch[1:] < batch[:-1]).any())):
        raise ValueError("batch must be a sorted, non-negative frame index (points grouped by frame)")
    b = int(batch.max()) + 1 if batch.numel() else 0
    if n_frames is None:
        n_frames = b
    elif b > n_frames:
        raise ValueError(f"batch holds frame {b - 1} but n_frames={n_frames}")
    counts = torch.bincount(batch.long(), minlength=n_frames)
    return torch.cumsum(counts, 0)


@dataclass
class PointCloudBatch:
    """Spectral point clouds of ``B`` frames, concatenated; frame ``b`` holds points
    ``offset[b-1]:offset[b]`` (``offset[-1] = N``). All per-point tensors are ``(N, ...)``.

    Attributes
    ----------
    offset : LongTensor ``(B,)``         cumulative end index of each frame's points
    range_bin, doppler_bin : LongTensor  range bin and consolidated Doppler index ``l`` (the seed's d_j)
    doppler_full : LongTensor            resolved full-axis Doppler bin ``d0`` of Tx 0
    range_m, azimuth_deg, elevation_deg, velocity_mps : float32
    amplitude : float32                  ``Ae = |B v|`` at the argmax (eq. 7)
    snr : float32                        CA-CFAR SNR ``|E|^2 / mu`` of the point's consolidated cell
    x, y, z : float32                    metres, x forward, y left, z up
    is_neighbour : BoolTensor            True for points added by RD-neighbourhood enrichment
    sector : float32 ``(N, n_az_sec * n_el_sec)`` or None   angle-sector maxima (eq. 10)
    rd_patch : float32 ``(N, n * n)`` or None   ``E`` around the point's cell, row-major
        (range offset outer, Doppler offset inner), 0 outside the grid
    tau : float32 ``(B,)``               threshold used per frame
    density : float32 ``(B,)``           achieved density of the encoded set: ``|S*(tau)| / (Nr Nd)``
                                         with RD-neighbourhood points, else ``|S(tau)| / (Nr Nd)``
    peak_density : float32 ``(B,)`` or None   ``|S(tau)| / (Nr Nd)`` of the CFAR peaks alone
                                         (equals ``density`` without RD-neighbourhood points)
    """

    offset: torch.Tensor
    range_bin: torch.Tensor
    doppler_bin: torch.Tensor
    doppler_full: torch.Tensor
    range_m: torch.Tensor
    azimuth_deg: torch.Tensor
    elevation_deg: torch.Tensor
    velocity_mps: torch.Tensor
    amplitude: torch.Tensor
    snr: torch.Tensor
    x: torch.Tensor
    y: torch.Tensor
    z: torch.Tensor
    is_neighbour: torch.Tensor
    sector: torch.Tensor | None
    rd_patch: torch.Tensor | None
    tau: torch.Tensor
    density: torch.Tensor
    peak_density: torch.Tensor | None = None

    _PER_POINT = POINT_FIELDS + LIST_FIELDS

    def __len__(self) -> int:
        """Number of frames."""
        return int(self.offset.numel())

    @property
    def num_points(self) -> int:
        return int(self.range_bin.numel())

    def batch_index(self) -> torch.Tensor:
        """Frame index of every point, ``(N,)``."""
        return offset2batch(self.offset)

    def frame(self, b: int) -> "PointCloudBatch":
        """The cloud of frame ``b`` alone (a batch of one)."""
        b, start, end = frame_span(self.offset, b)
        kw = {k: (None if getattr(self, k) is None else getattr(self, k)[start:end]) for k in self._PER_POINT}
        peak = None if self.peak_density is None else self.peak_density[b:b + 1]
        return PointCloudBatch(offset=self.offset.new_tensor([end - start]), tau=self.tau[b:b + 1],
                               density=self.density[b:b + 1], peak_density=peak, **kw)

    def to(self, device: torch.device | str) -> "PointCloudBatch":
        kw = {f.name: (None if getattr(self, f.name) is None else getattr(self, f.name).to(device))
              for f in dataclasses.fields(self)}
        return PointCloudBatch(**kw)


def collate_clouds(clouds: Sequence[PointCloudBatch]) -> PointCloudBatch:
    """Concatenate clouds (e.g. items of a point store in a DataLoader) into one batch.

    Per-point tensors are concatenated, ``offset`` re-accumulated, ``tau`` / ``density`` (and
    ``peak_density`` when every input has it) stacked; every input must carry the same optional
    enrichments. Use as ``collate_fn``.
    """
    if not clouds:
        raise ValueError("collate_clouds needs at least one cloud")
    out: dict[str, torch.Tensor | None] = {}
    for name in POINT_FIELDS + LIST_FIELDS:
        parts = [getattr(c, name) for c in clouds]
        if any(p is None for p in parts):
            if not all(p is None for p in parts):
                raise ValueError(f"cannot collate clouds with and without {name!r}")
            out[name] = None
        else:
            out[name] = torch.cat(parts)
    counts = torch.cat([torch.diff(c.offset, prepend=c.offset.new_zeros(1)) for c in clouds])   # (B,)
    peaks = [c.peak_density for c in clouds]
    peak = None if any(p is None for p in peaks) else torch.cat(peaks)
    return PointCloudBatch(offset=torch.cumsum(counts, 0), tau=torch.cat([c.tau for c in clouds]),
                           density=torch.cat([c.density for c in clouds]), peak_density=peak, **out)


def mirror_points(points: PointCloudBatch, sectors: tuple[int, int] | None = None) -> PointCloudBatch:
    """``points`` (any number of frames) mirrored about the radar's boresight: ``azimuth_deg`` and
    ``y`` negated, the ``sector`` descriptor (``n_az_sec x n_el_sec``, azimuth-major) reversed
    along azimuth; range, elevation, Doppler and amplitude stay. The frame a radar with the mirrored
    array would see of the mirrored scene (:mod:`radarpc.data.augment` says when the sector reversal
    is exact).

    Parameters
    ----------
    points : PointCloudBatch
    sectors : (int, int), optional
        ``(n_az_sec, n_el_sec)`` of the points' ``sector`` descriptor (the store's
        ``sectorAxE`` enrichment); required when the points carry one.

    Returns
    -------
    PointCloudBatch
        New tensors where they change; ``points`` is not modified.

    Raises
    ------
    ValueError
        The points carry a sector descriptor and ``sectors`` is missing or does not match its width.
    """
    sector = points.sector
    if sector is not None:
        if sectors is None or sectors[0] * sectors[1] != sector.shape[1]:
            raise ValueError(f"the points carry a {sector.shape[1]}-wide sector descriptor; give its "
                             f"(n_az_sec, n_el_sec) to mirror it, got {sectors}")
        n_as, n_es = sectors
        sector = sector.reshape(-1, n_as, n_es).flip(1).reshape(-1, n_as * n_es)   # (N, n_as n_es)
    return dataclasses.replace(points, azimuth_deg=-points.azimuth_deg, y=-points.y, sector=sector)
