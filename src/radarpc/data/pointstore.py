"""Parquet store of spectral point clouds: one row per point, one file per dataset conversion.

A store holds the point clouds of a list of RADIal frames, written by :class:`PointStoreWriter`
(usually through :func:`radarpc.pipelines.pointclouds.convert_dataset`) and read back by
:class:`PointStore` as per-frame :class:`~radarpc.points.PointCloudBatch` tensors.

File layout (pyarrow Parquet)::

    columns, one row per point, rows ordered by frame (frames in the order they were written):
      frame          int64     RADIal numSample of the frame the point belongs to
      sequence       dictionary<int32, string>   sequence name (labels.csv ``dataset`` column)
      range_m, azimuth_deg, elevation_deg        float32   polar position (m, deg; left positive)
      doppler_bin    int32     consolidated Doppler index (0 .. slot_width - 1)
      velocity_mps, amplitude, snr               float32   radial velocity, Ae = |s_j[k_j]|, linear SNR
      x, y, z        float32   Cartesian position (x forward, y left, z up, metres)
      range_bin      int32     range bin
      doppler_full   int32     resolved full-axis Doppler bin
      is_neighbour   bool      point added by the RD-neighbourhood enrichment (not a CFAR peak)
      sector         fixed_size_list<float32>[n_az * n_el]   angle-sector descriptor (optional)
      rd_patch       fixed_size_list<float32>[n * n]         RD-envelope neighbourhood (optional)
    key-value metadata "radarpc.pointstore": JSON with
      "metadata": PointStoreMetadata (sensor config dict, tau / target density, density mode,
                  achieved mean density, enrichments, CFAR window/guard, source, version, date)
      "frames":   the per-frame table (frame, sequence, n_points, n_peaks, tau, density), *including frames
                  without any point*, so that the reader yields an empty cloud for them.

Row groups hold whole frames (a frame never straddles two row groups); the reader locates a
frame's row group and row offset from the per-frame point counts and reads only that row group.

Examples
--------
>>> store = PointStore("data/sim_radial_pc057.parquet")        # doctest: +SKIP
>>> store.metadata.achieved_density, len(store)               # doctest: +SKIP
>>> cloud = store[0]             # PointCloudBatch of one frame # doctest: +SKIP
"""
from __future__ import annotations

import contextlib
import dataclasses
import datetime as _dt
import json
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, Sequence

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import torch

from radarpc import __version__
from radarpc.dsp.ddma import check_envelope_kind
from radarpc.dsp.density import DENSITY_MODES, check_density_value
from radarpc.io import DataFileError, temp_file_beside
from radarpc.points import (BOOL_FIELDS, FLOAT_FIELDS, INT_FIELDS, LIST_FIELDS, POINT_FIELDS, PointCloudBatch,
                             collate_clouds)
from radarpc.sensors.radial import DDMARadarConfig

__all__ = [
    "METADATA_KEY",
    "FORMAT_VERSION",
    "FLOAT_COLUMNS",
    "INT_COLUMNS",
    "BOOL_COLUMNS",
    "LIST_COLUMNS",
    "REQUIRED_COLUMNS",
    "THRESHOLD_MODES",
    "PointStoreMetadata",
    "FrameTable",
    "PointStoreWriter",
    "PointStore",
    "point_schema",
    "collate_clouds",
]

METADATA_KEY = b"radarpc.pointstore"
"""Parquet key-value metadata key holding the store's JSON description."""
FORMAT_VERSION = 1

FLOAT_COLUMNS: tuple[str, ...] = FLOAT_FIELDS
"""Per-point float32 columns."""
INT_COLUMNS: tuple[str, ...] = INT_FIELDS
"""Per-point integer columns (int32 on disk, int64 tensors in memory)."""
BOOL_COLUMNS: tuple[str, ...] = BOOL_FIELDS
LIST_COLUMNS: tuple[str, ...] = LIST_FIELDS
"""Optional enrichment columns, fixed-size lists of float32 (present when enabled)."""
_ORDER: tuple[str, ...] = (
    "frame", "sequence", "range_m", "azimuth_deg", "elevation_deg", "doppler_bin", "velocity_mps",
    "amplitude", "snr", "x", "y", "z", "range_bin", "doppler_full", "is_neighbour")
REQUIRED_COLUMNS: tuple[str, ...] = _ORDER
"""Columns every store has, in file order (the enrichment columns follow when present)."""
THRESHOLD_MODES: tuple[str, ...] = ("fixed-tau",) + DENSITY_MODES
"""How the CFAR threshold was chosen: one given tau, or from a density target
(:data:`radarpc.dsp.density.DENSITY_MODES`): a tau per frame hitting the target density, or one
tau calibrated on the training split to hit the target mean density."""


