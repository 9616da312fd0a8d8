"""Dataset conversion: a RADIal root -> a Parquet point store.

:func:`convert_dataset` runs :class:`~radarpc.dsp.pointcloud.SpectralPointCloud` over every
frame of a split and writes a :mod:`radarpc.data.pointstore` file. The source is a RADIal-layout
root or a dataset object (:mod:`radarpc.pipelines.sources`). The work is cut into chunks
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

The output is owned through :mod:`radarpc.runs`: rank 0 holds the lock on ``OUT`` for the whole
run, so a second conversion to the same ``OUT`` is refused instead of mixing its parts in; the
parts folder is a :class:`~radarpc.runs.RunFolder` keyed by the settings. The sparse-RD variant is
:mod:`radarpc.pipelines.sparse_rd`.
"""
from __future__ import annotations

import dataclasses
import datetime as _dt
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

import torch

from radarpc import __version__
from radarpc.config import from_dict, to_dict
from radarpc.data.pointstore import PointStore, PointStoreMetadata, PointStoreWriter
from radarpc.data.radial import RADIal
from radarpc.distributed import (DEFAULT_WAIT_S, DistEnv, WorkerJob, barrier, dist_env, parent_alive,
                                 rank_device, run_workers)
from radarpc.dsp.density import check_density
from radarpc.dsp.pointcloud import SpectralPointCloud, SpectralPointCloudConfig
from radarpc.io import DataFileError
from radarpc.runs import OutputLock, RunFolder, check_writable, is_temp_name, read_json
from radarpc.pipelines.sources import Source, batched, open_source, prefetched, source_fingerprint

__all__ = [
    "ConvertSettings",
    "ConvertResult",
    "DEFAULT_WAIT_S",
    "part_path",
    "parts_dir",
    "build_point_cloud",
    "calibrate_tau",
    "calibration_source_of",
    "check_dsp_settings",
    "convert_dataset",
]

_MANIFEST = "manifest.json"


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

    @classmethod
    def given(cls, settings: "ConvertSettings | None", fields: dict) -> "ConvertSettings":
        """``settings``, or one built from ``fields`` (a writer's ``**fields``); not both."""
        if settings is None:
            return cls(**fields)
        if fields:
            raise TypeError(f"give settings or its fields, not both (got {sorted(fields)})")
        return settings

    @property
    def mode(self) -> str:
        """``"fixed-tau"``, ``"per-frame"`` or ``"per-dataset"`` (:data:`radarpc.data.pointstore.THRESHOLD_MODES`)."""
        return "fixed-tau" if self.tau is not None else self.density_mode

    def to_dict(self) -> dict:
        """Plain JSON-able dict (lists for tuples); :meth:`from_dict` inverts it."""
        return to_dict(self)

    @classmethod
    def from_dict(cls, d: dict, where: str = "conversion settings") -> "ConvertSettings":
        return from_dict(cls, d, where=where)

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
    chunks_converted: int            # chunks computed in this call (on rank 0: by every rank)
    chunks_skipped: int              # chunks found complete from an earlier run (on rank 0: of every rank)
    chunk_frames: int = 0            # frames per chunk actually used (shrunk for many processes; from the manifest on resume)
    frames_reused: int = 0           # frames taken from an earlier run (finished parts, or the whole finished store)
    already_finished: bool = False   # ``out`` already held this conversion: nothing was computed


def parts_dir(out: str | os.PathLike) -> Path:
    """``OUT.parts``: the folder of finished chunks of a conversion to ``OUT``."""
    out = Path(out)
    return out.with_name(out.name + ".parts")


def part_path(out: str | os.PathLike, k: int) -> Path:
    """``OUT.parts/part-{k:05d}.parquet``."""
    return parts_dir(out) / f"part-{int(k):05d}.parquet"


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


def check_dsp_settings(settings: ConvertSettings, ds: Any, source_id: str) -> None:
    """Fail before any file is written: a reachable density, a non-empty split."""
    if settings.density is not None:
        check_density(settings.density, ds.sensor)
    if len(ds) == 0:
        raise ValueError(f"{source_id}: the {settings.split!r} split has no frames")


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
    batches = batched(list(range(n)), batch_size)
    it = (rd for _, rd in prefetched(train, batches, dev))
    if progress:
        from tqdm import tqdm
        it = tqdm(it, total=len(batches), desc="calibrate tau (train)", unit="batch")
    return spc.calibrate_tau(it, density=settings.density)


