"""Dataset conversion drivers: a RADIal root -> a Parquet point store, or -> a sparse-RD root.

:func:`convert_dataset` runs :class:`~radarpc.dsp.pointcloud.SpectralPointCloud` over every
frame of a split and writes a :mod:`radarpc.data.pointstore` file. The source is a RADIal-layout
root (read with :class:`~radarpc.data.radial.RADIal`) or any dataset object with ``frame_ids``,
``sequences``, ``sensor``, ``calibration`` and ``cube(i)`` (or ``ds[i][0]``) such as
:class:`~radarpc.sim.radial_writer.SimulatedRADIal`, which simulates the same frames on the fly. The work is cut into chunks
of ``chunk_frames`` frames; chunk ``k`` is written atomically to ``OUT.parts/part-{k:05d}.parquet``
and a finished chunk is never recomputed, so a killed conversion resumes where it stopped and
gives the same final file. At the end the parts are merged into ``OUT`` (atomically) and the
parts folder is removed. Chunks can be spread over

* local processes (``workers=N``: the i-th pending chunk goes to worker ``i % N``, spawned processes, each
  with ``torch`` threads = available threads / N), and
* ``torchrun`` ranks (``RANK``/``WORLD_SIZE``/``LOCAL_RANK`` set): rank ``r`` converts the chunks
  ``k % WORLD_SIZE == r`` on ``cuda:LOCAL_RANK`` when CUDA is available; rank 0 merges once every
  part exists (``torch.distributed`` barrier when a process group is initialised, else polling
  the parts folder, which must then be on a shared file system; ``wait_timeout_s``, 2 h by default,
  bounds the wait and the error names the missing parts and their ranks).

When there are fewer chunks than processes (``workers x WORLD_SIZE``) the chunks are shrunk so that
every process gets work; the chunk size is fixed by the first run (its manifest) so a resumed run
with another ``workers`` reuses the parts. Every setting that shapes the output
(:meth:`ConvertSettings.to_dict`, the source, the frames) is stored in the manifest and in the
store metadata and compared on resume and by the "already finished" check.

Density control (seed Sec. 3.2): the detected set is ``S(tau) = {(r, l) : E(r, l) / mu(r, l) >
tau}`` expanded to the ``M`` Tx replicas, density ``|S(tau)| / (Nr * ND)``. A target density
applies to the set the store encodes: ``S(tau)``, or ``S*(tau)`` (eq. 9) with an ``rdN``
enrichment. Give either a fixed linear SNR threshold ``tau`` or a target ``density``:
``per-frame`` picks a tau for every frame, ``per-dataset`` calibrates one tau on the *training*
split (stored in the metadata) and applies it to the requested split.

:func:`write_sparse_rd` writes the RD cubes masked to the set the matching point store encodes
(``S(tau)``, or ``S*(tau)`` with ``rdN``; same envelope, CFAR and per-frame taus) as a new RADIal-layout root
(labels, freespace, calibration and sensor description linked or copied) that the unchanged
:class:`~radarpc.data.radial.RADIal` reader and the dense FFTRadNet read: the sparse-RD baseline.
"""
from __future__ import annotations

import csv
import dataclasses
import datetime as _dt
import json
import os
import queue as _queue
import shutil
import time
import traceback
from dataclasses import dataclass
from pathlib import Path
from concurrent.futures import ThreadPoolExecutor
from typing import Any, Callable, Iterator, Protocol, Sequence, Union

import numpy as np
import torch

from radarpc import __version__
from radarpc.data.pointstore import PointStore, PointStoreMetadata, PointStoreWriter
from radarpc.data.radial import RADIal
from radarpc.data.radial_format import LABEL_COLUMNS, fft_path, freespace_path
from radarpc.dsp.density import check_density
from radarpc.dsp.pointcloud import SpectralPointCloud, SpectralPointCloudConfig
from radarpc.io import DataFileError, atomic_write, save_npy_atomic
from radarpc.machine import check_device
from radarpc.sensors.radial import Calibration, DDMARadarConfig, save_calibration

__all__ = [
    "RadarDataset",
    "Source",
    "open_source",
    "read_cube",
    "ConvertSettings",
    "ConvertResult",
    "SparseRDResult",
    "DistEnv",
    "dist_env",
    "part_path",
    "parts_dir",
    "build_point_cloud",
    "calibrate_tau",
    "convert_dataset",
    "write_sparse_rd",
]

_MANIFEST = "manifest.json"
DEFAULT_WAIT_S = 2 * 3600.0
"""Default time torchrun ranks wait for each other's files (without a process group)."""


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
        f = fft_path(root, num)
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