def point_schema(sector_size: int | None = None, rd_patch_size: int | None = None) -> pa.Schema:
    """The Arrow schema of a store, with the enrichment columns of the given sizes (None = absent)."""
    fields = [pa.field("frame", pa.int64(), nullable=False),
              pa.field("sequence", pa.dictionary(pa.int32(), pa.string()), nullable=False)]
    for name in _ORDER[2:]:
        if name in FLOAT_COLUMNS:
            t = pa.float32()
        elif name in INT_COLUMNS:
            t = pa.int32()
        else:
            t = pa.bool_()
        fields.append(pa.field(name, t, nullable=False))
    for name, n in (("sector", sector_size), ("rd_patch", rd_patch_size)):
        if n is not None:
            if int(n) < 1:
                raise ValueError(f"{name} size must be >= 1, got {n}")
            fields.append(pa.field(name, pa.list_(pa.float32(), int(n)), nullable=False))
    return pa.schema(fields)


# ---- metadata -----------------------------------------------------------------------------------
@dataclass(frozen=True)
class PointStoreMetadata:
    """What a store was made from and how; stored as JSON in the Parquet footer.

    Exactly one of ``tau`` (fixed or calibrated threshold) and ``target_density`` describes the
    request: ``density_mode == "fixed-tau"`` has ``tau`` only, ``"per-frame"`` has
    ``target_density`` only (the per-frame thresholds are in :class:`FrameTable`), and
    ``"per-dataset"`` has both (the target and the tau calibrated on the training split).
    """

    sensor: DDMARadarConfig                  # radar that produced the RD cubes
    density_mode: str                        # one of THRESHOLD_MODES
    tau: float | None                        # linear SNR threshold (fixed, or calibrated per-dataset)
    target_density: float | None             # requested density of the encoded set, in (0, 1]:
                                             #   |S*(tau)| / (Nr * ND) with rdN, else |S(tau)| / (Nr * ND)
    achieved_density: float                  # mean over frames of the encoded set's density (S*, or S)
    peak_density: float                      # mean over frames of |S(tau)| / (Nr * ND), CFAR peaks only
    enrich: tuple[str, ...]                  # enrichment names, e.g. ("rd3", "sector32")
    window: tuple[int, int]                  # CFAR window (range, Doppler), cells
    guard: tuple[int, int]                   # CFAR guard (range, Doppler), cells
    source_root: str                         # dataset root the cubes were read from
    split: str                               # split converted ("train", "val", "test", "all")
    radarpc_version: str = __version__       # package version that wrote the store
    created: str = ""                        # ISO-8601 UTC creation time
    envelope: str = "replicas"               # RD envelope: "replicas" (seed eq. 1) or "all-slots" (RADIal rpl.py)
    settings: dict = dataclasses.field(default_factory=dict)
    # ^ every setting that shapes the output, as resolved by the writer (``ConvertSettings.to_dict()``
    #   for :func:`radarpc.pipelines.pointclouds.convert_dataset`: threshold/density, mode, enrichments,
    #   CFAR geometry, envelope, split, calibration frames and source); compared on resume

    def __post_init__(self) -> None:
        check_envelope_kind(self.envelope)
        if not isinstance(self.settings, dict):
            raise ValueError(f"settings must be a dict of conversion settings, got {type(self.settings).__name__}")
        if self.density_mode not in THRESHOLD_MODES:
            raise ValueError(f"density_mode must be one of {THRESHOLD_MODES}, got {self.density_mode!r}")
        if self.density_mode in ("fixed-tau", "per-dataset") and self.tau is None:
            raise ValueError(f"density_mode {self.density_mode!r} needs tau")
        if self.density_mode in ("per-frame", "per-dataset") and self.target_density is None:
            raise ValueError(f"density_mode {self.density_mode!r} needs target_density")
        if self.tau is not None and not math.isfinite(self.tau):
            raise ValueError(f"tau must be a finite linear SNR threshold, got {self.tau}")
        if self.target_density is not None:
            try:
                check_density_value(self.target_density)
            except ValueError as e:
                raise ValueError(f"target_{e}") from None

    def to_dict(self) -> dict:
        """JSON-able dict; :meth:`from_dict` inverts it."""
        d = dataclasses.asdict(self)
        d["sensor"] = self.sensor.to_dict()
        d["enrich"] = list(self.enrich)
        d["window"] = list(self.window)
        d["guard"] = list(self.guard)
        d["settings"] = json.loads(json.dumps(self.settings))   # plain JSON types (tuples -> lists)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "PointStoreMetadata":
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = set(d) - names
        missing = {f.name for f in dataclasses.fields(cls)
                   if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING} - set(d)
        if unknown or missing:
            raise ValueError(f"point store metadata: unknown keys {sorted(unknown)}, missing keys {sorted(missing)}")
        kw = dict(d)
        # stores written before the envelope option existed summed every slot (RADIal rpl.py)
        kw.setdefault("envelope", "all-slots")
        kw["sensor"] = DDMARadarConfig.from_dict(d["sensor"])
        kw["enrich"] = tuple(str(e) for e in d["enrich"])
        kw["window"] = tuple(int(v) for v in d["window"])
        kw["guard"] = tuple(int(v) for v in d["guard"])
        for k in ("tau", "target_density"):
            kw[k] = None if d[k] is None else float(d[k])
        kw["achieved_density"] = float(d["achieved_density"])
        kw["peak_density"] = float(d["peak_density"])
        return cls(**kw)