def calibration_source_of(source: Source, ds: Any, calibration_source: Source | None) -> tuple[Source, str]:
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


# ---- chunk conversion (runs in the main process, in spawned workers, or on a torchrun rank) -----
@dataclass(frozen=True)
class _ChunkJob:
    dataset: Any                     # the source dataset (pickled to spawned workers)
    out: str
    settings: ConvertSettings
    tau: float | None
    meta: dict                       # PointStoreMetadata.to_dict() of the parts
    chunk_frames: int                # frames per chunk (from the manifest)
    batch_size: int
    device: str


def _chunk_positions(n_frames: int, chunk_frames: int, k: int) -> list[int]:
    return list(range(k * chunk_frames, min(n_frames, (k + 1) * chunk_frames)))


def _run_chunks(worker: WorkerJob, chunks: Sequence[int], on_done: Callable[[int, int], None]) -> None:
    """Convert the ``chunks`` of ``worker.payload`` whose part file is missing; ``on_done(k, n_frames)``
    after each. Runs in this process or in a spawned worker (:func:`radarpc.distributed.run_workers`)."""
    job: _ChunkJob = worker.payload
    ds = job.dataset
    dev = torch.device(job.device)
    spc = build_point_cloud(ds, job.settings, job.tau, dev)
    meta = PointStoreMetadata.from_dict(job.meta)
    for k in chunks:
        path = part_path(job.out, k)
        pos = _chunk_positions(len(ds), job.chunk_frames, k)
        if path.is_file():
            continue
        with PointStoreWriter(path, meta, row_group_frames=max(len(pos), 1)) as w, torch.no_grad():
            for b, rd in prefetched(ds, batched(pos, job.batch_size), dev):
                if not parent_alive(worker):
                    # orphaned (the parent was killed): stop; the unfinished part is dropped and a
                    # re-run converts it
                    raise SystemExit(f"conversion worker {os.getpid()}: parent {worker.parent_pid} is gone, stopping")
                clouds = spc(rd)
                w.write(clouds, [ds.frame_ids[p] for p in b], [ds.sequences[p] for p in b])
        on_done(k, len(pos))


