"""Training-time augmentation of point frames: the mirror about the radar's boresight.

A frame mirrored about the boresight (azimuth ``a -> -a``, lateral ``y -> -y``) is the frame a
radar with the mirrored array would see of the mirrored scene: range, Doppler, elevation and
amplitude stay, and so do the labels' range and radial velocity. It is the polar form of
OpenPCDet's random world flip. What it changes, per :class:`~radarpc.data.point_dataset.PointFrame`:

* points: ``azimuth_deg`` and ``y`` negated; the angle-sector descriptor ``sector``
  (``n_az_sec x n_el_sec``, azimuth-major) reversed along azimuth, which is exact when the
  calibration's ``Azimuth_table`` is symmetric about 0 (the simulator's is: -75 .. 75 deg in
  0.2-deg steps) because :func:`~radarpc.dsp.beamform.sector_pool`'s adaptive pooling keeps the
  symmetry. :class:`MirroredFrames` checks the root's table and refuses one that is not (a real
  RADIal table was not available to check);
* labels: ``radar_A_deg``, ``radar_Y_m`` and ``laser_Y_m`` negated (the LiDAR sits on the
  radar's axis). The camera box columns are left as they are: no image is mirrored;
* freespace ``(256, 224)``: columns reversed. RADIal's target samples the odd PNG columns
  227 .. 673 of 900 (:func:`~radarpc.data.radial.freespace_to_model`), whose mirror images are
  the even columns 226 .. 672, so a mirrored target sits 0.2 deg (one PNG column, a quarter of a
  target column) off the exact mirror.

:class:`MirroredFrames` applies it to each training frame with a given probability, decided by
``(seed, epoch, index)`` alone, so that a resumed run sees the same frames as an uninterrupted one.
"""
from __future__ import annotations

import dataclasses

import numpy as np
import torch

from radarpc.data.point_dataset import PointCloudDataset, PointFrame
from radarpc.data.radial_format import LABEL_TENSOR_COLUMNS
from radarpc.dsp.pointcloud import SpectralPointCloudConfig
from radarpc.points import mirror_points

__all__ = ["mirror_frame", "mirror_sectors", "MirroredFrames"]

_NEGATED_LABEL_COLUMNS = [LABEL_TENSOR_COLUMNS.index(c) for c in ("radar_A_deg", "radar_Y_m", "laser_Y_m")]


def mirror_frame(frame: PointFrame, sectors: tuple[int, int] | None = None) -> PointFrame:
    """``frame`` mirrored about the radar's boresight (module docstring): its points
    (:func:`radarpc.points.mirror_points`), labels and freespace.

    Parameters
    ----------
    frame : PointFrame
    sectors : (int, int), optional
        ``(n_az_sec, n_el_sec)`` of the points' ``sector`` descriptor; required when the points
        carry one.

    Returns
    -------
    PointFrame
        New tensors; ``frame`` is not modified.

    Raises
    ------
    ValueError
        The points carry a sector descriptor and ``sectors`` is missing or does not match its width.
    """
    labels = frame.labels.clone()                                                   # (n, 14)
    labels[:, _NEGATED_LABEL_COLUMNS] = -labels[:, _NEGATED_LABEL_COLUMNS]
    return dataclasses.replace(frame, points=mirror_points(frame.points, sectors), labels=labels,
                               freespace=frame.freespace.flip(-1))


def mirror_sectors(frames: PointCloudDataset) -> tuple[int, int] | None:
    """The ``(n_az_sec, n_el_sec)`` that :func:`mirror_points` needs for the points of ``frames``
    (None without a sector descriptor), once the root's calibration is checked to allow the mirror.

    Raises
    ------
    ValueError
        The points carry a sector descriptor and the root's ``Azimuth_table`` is not symmetric
        about 0 deg, so reversing the descriptor would not mirror it.
    """
    sectors = SpectralPointCloudConfig(enrich=frames.store.metadata.enrich).sectors
    if sectors is not None:
        az = np.asarray(frames.reader.calibration.azimuth_deg, dtype=np.float64)
        # float32 tables round at ~1e-5 deg; 1e-3 deg is far below any table's step
        if not np.allclose(az, -az[::-1], rtol=0.0, atol=1e-3):
            raise ValueError(
                f"the calibration table of {frames.root} has an Azimuth_table that is not symmetric about "
                f"0 deg ({az.size} azimuths, {az[0]:.3f} .. {az[-1]:.3f} deg), so reversing the sector "
                f"descriptor of {frames.store.path} would not mirror it; mirror nothing (mirror_probability "
                f"0, no mirror averaging) or use a store without a sector enrichment")
    return sectors


class MirroredFrames(torch.utils.data.Dataset):
    """A :class:`~radarpc.data.point_dataset.PointCloudDataset` whose items are mirrored at random.

    Item ``i`` of epoch ``e`` is mirrored (:func:`mirror_frame`) when a uniform draw seeded by
    ``(seed, e, i)`` (``(seed, e, i, stream)`` for ``stream > 0``) falls below ``probability``;
    the training loop sets ``e`` through :meth:`set_epoch` before it builds each epoch's loader
    (whose workers receive a copy).

    Parameters
    ----------
    frames : PointCloudDataset
    probability : float in [0, 1]
    seed : int
    stream : int
        Independent draws for several datasets under one seed (their position in a
        concatenation); 0 draws as without it.
    """

    def __init__(self, frames: PointCloudDataset, probability: float, seed: int, stream: int = 0) -> None:
        if not 0.0 <= probability <= 1.0:
            raise ValueError(f"mirror probability must be in [0, 1], got {probability}")
        self.frames = frames
        self.probability = float(probability)
        self.seed = int(seed)
        if stream < 0:
            raise ValueError(f"stream must be >= 0, got {stream}")
        self.stream = int(stream)
        self.epoch = 0
        self._sectors = mirror_sectors(frames)

    def set_epoch(self, epoch: int) -> None:
        """Draw the mirrors of epoch ``epoch`` from now on."""
        self.epoch = int(epoch)

    def is_mirrored(self, i: int) -> bool:
        """Whether item ``i`` is mirrored in the current epoch."""
        key = [self.seed, self.epoch, int(i) % len(self)] + ([self.stream] if self.stream else [])
        u = np.random.default_rng(key).random()
        return bool(u < self.probability)

    def __len__(self) -> int:
        return len(self.frames)

    def __getitem__(self, i: int) -> PointFrame:
        frame = self.frames[i]
        return mirror_frame(frame, self._sectors) if self.is_mirrored(i) else frame

    def __repr__(self) -> str:
        return (f"MirroredFrames({self.frames!r}, probability={self.probability}, seed={self.seed}"
                + (f", stream={self.stream})" if self.stream else ")"))