@dataclass(frozen=True)
class FrameTable:
    """Per-frame record of a store, every frame included (also those without points).

    Attributes
    ----------
    frame : ndarray int64 ``(F,)``      RADIal numSample, in file order
    sequence : tuple of str ``(F,)``    sequence name
    n_points : ndarray int64 ``(F,)``   rows of the frame
    n_peaks : ndarray int64 ``(F,)``    rows that are CFAR peaks (``is_neighbour`` False): ``|P(tau)|``
    tau : ndarray float64 ``(F,)``      CFAR threshold used for the frame
    density : ndarray float64 ``(F,)``  achieved density of the frame's encoded set
                                        (``|S*(tau)| / (Nr Nd)`` with RD-neighbourhood points, else
                                        ``|S(tau)| / (Nr Nd)``); ``|S(tau)|`` is ``n_tx * n_peaks``
    """

    frame: np.ndarray
    sequence: tuple[str, ...]
    n_points: np.ndarray
    n_peaks: np.ndarray
    tau: np.ndarray
    density: np.ndarray

    def __post_init__(self) -> None:
        n = self.frame.shape[0]
        for name in ("n_points", "n_peaks", "tau", "density"):
            if getattr(self, name).shape != (n,):
                raise ValueError(f"frame table: {name} has shape {getattr(self, name).shape}, expected ({n},)")
        if len(self.sequence) != n:
            raise ValueError(f"frame table: {len(self.sequence)} sequence names for {n} frames")
        if n and (int(self.n_peaks.min()) < 0 or bool((self.n_peaks > self.n_points).any())):
            raise ValueError("frame table: point counts must satisfy 0 <= n_peaks <= n_points")

    def __len__(self) -> int:
        return int(self.frame.shape[0])

    @property
    def row_start(self) -> np.ndarray:
        """``(F,)`` int64: first row of each frame in the file."""
        return (np.cumsum(self.n_points) - self.n_points).astype(np.int64)

    @classmethod
    def empty(cls) -> "FrameTable":
        z = np.zeros(0)
        return cls(frame=z.astype(np.int64), sequence=(), n_points=z.astype(np.int64),
                   n_peaks=z.astype(np.int64), tau=z, density=z)

    @classmethod
    def concat(cls, tables: Sequence["FrameTable"]) -> "FrameTable":
        if not tables:
            return cls.empty()
        return cls(frame=np.concatenate([t.frame for t in tables]).astype(np.int64),
                   sequence=tuple(s for t in tables for s in t.sequence),
                   n_points=np.concatenate([t.n_points for t in tables]).astype(np.int64),
                   n_peaks=np.concatenate([t.n_peaks for t in tables]).astype(np.int64),
                   tau=np.concatenate([t.tau for t in tables]).astype(np.float64),
                   density=np.concatenate([t.density for t in tables]).astype(np.float64))

    def to_dict(self) -> dict:
        names = sorted(set(self.sequence))
        index = {s: i for i, s in enumerate(names)}
        return {"frame": self.frame.tolist(), "sequence_names": names,
                "sequence": [index[s] for s in self.sequence], "n_points": self.n_points.tolist(),
                "n_peaks": self.n_peaks.tolist(), "tau": self.tau.tolist(), "density": self.density.tolist()}

    @classmethod
    def from_dict(cls, d: dict) -> "FrameTable":
        names = [str(s) for s in d["sequence_names"]]
        return cls(frame=np.asarray(d["frame"], dtype=np.int64).reshape(-1),
                   sequence=tuple(names[int(i)] for i in d["sequence"]),
                   n_points=np.asarray(d["n_points"], dtype=np.int64).reshape(-1),
                   n_peaks=np.asarray(d["n_peaks"], dtype=np.int64).reshape(-1),
                   tau=np.asarray(d["tau"], dtype=np.float64).reshape(-1),
                   density=np.asarray(d["density"], dtype=np.float64).reshape(-1))


def _encode_footer(meta: PointStoreMetadata, frames: FrameTable) -> dict[bytes, bytes]:
    doc = {"format_version": FORMAT_VERSION, "metadata": meta.to_dict(), "frames": frames.to_dict()}
    return {METADATA_KEY: json.dumps(doc, separators=(",", ":")).encode("utf-8")}


# ---- batch <-> Arrow ------------------------------------------------------------------------------
def _list_size(t: torch.Tensor | None, name: str, n_points: int) -> int | None:
    if t is None:
        return None
    if t.ndim != 2 or t.shape[0] != n_points:
        raise ValueError(f"{name} must be (N={n_points}, n), got {tuple(t.shape)}")
    return int(t.shape[1])