# ---- settings -------------------------------------------------------------------------------------
@dataclass(frozen=True)
class ConvertSettings:
    """What to compute: threshold or density, enrichments, CFAR geometry, envelope, split, chunking.

    Exactly one of ``tau`` and ``density`` is given. Threshold, density, window, guard, enrichment
    and envelope checks are those of :class:`~radarpc.dsp.pointcloud.SpectralPointCloudConfig`
    (one implementation). ``window``/``guard`` are full odd side lengths: RADIal rpl.py's
    ``(9, 9, 3, 3)`` half widths are ``window=(19, 19), guard=(7, 7)`` (with ``envelope="all-slots"``
    and ``tau=1.585``, RADIal's processing).
    """

    tau: float | None = None                 # fixed linear SNR threshold (RADIal default 1.585 = 2 dB)
    density: float | None = None             # target density of the encoded set (S*, with rdN, else S), in (0, 1]
    density_mode: str = "per-frame"          # "per-frame" or "per-dataset" (only with density)
    enrich: tuple[str, ...] = ()             # e.g. ("rd3", "sector32"); () = plain spectral points
    window: tuple[int, int] = (9, 9)         # CA-CFAR window (range, Doppler), full odd sizes
    guard: tuple[int, int] = (3, 3)          # CA-CFAR guard (range, Doppler), full odd sizes
    split: str = "all"                       # "train", "val", "test" or "all"
    chunk_frames: int = 64                   # frames per part file (the unit of resume and sharding)
    calibration_frames: int | None = None    # train frames used to calibrate per-dataset tau (None: all)
    envelope: str = "replicas"               # "replicas" (seed eq. 1) or "all-slots" (RADIal rpl.py)
    beamforming: str = "auto"                # "auto", "exact" or "screened": same points (see SpectralPointCloud)

    def __post_init__(self) -> None:
        if (self.tau is None) == (self.density is None):
            raise ValueError(f"give exactly one of tau (a linear SNR threshold) and density (a target "
                             f"fraction of RD cells), got tau={self.tau}, density={self.density}")
        cfg = self.point_cloud_config()          # validates tau/density/window/guard/enrich/envelope
        object.__setattr__(self, "window", cfg.window)
        object.__setattr__(self, "guard", cfg.guard)
        object.__setattr__(self, "enrich", cfg.enrich)
        if self.split not in ("train", "val", "test", "all"):
            raise ValueError(f"split must be one of train, val, test, all; got {self.split!r}")
        if isinstance(self.chunk_frames, bool) or int(self.chunk_frames) < 1:
            raise ValueError(f"chunk_frames must be >= 1, got {self.chunk_frames}")
        object.__setattr__(self, "chunk_frames", int(self.chunk_frames))
        if self.calibration_frames is not None:
            if int(self.calibration_frames) < 1:
                raise ValueError(f"calibration_frames must be >= 1, got {self.calibration_frames}")
            object.__setattr__(self, "calibration_frames", int(self.calibration_frames))

    def point_cloud_config(self) -> SpectralPointCloudConfig:
        """The :class:`SpectralPointCloudConfig` of these settings (per-dataset: the target density)."""
        return SpectralPointCloudConfig(tau=self.tau, density=self.density, density_mode=self.density_mode,
                                        window=tuple(self.window), guard=tuple(self.guard),
                                        enrich=tuple(self.enrich), envelope=self.envelope,
                                        beamforming=self.beamforming)

    @property
    def mode(self) -> str:
        """``"fixed-tau"``, ``"per-frame"`` or ``"per-dataset"`` (:data:`DENSITY_MODES`)."""
        return "fixed-tau" if self.tau is not None else self.density_mode

    def to_dict(self) -> dict:
        """Plain JSON-able dict (lists for tuples)."""
        d = dataclasses.asdict(self)
        d["enrich"], d["window"], d["guard"] = list(self.enrich), list(self.window), list(self.guard)
        return d

    def output_key(self) -> dict:
        """:meth:`to_dict` without ``chunk_frames`` (which changes the part files, not the store)."""
        d = self.to_dict()
        d.pop("chunk_frames")
        return d


@dataclass(frozen=True)
class ConvertResult:
    """Outcome of :func:`convert_dataset`."""

    path: Path | None                # the merged store (None on ranks other than 0)
    n_frames: int                    # frames in the converted split
    n_points: int                    # points written (0 on ranks other than 0)
    achieved_density: float          # mean density of the encoded set, |S*| with rdN, else |S| (nan off rank 0)
    peak_density: float              # mean |S(tau)| / (Nr * ND), CFAR peaks only (nan on ranks other than 0)
    tau: float | None                # the fixed or calibrated threshold (None in per-frame mode)
    chunks_converted: int            # chunks computed by this process (and its workers)
    chunks_skipped: int              # chunks found complete from an earlier run
    chunk_frames: int = 0            # frames per chunk actually used (shrunk for many processes; from the manifest on resume)


@dataclass(frozen=True)
class SparseRDResult:
    """Outcome of :func:`write_sparse_rd`."""

    root: Path                       # the sparse-RD root
    n_frames: int                    # frames in the root
    frames_written: int              # cubes computed in this call (the others existed)
    achieved_density: float          # mean density of the frames written in this call (nan if none)
    tau: float | None                # fixed or calibrated threshold (None in per-frame mode)
    frame_tau: dict[int, float] = dataclasses.field(default_factory=dict)      # per frame (numSample), all recorded frames
    frame_density: dict[int, float] = dataclasses.field(default_factory=dict)  # per frame, density of the kept set


@dataclass(frozen=True)
class DistEnv:
    """Position of this process in a ``torchrun`` job (``world_size == 1`` outside torchrun)."""

    rank: int = 0
    world_size: int = 1
    local_rank: int = 0


def dist_env() -> DistEnv:
    """Read ``RANK``, ``WORLD_SIZE`` and ``LOCAL_RANK`` as set by ``torchrun``."""
    def get(name: str, default: int) -> int:
        v = os.environ.get(name)
        if v is None or v == "":
            return default
        try:
            return int(v)
        except ValueError:
            raise ValueError(f"environment variable {name}={v!r} is not an integer") from None
    env = DistEnv(rank=get("RANK", 0), world_size=get("WORLD_SIZE", 1), local_rank=get("LOCAL_RANK", 0))
    if env.world_size < 1 or not 0 <= env.rank < env.world_size:
        raise ValueError(f"RANK={env.rank} must be in [0, WORLD_SIZE={env.world_size})")
    return env


def parts_dir(out: str | os.PathLike) -> Path:
    """``OUT.parts``: the folder of finished chunks of a conversion to ``OUT``."""
    out = Path(out)
    return out.with_name(out.name + ".parts")


def part_path(out: str | os.PathLike, k: int) -> Path:
    """``OUT.parts/part-{k:05d}.parquet``."""
    return parts_dir(out) / f"part-{int(k):05d}.parquet"


