"""Point clouds joined with their RADIal labels and freespace: what a point-cloud detector trains on.

:class:`PointCloudDataset` pairs every frame of a Parquet point store
(:class:`~radarpc.data.pointstore.PointStore`) with the labels and the freespace target of the same
frame (``numSample``) in the RADIal-layout root the store was made from, read by
:class:`~radarpc.data.radial.RADIal` without its RD cubes. An item is a :class:`PointFrame`;
:func:`collate_point_frames` batches items into a :class:`PointFrameBatch` whose points are one
offset-batched :class:`~radarpc.points.PointCloudBatch` and whose labels are concatenated with the
same offset convention (frame ``b`` holds rows ``label_offset[b-1]:label_offset[b]``).

Examples
--------
>>> from torch.utils.data import DataLoader                                     # doctest: +SKIP
>>> ds = PointCloudDataset("data/sim_radial_pc057.parquet", "data/sim_radial", split="train")  # doctest: +SKIP
>>> loader = DataLoader(ds, batch_size=4, shuffle=True, collate_fn=collate_point_frames)      # doctest: +SKIP
>>> batch = next(iter(loader)).to("cuda")                                       # doctest: +SKIP
>>> batch.points.x, batch.points.offset, batch.labels, batch.label_offset      # doctest: +SKIP
"""
from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np
import torch

from radarpc.data.pointstore import PointStore
from radarpc.data.radial import SPLIT_CHOICES, RADIal
from radarpc.points import PointCloudBatch, collate_clouds, offset2batch

__all__ = [
    "PointFrame",
    "PointFrameBatch",
    "PointCloudDataset",
    "collate_point_frames",
    "check_store_root",
]


@dataclass(frozen=True)
class PointFrame:
    """One frame of a :class:`PointCloudDataset`.

    Attributes
    ----------
    points : PointCloudBatch
        The frame's point cloud (a batch of one, ``offset = [N]``), as ``PointStore[i]``.
    labels : float32 ``(n_vehicles, 14)``
        Columns :data:`~radarpc.data.radial_format.LABEL_TENSOR_COLUMNS` (box centre at
        ``radar_X_m``, ``radar_Y_m``; ``(0, 14)`` for a frame without vehicles), as the RADIal
        reader's item.
    freespace : bool ``(256, 224)``
        RADIal's freespace target (:func:`~radarpc.data.radial.freespace_to_model`).
    frame : int
        RADIal ``numSample``.
    sequence : str
        Sequence name (``labels.csv`` ``dataset`` column).
    """

    points: PointCloudBatch
    labels: torch.Tensor
    freespace: torch.Tensor
    frame: int
    sequence: str


@dataclass(frozen=True)
class PointFrameBatch:
    """``B`` frames of a :class:`PointCloudDataset`, built by :func:`collate_point_frames`.

    Points and labels are concatenated (no padding) and delimited by cumulative offsets, the
    convention of :class:`~radarpc.points.PointCloudBatch`.

    Attributes
    ----------
    points : PointCloudBatch
        Every frame's points; frame ``b`` holds points ``points.offset[b-1]:points.offset[b]``.
    labels : float32 ``(M, 14)``
        Every frame's label rows, columns :data:`~radarpc.data.radial_format.LABEL_TENSOR_COLUMNS`.
    label_offset : LongTensor ``(B,)``
        Cumulative end row of each frame's labels in :attr:`labels` (``label_offset[-1] = M``).
    freespace : bool ``(B, 256, 224)``
    frames : LongTensor ``(B,)``
        RADIal ``numSample`` of each frame.
    sequences : tuple of str ``(B,)``
    """

    points: PointCloudBatch
    labels: torch.Tensor
    label_offset: torch.Tensor
    freespace: torch.Tensor
    frames: torch.Tensor
    sequences: tuple[str, ...]

    def __len__(self) -> int:
        """Number of frames."""
        return int(self.frames.numel())

    def label_batch_index(self) -> torch.Tensor:
        """Frame index of every label row, ``(M,)`` long."""
        return offset2batch(self.label_offset)

    def frame_labels(self, b: int) -> torch.Tensor:
        """The label rows of frame ``b``, ``(n_b, 14)``."""
        n = len(self)
        if not -n <= b < n:
            raise IndexError(f"frame {b} out of range for a batch of {n} frames")
        b = b % n
        start = int(self.label_offset[b - 1]) if b > 0 else 0
        return self.labels[start:int(self.label_offset[b])]

    def to(self, device: torch.device | str) -> "PointFrameBatch":
        """The batch with every tensor on ``device``."""
        return dataclasses.replace(self, points=self.points.to(device), labels=self.labels.to(device),
                                   label_offset=self.label_offset.to(device),
                                   freespace=self.freespace.to(device), frames=self.frames.to(device))