def _batch_to_table(clouds: PointCloudBatch, frames: Sequence[int], sequences: Sequence[str],
                    schema: pa.Schema) -> tuple[pa.Table, np.ndarray]:
    """Arrow table of every point of ``clouds`` and the ``(B,)`` point count per frame."""
    offset = clouds.offset.detach().to("cpu", torch.int64).numpy()                 # (B,)
    counts = np.diff(np.concatenate([[0], offset]))                                # (B,)
    if offset.ndim != 1 or (counts < 0).any():
        raise ValueError(f"clouds.offset must be a non-decreasing (B,) vector of cumulative point counts, "
                         f"got {offset.tolist()}")
    n = int(offset[-1]) if offset.size else 0
    cols: dict[str, pa.Array] = {}
    cols["frame"] = pa.array(np.repeat(np.asarray(frames, dtype=np.int64), counts), pa.int64())
    seq_codes = np.repeat(np.arange(len(sequences), dtype=np.int32), counts)
    cols["sequence"] = pa.DictionaryArray.from_arrays(pa.array(seq_codes, pa.int32()),
                                                      pa.array(list(sequences), pa.string()))
    for name in POINT_FIELDS:
        t = getattr(clouds, name)
        if t is None or t.ndim != 1 or t.shape[0] != n:
            raise ValueError(f"point field {name!r} must be a ({n},) tensor, got "
                             f"{None if t is None else tuple(t.shape)}")
        a = t.detach().to("cpu").numpy()
        if name in FLOAT_COLUMNS:
            if not np.isfinite(a).all():
                raise ValueError(f"point field {name!r} holds NaN or infinite values")
            cols[name] = pa.array(a.astype(np.float32, copy=False), pa.float32())
        elif name in INT_COLUMNS:
            cols[name] = pa.array(a.astype(np.int32), pa.int32())
        else:
            cols[name] = pa.array(a.astype(np.bool_, copy=False), pa.bool_())
    for name in LIST_COLUMNS:
        if name not in schema.names:
            continue
        t = getattr(clouds, name, None)
        size = schema.field(name).type.list_size
        if t is None or t.ndim != 2 or t.shape != (n, size):
            raise ValueError(f"{name} must be ({n}, {size}) as in the store's schema, got "
                             f"{None if t is None else tuple(t.shape)}")
        flat = t.detach().to("cpu", torch.float32).reshape(-1).numpy()
        if not np.isfinite(flat).all():
            raise ValueError(f"point field {name!r} holds NaN or infinite values")
        cols[name] = pa.FixedSizeListArray.from_arrays(pa.array(flat, pa.float32()), size)
    return pa.table([cols[f.name] for f in schema], schema=schema), counts.astype(np.int64)