def _default_device(device: torch.device | str | None, env: DistEnv) -> torch.device:
    if device is not None:
        return check_device(device)
    if torch.cuda.is_available():
        return torch.device(f"cuda:{env.local_rank}")
    return torch.device("cpu")


# ---- DSP ----------------------------------------------------------------------------------------
def build_point_cloud(ds: Any, settings: ConvertSettings, tau: float | None,
                      device: torch.device | str) -> SpectralPointCloud:
    """The :class:`SpectralPointCloud` for ``settings`` on ``ds``'s sensor and calibration.

    ``tau`` is the fixed or calibrated threshold (fixed-tau and per-dataset modes); in
    per-frame mode the module picks a tau per frame for ``settings.density``.
    """
    common = dict(window=tuple(settings.window), guard=tuple(settings.guard), enrich=tuple(settings.enrich),
                  envelope=settings.envelope, beamforming=settings.beamforming)
    if settings.mode == "per-frame":
        spc = SpectralPointCloud(ds.sensor, ds.calibration, density=settings.density,
                                 density_mode="per-frame", **common)
    else:
        if tau is None:
            raise ValueError(f"density mode {settings.mode!r} needs a tau")
        spc = SpectralPointCloud(ds.sensor, ds.calibration, tau=float(tau), **common)
    return spc.to(device).eval()


def _check_dsp_settings(settings: ConvertSettings, ds: Any, source_id: str) -> None:
    """Fail before any file is written: a reachable density, a non-empty split."""
    if settings.density is not None:
        check_density(settings.density, ds.sensor)
    if len(ds) == 0:
        raise ValueError(f"{source_id}: the {settings.split!r} split has no frames")


def _load_batch(ds: Any, positions: Sequence[int], device: torch.device) -> torch.Tensor:
    """RD cubes of items ``positions`` as complex64 ``(B, Nr, Nd, Nrx)`` on ``device``."""
    return torch.stack([read_cube(ds, p).to(device) for p in positions])


def _prefetched(ds: Any, batches: Sequence[Sequence[int]], device: torch.device
                ) -> Iterator[tuple[list[int], torch.Tensor]]:
    """Yield ``(positions, rd)`` per batch, reading the next batch in a thread meanwhile (file reads
    and validation overlap the DSP)."""
    if not batches:
        return
    with ThreadPoolExecutor(max_workers=1) as pool:
        fut = pool.submit(_load_batch, ds, batches[0], device)
        for j, pos in enumerate(batches):
            rd = fut.result()
            if j + 1 < len(batches):
                fut = pool.submit(_load_batch, ds, batches[j + 1], device)
            yield list(pos), rd


def _batches(positions: Sequence[int], batch_size: int) -> list[list[int]]:
    return [list(positions[i:i + batch_size]) for i in range(0, len(positions), batch_size)]


def calibrate_tau(source: Source, settings: ConvertSettings, *, batch_size: int = 8,
                  device: torch.device | str = "cpu", progress: bool = False) -> float:
    """One tau for the whole dataset: the mean density over the *training* split hits the target.

    ``source`` is a RADIal root (its ``train`` split is opened) or a dataset object holding the
    training frames (used as given, e.g. ``SimulatedRADIal(..., split="train")``). The density is
    that of the encoded set (``S*(tau)`` when ``settings.enrich`` has ``rdN``, else ``S(tau)``),
    on ``settings.envelope``. :meth:`SpectralPointCloud.calibrate_tau` (pooled CFAR SNR maps, see
    :func:`radarpc.dsp.density.tau_for_density`) over the first ``settings.calibration_frames``
    training frames (all of them by default).
    """
    if settings.density is None:
        raise ValueError("calibrate_tau needs settings.density")
    train, sid, _ = open_source(source, "train") if isinstance(source, (str, os.PathLike)) \
        else open_source(source, "all")
    n = len(train) if settings.calibration_frames is None else min(len(train), int(settings.calibration_frames))
    if n == 0:
        raise ValueError(f"{sid}: the training split has no frames to calibrate a per-dataset tau on")
    dev = torch.device(device)
    spc = build_point_cloud(train, dataclasses.replace(settings, density_mode="per-dataset"), 1.0, dev)
    batches = _batches(list(range(n)), batch_size)
    it = (rd for _, rd in _prefetched(train, batches, dev))
    if progress:
        from tqdm import tqdm
        it = tqdm(it, total=len(batches), desc="calibrate tau (train)", unit="batch")
    return spc.calibrate_tau(it, density=settings.density)


def _calibration_source(source: Source, ds: Any, calibration_source: Source | None) -> tuple[Source, str]:
    """The training frames of a per-dataset tau, and their id (recorded and compared on resume)."""
    if calibration_source is not None:
        cal = calibration_source
    elif isinstance(source, (str, os.PathLike)):
        cal = source
    elif getattr(ds, "split", None) == "train":
        cal = ds
    else:
        raise ValueError("per-dataset density mode with a dataset object needs calibration_source= its "
                         "training split (e.g. SimulatedRADIal(..., split='train')) or a root path")
    if isinstance(cal, (str, os.PathLike)):
        frames = RADIal(Path(cal), split="train")
        cal_id = str(Path(cal).resolve()) + ":train"
    else:
        frames, cal_id, _ = open_source(cal)
    fp = source_fingerprint(frames)
    return cal, cal_id if fp is None else f"{cal_id}@{fp}"      # changed training files: a new tau


