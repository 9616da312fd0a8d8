"""Where dataset-level jobs read RD cubes from: a RADIal root or a dataset object.

A job's source is a RADIal-layout root folder (opened with :class:`~radarpc.data.radial.RADIal`)
or any dataset object with ``frame_ids``, ``sequences``, ``sensor``, ``calibration`` and
``cube(i)`` (or ``ds[i][0]``) such as :class:`~radarpc.sim.radial_writer.SimulatedRADIal`, which
simulates the same frames on the fly. :func:`source_fingerprint` identifies the data a job read,
so that a resumed job notices changed inputs; :func:`prefetched` reads the next batch of cubes
in a thread while the current one is processed.
"""
from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any, Iterator, Protocol, Sequence, Union

import torch

from radarpc.data.radial import RADIal
from radarpc.data.radial_format import fft_path, stored_fft_path
from radarpc.sensors.radial import Calibration, DDMARadarConfig

__all__ = ["RadarDataset", "Source", "open_source", "source_fingerprint", "read_cube", "load_batch",
           "prefetched", "batched"]


class RadarDataset(Protocol):
    """What the converters need from a dataset object (RADIal, SimulatedRADIal, ...).

    ``cube(i)`` -> complex64 ``(Nr, Nd, Nrx)`` tensor of item ``i`` (``ds[i][0]`` is used when
    the object has no ``cube``); ``frame_labels(i)`` (raw ``labels.csv`` rows) and
    ``freespace_mask(i)`` (uint8 PNG content) are used only by :func:`write_sparse_rd` for an
    object without a ``root`` folder. :class:`radarpc.data.radial.RadialFrames` (RADIal,
    SimulatedRADIal) provides all of them.
    """

    frame_ids: list[int]
    sequences: list[str]
    sensor: DDMARadarConfig

    @property
    def calibration(self) -> Calibration: ...

    def __len__(self) -> int: ...


Source = Union[str, os.PathLike, RadarDataset]
"""A RADIal-layout root folder or a :class:`RadarDataset` object."""


def open_source(source: Source, split: str = "all") -> tuple[Any, str, str]:
    """``(dataset, source_id, split)`` for a root path or a dataset object.

    A path opens ``RADIal(root, split=split)``; its id is the resolved path. A dataset object is
    used as given (it *is* the split: ``split`` must be ``"all"`` or the object's ``split``); its
    id is its resolved ``root`` when it has one, else its ``repr`` (SimulatedRADIal: sensor,
    split, frames and seed). Raises ``ValueError`` for an object lacking the interface.
    """
    if isinstance(source, (str, os.PathLike)):
        root = Path(source)
        return RADIal(root, split=split), str(root.resolve()), split
    missing = [a for a in ("frame_ids", "sequences", "sensor", "calibration", "__len__") if not hasattr(source, a)]
    if not hasattr(source, "cube") and not hasattr(source, "__getitem__"):
        missing.append("cube (or __getitem__)")
    if missing:
        raise ValueError(f"source must be a RADIal root path or a dataset with frame_ids, sequences, sensor, "
                         f"calibration and cube(i); {type(source).__name__} lacks {missing}")
    own = getattr(source, "split", None)
    if split != "all" and own is not None and own != split:
        raise ValueError(f"split={split!r} does not match the dataset object's split {own!r}; pass the "
                         f"dataset of that split (or split='all')")
    resolved = own if (split == "all" and own in ("train", "val", "test", "all")) else split
    root = getattr(source, "root", None)
    sid = str(Path(root).resolve()) if root is not None else repr(source)
    return source, sid, resolved


_ROOT_FILES = ("labels.csv", "calibration.npz", "CalibrationTable.npy", "sensor.json", "scene.json")


def source_fingerprint(ds: Any) -> str | None:
    """A digest of the data a conversion of ``ds`` reads, so that a resumed run notices changed data.

    For a dataset with a ``root`` folder: the name and size of the RD cube of every frame, and the
    name and content digest of the root's small files (``labels.csv``, the calibration,
    ``sensor.json``, the simulator's ``scene.json``). Contents, not modification times: an
    identical copy (another node's local copy, a re-run of ``radarpc simulate`` that rewrites the
    same files) has the same fingerprint, while a re-simulated root (other seed, scene or sensor)
    or an edited label file does not. Cubes are not read (that would read the whole dataset): a
    cube rewritten in place with other values of the same size goes unnoticed. ``None`` for an
    object without a root (SimulatedRADIal: its ``repr``, the source id, fixes its frames).
    """
    root = getattr(ds, "root", None)
    if root is None:
        return None
    import hashlib

    root = Path(root)
    h = hashlib.sha256()
    for num in ds.frame_ids:
        f = stored_fft_path(root, num) or fft_path(root, num)        # .npy, else .npz
        try:
            h.update(f"{f.relative_to(root)} {f.stat().st_size}\n".encode())
        except FileNotFoundError:
            h.update(f"{f.relative_to(root)} -\n".encode())
    for name in _ROOT_FILES:
        try:
            digest = hashlib.sha256((root / name).read_bytes()).hexdigest()
        except FileNotFoundError:
            digest = "-"
        h.update(f"{name} {digest}\n".encode())
    return h.hexdigest()


def read_cube(ds: Any, i: int) -> torch.Tensor:
    """RD cube of item ``i``: ``ds.cube(i)`` (RADIal, SimulatedRADIal: the cube alone, without
    labels and freespace), else ``ds[i][0]``. Returns a complex ``(Nr, Nd, Nrx)`` tensor."""
    cube = getattr(ds, "cube", None)
    return cube(i) if callable(cube) else ds[i][0]


def load_batch(ds: Any, positions: Sequence[int], device: torch.device) -> torch.Tensor:
    """RD cubes of items ``positions`` as complex64 ``(B, Nr, Nd, Nrx)`` on ``device``."""
    return torch.stack([read_cube(ds, p).to(device) for p in positions])


def prefetched(ds: Any, batches: Sequence[Sequence[int]], device: torch.device
                ) -> Iterator[tuple[list[int], torch.Tensor]]:
    """Yield ``(positions, rd)`` per batch, reading the next batch in a thread meanwhile (file reads
    and validation overlap the DSP)."""
    if not batches:
        return
    with ThreadPoolExecutor(max_workers=1) as pool:
        fut = pool.submit(load_batch, ds, batches[0], device)
        for j, pos in enumerate(batches):
            rd = fut.result()
            if j + 1 < len(batches):
                fut = pool.submit(load_batch, ds, batches[j + 1], device)
            yield list(pos), rd


def batched(positions: Sequence[int], batch_size: int) -> list[list[int]]:
    return [list(positions[i:i + batch_size]) for i in range(0, len(positions), batch_size)]