# ---- the driver ---------------------------------------------------------------------------------
def convert_dataset(
    source: Source,
    out: str | os.PathLike,
    settings: ConvertSettings | None = None,
    *,
    batch_size: int = 8,
    calibration_source: Source | None = None,
    workers: int = 1,
    device: torch.device | str | None = None,
    resume: bool = True,
    overwrite: bool = False,
    progress: bool = True,
    wait_timeout_s: float = DEFAULT_WAIT_S,
    on_chunk_done: Callable[[int], None] | None = None,
    **fields: Any,
) -> ConvertResult:
    """Convert the frames of a RADIal root (or dataset object) into a Parquet point store.

    What is computed is one :class:`ConvertSettings`, passed whole (``settings``) or as its fields
    (``tau=``, ``density=``, ``enrich=``, ...; not both); the other parameters only say how the
    work runs and never change the output.

    Parameters
    ----------
    source : path-like or dataset
        RADIal-layout root (real or simulated), or a dataset object (:class:`RadarDataset`, e.g.
        :class:`~radarpc.sim.radial_writer.SimulatedRADIal`): its frames are converted as given.
    out : path-like
        The ``.parquet`` store to write (atomically, at the very end).
    settings : ConvertSettings, optional
        Threshold or density, enrichments, CFAR geometry, envelope, beamforming, split, chunking
        (see :class:`ConvertSettings`); ``**fields`` builds it when not given.
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
        ``out`` already holds this conversion). False starts over. Parts of an interrupted run
        with other settings or other source files are always discarded (the parts folder is this
        job's scratch space; fixing the input is enough to rerun).
    overwrite : bool
        Replace an existing ``out`` that is not this conversion (a store made with other
        settings or from another source, or another file). Without it such a file is refused,
        never silently replaced. A store of the same conversion whose source files have changed
        since is converted again without it.
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
    settings = ConvertSettings.given(settings, fields)
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
    dev = rank_device(device, env)
    ds, source_id, split_used = open_source(source, settings.split)
    settings = dataclasses.replace(settings, split=split_used)
    check_dsp_settings(settings, ds, source_id)
    cal_src, cal_id = (None, None)
    if settings.mode == "per-dataset":
        cal_src, cal_id = calibration_source_of(source, ds, calibration_source)
    n = len(ds)
    key = _manifest_key(source_id, settings, ds.frame_ids, cal_id, source_fingerprint(ds))
    # Rank 0 owns the output for the whole run: a second conversion to the same store is refused
    # rather than mixing its parts in. Other ranks write their own parts under rank 0's manifest.
    lock = OutputLock(out, "point store")
    if env.rank == 0:
        check_writable(out, "point store")
        lock.acquire()
    try:
        return _convert_locked(ds, source_id, out, settings, key, cal_src, env, dev, n, lock,
                               batch_size=int(batch_size), workers=int(workers), resume=resume, overwrite=overwrite,
                               progress=progress, wait_timeout_s=wait_timeout_s, on_chunk_done=on_chunk_done)
    finally:
        lock.release()


def _convert_locked(ds: Any, source_id: str, out: Path, settings: ConvertSettings, key: dict, cal_src: Any,
                    env: DistEnv, dev: torch.device, n: int, lock: OutputLock, *, batch_size: int, workers: int,
                    resume: bool, overwrite: bool, progress: bool, wait_timeout_s: float,
                    on_chunk_done: Callable[[int], None] | None) -> ConvertResult:
    pdir = parts_dir(out)
    # Every rank makes the same decision about an existing store (rank 0 under the lock), so that
    # no rank waits for a job that rank 0 has finished or refused.
    if out.exists():
        try:
            store = PointStore(out)
        except DataFileError as e:
            if not overwrite:
                raise DataFileError(out, f"{e.problem}; it is in the way of this conversion: remove it, or pass "
                                         f"overwrite=True (CLI: --overwrite) to replace it") from e
            store = None
        if store is not None:
            m = store.metadata
            same = m.settings.get("key") == key
            if same and resume and not pdir.exists():
                # A finished conversion with these settings: nothing to do.
                chunk = int(m.settings.get("chunk_frames") or settings.chunk_frames)
                if env.rank != 0:
                    return ConvertResult(None, n, 0, float("nan"), float("nan"), m.tau, 0, 0, chunk,
                                         already_finished=True)
                return ConvertResult(out, n, int(store.frame_table.n_points.sum()), m.achieved_density,
                                     m.peak_density, m.tau, 0, -(-n // chunk), chunk, frames_reused=n,
                                     already_finished=True)
            old = m.settings.get("key") or {}
            # Another request (other settings or another source) is refused; the same request on
            # changed source files (a re-simulated root, edited labels) is converted again.
            other = [k for k in ("source", "settings") if old.get(k) != key[k]]
            if other and not overwrite:
                raise FileExistsError(f"{out} holds a point store made with other {' and '.join(other)}; pass "
                                      f"overwrite=True (CLI: --overwrite) to replace it, or choose another --out")

    # The manifest fixes the settings, the frames, the chunk size, the calibrated tau and the date.
    job_id = os.environ.get("TORCHELASTIC_RUN_ID") if env.world_size > 1 else None
    parts = RunFolder(pdir, {_MANIFEST: {"key": key}}, what="conversion parts folder", indent=None, lock=lock)
    if env.rank == 0:
        # a merge killed half-way leaves its temp file beside the store: ours, since we hold the lock
        for tmp in out.parent.glob(f".{out.name}.*.tmp"):
            if is_temp_name(tmp.name) and "." not in tmp.name[len(out.name) + 2:-4]:   # not another output's
                tmp.unlink(missing_ok=True)
        # Parts of another run (other settings, changed source files, or resume=False) are stale:
        # the folder is this output's scratch space and we hold its lock, so they go.
        if not resume or (pdir.exists() and parts.differences()):
            _remove_parts_dir(pdir)
        parts.start(write_manifests=False)
        manifest = read_json(pdir / _MANIFEST) if parts.resumed else None
        if manifest is None:
            chunk = settings.chunk_frames
            procs = workers * env.world_size
            if procs > 1 and -(-n // chunk) < procs:          # share the work: at least one chunk each
                chunk = max(1, -(-n // procs))
            cal_tau = settings.tau
            if settings.mode == "per-dataset":
                cal_tau = calibrate_tau(cal_src, settings, batch_size=batch_size, device=dev, progress=progress)
            meta = PointStoreMetadata(
                sensor=ds.sensor, density_mode=settings.mode, tau=cal_tau, target_density=settings.density,
                achieved_density=0.0, peak_density=0.0, enrich=settings.enrich, window=settings.window,
                guard=settings.guard, source_root=source_id, split=settings.split, radarpc_version=__version__,
                created=_dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
                envelope=settings.envelope,
                settings=dict(dataclasses.replace(settings, chunk_frames=chunk).to_dict(), key=key))
            manifest = dict(key=key, tau=cal_tau, meta=meta.to_dict(), chunk_frames=chunk)
        # The job's id (torchrun's, the same on every rank) tells the other ranks, when they poll
        # without a process group, that this manifest is this job's and not a stale one.
        manifest["job"] = job_id
        parts.write_manifest(_MANIFEST, manifest)

    def current(path: Path) -> bool:
        m = read_json(path)
        return isinstance(m, dict) and (job_id is None or m.get("job") == job_id)

    barrier(env, [pdir / _MANIFEST], ["rank 0 (manifest)"], wait_timeout_s, ready=current)
    if env.rank != 0:
        manifest = read_json(pdir / _MANIFEST)
        if not isinstance(manifest, dict) or manifest.get("key") != key:
            raise ValueError(f"rank {env.rank}: {pdir / _MANIFEST} does not match this rank's settings")
    chunk = int(manifest["chunk_frames"])
    n_chunks = -(-n // chunk)
    # Rank 0 sees which parts existed before any rank starts (the barrier above): the job's totals.
    existed = [k for k in range(n_chunks) if part_path(out, k).is_file()] if env.rank == 0 else []

    mine = tuple(k for k in range(n_chunks) if k % env.world_size == env.rank)
    todo = tuple(k for k in mine if not part_path(out, k).is_file())
    skipped = len(mine) - len(todo)
    job = WorkerJob(run=_run_chunks, payload=_ChunkJob(
        dataset=ds, out=str(out), settings=settings, tau=manifest["tau"], meta=manifest["meta"],
        chunk_frames=chunk, batch_size=batch_size, device=str(dev)), items=todo)
    bar = None
    if progress:
        from tqdm import tqdm
        done_frames = sum(len(_chunk_positions(n, chunk, k)) for k in mine if k not in todo)
        bar = tqdm(total=sum(len(_chunk_positions(n, chunk, k)) for k in mine),
                   initial=done_frames, desc=f"pointcloud {Path(source_id).name or source_id}", unit="frame")
    converted = 0

    def on_done(k: int, n_frames: int) -> None:
        nonlocal converted
        converted += 1
        if bar is not None:
            bar.update(n_frames)
        if on_chunk_done is not None:
            on_chunk_done(k)

    try:
        if todo:
            if workers > 1 and len(todo) > 1:
                run_workers(job, min(workers, len(todo)), on_done, what="conversion worker")
            else:
                _run_chunks(job, todo, on_done)
    finally:
        if bar is not None:
            bar.close()

    # Every part exists -> rank 0 merges.
    all_parts = [part_path(out, k) for k in range(n_chunks)]
    if env.rank != 0:
        barrier(env, [], [], wait_timeout_s)
        return ConvertResult(None, n, 0, float("nan"), float("nan"), manifest["tau"], converted, skipped, chunk)
    barrier(env, all_parts, [f"rank {k % env.world_size}, chunk {k}" for k in range(n_chunks)], wait_timeout_s)
    meta = PointStoreMetadata.from_dict(manifest["meta"])
    with PointStoreWriter(out, meta, row_group_frames=chunk) as w:
        for p in all_parts:
            w.append_store(PointStore(p))
    _remove_parts_dir(pdir)
    store = PointStore(out)
    reused = sum(len(_chunk_positions(n, chunk, k)) for k in existed)
    return ConvertResult(out, n, int(store.frame_table.n_points.sum()), store.metadata.achieved_density,
                         store.metadata.peak_density, manifest["tau"], n_chunks - len(existed), len(existed), chunk,
                         frames_reused=reused)


def _remove_parts_dir(d: Path) -> None:
    """Remove a parts folder holding only files a conversion writes (refuse anything else)."""
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