# ---- manifest -----------------------------------------------------------------------------------
def _manifest_key(source_id: str, settings: ConvertSettings, frames: Sequence[int],
                  calibration_id: str | None, fingerprint: str | None = None) -> dict:
    """What must match for parts (or a finished store) of an earlier run to be reused: every
    setting that shapes the output (not ``chunk_frames``), the source, its frames, the state of
    its files (:func:`source_fingerprint`) and, in per-dataset mode, the training frames tau was
    calibrated on."""
    return {"source": source_id, "settings": settings.output_key(), "frames": [int(f) for f in frames],
            "calibration_source": calibration_id, "source_files": fingerprint}


def _read_manifest(d: Path) -> dict | None:
    p = d / _MANIFEST
    if not p.is_file():
        return None
    try:
        return json.loads(p.read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError) as e:
        raise DataFileError(p, f"conversion manifest is unreadable ({e}); delete {d} to start over") from e


def _remove_parts_dir(d: Path) -> None:
    """Remove a parts folder holding only files this module writes (refuse anything else)."""
    if not d.exists():
        return
    ours = [p for p in d.iterdir() if p.name == _MANIFEST or
            (p.name.startswith(("part-", ".part-", f".{_MANIFEST}")) and p.suffix in (".parquet", ".tmp"))]
    for p in ours:
        p.unlink()
    try:
        d.rmdir()
    except OSError as e:
        raise FileExistsError(f"{d} holds files that a conversion did not write; not removing it ({e})") from e


def _wait_for_files(files: Sequence[Path], owners: Sequence[str], timeout_s: float, poll_s: float = 1.0) -> None:
    """Wait until every file exists; on timeout a ``TimeoutError`` names the missing ones and who writes them."""
    t0 = time.monotonic()
    while True:
        missing = [(f, o) for f, o in zip(files, owners) if not f.is_file()]
        if not missing:
            return
        if time.monotonic() - t0 > timeout_s:
            shown = "; ".join(f"{f} (from {o})" for f, o in missing[:8])
            more = f"; ... {len(missing) - 8} more" if len(missing) > 8 else ""
            raise TimeoutError(f"gave up after {timeout_s:.0f} s waiting for {len(missing)} of {len(files)} "
                               f"file(s): {shown}{more}. Is that rank still running (or did it fail)? "
                               f"Raise wait_timeout_s (CLI --wait-timeout) for slow ranks")
        time.sleep(poll_s)


# ---- chunk conversion (runs in the main process, in spawned workers, or on a torchrun rank) -----
@dataclass(frozen=True)
class _ChunkJob:
    dataset: Any                     # the source dataset (pickled to spawned workers)
    out: str
    settings: ConvertSettings
    tau: float | None
    meta: dict                       # PointStoreMetadata.to_dict() of the parts
    chunks: tuple[int, ...]          # chunk indices this job converts
    chunk_frames: int                # frames per chunk (from the manifest)
    batch_size: int
    device: str
    threads: int | None              # torch threads of a spawned worker (None: leave as is)
    parent_pid: int | None = None    # a spawned worker's parent: the worker stops if it dies


def _chunk_positions(n_frames: int, chunk_frames: int, k: int) -> list[int]:
    return list(range(k * chunk_frames, min(n_frames, (k + 1) * chunk_frames)))


def _run_chunks(job: _ChunkJob, on_done: Callable[[int, int], None]) -> int:
    """Convert ``job.chunks`` whose part file is missing; ``on_done(k, n_frames)`` after each."""
    if job.threads is not None:
        torch.set_num_threads(job.threads)
    ds = job.dataset
    dev = torch.device(job.device)
    spc = build_point_cloud(ds, job.settings, job.tau, dev)
    meta = PointStoreMetadata.from_dict(job.meta)
    done = 0
    for k in job.chunks:
        path = part_path(job.out, k)
        pos = _chunk_positions(len(ds), job.chunk_frames, k)
        if path.is_file():
            continue
        with PointStoreWriter(path, meta, row_group_frames=max(len(pos), 1)) as w, torch.no_grad():
            for b, rd in _prefetched(ds, _batches(pos, job.batch_size), dev):
                if job.parent_pid is not None and os.getppid() != job.parent_pid:
                    # orphaned (the parent was killed): stop; the unfinished part is dropped and a
                    # re-run converts it
                    raise SystemExit(f"conversion worker {os.getpid()}: parent {job.parent_pid} is gone, stopping")
                clouds = spc(rd)
                w.write(clouds, [ds.frame_ids[p] for p in b], [ds.sequences[p] for p in b])
        done += 1
        on_done(k, len(pos))
    return done


def _worker_main(job: _ChunkJob, q) -> None:  # pragma: no cover - runs in a spawned process
    try:
        _run_chunks(job, lambda k, n: q.put(("done", k, n)))
    except KeyboardInterrupt:        # Ctrl-C reaches the whole process group: the parent reports it
        raise SystemExit(130)
    except SystemExit:               # orphaned (see _run_chunks): nobody to report to
        raise
    except BaseException:  # noqa: BLE001 - report any failure to the parent, then exit non-zero
        q.put(("error", -1, traceback.format_exc()))
        raise SystemExit(1)


