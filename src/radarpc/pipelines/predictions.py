"""Filling a prediction folder frame by frame, resumably: the loop every method's writer shares.

A method (the OS-CFAR baseline, :mod:`radarpc.pipelines.oscfar`; RaLD's generation,
:mod:`radarpc.pipelines.rald_generate`) predicts one cloud per paired frame of a ColoRadar split;
:func:`fill_predictions` writes them in the layout of :mod:`radarpc.eval.predictions`:

* ``{run}/{frame:06d}.npy`` -- one float32 ``(N, 3)`` cloud per frame, written atomically (a
  temp file beside it, then a rename), so a killed job never leaves a half-written cloud under
  its final name;
* ``index.json`` -- one entry per frame (run, scene, frame, paired LiDAR scan, timestamps, file,
  point count, ``empty``), the method, root and split, and what the caller adds (its settings);
* optionally a per-frame record CSV (``records``, e.g. ``generation.csv``): the entry's run,
  scene, frame, file, point count and ``empty``, then the method's own values (timings, counts).

Resume: a frame whose cloud the caller may keep (``keep(i, path)``: the folder holds a run of
the same settings and the file exists) and that reads as a valid cloud is kept, not predicted
again; with a record CSV it also needs its row, else it is predicted again (the prediction is
a function of the settings and the frame, so the file is rewritten unchanged and the row
recovered). The CSV is rewritten atomically every ``flush_seconds`` and at the end. Clouds
without a point are written like any other (a ``(0, 3)`` array), listed in the result
(:attr:`FilledFolder.empty`) and flagged in the index and the records: never silently.

The caller owns the folder: it holds the folder's lock and decides what may be kept
(:func:`radarpc.runs.locked_output`, :class:`radarpc.runs.RunFolder`).
"""
from __future__ import annotations

import csv
import io
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Mapping

import numpy as np

from radarpc.eval.predictions import prediction_path, write_index
from radarpc.io import DataFileError, atomic_write, load_array, save_npy_atomic

__all__ = ["FramePrediction", "FilledFolder", "index_entry", "read_records", "fill_predictions"]

_RECORD_KEYS = ("run", "scene", "frame", "file", "n_points", "empty")


@dataclass(frozen=True)
class FramePrediction:
    """A method's output for one frame."""

    points: np.ndarray                                             # (N, 3) float32, radar frame (N may be 0)
    record: Mapping[str, object] = field(default_factory=dict)     # the frame's values for the record CSV
    warning: str | None = None                                     # e.g. an empty decoding, said once per frame


@dataclass(frozen=True)
class FilledFolder:
    """What :func:`fill_predictions` did."""

    entries: list[dict]                          # index.json's frames, in the split's order
    n_new: int                                   # clouds predicted by this job (the rest were kept)
    empty: tuple[tuple[str, int], ...]           # (run, frame) of the clouds without a point, all frames
    warnings: tuple[str, ...]                    # "run R frame F: ..." of the frames predicted by this job

    @property
    def n_frames(self) -> int:
        return len(self.entries)


def index_entry(ds, i: int, out: str | os.PathLike, path: str | os.PathLike, n_points: int) -> dict:
    """The ``index.json`` entry of item ``i`` of a :class:`radarpc.data.coloradar.ColoRadar` split
    whose cloud of ``n_points`` points is at ``path`` inside the folder ``out``."""
    k, ri, li = ds.index[i]
    run = ds.runs[k]
    return {"run": run.name, "scene": run.scene, "frame": int(ri), "lidar_index": int(li),
            "lidar_file": str(run.lidar_path(li)), "radar_time": float(run.radar_timestamps[ri]),
            "lidar_time": float(run.lidar_timestamps[li]), "file": Path(path).relative_to(out).as_posix(),
            "n_points": int(n_points), "empty": int(n_points) == 0}


def read_records(path: str | os.PathLike) -> dict[tuple[str, int], dict[str, str]]:
    """The rows of a record CSV by ``(run, frame)`` (values as written, strings); ``{}`` when the
    file is missing. A row without a run or an integer frame is skipped.

    Raises
    ------
    DataFileError
        The file exists but is not a CSV with ``run`` and ``frame`` columns.
    """
    path = Path(path)
    if not path.is_file():
        return {}
    try:
        with open(path, newline="", encoding="utf-8") as f:
            reader = csv.DictReader(f)
            if reader.fieldnames is None or not {"run", "frame"} <= set(reader.fieldnames):
                raise DataFileError(path, f"expected a CSV with 'run' and 'frame' columns, found {reader.fieldnames}")
            rows = list(reader)
    except (OSError, UnicodeDecodeError, csv.Error) as e:
        raise DataFileError(path, f"is not a readable CSV ({e})") from e
    out = {}
    for row in rows:
        run, frame = row.get("run"), row.get("frame")
        if run and frame is not None and frame.isdigit():
            out[(run, int(frame))] = row
    return out


