"""Dataset conversion drivers: a RADIal root -> a Parquet point store, or -> a sparse-RD root.

:func:`convert_dataset` runs :class:`~radarpc.dsp.pointcloud.SpectralPointCloud` over every
frame of a split and writes a :mod:`radarpc.data.pointstore` file. The work is cut into chunks
of ``chunk_frames`` frames; chunk ``k`` is written atomically to ``OUT.parts/part-{k:05d}.parquet``
and a finished chunk is never recomputed, so a killed conversion resumes where it stopped and
gives the same final file. At the end the parts are merged into ``OUT`` (atomically) and the
parts folder is removed. Chunks can be spread over

* local processes (``workers=N``: the i-th pending chunk goes to worker ``i % N``, spawned processes, each
  with ``torch`` threads = available threads / N), and
* ``torchrun`` ranks (``RANK``/``WORLD_SIZE``/``LOCAL_RANK`` set): rank ``r`` converts the chunks
  ``k % WORLD_SIZE == r`` on ``cuda:LOCAL_RANK`` when CUDA is available; rank 0 merges once every
  part exists (``torch.distributed`` barrier when a process group is initialised, else polling
  the parts folder, which must then be on a shared file system).

Density control (seed Sec. 3.2): the detected set is ``S(tau) = {(r, l) : E(r, l) / mu(r, l) >
tau}`` expanded to the ``M`` Tx replicas, density ``|S(tau)| / (Nr * ND)``. A target density
applies to the set the store encodes: ``S(tau)``, or ``S*(tau)`` (eq. 9) with an ``rdN``
enrichment. Give either a fixed linear SNR threshold ``tau`` or a target ``density``:
``per-frame`` picks a tau for every frame, ``per-dataset`` calibrates one tau on the *training*
split (stored in the metadata) and applies it to the requested split.

:func:`write_sparse_rd` writes the RD cubes masked to ``S(tau)`` as a new RADIal-layout root
(labels, freespace, calibration and sensor description linked or copied) that the unchanged
:class:`~radarpc.data.radial.RADIal` reader and the dense FFTRadNet read: the sparse-RD baseline.
"""
from __future__ import annotations

import csv
import dataclasses
import datetime as _dt
import json
import math
import os
import queue as _queue
import shutil
import time
import traceback
from dataclasses import dataclass
from pathlib import Path
from concurrent.futures import ThreadPoolExecutor
from typing import Callable, Iterator, Sequence

import numpy as np
import torch

from radarpc import __version__
from radarpc.data.pointstore import PointStore, PointStoreMetadata, PointStoreWriter
from radarpc.data.radial import RADIal, find_fft_file, load_rd
from radarpc.data.radial_format import LABEL_COLUMNS, fft_path, freespace_path
from radarpc.io import DataFileError, atomic_write, save_npy_atomic