def _run_workers(job: _ChunkJob, workers: int, on_done: Callable[[int, int], None]) -> int:
    """Spread ``job.chunks`` over ``workers`` spawned processes (the i-th pending chunk goes to
    worker ``i % workers``); relay their progress to ``on_done`` and their errors as RuntimeError."""
    import torch.multiprocessing as mp

    ctx = mp.get_context("spawn")
    q = ctx.Queue()
    threads = max(1, torch.get_num_threads() // workers)
    procs = []
    for w in range(workers):
        mine = tuple(k for i, k in enumerate(job.chunks) if i % workers == w)
        if mine:
            p = ctx.Process(target=_worker_main,
                            args=(dataclasses.replace(job, chunks=mine, threads=threads, parent_pid=os.getpid()), q),
                            daemon=False)
            p.start()
            procs.append(p)
    done, errors, finished = 0, [], False
    try:
        while True:
            try:
                kind, k, payload = q.get(timeout=0.5)
            except _queue.Empty:
                if not any(p.is_alive() for p in procs):
                    # drain what arrived between the last get and the exit
                    try:
                        kind, k, payload = q.get(timeout=0.5)
                    except _queue.Empty:
                        break
                else:
                    continue
            if kind == "done":
                done += 1
                on_done(k, payload)
            else:
                errors.append(payload)
        finished = True
    finally:
        # On a worker error or an exception here (e.g. Ctrl-C), stop the others: finished parts stay.
        for p in procs:
            if p.is_alive() and (errors or not finished):
                p.terminate()
            p.join()
    bad = [p.exitcode for p in procs if p.exitcode != 0]
    if errors or bad:
        raise RuntimeError("conversion worker failed:\n" + ("\n".join(errors) or f"exit codes {bad}"))
    return done


# ---- the driver ---------------------------------------------------------------------------------
def convert_dataset(
    source: Source,
    out: str | os.PathLike,
    *,
    tau: float | None = None,
    density: float | None = None,
    density_mode: str = "per-frame",
    enrich: Sequence[str] = (),
    window: tuple[int, int] = (9, 9),
    guard: tuple[int, int] = (3, 3),
    envelope: str = "replicas",
    beamforming: str = "auto",
    split: str = "all",
    batch_size: int = 8,
    chunk_frames: int = 64,
    calibration_frames: int | None = None,
    calibration_source: Source | None = None,
    workers: int = 1,
    device: torch.device | str | None = None,
    resume: bool = True,
    progress: bool = True,
    wait_timeout_s: float = DEFAULT_WAIT_S,
    on_chunk_done: Callable[[int], None] | None = None,
) -> ConvertResult:
    """Convert the frames of a RADIal root (or dataset object) into a Parquet point store.

    Parameters
    ----------
    source : path-like or dataset
        RADIal-layout root (real or simulated), or a dataset object (:class:`RadarDataset`, e.g.
        :class:`~radarpc.sim.radial_writer.SimulatedRADIal`): its frames are converted as given.
    out : path-like
        The ``.parquet`` store to write (atomically, at the very end).
    tau, density : float
        Exactly one: a linear SNR threshold, or a target density in (0, 1].
    density_mode : {"per-frame", "per-dataset"}
        With ``density``: a tau per frame, or one tau calibrated on the training split.
    enrich : sequence of str
        Enrichments passed to :class:`SpectralPointCloud` (e.g. ``("rd3", "sector32")``).
    window, guard : (int, int)
        CA-CFAR window and guard (range, Doppler), full odd sizes (RADIal rpl.py: 19,19 and 7,7).
    envelope : {"replicas", "all-slots"}
        Seed eq. 1 (sum over the ``n_tx`` replica bins) or RADIal rpl.py's sum over every slot.
    beamforming : {"auto", "exact", "screened"}
        How each point's direction is found (the same points either way, only the speed differs),
        see :class:`SpectralPointCloud` and :mod:`radarpc.dsp.beamform`.
    split : {"all", "train", "val", "test"}
        With a root path: the split to convert. A dataset object is its own split.
    batch_size : int
        Frames per forward pass.
    chunk_frames : int
        Frames per part file (unit of resume and sharding); shrunk when there are fewer chunks
        than processes; a resumed run keeps the first run's size.
    calibration_frames : int, optional
        Training frames used for the per-dataset tau (default all).
    calibration_source : path-like or dataset, optional
        Per-dataset mode: the training frames (default the root's train split, or the dataset
        object itself if its ``split`` is ``"train"``).
    workers : int
        Local processes (spawned) sharing the chunks; 1 runs in this process. A script that
        calls this with ``workers > 1`` needs the usual ``if __name__ == "__main__":`` guard
        (spawned workers import the main module; a dataset object must be picklable).
    device : torch.device or str, optional
        Default ``cuda:LOCAL_RANK`` when CUDA is available, else CPU.
    resume : bool
        Reuse finished parts of an earlier run with the same settings (and return at once if
        ``out`` already holds this conversion). False starts over.
    progress : bool
        tqdm progress bar over frames.
    wait_timeout_s : float
        Under torchrun without a process group: how long ranks wait for each other's files
        (default 2 h); the error names the missing parts and the ranks that own them.
    on_chunk_done : callable, optional
        Called with the chunk index after each chunk finished in this call (in this process).

    Returns
    -------
    ConvertResult
    """
    settings = ConvertSettings(tau=tau, density=density, density_mode=density_mode, enrich=tuple(enrich),
                               window=tuple(window), guard=tuple(guard), envelope=envelope,
                               beamforming=beamforming, split=split, chunk_frames=chunk_frames,
                               calibration_frames=calibration_frames)
    if int(batch_size) < 1:
        raise ValueError(f"batch_size must be >= 1, got {batch_size}")
    if int(workers) < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    if not (wait_timeout_s >= 0):
        raise ValueError(f"wait_timeout_s must be >= 0 seconds, got {wait_timeout_s}")
    out = Path(out)
    if out.is_dir():
        raise IsADirectoryError(f"the point store {out} is a directory; give the path of a .parquet file")
    env = dist_env()
    dev = _default_device(device, env)
    ds, source_id, split_used = open_source(source, settings.split)
    settings = dataclasses.replace(settings, split=split_used)
    _check_dsp_settings(settings, ds, source_id)
    cal_src, cal_id = (None, None)
    if settings.mode == "per-dataset":
        cal_src, cal_id = _calibration_source(source, ds, calibration_source)
    n = len(ds)
    key = _manifest_key(source_id, settings, ds.frame_ids, cal_id, source_fingerprint(ds))
    pdir = parts_dir(out)

    # A finished conversion with these settings: nothing to do.
    if resume and out.is_file() and not pdir.exists():
        try:
            store = PointStore(out)
        except DataFileError as e:
            raise DataFileError(out, f"{e.problem}; it is in the way of this conversion: remove it, or pass "
                                     f"resume=False (CLI: --no-resume) to overwrite it") from e
        m = store.metadata
        if m.settings.get("key") == key:
            chunk = int(m.settings.get("chunk_frames") or settings.chunk_frames)
            return ConvertResult(out, n, int(store.frame_table.n_points.sum()), m.achieved_density,
                                 m.peak_density, m.tau, 0, -(-n // chunk), chunk)

    # The manifest fixes the settings, the frames, the chunk size, the calibrated tau and the date.
    if env.rank == 0:
        if not resume:
            _remove_parts_dir(pdir)
        manifest = _read_manifest(pdir)
        if manifest is not None and manifest.get("key") != key:
            old_key = manifest.get("key") or {}
            what = [k for k in key if old_key.get(k) != key[k]]
            raise ValueError(f"{pdir} holds parts of a conversion with other {', '.join(what) or 'settings'} "
                             f"(recorded {old_key}, now {key}); delete it or pass resume=False "
                             f"(CLI: --no-resume) to start over")
        if manifest is None:
            chunk = settings.chunk_frames
            procs = int(workers) * env.world_size
            if procs > 1 and -(-n // chunk) < procs:          # share the work: at least one chunk each
                chunk = max(1, -(-n // procs))
            cal_tau = settings.tau
            if settings.mode == "per-dataset":
                cal_tau = calibrate_tau(cal_src, settings, batch_size=int(batch_size), device=dev, progress=progress)
            meta = PointStoreMetadata(
                sensor=ds.sensor, density_mode=settings.mode, tau=cal_tau, target_density=settings.density,
                achieved_density=0.0, peak_density=0.0, enrich=settings.enrich, window=settings.window,
                guard=settings.guard, source_root=source_id, split=settings.split, radarpc_version=__version__,
                created=_dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
                envelope=settings.envelope,
                settings=dict(dataclasses.replace(settings, chunk_frames=chunk).to_dict(), key=key))
            manifest = dict(key=key, tau=cal_tau, meta=meta.to_dict(), chunk_frames=chunk)
            pdir.mkdir(parents=True, exist_ok=True)
            with atomic_write(pdir / _MANIFEST, "w") as f:
                json.dump(manifest, f)
    _barrier(env, [pdir / _MANIFEST], ["rank 0 (manifest)"], wait_timeout_s)
    if env.rank != 0:
        manifest = _read_manifest(pdir)
        if manifest is None or manifest.get("key") != key:
            raise ValueError(f"rank {env.rank}: {pdir / _MANIFEST} does not match this rank's settings")
    chunk = int(manifest["chunk_frames"])
    n_chunks = -(-n // chunk)

    mine = tuple(k for k in range(n_chunks) if k % env.world_size == env.rank)
    todo = tuple(k for k in mine if not part_path(out, k).is_file())
    skipped = len(mine) - len(todo)
    job = _ChunkJob(dataset=ds, out=str(out), settings=settings, tau=manifest["tau"], meta=manifest["meta"],
                    chunks=todo, chunk_frames=chunk, batch_size=int(batch_size), device=str(dev), threads=None)
    bar = None
    if progress:
        from tqdm import tqdm
        done_frames = sum(len(_chunk_positions(n, chunk, k)) for k in mine if k not in todo)
        bar = tqdm(total=sum(len(_chunk_positions(n, chunk, k)) for k in mine),
                   initial=done_frames, desc=f"pointcloud {Path(source_id).name or source_id}", unit="frame")

    def on_done(k: int, n_frames: int) -> None:
        if bar is not None:
            bar.update(n_frames)
        if on_chunk_done is not None:
            on_chunk_done(k)

    try:
        if todo:
            if int(workers) > 1 and len(todo) > 1:
                converted = _run_workers(job, min(int(workers), len(todo)), on_done)
            else:
                converted = _run_chunks(job, on_done)
        else:
            converted = 0
    finally:
        if bar is not None:
            bar.close()

    # Every part exists -> rank 0 merges.
    all_parts = [part_path(out, k) for k in range(n_chunks)]
    if env.rank != 0:
        _barrier(env, [], [], wait_timeout_s)
        return ConvertResult(None, n, 0, float("nan"), float("nan"), manifest["tau"], converted, skipped, chunk)
    _barrier(env, all_parts, [f"rank {k % env.world_size}, chunk {k}" for k in range(n_chunks)], wait_timeout_s)
    meta = PointStoreMetadata.from_dict(manifest["meta"])
    with PointStoreWriter(out, meta, row_group_frames=chunk) as w:
        for p in all_parts:
            w.append_store(PointStore(p))
    _remove_parts_dir(pdir)
    store = PointStore(out)
    return ConvertResult(out, n, int(store.frame_table.n_points.sum()), store.metadata.achieved_density,
                         store.metadata.peak_density, manifest["tau"], converted, skipped, chunk)


def _barrier(env: DistEnv, files: Sequence[Path], owners: Sequence[str], timeout_s: float) -> None:
    """Synchronise torchrun ranks: a process-group barrier if one is initialised, else wait for
    ``files`` (written by ``owners``) to exist. Nothing to wait for outside torchrun."""
    if env.world_size == 1:
        return
    if torch.distributed.is_available() and torch.distributed.is_initialized():
        torch.distributed.barrier()
        return
    if files:
        _wait_for_files(files, owners, timeout_s)


# ---- sparse RD root -----------------------------------------------------------------------------
def _link_or_copy(src: Path, dst: Path, *, overwrite: bool = False) -> None:
    """Hard-link ``src`` to ``dst`` (copy across file systems), atomically; an existing ``dst`` is
    kept unless ``overwrite``."""
    if dst.exists() and not overwrite:
        return
    dst.parent.mkdir(parents=True, exist_ok=True)
    tmp = dst.with_name(f".{dst.name}.{os.getpid()}.tmp")
    try:
        os.link(src, tmp)
    except OSError:
        shutil.copyfile(src, tmp)
    os.replace(tmp, dst)


def _write_split_labels(src: Path, dst: Path, keep: set[int]) -> None:
    """Copy ``labels.csv`` keeping only the rows of frames ``keep`` (atomic)."""
    with open(src, newline="", encoding="utf-8-sig") as f:
        rows = list(csv.reader(f))
    if not rows or tuple(h.strip() for h in rows[0]) != LABEL_COLUMNS:
        raise DataFileError(src, "header is not RADIal's labels header")
    with atomic_write(dst, "w") as f:
        w = csv.writer(f, lineterminator="\n")
        w.writerow(rows[0])
        for r in rows[1:]:
            if r and int(float(r[0])) in keep:
                w.writerow(r)


def _write_png(path: Path, mask: np.ndarray) -> None:
    """A 2-D uint8 mask as a greyscale PNG, atomically."""
    from PIL import Image

    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(path, "wb") as f:
        Image.fromarray(np.ascontiguousarray(mask, dtype=np.uint8)).save(f, format="PNG")


def _write_labels_from_dataset(ds: Any, dst: Path) -> None:
    """``labels.csv`` from a dataset object's raw rows (``frame_labels(i)``), atomic."""
    if not hasattr(ds, "frame_labels"):
        raise ValueError(f"{type(ds).__name__} has neither a root folder nor frame_labels(i): cannot write "
                         f"the sparse root's labels.csv")
    with atomic_write(dst, "w") as f:
        w = csv.writer(f, lineterminator="\n")
        w.writerow(LABEL_COLUMNS)
        for i in range(len(ds)):
            for row in ds.frame_labels(i):
                w.writerow([row[c] for c in LABEL_COLUMNS])


def write_sparse_rd(
    source: Source,
    out_root: str | os.PathLike,
    *,
    tau: float | None = None,
    density: float | None = None,
    density_mode: str = "per-frame",
    enrich: Sequence[str] = (),
    window: tuple[int, int] = (9, 9),
    guard: tuple[int, int] = (3, 3),
    envelope: str = "replicas",
    split: str = "all",
    batch_size: int = 8,
    calibration_frames: int | None = None,
    calibration_source: Source | None = None,
    calibrated_tau: float | None = None,
    device: torch.device | str | None = None,
    resume: bool = True,
    progress: bool = True,
) -> SparseRDResult:
    """Write a RADIal-layout root whose RD cubes are masked to the set the point store encodes.

    ``R_sparse[r, d, c] = R[r, d, c]`` if ``(r, d)`` is in the encoded set else 0 (all Rx
    channels kept). The encoded set is exactly the one :func:`convert_dataset` with the same
    arguments turns into points: ``S(tau)`` (the ``n_tx`` replica bins of every CFAR peak), or
    with an ``rdN`` enrichment ``S*(tau)`` (the replica bins of every cell of the ``n x n``
    neighbourhoods), with the same envelope, CFAR and per-frame (or calibrated) taus; a density
    target applies to that set. ``labels.csv`` (restricted to the split's frames), the freespace
    PNGs, ``calibration.npz`` / ``CalibrationTable.npy`` and ``sensor.json`` are hard-linked (or
    copied) from the source root; for a dataset object without a ``root`` (SimulatedRADIal),
    ``labels.csv`` is written from ``frame_labels(i)``, ``calibration.npz`` and ``sensor.json``
    from its calibration and sensor, and the freespace PNGs from ``freespace_mask(i)`` (when the
    object has it; ``sparse_rd.json`` records ``"freespace"``). Each cube is written
    atomically and existing cubes are kept when ``resume`` (so a killed run resumes).

    ``sparse_rd.json`` records the source, the settings and the tau (a resumed run must match
    them), every frame's tau and achieved density (``frames``: numSample -> ``{"tau",
    "density", "peak_density"}``), their mean, and whether the run completed.

    Parameters are those of :func:`convert_dataset`, plus ``calibrated_tau``: in per-dataset mode,
    the tau already calibrated for the matching store (``ConvertResult.tau``), used instead of
    calibrating again.

    Returns
    -------
    SparseRDResult
    """
    from radarpc.dsp.sparse_rd import sparse_rd, sparse_rd_mask

    settings = ConvertSettings(tau=tau, density=density, density_mode=density_mode, enrich=tuple(enrich),
                               window=tuple(window), guard=tuple(guard), envelope=envelope,
                               split=split, calibration_frames=calibration_frames)
    if int(batch_size) < 1:
        raise ValueError(f"batch_size must be >= 1, got {batch_size}")
    out_root = Path(out_root)
    ds, source_id, split_used = open_source(source, settings.split)
    settings = dataclasses.replace(settings, split=split_used)
    root = Path(ds.root) if getattr(ds, "root", None) is not None else None
    if root is not None and root.resolve() == out_root.resolve():
        raise ValueError(f"the sparse-RD root must differ from the source root {root}")
    dev = _default_device(device, DistEnv())
    _check_dsp_settings(settings, ds, source_id)
    cal_src, cal_id = (None, None)
    if settings.mode == "per-dataset":
        try:
            cal_src, cal_id = _calibration_source(source, ds, calibration_source)
        except ValueError:
            if calibrated_tau is None:                 # nothing to calibrate on
                raise
            cal_id = f"given tau {float(calibrated_tau)!r}"
    info_path = out_root / "sparse_rd.json"
    if out_root.is_dir() and not info_path.is_file() and any(out_root.iterdir()):
        raise FileExistsError(f"{out_root} is not empty and is not a sparse-RD root (no sparse_rd.json): "
                              f"refusing to write masked cubes into it; choose a new or empty folder")
    key = {"source_root": source_id, "settings": settings.output_key(), "source_files": source_fingerprint(ds),
           "calibration_source": cal_id}
    prev = None
    if resume and info_path.is_file():
        try:
            prev = json.loads(info_path.read_text(encoding="utf-8"))
        except (OSError, json.JSONDecodeError) as e:
            raise DataFileError(info_path, f"is unreadable ({e}); delete it or pass resume=False") from e
        if {k: prev.get(k) for k in key} != key:
            raise ValueError(f"{out_root} holds a sparse-RD root made from other data or settings (see "
                             f"{info_path}); write to another folder or pass resume=False (CLI: --no-resume)")
    cal_tau = settings.tau
    if settings.mode == "per-dataset":
        if prev is not None:
            cal_tau = prev["tau"]
        elif calibrated_tau is not None:
            cal_tau = float(calibrated_tau)
        else:
            cal_tau = calibrate_tau(cal_src, settings, batch_size=int(batch_size), device=dev, progress=progress)
        if calibrated_tau is not None and cal_tau != float(calibrated_tau):
            raise ValueError(f"calibrated_tau={calibrated_tau} differs from the tau {cal_tau} of the existing "
                             f"sparse root {out_root}; pass resume=False to rewrite it")
    spc = build_point_cloud(ds, settings, cal_tau, dev)

    out_root.mkdir(parents=True, exist_ok=True)
    frames: dict[str, dict] = dict(prev.get("frames") or {}) if prev is not None else {}
    info = dict(key, tau=cal_tau, mode=settings.mode, radarpc_version=__version__, complete=False,
                frames=frames)
    with atomic_write(info_path, "w") as f:
        json.dump(info, f, indent=1)
    if root is not None:
        for name in ("calibration.npz", "CalibrationTable.npy", "sensor.json"):
            if (root / name).is_file():
                _link_or_copy(root / name, out_root / name, overwrite=not resume)
        if not resume or not (out_root / "labels.csv").is_file():
            _write_split_labels(root / "labels.csv", out_root / "labels.csv", set(ds.frame_ids))
    else:
        if not resume or not (out_root / "calibration.npz").is_file():
            save_calibration(out_root / "calibration.npz", ds.calibration)
        if not resume or not (out_root / "sensor.json").is_file():
            with atomic_write(out_root / "sensor.json", "w") as f:
                json.dump(ds.sensor.to_dict(), f, indent=1)
        if not resume or not (out_root / "labels.csv").is_file():
            _write_labels_from_dataset(ds, out_root / "labels.csv")

    # a frame is done when its cube is on disk and recorded (a run killed between the two redoes it)
    todo = [p for p in range(len(ds)) if not (resume and str(ds.frame_ids[p]) in frames
                                              and fft_path(out_root, ds.frame_ids[p]).is_file())]
    it = _prefetched(ds, _batches(todo, int(batch_size)), dev)
    if progress:
        from tqdm import tqdm
        it = tqdm(it, total=-(-len(todo) // int(batch_size)), desc=f"sparse RD {Path(source_id).name}", unit="batch")
    written: list[float] = []
    with torch.no_grad():
        for pos, rd in it:                                                 # rd: (B, Nr, Nd, Nrx)
            enc = spc.encode(rd)                                           # the point cloud's detection
            mask_full = sparse_rd_mask(enc.kept, ds.sensor, enc.tx0_doppler())   # (B, Nr, Nd) bool
            sparse = sparse_rd(rd, mask_full)                              # (B, Nr, Nd, Nrx)
            dens = mask_full.double().mean(dim=(1, 2)).cpu()               # (B,) encoded-set density
            peak = enc.peaks.flatten(1).double().sum(1).cpu() * ds.sensor.n_tx / (
                ds.sensor.n_range * ds.sensor.n_doppler)                   # (B,) |S(tau)| / (Nr ND)
            for b, p in enumerate(pos):
                num = ds.frame_ids[p]
                save_npy_atomic(fft_path(out_root, num), sparse[b].cpu().numpy().astype(np.complex64))
                frames[str(num)] = {"tau": float(enc.tau[b]), "density": float(dens[b]),
                                    "peak_density": float(peak[b])}
                written.append(float(dens[b]))
            with atomic_write(info_path, "w") as f:                      # the records so far (resume)
                json.dump(info, f, indent=1)
    has_freespace = root is not None or callable(getattr(ds, "freespace_mask", None))
    for i, num in enumerate(ds.frame_ids):
        dst = freespace_path(out_root, num)
        if root is not None:
            if freespace_path(root, num).is_file():
                _link_or_copy(freespace_path(root, num), dst, overwrite=not resume)
        elif has_freespace and (not resume or not dst.is_file()):
            _write_png(dst, ds.freespace_mask(i))
    recorded = [frames[str(num)] for num in ds.frame_ids if str(num) in frames]
    info.update(complete=True, frames_written_last_run=len(todo),
                mean_density_last_run=float(np.mean(written)) if written else None,
                mean_density=float(np.mean([r["density"] for r in recorded])) if recorded else None,
                freespace=has_freespace)
    with atomic_write(info_path, "w") as f:
        json.dump(info, f, indent=1)
    return SparseRDResult(out_root, len(ds), len(todo), float(np.mean(written)) if written else float("nan"),
                          cal_tau, frame_tau={int(k): v["tau"] for k, v in frames.items()},
                          frame_density={int(k): v["density"] for k, v in frames.items()})