def collate_point_frames(items: Sequence[PointFrame]) -> PointFrameBatch:
    """DataLoader ``collate_fn`` of :class:`PointCloudDataset`: items -> :class:`PointFrameBatch`.

    Points go through :func:`~radarpc.points.collate_clouds`; labels are concatenated and their
    per-frame counts accumulated into ``label_offset``; freespace masks are stacked.
    """
    if not items:
        raise ValueError("collate_point_frames needs at least one item")
    counts = torch.tensor([it.labels.shape[0] for it in items], dtype=torch.int64,
                          device=items[0].labels.device)                               # (B,)
    return PointFrameBatch(
        points=collate_clouds([it.points for it in items]),
        labels=torch.cat([it.labels for it in items]),                                 # (M, 14)
        label_offset=torch.cumsum(counts, 0),
        freespace=torch.stack([it.freespace for it in items]),                         # (B, 256, 224)
        frames=torch.tensor([it.frame for it in items], dtype=torch.int64, device=counts.device),
        sequences=tuple(it.sequence for it in items),
    )


def check_store_root(store: PointStore, root: str | os.PathLike) -> None:
    """Refuse a point store whose metadata says it was made from another RADIal root.

    A store made from a root records the root's resolved path in ``metadata.source_root``; one
    made from a dataset object records the object's repr (not a path) and passes. A recorded
    path that still exists and is not ``root`` (e.g. ``root`` is a copy of it) is refused; a
    recorded path that no longer exists (the root was moved) passes.

    Raises
    ------
    ValueError
        Naming the store, the root it was made from and ``root``.
    """
    made_from = Path(store.metadata.source_root) if store.metadata.source_root else None
    if (made_from is not None and made_from.is_absolute() and made_from.is_dir()
            and made_from.resolve() != Path(root).resolve()):
        raise ValueError(f"the point store {store.path} was made from {store.metadata.source_root}, not from "
                         f"{root} (another dataset, or a copy of it)")