__all__ = [
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


# ---- settings -------------------------------------------------------------------------------------
@dataclass(frozen=True)
class ConvertSettings:
    """What to compute: threshold or density, enrichments, CFAR geometry, split and chunking.

    Exactly one of ``tau`` and ``density`` is given.
    """

    tau: float | None = None                 # fixed linear SNR threshold (RADIal default 1.585 = 2 dB)
    density: float | None = None             # target density of the encoded set (S*, with rdN, else S), in (0, 1]
    density_mode: str = "per-frame"          # "per-frame" or "per-dataset" (only with density)
    enrich: tuple[str, ...] = ()             # e.g. ("rd3", "sector32"); () = plain spectral points
    window: tuple[int, int] = (9, 9)         # CA-CFAR window (range, Doppler), cells
    guard: tuple[int, int] = (3, 3)          # CA-CFAR guard (range, Doppler), cells
    split: str = "all"                       # "train", "val", "test" or "all"
    chunk_frames: int = 64                   # frames per part file (the unit of resume and sharding)
    calibration_frames: int | None = None    # train frames used to calibrate per-dataset tau (None: all)

    def __post_init__(self) -> None:
        if (self.tau is None) == (self.density is None):
            raise ValueError(f"give exactly one of tau (a linear SNR threshold) and density (a target "
                             f"fraction of RD cells), got tau={self.tau}, density={self.density}")
        if self.tau is not None and not (math.isfinite(self.tau) and self.tau > 0):
            raise ValueError(f"tau must be a positive finite linear SNR threshold, got {self.tau}")
        if self.density is not None and not (math.isfinite(self.density) and 0.0 < self.density <= 1.0):
            raise ValueError(f"density must be a fraction of RD cells in (0, 1], got {self.density}")
        if self.density_mode not in ("per-frame", "per-dataset"):
            raise ValueError(f"density_mode must be 'per-frame' or 'per-dataset', got {self.density_mode!r}")
        if self.split not in ("train", "val", "test", "all"):
            raise ValueError(f"split must be one of train, val, test, all; got {self.split!r}")
        for name in ("window", "guard"):
            v = getattr(self, name)
            if len(v) != 2 or any(int(x) != x or int(x) < 1 or int(x) % 2 == 0 for x in v):
                raise ValueError(f"CFAR {name} must be two positive odd integers (full side lengths "
                                 f"along range and Doppler), got {v}")
        if any(g >= w for g, w in zip(self.guard, self.window)):
            raise ValueError(f"guard {self.guard} must be smaller than window {self.window} on both axes")
        if int(self.chunk_frames) < 1:
            raise ValueError(f"chunk_frames must be >= 1, got {self.chunk_frames}")
        if self.calibration_frames is not None and int(self.calibration_frames) < 1:
            raise ValueError(f"calibration_frames must be >= 1, got {self.calibration_frames}")

    @property
    def mode(self) -> str:
        """``"fixed-tau"``, ``"per-frame"`` or ``"per-dataset"`` (:data:`DENSITY_MODES`)."""
        return "fixed-tau" if self.tau is not None else self.density_mode

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["enrich"], d["window"], d["guard"] = list(self.enrich), list(self.window), list(self.guard)
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


@dataclass(frozen=True)
class SparseRDResult:
    """Outcome of :func:`write_sparse_rd`."""

    root: Path                       # the sparse-RD root
    n_frames: int                    # frames in the root
    frames_written: int              # cubes computed in this call (the others existed)
    achieved_density: float          # mean density of the frames written in this call (nan if none)
    tau: float | None                # fixed or calibrated threshold (None in per-frame mode)


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
        return torch.device(device)
    if torch.cuda.is_available():
        return torch.device(f"cuda:{env.local_rank}")
    return torch.device("cpu")


# ---- DSP ----------------------------------------------------------------------------------------
def build_point_cloud(ds: RADIal, settings: ConvertSettings, tau: float | None,
                      device: torch.device | str) -> torch.nn.Module:
    """The :class:`SpectralPointCloud` for ``settings`` on ``ds``'s sensor and calibration.

    ``tau`` is the fixed or calibrated threshold (fixed-tau and per-dataset modes); in
    per-frame mode the module picks a tau per frame for ``settings.density``.
    """
    from radarpc.dsp.pointcloud import SpectralPointCloud

    common = dict(window=tuple(settings.window), guard=tuple(settings.guard), enrich=tuple(settings.enrich))
    if settings.mode == "per-frame":
        spc = SpectralPointCloud(ds.sensor, ds.calibration, density=settings.density,
                                 density_mode="per-frame", **common)
    else:
        if tau is None:
            raise ValueError(f"density mode {settings.mode!r} needs a tau")
        spc = SpectralPointCloud(ds.sensor, ds.calibration, tau=float(tau), **common)
    return spc.to(device).eval()


def _check_dsp_settings(settings: ConvertSettings, ds: RADIal) -> None:
    """Fail before any file is written: enrichment names, CFAR sizes, a reachable density."""
    from radarpc.dsp.density import check_density
    from radarpc.dsp.pointcloud import SpectralPointCloudConfig

    SpectralPointCloudConfig(tau=settings.tau, density=settings.density, density_mode=settings.density_mode,
                             window=settings.window, guard=settings.guard, enrich=settings.enrich)
    if settings.density is not None:
        check_density(settings.density, ds.sensor)
    if len(ds) == 0:
        raise ValueError(f"{ds.root}: the {settings.split!r} split has no frames")


def _load_batch(ds: RADIal, positions: Sequence[int], device: torch.device) -> torch.Tensor:
    """RD cubes of items ``positions`` as complex64 ``(B, Nr, Nd, Nrx)`` on ``device``."""
    cubes = [torch.from_numpy(load_rd(find_fft_file(ds.root, ds.frame_ids[p]), ds.sensor)) for p in positions]
    return torch.stack(cubes).to(device)


def _prefetched(ds: RADIal, batches: Sequence[Sequence[int]], device: torch.device
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


def calibrate_tau(root: str | os.PathLike, settings: ConvertSettings, *, batch_size: int = 8,
                  device: torch.device | str = "cpu", progress: bool = False) -> float:
    """One tau for the whole dataset: the mean density over the *training* split hits the target.

    The density is that of the encoded set (``S*(tau)`` when ``settings.enrich`` has ``rdN``, else
    ``S(tau)``). :meth:`SpectralPointCloud.calibrate_tau` (pooled CFAR SNR maps, see
    :func:`radarpc.dsp.density.tau_for_density`) over the first ``settings.calibration_frames``
    training frames (all of them by default).
    """
    if settings.density is None:
        raise ValueError("calibrate_tau needs settings.density")
    train = RADIal(root, split="train")
    n = len(train) if settings.calibration_frames is None else min(len(train), int(settings.calibration_frames))
    if n == 0:
        raise ValueError(f"{root}: the training split has no frames to calibrate a per-dataset tau on")
    dev = torch.device(device)
    spc = build_point_cloud(train, dataclasses.replace(settings, density_mode="per-dataset"), 1.0, dev)
    batches = _batches(list(range(n)), batch_size)
    it = (rd for _, rd in _prefetched(train, batches, dev))
    if progress:
        from tqdm import tqdm
        it = tqdm(it, total=len(batches), desc="calibrate tau (train)", unit="batch")
    return spc.calibrate_tau(it, density=settings.density)


# ---- manifest -----------------------------------------------------------------------------------
def _manifest_key(root: Path, settings: ConvertSettings, frames: Sequence[int]) -> dict:
    # What must match for parts of an earlier run to be reused.
    return {"root": str(root.resolve()), "settings": settings.to_dict(), "frames": [int(f) for f in frames]}


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


def _wait_for(pred: Callable[[], bool], what: str, timeout_s: float, poll_s: float = 1.0) -> None:
    t0 = time.monotonic()
    while not pred():
        if time.monotonic() - t0 > timeout_s:
            raise TimeoutError(f"gave up after {timeout_s:.0f} s waiting for {what}")
        time.sleep(poll_s)


# ---- chunk conversion (runs in the main process, in spawned workers, or on a torchrun rank) -----
@dataclass(frozen=True)
class _ChunkJob:
    root: str
    out: str
    settings: ConvertSettings
    tau: float | None
    meta: dict                       # PointStoreMetadata.to_dict() of the parts
    chunks: tuple[int, ...]          # chunk indices this job converts
    batch_size: int
    device: str
    threads: int | None              # torch threads of a spawned worker (None: leave as is)


def _chunk_positions(n_frames: int, chunk_frames: int, k: int) -> list[int]:
    return list(range(k * chunk_frames, min(n_frames, (k + 1) * chunk_frames)))


def _run_chunks(job: _ChunkJob, on_done: Callable[[int, int], None]) -> int:
    """Convert ``job.chunks`` whose part file is missing; ``on_done(k, n_frames)`` after each."""
    if job.threads is not None:
        torch.set_num_threads(job.threads)
    ds = RADIal(job.root, split=job.settings.split)
    dev = torch.device(job.device)
    spc = build_point_cloud(ds, job.settings, job.tau, dev)
    meta = PointStoreMetadata.from_dict(job.meta)
    done = 0
    for k in job.chunks:
        path = part_path(job.out, k)
        pos = _chunk_positions(len(ds), job.settings.chunk_frames, k)
        if path.is_file():
            continue
        with PointStoreWriter(path, meta, row_group_frames=max(len(pos), 1)) as w, torch.no_grad():
            for b, rd in _prefetched(ds, _batches(pos, job.batch_size), dev):
                clouds = spc(rd)
                w.write(clouds, [ds.frame_ids[p] for p in b], [ds.sequences[p] for p in b])
        done += 1
        on_done(k, len(pos))
    return done


def _worker_main(job: _ChunkJob, q) -> None:  # pragma: no cover - runs in a spawned process
    try:
        _run_chunks(job, lambda k, n: q.put(("done", k, n)))
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
            p = ctx.Process(target=_worker_main, args=(dataclasses.replace(job, chunks=mine, threads=threads), q),
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
    root: str | os.PathLike,
    out: str | os.PathLike,
    *,
    tau: float | None = None,
    density: float | None = None,
    density_mode: str = "per-frame",
    enrich: Sequence[str] = (),
    window: tuple[int, int] = (9, 9),
    guard: tuple[int, int] = (3, 3),
    split: str = "all",
    batch_size: int = 8,
    chunk_frames: int = 64,
    calibration_frames: int | None = None,
    workers: int = 1,
    device: torch.device | str | None = None,
    resume: bool = True,
    progress: bool = True,
    wait_timeout_s: float = 24 * 3600.0,
    on_chunk_done: Callable[[int], None] | None = None,
) -> ConvertResult:
    """Convert the frames of a RADIal root into a Parquet point store.

    Parameters
    ----------
    root : path-like
        RADIal-layout root (real or simulated).
    out : path-like
        The ``.parquet`` store to write (atomically, at the very end).
    tau, density : float
        Exactly one: a linear SNR threshold, or a target density in (0, 1].
    density_mode : {"per-frame", "per-dataset"}
        With ``density``: a tau per frame, or one tau calibrated on the training split.
    enrich : sequence of str
        Enrichments passed to :class:`SpectralPointCloud` (e.g. ``("rd3", "sector32")``).
    window, guard : (int, int)
        CA-CFAR window and guard (range, Doppler).
    split : {"all", "train", "val", "test"}
    batch_size : int
        Frames per forward pass.
    chunk_frames : int
        Frames per part file (unit of resume and sharding).
    calibration_frames : int, optional
        Training frames used for the per-dataset tau (default all).
    workers : int
        Local processes (spawned) sharing the chunks; 1 runs in this process. A script that
        calls this with ``workers > 1`` needs the usual ``if __name__ == "__main__":`` guard
        (spawned workers import the main module).
    device : torch.device or str, optional
        Default ``cuda:LOCAL_RANK`` when CUDA is available, else CPU.
    resume : bool
        Reuse finished parts of an earlier run with the same settings (and return at once if
        ``out`` already holds this conversion). False starts over.
    progress : bool
        tqdm progress bar over frames.
    wait_timeout_s : float
        Under torchrun without a process group: how long ranks wait for each other's files.
    on_chunk_done : callable, optional
        Called with the chunk index after each chunk finished in this call (in this process).

    Returns
    -------
    ConvertResult
    """
    settings = ConvertSettings(tau=tau, density=density, density_mode=density_mode, enrich=tuple(enrich),
                               window=tuple(int(v) for v in window), guard=tuple(int(v) for v in guard),
                               split=split, chunk_frames=int(chunk_frames), calibration_frames=calibration_frames)
    if int(batch_size) < 1:
        raise ValueError(f"batch_size must be >= 1, got {batch_size}")
    if int(workers) < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    root, out = Path(root), Path(out)
    env = dist_env()
    dev = _default_device(device, env)
    ds = RADIal(root, split=settings.split)
    _check_dsp_settings(settings, ds)
    n = len(ds)
    key = _manifest_key(root, settings, ds.frame_ids)
    n_chunks = -(-n // settings.chunk_frames)
    pdir = parts_dir(out)

    # A finished conversion with these settings: nothing to do.
    if resume and out.is_file() and not pdir.exists():
        store = PointStore(out)
        m = store.metadata
        if (m.source_root == key["root"] and m.split == settings.split and store.frames == key["frames"]
                and m.enrich == settings.enrich and m.window == settings.window and m.guard == settings.guard
                and m.density_mode == settings.mode and m.target_density == settings.density
                and (settings.tau is None or m.tau == settings.tau)):
            return ConvertResult(out, n, int(store.frame_table.n_points.sum()), m.achieved_density,
                                 m.peak_density, m.tau, 0, n_chunks)

    # The manifest fixes the settings, the frames, the calibrated tau and the creation date.
    if env.rank == 0:
        if not resume:
            _remove_parts_dir(pdir)
        manifest = _read_manifest(pdir)
        if manifest is not None and {k: manifest.get(k) for k in key} != key:
            raise ValueError(f"{pdir} holds parts of a conversion with other settings or frames; "
                             f"delete it or pass resume=False (CLI: --no-resume) to start over")
        if manifest is None:
            cal_tau = settings.tau
            if settings.mode == "per-dataset":
                cal_tau = calibrate_tau(root, settings, batch_size=int(batch_size), device=dev, progress=progress)
            meta = PointStoreMetadata(
                sensor=ds.sensor, density_mode=settings.mode, tau=cal_tau, target_density=settings.density,
                achieved_density=0.0, peak_density=0.0, enrich=settings.enrich, window=settings.window, guard=settings.guard,
                source_root=key["root"], split=settings.split, radarpc_version=__version__,
                created=_dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"))
            manifest = dict(key, tau=cal_tau, meta=meta.to_dict(), n_chunks=n_chunks)
            pdir.mkdir(parents=True, exist_ok=True)
            with atomic_write(pdir / _MANIFEST, "w") as f:
                json.dump(manifest, f)
    _barrier(env, pdir / _MANIFEST, wait_timeout_s)
    if env.rank != 0:
        manifest = _read_manifest(pdir)
        if manifest is None or {k: manifest.get(k) for k in key} != key:
            raise ValueError(f"rank {env.rank}: {pdir / _MANIFEST} does not match this rank's settings")

    mine = tuple(k for k in range(n_chunks) if k % env.world_size == env.rank)
    todo = tuple(k for k in mine if not part_path(out, k).is_file())
    skipped = len(mine) - len(todo)
    job = _ChunkJob(root=str(root), out=str(out), settings=settings, tau=manifest["tau"], meta=manifest["meta"],
                    chunks=todo, batch_size=int(batch_size), device=str(dev), threads=None)
    bar = None
    if progress:
        from tqdm import tqdm
        done_frames = sum(len(_chunk_positions(n, settings.chunk_frames, k)) for k in mine if k not in todo)
        bar = tqdm(total=sum(len(_chunk_positions(n, settings.chunk_frames, k)) for k in mine),
                   initial=done_frames, desc=f"pointcloud {root.name}", unit="frame")

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
    _barrier(env, None, wait_timeout_s, wait_files=all_parts)
    if env.rank != 0:
        return ConvertResult(None, n, 0, float("nan"), float("nan"), manifest["tau"], converted, skipped)
    meta = PointStoreMetadata.from_dict(manifest["meta"])
    with PointStoreWriter(out, meta, row_group_frames=settings.chunk_frames) as w:
        for p in all_parts:
            w.append_store(PointStore(p))
    _remove_parts_dir(pdir)
    store = PointStore(out)
    return ConvertResult(out, n, int(store.frame_table.n_points.sum()), store.metadata.achieved_density,
                         store.metadata.peak_density,
                         manifest["tau"], converted, skipped)


def _barrier(env: DistEnv, wait_file: Path | None, timeout_s: float, wait_files: Sequence[Path] = ()) -> None:
    """Synchronise torchrun ranks: a process-group barrier if one is initialised, else wait for files."""
    if env.world_size == 1:
        return
    if torch.distributed.is_available() and torch.distributed.is_initialized():
        torch.distributed.barrier()
        return
    files = list(wait_files) + ([wait_file] if wait_file is not None else [])
    if env.rank == 0 and wait_file is not None:
        return  # rank 0 wrote the manifest itself
    if env.rank != 0 and wait_file is None:
        return  # only rank 0 waits for the parts
    _wait_for(lambda: all(f.is_file() for f in files), f"{len(files)} file(s) such as {files[0]}", timeout_s)


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


def write_sparse_rd(
    root: str | os.PathLike,
    out_root: str | os.PathLike,
    *,
    tau: float | None = None,
    density: float | None = None,
    density_mode: str = "per-frame",
    window: tuple[int, int] = (9, 9),
    guard: tuple[int, int] = (3, 3),
    split: str = "all",
    batch_size: int = 8,
    calibration_frames: int | None = None,
    device: torch.device | str | None = None,
    resume: bool = True,
    progress: bool = True,
) -> SparseRDResult:
    """Write a RADIal-layout root whose RD cubes are masked to the detected set ``S(tau)``.

    ``R_sparse[r, d, c] = R[r, d, c]`` if ``(r, d) in S(tau)`` else 0 (all Rx channels kept).
    ``labels.csv`` (restricted to the split's frames), the freespace PNGs, ``calibration.npz`` /
    ``CalibrationTable.npy`` and ``sensor.json`` are hard-linked (or copied); each cube is
    written atomically and existing cubes are kept when ``resume`` (so a killed run resumes).
    ``sparse_rd.json`` records the source, the settings and the tau (a resumed run must match
    them), whether the run completed and the mean density of the frames it wrote.

    Parameters are those of :func:`convert_dataset`.

    Returns
    -------
    SparseRDResult
    """
    from radarpc.dsp.sparse_rd import sparse_rd, sparse_rd_mask

    settings = ConvertSettings(tau=tau, density=density, density_mode=density_mode,
                               window=tuple(int(v) for v in window), guard=tuple(int(v) for v in guard),
                               split=split, calibration_frames=calibration_frames)
    if int(batch_size) < 1:
        raise ValueError(f"batch_size must be >= 1, got {batch_size}")
    root, out_root = Path(root), Path(out_root)
    if root.resolve() == out_root.resolve():
        raise ValueError(f"the sparse-RD root must differ from the source root {root}")
    dev = _default_device(device, DistEnv())
    ds = RADIal(root, split=settings.split)
    _check_dsp_settings(settings, ds)
    info_path = out_root / "sparse_rd.json"
    key = {"source_root": str(root.resolve()), "settings": settings.to_dict()}
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
        cal_tau = prev["tau"] if prev is not None else calibrate_tau(
            root, settings, batch_size=int(batch_size), device=dev, progress=progress)
    spc = build_point_cloud(ds, settings, cal_tau, dev)

    out_root.mkdir(parents=True, exist_ok=True)
    info = dict(key, tau=cal_tau, mode=settings.mode, radarpc_version=__version__, complete=False)
    with atomic_write(info_path, "w") as f:
        json.dump(info, f, indent=1)
    for name in ("calibration.npz", "CalibrationTable.npy", "sensor.json"):
        if (root / name).is_file():
            _link_or_copy(root / name, out_root / name, overwrite=not resume)
    if not resume or not (out_root / "labels.csv").is_file():
        _write_split_labels(root / "labels.csv", out_root / "labels.csv", set(ds.frame_ids))

    todo = [p for p in range(len(ds)) if not (resume and fft_path(out_root, ds.frame_ids[p]).is_file())]
    it = _prefetched(ds, _batches(todo, int(batch_size)), dev)
    if progress:
        from tqdm import tqdm
        it = tqdm(it, total=-(-len(todo) // int(batch_size)), desc=f"sparse RD {root.name}", unit="batch")
    densities: list[torch.Tensor] = []
    with torch.no_grad():
        for pos, rd in it:                                                 # rd: (B, Nr, Nd, Nrx)
            _, cfar, mask = spc.detect(rd)
            mask_full = sparse_rd_mask(mask, ds.sensor, rd)                  # (B, Nr, Nd) bool
            sparse = sparse_rd(rd, mask_full)                              # (B, Nr, Nd, Nrx)
            densities.append(mask_full.float().mean(dim=(1, 2)).cpu())
            for b, p in enumerate(pos):
                num = ds.frame_ids[p]
                save_npy_atomic(fft_path(out_root, num), sparse[b].cpu().numpy().astype(np.complex64))
    for num in ds.frame_ids:
        fs = freespace_path(root, num)
        if fs.is_file():
            _link_or_copy(fs, freespace_path(out_root, num), overwrite=not resume)
    dens = torch.cat(densities) if densities else torch.zeros(0)
    info.update(complete=True, frames_written_last_run=len(todo),
                mean_density_last_run=float(dens.mean()) if dens.numel() else None)
    with atomic_write(info_path, "w") as f:
        json.dump(info, f, indent=1)
    return SparseRDResult(out_root, len(ds), len(todo), float(dens.mean()) if dens.numel() else float("nan"), cal_tau)