# ---- writer -----------------------------------------------------------------------------------
class PointStoreWriter:
    """Write point clouds to a Parquet store, atomically (temp file renamed onto ``path`` at close).

    Parameters
    ----------
    path : path-like
        Final ``.parquet`` file. Nothing appears under this name before :meth:`close` succeeds.
    metadata : PointStoreMetadata
        Description of the conversion. ``achieved_density`` and ``peak_density`` are recomputed
        at close from the frames written; ``created`` is set to now (UTC) when empty.
    row_group_frames : int
        Frames buffered before a row group is written (row groups hold whole frames).
    compression : str
        Parquet codec.

    Examples
    --------
    >>> with PointStoreWriter("pc.parquet", meta) as w:           # doctest: +SKIP
    ...     w.write(spc(rd_batch), frames=[0, 1], sequences=["A", "A"])
    """

    def __init__(self, path: str | os.PathLike, metadata: PointStoreMetadata, *,
                 row_group_frames: int = 64, compression: str = "zstd") -> None:
        if int(row_group_frames) < 1:
            raise ValueError(f"row_group_frames must be >= 1, got {row_group_frames}")
        self.path = Path(path)
        self.metadata = metadata
        self.row_group_frames = int(row_group_frames)
        self.compression = compression
        self._schema: pa.Schema | None = None
        self._writer: pq.ParquetWriter | None = None
        self._tmp: Path | None = None
        self._pending: list[pa.Table] = []
        self._pending_frames = 0
        self._frames: list[FrameTable] = []
        self._seen: set[int] = set()
        self._closed = False

    # -- context manager: close on success, abort (remove the temp file) on error
    def __enter__(self) -> "PointStoreWriter":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()

    def _open(self, schema: pa.Schema) -> None:
        self._tmp = temp_file_beside(self.path)
        self._schema = schema
        self._writer = pq.ParquetWriter(str(self._tmp), schema, compression=self.compression)

    def _check_open(self) -> None:
        if self._closed:
            raise ValueError(f"point store writer for {self.path} is already closed")

    def write(self, clouds: PointCloudBatch, frames: Sequence[int], sequences: Sequence[str]) -> None:
        """Append the ``B`` frames of ``clouds``.

        Parameters
        ----------
        clouds : PointCloudBatch
            ``B`` frames (``offset`` ``(B,)``), on any device; per-frame ``tau`` and ``density``.
        frames : sequence of int, ``(B,)``
            RADIal numSample of each frame; each frame may be written once.
        sequences : sequence of str, ``(B,)``
            Sequence name of each frame.
        """
        self._check_open()
        b = int(clouds.offset.shape[0])
        if len(frames) != b or len(sequences) != b:
            raise ValueError(f"{b} frames in the batch but {len(frames)} frame ids and "
                             f"{len(sequences)} sequence names")
        dup = self._seen.intersection(int(f) for f in frames)
        if dup or len(set(int(f) for f in frames)) != b:
            raise ValueError(f"frames written twice to {self.path}: {sorted(dup) or list(frames)}")
        if self._schema is None:
            n = int(clouds.offset[-1]) if b else 0
            self._open(point_schema(_list_size(getattr(clouds, "sector", None), "sector", n),
                                    _list_size(getattr(clouds, "rd_patch", None), "rd_patch", n)))
        assert self._schema is not None
        table, counts = _batch_to_table(clouds, frames, sequences, self._schema)
        peak = ~clouds.is_neighbour.detach().to("cpu").numpy().astype(np.bool_)            # (N,)
        frame_of = np.repeat(np.arange(b), counts)                                          # (N,)
        n_peaks = np.bincount(frame_of[peak], minlength=b).astype(np.int64)                 # (B,)
        tau = clouds.tau.detach().to("cpu", torch.float64).numpy().reshape(-1)
        dens = clouds.density.detach().to("cpu", torch.float64).numpy().reshape(-1)
        if tau.shape != (b,) or dens.shape != (b,):
            raise ValueError(f"clouds.tau and clouds.density must be ({b},), got {tau.shape} and {dens.shape}")
        self._append(table, FrameTable(frame=np.asarray(frames, dtype=np.int64), sequence=tuple(map(str, sequences)),
                                       n_points=counts, n_peaks=n_peaks, tau=tau, density=dens))

    def _append(self, table: pa.Table, frames: FrameTable) -> None:
        self._seen.update(frames.frame.tolist())
        self._frames.append(frames)
        # Cut the rows at frame boundaries into row groups of row_group_frames frames.
        i, row = 0, 0
        while i < len(frames):
            take = min(self.row_group_frames - self._pending_frames, len(frames) - i)
            rows = int(frames.n_points[i:i + take].sum())
            if rows:
                self._pending.append(table.slice(row, rows))
            i, row = i + take, row + rows
            self._pending_frames += take
            if self._pending_frames >= self.row_group_frames:
                self.flush()

    def append_store(self, store: "PointStore") -> None:
        """Append every frame of another store row group by row group (merging shards)."""
        self._check_open()
        if self._schema is None:
            self._open(store.schema)
        if not store.schema.equals(self._schema):
            raise ValueError(f"{store.path}: schema differs from the store being written\n"
                             f"{store.schema}\nvs\n{self._schema}")
        dup = self._seen.intersection(store.frame_table.frame.tolist())
        if dup:
            raise ValueError(f"{store.path}: frames already written to {self.path}: {sorted(dup)[:10]}")
        self.flush()
        self._frames.append(store.frame_table)
        self._seen.update(store.frame_table.frame.tolist())
        for rg in range(store.num_row_groups):
            self._write_rows(store.read_row_group(rg))

    def _write_rows(self, table: pa.Table) -> None:
        assert self._writer is not None and self._schema is not None
        if table.num_rows:
            self._writer.write_table(table.cast(self._schema), row_group_size=table.num_rows)

    def flush(self) -> None:
        """Write the buffered frames as one row group."""
        if self._pending:
            self._write_rows(pa.concat_tables(self._pending).combine_chunks())
        self._pending = []
        self._pending_frames = 0

    def close(self) -> Path:
        """Flush, write the footer metadata and rename the temp file onto :attr:`path`.

        Returns
        -------
        Path
            The final file.
        """
        self._check_open()
        try:
            if self._schema is None:  # nothing written: a valid store without frames
                self._open(point_schema())
            self.flush()
            frames = FrameTable.concat(self._frames)
            achieved = float(frames.density.mean()) if len(frames) else 0.0
            sensor = self.metadata.sensor
            # |S(tau)| = n_tx |P(tau)| (each consolidated peak maps to its n_tx replica bins)
            peak = float(frames.n_peaks.mean()) * sensor.n_tx / (sensor.n_range * sensor.n_doppler) \
                if len(frames) else 0.0
            meta = dataclasses.replace(
                self.metadata, achieved_density=achieved, peak_density=peak,
                created=self.metadata.created or _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"))
            assert self._writer is not None and self._tmp is not None
            self._writer.add_key_value_metadata(_encode_footer(meta, frames))
            self._writer.close()
            with open(self._tmp, "rb") as f:
                os.fsync(f.fileno())
            os.replace(self._tmp, self.path)
            self.metadata = meta
        except BaseException:
            self.abort()
            raise
        self._closed = True
        return self.path

    def abort(self) -> None:
        """Drop everything written so far (the final file is never created)."""
        if self._writer is not None:
            with contextlib.suppress(Exception):
                self._writer.close()
        if self._tmp is not None:
            with contextlib.suppress(FileNotFoundError):
                self._tmp.unlink()
        self._writer = None
        self._closed = True


# ---- reader -----------------------------------------------------------------------------------
class PointStore:
    """Read a point store: per-frame point clouds as tensors, reading only the needed row group.

    Parameters
    ----------
    path : path-like
        A ``.parquet`` file written by :class:`PointStoreWriter`.
    device : torch.device or str, optional
        Where returned tensors live (default CPU).

    Attributes
    ----------
    path : Path
    metadata : PointStoreMetadata
    frame_table : FrameTable
        One record per frame (empty frames included).
    frames : list of int
        RADIal numSample of each item.
    sequences : list of str
        Sequence name of each item.
    schema : pyarrow.Schema

    Raises
    ------
    DataFileError
        The file is missing, not Parquet, not a radarpc point store, lacks columns, has columns of
        the wrong type, or its row count disagrees with its frame table.
    """

    def __init__(self, path: str | os.PathLike, *, device: torch.device | str | None = None) -> None:
        self.path = Path(path)
        self.device = torch.device(device) if device is not None else torch.device("cpu")
        if not self.path.is_file():
            raise DataFileError(self.path, "point store is missing (expected a .parquet file written by "
                                           "`radarpc pointcloud`)")
        try:
            pf = pq.ParquetFile(str(self.path))
            schema = pf.schema_arrow
            kv = pf.metadata.metadata or {}
            rg_rows = np.asarray([pf.metadata.row_group(i).num_rows for i in range(pf.num_row_groups)],
                                 dtype=np.int64)
            rg_frames = _frame_stats(pf, schema)                  # [(min, max) or None] per row group
        except (pa.ArrowException, OSError) as e:
            raise DataFileError(self.path, f"is not a readable Parquet file ({e})") from e
        if METADATA_KEY not in kv:
            raise DataFileError(self.path, f"is Parquet but not a radarpc point store (no "
                                           f"{METADATA_KEY.decode()!r} metadata)")
        try:
            doc = json.loads(kv[METADATA_KEY].decode("utf-8"))
            if int(doc.get("format_version", -1)) != FORMAT_VERSION:
                raise ValueError(f"format_version {doc.get('format_version')!r}, expected {FORMAT_VERSION}")
            self.metadata = PointStoreMetadata.from_dict(doc["metadata"])
            self.frame_table = FrameTable.from_dict(doc["frames"])
        except (ValueError, KeyError, TypeError, UnicodeDecodeError) as e:
            raise DataFileError(self.path, f"has unreadable point store metadata ({e})") from e
        missing = [c for c in REQUIRED_COLUMNS if c not in schema.names]
        if missing:
            raise DataFileError(self.path, f"lacks point store columns {missing}; expected {list(REQUIRED_COLUMNS)}")
        want = point_schema(*(schema.field(c).type.list_size if c in schema.names and
                              pa.types.is_fixed_size_list(schema.field(c).type) else None
                              for c in LIST_COLUMNS))
        for f in want:
            if f.name not in schema.names or not schema.field(f.name).type.equals(f.type):
                got = schema.field(f.name).type if f.name in schema.names else "absent"
                raise DataFileError(self.path, f"column {f.name!r} has type {got}, expected {f.type}")
        for c in LIST_COLUMNS:
            if c in schema.names and not pa.types.is_fixed_size_list(schema.field(c).type):
                raise DataFileError(self.path, f"column {c!r} has type {schema.field(c).type}, expected "
                                               f"fixed_size_list<float>")
        self.schema = want
        ft = self.frame_table
        if int(ft.n_points.sum()) != int(rg_rows.sum()):
            raise DataFileError(self.path, f"holds {int(rg_rows.sum())} rows but its frame table counts "
                                           f"{int(ft.n_points.sum())} points")
        # Frame -> (row group, first row inside it). Row groups hold whole frames.
        rg_start = np.concatenate([[0], np.cumsum(rg_rows)]).astype(np.int64)   # (G+1,)
        start = ft.row_start                                                     # (F,)
        self._rg = np.searchsorted(rg_start, start, side="right") - 1            # (F,)
        self._rg_offset = start - rg_start[np.clip(self._rg, 0, len(rg_start) - 1)]     # (F,)
        nonempty = ft.n_points > 0
        rg_ok = (self._rg >= 0) & (self._rg < len(rg_rows))
        end_ok = np.zeros_like(nonempty)
        end_ok[rg_ok] = self._rg_offset[rg_ok] + ft.n_points[rg_ok] <= rg_rows[self._rg[rg_ok]]
        if np.any(nonempty & ~(rg_ok & end_ok)):
            raise DataFileError(self.path, "a frame straddles two row groups; the file was not written by "
                                           "PointStoreWriter")
        for g, mm in enumerate(rg_frames):  # row-group statistics agree with the frame table
            ids = ft.frame[(self._rg == g) & nonempty]
            if mm is not None and ids.size and mm != (int(ids.min()), int(ids.max())):
                raise DataFileError(self.path, f"row group {g} holds frames {mm[0]}..{mm[1]} but the frame table "
                                               f"puts frames {int(ids.min())}..{int(ids.max())} there")
        self.num_row_groups = int(len(rg_rows))
        self._rg_rows = rg_rows                                                  # (G,)
        self.frames: list[int] = ft.frame.tolist()
        self.sequences: list[str] = list(ft.sequence)
        self._pf: pq.ParquetFile | None = None
        self._pf_pid = -1
        self._cache: tuple[int, pa.Table] | None = None
        self._rg_bytes = np.asarray([pf.metadata.row_group(g).total_byte_size for g in range(pf.num_row_groups)],
                                    dtype=np.int64)                     # uncompressed, from the footer
        self._memory: pa.Table | None = None                            # rows of the preloaded items
        self._memory_start: np.ndarray | None = None                    # (F,) row in _memory, -1 if not there

    # -- file access (one handle per process, so that DataLoader workers each open their own)
    def _file(self) -> pq.ParquetFile:
        if self._pf is None or self._pf_pid != os.getpid():
            self._pf = pq.ParquetFile(str(self.path))
            self._pf_pid = os.getpid()
            self._cache = None
        return self._pf

    def __getstate__(self) -> dict:
        state = self.__dict__.copy()
        state["_pf"], state["_pf_pid"], state["_cache"] = None, -1, None
        # a spawned worker gets the store without its preloaded rows (pickling them would copy
        # them into every worker each epoch) and reads row groups; forked workers share them
        state["_memory"], state["_memory_start"] = None, None
        return state

    def read_row_group(self, rg: int) -> pa.Table:
        """Row group ``rg`` as an Arrow table (the last one read is cached)."""
        if self._cache is not None and self._cache[0] == rg and self._pf_pid == os.getpid():
            return self._cache[1]
        try:
            table = self._file().read_row_group(int(rg))
        except (pa.ArrowException, OSError) as e:
            raise DataFileError(self.path, f"row group {rg} is corrupt or truncated ({e})") from e
        self._cache = (int(rg), table)
        return table

    def __len__(self) -> int:
        return len(self.frames)

    def _items(self, items: Sequence[int] | None) -> np.ndarray:
        n = len(self)
        idx = np.arange(n, dtype=np.int64) if items is None else np.asarray(items, dtype=np.int64).reshape(-1)
        if idx.size and (idx.min() < -n or idx.max() >= n):
            raise IndexError(f"{self.path}: item indices must be in [-{n}, {n}), got {idx.min()}..{idx.max()}")
        return np.unique(idx % max(n, 1))

    def decoded_bytes(self, items: Sequence[int] | None = None) -> int:
        """Estimated memory (bytes) of items ``items`` (all by default) once decoded: each row
        group's uncompressed size from the footer, shared out by rows."""
        idx = self._items(items)
        idx = idx[self.frame_table.n_points[idx] > 0]
        rows = self._rg_rows.astype(np.float64)
        per_row = np.divide(self._rg_bytes, rows, out=np.zeros_like(rows), where=rows > 0)
        return int(np.sum(self.frame_table.n_points[idx] * per_row[self._rg[idx]]))

    def preload(self, items: Sequence[int] | None = None) -> int:
        """Hold the rows of items ``items`` (all by default) in memory, decoded.

        A store is compressed in row groups of many frames, and reading one frame decodes its
        whole row group; an epoch in random order reads each row group about as many times as it
        holds frames. Once preloaded, an item is a slice of one in-memory table. DataLoader
        workers started by fork share the rows with the process that loaded them; items not
        preloaded (and every item in a spawned worker) are read from the file as before.

        Parameters
        ----------
        items : sequence of int, optional
            Item positions; replaces what an earlier call held.

        Returns
        -------
        int
            Bytes held (Arrow buffers).
        """
        idx = self._items(items)
        idx = idx[self.frame_table.n_points[idx] > 0]
        self._memory, self._memory_start = None, None
        if idx.size == 0:
            return 0
        groups = np.unique(self._rg[idx])
        try:
            table = self._file().read_row_groups([int(g) for g in groups])
        except (pa.ArrowException, OSError) as e:
            raise DataFileError(self.path, f"row groups could not be read ({e})") from e
        # row of each item inside ``table`` (its row groups one after another)
        rows = self._rg_rows[groups]
        group_start = dict(zip(groups.tolist(), np.concatenate([[0], np.cumsum(rows)[:-1]]).tolist()))
        counts = self.frame_table.n_points[idx]
        src = np.asarray([group_start[int(g)] for g in self._rg[idx]], dtype=np.int64) + self._rg_offset[idx]
        take = np.repeat(src - np.concatenate([[0], np.cumsum(counts)[:-1]]), counts) + np.arange(counts.sum())
        self._memory = table.take(pa.array(take)).combine_chunks()
        start = np.full(len(self), -1, dtype=np.int64)
        start[idx] = np.concatenate([[0], np.cumsum(counts)[:-1]])
        self._memory_start = start
        return int(self._memory.nbytes)

    def index_of(self, frame: int) -> int:
        """Position of RADIal frame ``frame`` in the store."""
        hits = np.nonzero(self.frame_table.frame == int(frame))[0]
        if hits.size == 0:
            raise KeyError(f"frame {frame} is not in {self.path}")
        return int(hits[0])

    def frame_rows(self, i: int) -> pa.Table:
        """The Arrow rows of item ``i`` (possibly zero rows)."""
        n = len(self)
        if not -n <= int(i) < n:
            raise IndexError(f"index {i} out of range for a point store of {n} frames")
        i = int(i) % n
        count = int(self.frame_table.n_points[i])
        if count == 0:
            return self.schema.empty_table()
        if self._memory_start is not None and self._memory_start[i] >= 0:
            table = self._memory.slice(int(self._memory_start[i]), count)
        else:
            table = self.read_row_group(int(self._rg[i])).slice(int(self._rg_offset[i]), count)
        got = table.column("frame")
        expect = int(self.frame_table.frame[i])
        if got[0].as_py() != expect or got[count - 1].as_py() != expect:
            raise DataFileError(self.path, f"rows of frame {expect} are not where its frame table puts them")
        return table

    def __getitem__(self, i: int) -> PointCloudBatch:
        """The point cloud of item ``i`` as a one-frame :class:`PointCloudBatch`."""
        return self.read_frames([i])

    def __iter__(self) -> Iterator[PointCloudBatch]:
        for i in range(len(self)):
            yield self[i]

    def read_frames(self, indices: Sequence[int]) -> PointCloudBatch:
        """Items ``indices`` concatenated into one :class:`PointCloudBatch` (``offset`` ``(B,)``)."""
        indices = [int(i) for i in indices]
        tables = [self.frame_rows(i) for i in indices]
        table = pa.concat_tables([t.cast(self.schema) for t in tables]) if tables else self.schema.empty_table()
        idx = np.asarray([i % max(len(self), 1) for i in indices], dtype=np.int64)
        counts = self.frame_table.n_points[idx]
        tau = torch.as_tensor(self.frame_table.tau[idx], dtype=torch.float32)
        dens = torch.as_tensor(self.frame_table.density[idx], dtype=torch.float32)
        s = self.metadata.sensor                       # |S(tau)| = n_tx |P(tau)|
        peak = torch.as_tensor(self.frame_table.n_peaks[idx] * (s.n_tx / (s.n_range * s.n_doppler)),
                               dtype=torch.float32)
        return _table_to_batch(table, counts, tau, dens, self.device, peak)


def _frame_stats(pf: pq.ParquetFile, schema: pa.Schema) -> list[tuple[int, int] | None]:
    """``(min, max)`` of the ``frame`` column of every row group, from the footer statistics."""
    if "frame" not in schema.names:
        return []
    col = schema.names.index("frame")
    out: list[tuple[int, int] | None] = []
    for g in range(pf.num_row_groups):
        st = pf.metadata.row_group(g).column(col).statistics
        out.append((int(st.min), int(st.max)) if st is not None and st.has_min_max else None)
    return out


def _column_numpy(table: pa.Table, name: str) -> np.ndarray:
    col = table.column(name).combine_chunks()
    if pa.types.is_fixed_size_list(col.type):
        size = col.type.list_size
        flat = col.flatten().to_numpy(zero_copy_only=False)
        return flat.reshape(-1, size)
    return col.to_numpy(zero_copy_only=False)


def _table_to_batch(table: pa.Table, counts: np.ndarray, tau: torch.Tensor, density: torch.Tensor,
                    device: torch.device, peak_density: torch.Tensor | None = None) -> PointCloudBatch:
    fields: dict[str, torch.Tensor | None] = {}
    for name in FLOAT_COLUMNS:
        fields[name] = torch.from_numpy(_column_numpy(table, name).astype(np.float32, copy=True)).to(device)
    for name in INT_COLUMNS:
        fields[name] = torch.from_numpy(_column_numpy(table, name).astype(np.int64)).to(device)
    for name in BOOL_COLUMNS:
        fields[name] = torch.from_numpy(_column_numpy(table, name).astype(np.bool_, copy=True)).to(device)
    for name in LIST_COLUMNS:
        fields[name] = (torch.from_numpy(_column_numpy(table, name).astype(np.float32, copy=True)).to(device)
                        if name in table.schema.names else None)
    offset = torch.from_numpy(np.cumsum(counts).astype(np.int64)).to(device)      # (B,)
    return PointCloudBatch(offset=offset, tau=tau.to(device), density=density.to(device),
                           peak_density=None if peak_density is None else peak_density.to(device), **fields)