class PointCloudDataset(torch.utils.data.Dataset):
    """Frames of a point store joined by ``numSample`` with the labels and freespace of its root.

    Parameters
    ----------
    store : PointStore or path-like
        A point store made from ``root`` (``radarpc pointcloud ROOT --out FILE.parquet``).
    root : path-like
        The RADIal-layout root the store was made from; its ``labels.csv`` and freespace PNGs
        are read (never its RD cubes).
    split : {"train", "val", "test", "all"}, optional
        Keep the store's frames of this split of ``root`` (by sequence, as :class:`RADIal`).
        None (default) keeps every frame of the store, i.e. the split it was made from.
    difficult : bool
        As for :class:`RADIal`: False drops label rows with ``Difficult == 1`` and the frames
        all of whose vehicles are difficult.
    validate : bool
        Validate every freespace PNG read (as :class:`RADIal`).
    skip : iterable of int, optional
        RADIal frame numbers to leave out (as :class:`RADIal`'s ``skip``).

    Attributes
    ----------
    store : PointStore
    reader : RADIal
        The root's reader (split ``split`` or ``"all"``), on the store's device.
    frame_ids : list of int
        ``numSample`` of each item, in store order.
    sequences : list of str
        Sequence name of each item.

    Raises
    ------
    ValueError
        The store was made from another root, holds frames that ``root`` does not list (or lists
        under another sequence), was made from a split other than ``split``, or keeps no frame.
    """

    def __init__(self, store: PointStore | str | os.PathLike, root: str | os.PathLike,
                 split: str | None = None, *, difficult: bool = True, validate: bool = True,
                 skip: Iterable[int] | None = None) -> None:
        if split is not None and split not in SPLIT_CHOICES:
            raise ValueError(f"split must be one of {SPLIT_CHOICES} or None, got {split!r}")
        self.store = store if isinstance(store, PointStore) else PointStore(store)
        self.root = Path(root)
        self.split = split
        check_store_root(self.store, self.root)
        made = self.store.metadata.split
        if split not in (None, "all") and made not in ("all", split):
            raise ValueError(f"the point store {self.store.path} holds the {made!r} split of "
                             f"{self.store.metadata.source_root}, so no {split!r} frame")
        self.reader = RADIal(self.root, split=split or "all", difficult=difficult, validate=validate,
                             device=self.store.device, skip=skip)
        # every frame of the store must be a frame of the root, in the same sequence
        lab = self.reader.labels
        ids, first = np.unique(lab.num_sample, return_index=True)
        root_seq = dict(zip(ids.tolist(), (lab.dataset[k] for k in first.tolist())))
        missing = [f for f in self.store.frames if f not in root_seq]
        if missing:
            raise ValueError(f"the point store {self.store.path} holds {len(missing)} frame(s) that "
                             f"{lab.path} does not list (numSample {missing[:10]}); it was not made from {root}")
        moved = [(f, s) for f, s in zip(self.store.frames, self.store.sequences) if root_seq[f] != s]
        if moved:
            f, s = moved[0]
            raise ValueError(f"the point store {self.store.path} puts frame {f} in sequence {s!r} but {lab.path} "
                             f"puts it in {root_seq[f]!r} ({len(moved)} such frame(s)); it was not made from {root}")
        pos = {f: k for k, f in enumerate(self.reader.frame_ids)}
        keep = [j for j, f in enumerate(self.store.frames) if f in pos]
        if not keep:
            raise ValueError(f"no frame of the point store {self.store.path} ({len(self.store)} frames) is in the "
                             f"{split or 'all'!r} split of {root}" + ("" if difficult else " with difficult=False"))
        self._store_index = keep                                      # item -> store position
        self._reader_index = [pos[self.store.frames[j]] for j in keep]  # item -> reader position
        self.frame_ids: list[int] = [self.store.frames[j] for j in keep]
        self.sequences: list[str] = [self.store.sequences[j] for j in keep]

    def __len__(self) -> int:
        return len(self._store_index)

    def __getitem__(self, i: int) -> PointFrame:
        n = len(self)
        if not -n <= int(i) < n:
            raise IndexError(f"index {i} out of range for a PointCloudDataset of {n} frames")
        i = int(i) % n
        k = self._reader_index[i]
        return PointFrame(points=self.store[self._store_index[i]], labels=self.reader.label_tensor(k),
                          freespace=self.reader.freespace(k), frame=self.frame_ids[i],
                          sequence=self.sequences[i])

    def decoded_bytes(self) -> int:
        """Estimated memory of this dataset's point frames once decoded (:meth:`PointStore.decoded_bytes`)."""
        return self.store.decoded_bytes(self._store_index)

    def preload(self) -> int:
        """Hold this dataset's point frames in memory (:meth:`PointStore.preload`); bytes held."""
        return self.store.preload(self._store_index)

    def index_of(self, frame: int) -> int:
        """Position of RADIal frame ``frame`` among the items."""
        try:
            return self.frame_ids.index(int(frame))
        except ValueError:
            raise KeyError(f"frame {frame} is not in {self!r}") from None

    def __repr__(self) -> str:
        return (f"PointCloudDataset(store={str(self.store.path)!r}, root={str(self.root)!r}, "
                f"split={self.split!r}, frames={len(self)})")
