"""Training-time augmentation: of point frames, the mirror about the radar's boresight and a
rotation about the radar's vertical axis; of RD cubes, the superposition of two scenes.

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

A frame rotated by ``delta`` about the vertical axis (azimuth ``a -> a + delta``) is the frame a
radar mounted ``delta`` off the car's axis would see: the polar form of OpenPCDet's random world
rotation, kept to a few degrees because traffic, roads and the ego motion fix a direction. What it
changes (:func:`rotate_frame`):

* points: ``azimuth_deg`` shifted, ``(x, y)`` rotated. Range, elevation, amplitude and Doppler stay:
  the radial velocities are those of the same scene seen from a yawed mount (static clutter then
  reads ``-v cos(a - delta)`` instead of ``-v cos a``, at most ``v sin|a| sin|delta|`` apart). The
  ``sector`` descriptor, maxima of the angle spectrum over fixed azimuth sectors, would need the
  spectrum itself to rotate; it is left as measured, and :class:`~radarpc.experiments.radial_detection.config.ExperimentConfig`
  refuses rotation for a model that reads it;
* labels: ``radar_A_deg`` shifted, ``radar_X_m, radar_Y_m`` rotated, ``laser_X_m, laser_Y_m`` moved
  with them (the LiDAR frame is the radar frame translated); range, Doppler, power and the camera
  box stay;
* freespace ``(256, 224)``: shifted by whole columns of the target (0.4 deg each,
  :data:`FREESPACE_COLUMN_DEG`), so angles are multiples of a column; the columns it uncovers at
  the edge repeat the edge column (at most ``max_deg / 0.4`` of them, at +-44.8 deg).

:class:`RotatedFrames` draws an angle uniformly from the multiples of a column within
``+-max_deg`` for each training frame, by ``(seed, epoch, index, stream)`` like the mirror.

The RD cube is linear in the scene: the received signal is the sum of every scatterer's echo plus
receiver noise, and the range and Doppler FFTs are linear. So the sum of two frames' cubes is the
cube of both scenes at once, seen by one radar (:func:`superpose_frames`), with these differences
from a recorded frame: the noise is that of two receivers (3 dB above one), neither scene occludes
the other, and the static clutter of two ego motions is present. Its labels are both frames'
vehicles; its freespace target is free where both frames are free. A frame then holds twice the
vehicles for the cost of one forward pass. :class:`SuperposedFrames` superposes a share of the
training frames, each with a partner drawn from the same dataset by ``(seed, epoch, index, stream)``.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import torch

from radarpc.data.point_dataset import PointCloudDataset, PointFrame
from radarpc.data.radial_format import (FREESPACE_CROP, FREESPACE_FOV_DEG, FREESPACE_OUT, FREESPACE_SHAPE,
                                        LABEL_TENSOR_COLUMNS)
from radarpc.dsp.pointcloud import SpectralPointCloudConfig
from radarpc.points import mirror_points

__all__ = ["mirror_frame", "mirror_sectors", "MirroredFrames", "rotate_frame", "RotatedFrames", "superpose_frames",
           "SuperposedFrames", "FREESPACE_COLUMN_DEG"]

_NEGATED_LABEL_COLUMNS = [LABEL_TENSOR_COLUMNS.index(c) for c in ("radar_A_deg", "radar_Y_m", "laser_Y_m")]
_COL = {c: LABEL_TENSOR_COLUMNS.index(c) for c in LABEL_TENSOR_COLUMNS}

FREESPACE_COLUMN_DEG: float = FREESPACE_FOV_DEG / FREESPACE_SHAPE[1] * FREESPACE_CROP[1] / FREESPACE_OUT[1]
"""Azimuth step of the ``(256, 224)`` freespace target: two 0.2-deg PNG columns, 0.4 deg."""


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


class _DrawnPerEpoch(torch.utils.data.Dataset):
    """The draw bookkeeping the augmenting wrappers share: the wrapped ``frames``, the ``seed``,
    the ``stream`` (independent draws for several datasets under one seed, their position in a
    concatenation) and the epoch, which :meth:`set_epoch` sets here and in a wrapped dataset."""

    def __init__(self, frames, seed: int, stream: int) -> None:
        if stream < 0:
            raise ValueError(f"stream must be >= 0, got {stream}")
        self.frames = frames
        self.seed = int(seed)
        self.stream = int(stream)
        self.epoch = 0

    def set_epoch(self, epoch: int) -> None:
        """Draw the items of epoch ``epoch`` from now on."""
        self.epoch = int(epoch)
        if hasattr(self.frames, "set_epoch"):
            self.frames.set_epoch(epoch)

    def __len__(self) -> int:
        return len(self.frames)


class MirroredFrames(_DrawnPerEpoch):
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
        super().__init__(frames, seed, stream)
        self.probability = float(probability)
        self._sectors = mirror_sectors(frames)

    def is_mirrored(self, i: int) -> bool:
        """Whether item ``i`` is mirrored in the current epoch."""
        key = [self.seed, self.epoch, int(i) % len(self)] + ([self.stream] if self.stream else [])
        u = np.random.default_rng(key).random()
        return bool(u < self.probability)

    def __getitem__(self, i: int) -> PointFrame:
        frame = self.frames[i]
        return mirror_frame(frame, self._sectors) if self.is_mirrored(i) else frame

    def __repr__(self) -> str:
        return (f"MirroredFrames({self.frames!r}, probability={self.probability}, seed={self.seed}"
                + (f", stream={self.stream})" if self.stream else ")"))


def rotate_frame(frame: PointFrame, angle_deg: float) -> PointFrame:
    """``frame`` rotated by ``angle_deg`` about the radar's vertical axis, azimuth growing to the
    left (module docstring): its points, labels and freespace.

    Parameters
    ----------
    frame : PointFrame
    angle_deg : float
        A multiple of :data:`FREESPACE_COLUMN_DEG` (0.4 deg), so that the freespace target moves by
        whole columns.

    Returns
    -------
    PointFrame
        New tensors; ``frame`` is not modified. The points' ``sector`` descriptor is the measured one.

    Raises
    ------
    ValueError
        ``angle_deg`` is not a multiple of a freespace column.
    """
    k = round(angle_deg / FREESPACE_COLUMN_DEG)
    if not np.isfinite(angle_deg) or abs(angle_deg - k * FREESPACE_COLUMN_DEG) > 1e-9:
        raise ValueError(f"rotation angle must be a multiple of the freespace column, {FREESPACE_COLUMN_DEG} deg, "
                         f"got {angle_deg}")
    delta = math.radians(k * FREESPACE_COLUMN_DEG)
    c, s = math.cos(delta), math.sin(delta)

    def rotate(x: torch.Tensor, y: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        # (x forward, y left): x' = r cos(a + delta), y' = r sin(a + delta)
        x64, y64 = x.double(), y.double()
        return (c * x64 - s * y64).to(x.dtype), (s * x64 + c * y64).to(y.dtype)

    p = frame.points
    px, py = rotate(p.x, p.y)
    points = dataclasses.replace(p, azimuth_deg=(p.azimuth_deg.double() + k * FREESPACE_COLUMN_DEG).to(p.azimuth_deg.dtype),
                                 x=px, y=py)

    labels = frame.labels.clone()                                                   # (n, 14)
    rx, ry = labels[:, _COL["radar_X_m"]], labels[:, _COL["radar_Y_m"]]
    lx = labels[:, _COL["laser_X_m"]] - rx                                         # LiDAR frame offset
    ly = labels[:, _COL["laser_Y_m"]] - ry
    rx, ry = rotate(rx, ry)
    labels[:, _COL["radar_X_m"]], labels[:, _COL["radar_Y_m"]] = rx, ry
    labels[:, _COL["laser_X_m"]], labels[:, _COL["laser_Y_m"]] = rx + lx, ry + ly
    labels[:, _COL["radar_A_deg"]] = (labels[:, _COL["radar_A_deg"]].double() + k * FREESPACE_COLUMN_DEG).to(labels.dtype)

    width = frame.freespace.shape[-1]
    source = (torch.arange(width, device=frame.freespace.device) - k).clamp(0, width - 1)   # new[j] = old[j - k]
    return dataclasses.replace(frame, points=points, labels=labels, freespace=frame.freespace[..., source])


class RotatedFrames(_DrawnPerEpoch):
    """A dataset of point frames (a :class:`~radarpc.data.point_dataset.PointCloudDataset`, or a
    wrapper of one) whose items are rotated at random (:func:`rotate_frame`).

    Item ``i`` of epoch ``e`` is rotated by ``k`` freespace columns (0.4 deg each), ``k`` drawn
    uniformly from the integers with ``|k| 0.4 <= max_deg`` by a generator seeded with
    ``(seed, e, i, stream, 1)``, so its draws are independent of :class:`MirroredFrames`' under the
    same seed. :meth:`set_epoch` reaches a wrapped dataset too.

    Parameters
    ----------
    frames : Dataset of PointFrame
    max_deg : float >= 0
    seed : int
    stream : int >= 0
        Independent draws for several datasets under one seed (their position in a concatenation).
    """

    def __init__(self, frames, max_deg: float, seed: int, stream: int = 0) -> None:
        if not (np.isfinite(max_deg) and max_deg >= 0):
            raise ValueError(f"rotation max_deg must be a finite angle >= 0, got {max_deg}")
        super().__init__(frames, seed, stream)
        self.max_deg = float(max_deg)
        self.max_columns = int(math.floor(self.max_deg / FREESPACE_COLUMN_DEG + 1e-9))

    def angle_deg(self, i: int) -> float:
        """The rotation of item ``i`` in the current epoch (deg)."""
        rng = np.random.default_rng([self.seed, self.epoch, int(i) % len(self), self.stream, 1])
        return float(rng.integers(-self.max_columns, self.max_columns, endpoint=True)) * FREESPACE_COLUMN_DEG

    def __getitem__(self, i: int) -> PointFrame:
        frame = self.frames[i]
        angle = self.angle_deg(i)
        return rotate_frame(frame, angle) if angle != 0.0 else frame

    def __repr__(self) -> str:
        return f"RotatedFrames({self.frames!r}, max_deg={self.max_deg}, seed={self.seed}, stream={self.stream})"


CubeFrame = tuple[torch.Tensor, torch.Tensor, torch.Tensor]
"""An RD item ``(rd, labels, freespace)`` of :class:`~radarpc.data.radial.RadialFrames`."""


def superpose_frames(a: CubeFrame, b: CubeFrame) -> CubeFrame:
    """The frame of scenes ``a`` and ``b`` seen at once (module docstring).

    Parameters
    ----------
    a, b : (rd, labels, freespace)
        Items of :class:`~radarpc.data.radial.RadialFrames`: complex ``(Nr, Nd, Nrx)`` cubes of
        one sensor, float ``(n, 14)`` label rows, bool ``(256, 224)`` freespace targets.

    Returns
    -------
    (rd, labels, freespace)
        ``rd_a + rd_b``; the rows of ``a`` then ``b``; ``freespace_a & freespace_b``.
    """
    (rd_a, lab_a, fs_a), (rd_b, lab_b, fs_b) = a, b
    if rd_a.shape != rd_b.shape or not (rd_a.is_complex() and rd_b.is_complex()):
        raise ValueError(f"only complex RD cubes of one shape superpose, got {tuple(rd_a.shape)} "
                         f"{rd_a.dtype} and {tuple(rd_b.shape)} {rd_b.dtype}")
    if fs_a.shape != fs_b.shape or lab_a.shape[1:] != lab_b.shape[1:]:
        raise ValueError(f"frames of different targets: freespace {tuple(fs_a.shape)} and {tuple(fs_b.shape)}, "
                         f"labels {tuple(lab_a.shape)} and {tuple(lab_b.shape)}")
    return rd_a + rd_b, torch.cat([lab_a, lab_b]), fs_a & fs_b


class SuperposedFrames(_DrawnPerEpoch):
    """A dataset of RD frames (:class:`~radarpc.data.radial.RadialFrames`) some of whose items are
    superposed with another of its frames (:func:`superpose_frames`).

    Item ``i`` of epoch ``e`` is superposed when a uniform draw from a generator seeded with
    ``(seed, e, i, stream, 2)`` falls below ``probability``; its partner, drawn next from the
    same generator, is any other item, uniformly. So a resumed run sees the same frames, and the
    draws are independent of :class:`MirroredFrames`' and :class:`RotatedFrames`'.

    Parameters
    ----------
    frames : RadialFrames
        At least two frames.
    probability : float in [0, 1]
    seed : int
    stream : int >= 0
        Independent draws for several datasets under one seed (their position in a concatenation).
    """

    def __init__(self, frames, probability: float, seed: int, stream: int = 0) -> None:
        if not 0.0 <= probability <= 1.0:
            raise ValueError(f"superposition probability must be in [0, 1], got {probability}")
        if len(frames) < 2:
            raise ValueError(f"superposition needs at least 2 frames to pair, {frames!r} has {len(frames)}")
        super().__init__(frames, seed, stream)
        self.probability = float(probability)

    def partner(self, i: int) -> int | None:
        """The item superposed on item ``i`` in the current epoch, or None."""
        n = len(self)
        i = int(i) % n
        rng = np.random.default_rng([self.seed, self.epoch, i, self.stream, 2])
        if not rng.random() < self.probability:
            return None
        j = int(rng.integers(n - 1))
        return j + (j >= i)                  # any item but i itself

    def __getitem__(self, i: int) -> CubeFrame:
        frame = self.frames[i]
        j = self.partner(i)
        return frame if j is None else superpose_frames(frame, self.frames[j])

    def __repr__(self) -> str:
        return (f"SuperposedFrames({self.frames!r}, probability={self.probability}, seed={self.seed}, "
                f"stream={self.stream})")