def _write_records(path: Path, rows: list[dict]) -> None:
    names: list[str] = list(_RECORD_KEYS)
    for row in rows:
        names += [k for k in row if k not in names]
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=names, restval="", lineterminator="\n")
    w.writeheader()
    w.writerows(rows)
    with atomic_write(path, "w") as f:
        f.write(buf.getvalue())


def _kept_rows(path: Path) -> int | None:
    """Rows of the cloud at ``path`` if it reads as a valid float ``(N, 3)`` cloud, else None."""
    try:
        return int(load_array(path, shape=(None, 3), complex_=False).shape[0])
    except DataFileError:
        return None


def fill_predictions(
    out: str | os.PathLike,
    ds,
    predict: Callable[[int], np.ndarray | FramePrediction],
    *,
    keep: Callable[[int, Path], bool],
    method: str,
    root: str | os.PathLike,
    split: str,
    index_extra: Mapping[str, object] | Callable[[FilledFolder], Mapping[str, object]] | None = None,
    records: str | None = None,
    flush_seconds: float = 10.0,
    progress: bool = True,
    desc: str = "",
    on_warning: Callable[[str], None] | None = None,
) -> FilledFolder:
    """Write one cloud per item of ``ds`` into ``out``, keeping what may be kept (module docstring).

    Parameters
    ----------
    out : path-like
        The prediction folder; the caller holds its lock.
    ds : radarpc.data.coloradar.ColoRadar
        The split's paired frames.
    predict : callable
        ``predict(i)``: item ``i``'s cloud, an ``(N, 3)`` array or a :class:`FramePrediction`.
    keep : callable
        ``keep(i, path)``: whether an existing cloud of item ``i`` at ``path`` was made with this
        job's settings (it is then kept if it reads as a valid cloud).
    method, root, split : str
        Written into ``index.json`` (the root resolved).
    index_extra : mapping or callable, optional
        More keys of ``index.json`` (e.g. the method's settings), or a function of the result
        that returns them.
    records : str, optional
        File name of the per-frame record CSV inside ``out`` (e.g. ``"generation.csv"``).
    flush_seconds : float
        The record CSV is rewritten at least this often (and at the end, or on an error).
    progress : bool
        A tqdm bar over the frames.
    desc : str
        Its label.
    on_warning : callable, optional
        Called with each new frame's warning (``"run R frame F: ..."``) as it happens.

    Returns
    -------
    FilledFolder
    """
    from tqdm import tqdm

    out = Path(out)
    rec_path = out / records if records else None
    old_rows = read_records(rec_path) if rec_path is not None else {}
    rows: list[dict] = []
    entries: list[dict] = []
    empty: list[tuple[str, int]] = []
    warnings: list[str] = []
    n_new = 0
    last_flush = time.monotonic()
    finished = False
    try:
        for i in tqdm(range(len(ds)), desc=desc or f"{method} {split}", unit="frame", disable=not progress):
            k, ri, _ = ds.index[i]
            run = ds.runs[k].name
            path = prediction_path(out, run, ri)
            old = old_rows.get((run, int(ri)))
            n = _kept_rows(path) if keep(i, path) and (rec_path is None or old is not None) else None
            if n is None:
                pred = predict(i)
                if not isinstance(pred, FramePrediction):
                    pred = FramePrediction(np.asarray(pred))
                pts = np.ascontiguousarray(pred.points, dtype=np.float32)
                if pts.ndim != 2 or pts.shape[1] != 3:
                    raise ValueError(f"{method}: run {run} frame {ri}: a cloud must be (N, 3), got shape {pts.shape}")
                save_npy_atomic(path, pts)
                n, n_new = int(pts.shape[0]), n_new + 1
                if pred.warning:
                    warnings.append(f"run {run} frame {ri}: {pred.warning}")
                    if on_warning is not None:
                        on_warning(warnings[-1])
                row = None
            else:
                row = old
            entry = index_entry(ds, i, out, path, n)
            entries.append(entry)
            if n == 0:
                empty.append((run, int(ri)))
            if rec_path is not None:
                rows.append(row if row is not None else
                            {**{k2: entry[k2] for k2 in _RECORD_KEYS}, **dict(pred.record)})
                if time.monotonic() - last_flush >= flush_seconds:
                    _write_records(rec_path, _with_unreached(rows, old_rows))
                    last_flush = time.monotonic()
        finished = True
    finally:
        if rec_path is not None and (rows or old_rows):
            # interrupted: the rows of frames not reached yet stay for the next run; finished: the
            # split's rows only
            _write_records(rec_path, rows if finished else _with_unreached(rows, old_rows))
    result = FilledFolder(entries, n_new, tuple(empty), tuple(warnings))
    extra = index_extra(result) if callable(index_extra) else index_extra
    write_index(out, method, root, split, entries, extra=extra)
    return result


def _with_unreached(rows: list[dict], old_rows: Mapping[tuple[str, int], dict]) -> list[dict]:
    done = {(str(r["run"]), int(r["frame"])) for r in rows}
    return rows + [r for key, r in old_rows.items() if key not in done]
