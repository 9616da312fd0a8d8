"""Export jobs: a Parquet point store or a ColoRadar prediction folder -> one file per frame.

A point store (:mod:`radarpc.data.pointstore`) is exported in OpenPCDet's custom-dataset layout::

    OUT/
      points/{frame:06d}.{npy|bin|ply}   (N, C) float32 points of RADIal frame ``frame`` (numSample)
      ImageSets/{split}.txt              the exported sample ids, one a line (split = the store's)
      columns.txt                        the column order, units, and how to read a file
      export.json                        the export's settings and the store's metadata subset

A prediction folder (:mod:`radarpc.eval.predictions`) is exported as PLY beside its layout::

    OUT/
      {run}/{frame:06d}.ply              x, y, z float properties (the single-chip radar frame)
      columns.txt, export.json

The formats and the column order are documented in :mod:`radarpc.data.export`.

An evaluation's detections file (``eval_{split}..._detections.csv``, :mod:`radarpc.eval.detection_files`)
becomes one ``.npz`` or ``.jsonl`` file (:func:`export_detections`).

Ownership and resume (:class:`radarpc.runs.RunFolder`): the output folder is locked for the whole
job; ``export.json`` is the run's key (source, its identity, format, columns), so a rerun with the
same settings keeps the frames already written and writes the rest, and a folder holding anything
else is refused unless ``overwrite`` (which removes only this job's entries). The source's path is
recorded, not compared (its identity is: a moved source resumes the export). Every file is
written atomically.
"""
from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from radarpc.data.export import (
    DEFAULT_COLUMNS,
    check_columns,
    check_format,
    columns_text,
    frame_file_name,
    frame_points,
    write_frame,
)
from radarpc.data.pointstore import PointStore
from radarpc.eval.detection_files import DETECTION_FORMATS, read_detections, write_detections_as
from radarpc.eval.predictions import INDEX_FILE
from radarpc.io import atomic_write, load_array
from radarpc.runs import RunFolder, read_json

__all__ = ["EXPORT_FILE", "COLUMNS_FILE", "ExportRun", "DetectionsExport", "export_store", "export_predictions",
           "export_detections", "export"]

EXPORT_FILE = "export.json"
"""The export folder's manifest: settings (the run's key) and the source's description."""
COLUMNS_FILE = "columns.txt"
EXPORT_VERSION = 1

# point-store metadata copied into export.json (what a user of the files needs to know)
_STORE_FIELDS = ("source_root", "split", "density_mode", "tau", "target_density", "achieved_density",
                 "peak_density", "enrich", "window", "guard", "envelope", "created", "radarpc_version")


@dataclass(frozen=True)
class ExportRun:
    """What an export job did."""

    out: Path
    fmt: str
    columns: tuple[str, ...]
    n_frames: int        # files of the export (one per frame)
    n_new: int           # of which written by this job (the rest were kept from an earlier run)
    n_points: int        # points written by this job
    n_empty: int         # frames without points (valid empty files)

    @property
    def n_reused(self) -> int:
        return self.n_frames - self.n_new


def _run_folder(out: Path, key: dict, owned: Sequence[str]) -> RunFolder:
    # the source is known by its content (the store's metadata, the predictions' digest), not its place
    return RunFolder(out, {EXPORT_FILE: key}, what="export folder", owned=tuple(owned), locators=("source",))


def _check_apart(source: Path, out: Path) -> None:
    s, o = source.resolve(), out.resolve()
    if s == o or s in o.parents or o in s.parents:
        raise ValueError(f"--out {out} overlaps the source {source}; export into a separate folder")


def export_store(store: str | os.PathLike | PointStore, out: str | os.PathLike, fmt: str = "npy",
                 columns: Sequence[str] = DEFAULT_COLUMNS, *, overwrite: bool = False,
                 progress: bool = True) -> ExportRun:
    """Write every frame of a point store as ``out/points/{frame:06d}.{fmt}`` (module docstring).

    Parameters
    ----------
    store : path-like or PointStore
        The ``.parquet`` store.
    out : path-like
        The export folder.
    fmt : str
        ``"npy"``, ``"bin"`` or ``"ply"`` (:data:`radarpc.data.export.FORMATS`).
    columns : sequence of str
        Column order (starting with x, y, z); default :data:`radarpc.data.export.DEFAULT_COLUMNS`.
    overwrite : bool
        Replace an export with other settings (only this job's entries are removed).
    progress : bool
        A tqdm bar over frames.

    Raises
    ------
    radarpc.io.DataFileError
        ``store`` is missing or not a point store.
    ValueError
        Unknown format or column.
    radarpc.runs.RunMismatchError
        ``out`` is not empty and holds no export with these settings, without ``overwrite``.
    radarpc.runs.OutputBusyError
        Another process writes ``out``.
    """
    from tqdm import tqdm

    fmt, cols = check_format(fmt), check_columns(columns)
    store = store if isinstance(store, PointStore) else PointStore(store)
    out = Path(out)
    _check_apart(store.path, out)
    meta = store.metadata.to_dict()
    layout = f"points/{{frame:06d}}.{fmt}"
    key = {"export_version": EXPORT_VERSION, "kind": "point-store", "source": str(store.path.resolve()),
           "format": fmt, "columns": list(cols), "layout": layout, "n_frames": len(store),
           # identifies the store's content: a store rewritten at the same path has another `created`
           "store": {k: meta[k] for k in _STORE_FIELDS},
           "openpcdet": {"POINT_FEATURE_ENCODING": {"encoding_type": "absolute_coordinates_encoding",
                                                    "used_feature_list": list(cols),
                                                    "src_feature_list": list(cols)},
                         "NUM_POINT_FEATURES": len(cols)}}
    split = str(store.metadata.split)
    n_new = n_points = n_empty = 0
    ids = [f"{int(f):06d}" for f in store.frames]
    with _run_folder(out, key, ("points", "ImageSets", COLUMNS_FILE)).start(overwrite=overwrite) as run:
        for i in tqdm(range(len(store)), desc=f"export {fmt}", unit="frame", disable=not progress):
            n = int(store.frame_table.n_points[i])
            n_empty += n == 0
            path = out / "points" / frame_file_name(store.frames[i], fmt)
            if run.done(path):
                continue
            write_frame(path, frame_points(store, i, cols), fmt, cols,
                        comments=(f"radarpc export of frame {ids[i]} from {store.path.name}",))
            n_new += 1
            n_points += n
        with atomic_write(out / "ImageSets" / f"{split}.txt", "w") as f:
            f.write("".join(f"{s}\n" for s in ids))
        with atomic_write(out / COLUMNS_FILE, "w") as f:
            f.write(columns_text(cols, fmt, f"points/*.{fmt}"))
    return ExportRun(out, fmt, cols, len(store), n_new, n_points, n_empty)


def _prediction_files(folder: Path) -> list[tuple[str, str]]:
    """``[(run, stem)]`` of the ``{run}/{frame:06d}.npy`` files of a prediction folder, sorted."""
    files = sorted((p.parent.name, p.stem) for p in folder.glob("*/*.npy")
                   if p.is_file() and p.stem.isdigit() and not p.parent.name.startswith("."))
    if not files:
        raise ValueError(f"{folder} is not a prediction folder: no {{run}}/{{frame:06d}}.npy files in it "
                         "(written by `radarpc baseline os-cfar`)")
    return files


def _npy_rows(path: Path) -> int:
    """Rows of a ``.npy`` array, from its header alone."""
    fmt = np.lib.format
    with open(path, "rb") as f:
        version = fmt.read_magic(f)
        read = fmt.read_array_header_1_0 if version == (1, 0) else fmt.read_array_header_2_0
        shape = read(f)[0]
    return int(shape[0]) if shape else 1


def _digest(paths: Sequence[Path]) -> str | None:
    h = hashlib.sha256()
    found = False
    for p in paths:
        if p.is_file():
            data = p.read_bytes()
            h.update(p.name.encode() + b"\0" + (_index_content(data) if p.name == INDEX_FILE else data))
            found = True
    return h.hexdigest() if found else None


def _index_content(data: bytes) -> bytes:
    """A prediction index as its clouds' identity: without where the model's run folder lay
    (``model.run``, a locator the generation updates when a moved run resumes it)."""
    try:
        index = json.loads(data)
    except ValueError:
        return data
    model = index.get("model") if isinstance(index, dict) else None
    if not (isinstance(model, dict) and "run" in model):
        return data
    return json.dumps({**index, "model": {k: v for k, v in model.items() if k != "run"}}, sort_keys=True).encode()


def export_predictions(folder: str | os.PathLike, out: str | os.PathLike, *, overwrite: bool = False,
                       progress: bool = True) -> ExportRun:
    """Write every cloud of a prediction folder as ``out/{run}/{frame:06d}.ply`` (x, y, z floats).

    Empty predictions give PLY files with ``element vertex 0``. The key holds a digest of the
    folder's ``index.json`` (without the model's run folder, ``model.run``) and ``config.yaml``, so
    predictions made again with other parameters are exported again rather than kept.

    Raises
    ------
    ValueError
        ``folder`` holds no ``{run}/{frame:06d}.npy`` file, or ``out`` overlaps it.
    radarpc.io.DataFileError
        A prediction file is not a float ``(N, 3)`` array.
    radarpc.runs.RunMismatchError, radarpc.runs.OutputBusyError
        As :func:`export_store`.
    """
    from tqdm import tqdm

    folder, out = Path(folder), Path(out)
    if not folder.is_dir():
        raise NotADirectoryError(f"prediction folder {folder} is missing or not a folder")
    _check_apart(folder, out)
    files = _prediction_files(folder)
    index = read_json(folder / INDEX_FILE)
    index = index if isinstance(index, dict) else {}
    cols = ("x", "y", "z")
    key = {"export_version": EXPORT_VERSION, "kind": "predictions", "source": str(folder.resolve()),
           "format": "ply", "columns": list(cols), "layout": "{run}/{frame:06d}.ply", "n_frames": len(files),
           "method": index.get("method"), "root": index.get("root"), "split": index.get("split"),
           "source_digest": _digest([folder / INDEX_FILE, folder / "config.yaml"])}
    runs = sorted({r for r, _ in files})
    n_new = n_points = n_empty = 0
    with _run_folder(out, key, (*runs, COLUMNS_FILE)).start(overwrite=overwrite) as run:
        for name, stem in tqdm(files, desc="export ply", unit="frame", disable=not progress):
            path = out / name / f"{stem}.ply"
            src = folder / name / f"{stem}.npy"
            if run.done(path):
                n_empty += _npy_rows(src) == 0
                continue
            pts = load_array(src, shape=(None, 3), complex_=False)
            write_frame(path, pts, "ply", cols, comments=(f"radarpc export of {name}/{stem}.npy",))
            n_new += 1
            n_points += int(pts.shape[0])
            n_empty += pts.shape[0] == 0
        with atomic_write(out / COLUMNS_FILE, "w") as f:
            f.write(columns_text(cols, "ply", "{run}/*.ply"))
    return ExportRun(out, "ply", cols, len(files), n_new, n_points, n_empty)


@dataclass(frozen=True)
class DetectionsExport:
    """What :func:`export_detections` wrote."""

    out: Path
    fmt: str
    n_frames: int
    n_detections: int


def export_detections(source: str | os.PathLike, out: str | os.PathLike, fmt: str | None = None, *,
                      overwrite: bool = False) -> DetectionsExport:
    """Convert an evaluation's ``eval_{split}..._detections.csv`` (with the frame list of its
    ``.json``) into ``out``, an ``.npz`` or ``.jsonl`` file (:mod:`radarpc.eval.detection_files`).

    ``fmt``, when given, must agree with ``out``'s suffix; an existing ``out`` is replaced only
    with ``overwrite``. The file is written atomically.
    """
    source, out = Path(source), Path(out)
    if not source.is_file():
        raise FileNotFoundError(f"{source} does not exist: expected an evaluation's detections file "
                                "(eval_{split}..._detections.csv, written by `radarpc evaluate`)")
    suffix = out.suffix.lstrip(".").lower()
    if fmt is not None and fmt != suffix:
        raise ValueError(f"--format {fmt} but --out {out} ends in {out.suffix or 'no suffix'}: detections are "
                         f"written as {' or '.join('.' + f for f in DETECTION_FORMATS)}, named by the suffix")
    if out.is_dir():
        raise ValueError(f"--out {out} is a folder: detections export to one file (.npz or .jsonl)")
    if out.exists() and not overwrite:
        raise ValueError(f"--out {out} exists; pass --overwrite to replace it")
    table = read_detections(source)
    written = write_detections_as(table, out)
    return DetectionsExport(out, written, len(table.root), len(table.rows))


def export(source: str | os.PathLike, out: str | os.PathLike, fmt: str | None = None,
           columns: Sequence[str] | None = None, *, overwrite: bool = False, progress: bool = True) -> ExportRun:
    """Export a point store (a file) or a prediction folder (a folder), whichever ``source`` is.

    ``fmt`` defaults to ``npy`` for a store and ``ply`` for predictions (their only format);
    ``columns`` applies to stores only.
    """
    source = Path(source)
    if source.name.endswith("_detections.csv"):
        raise ValueError(f"{source} is an evaluation's detections file: export it with export_detections")
    if fmt is not None:
        check_format(fmt)
    if source.is_dir():
        if fmt not in (None, "ply"):
            raise ValueError(f"{source} is a prediction folder: its clouds are already .npy (N, 3) files and "
                             f"are exported as ply only, not {fmt}")
        if columns is not None:
            raise ValueError(f"{source} is a prediction folder: its clouds have the columns x, y, z only; "
                             "drop --columns")
        return export_predictions(source, out, overwrite=overwrite, progress=progress)
    if not source.exists():
        raise FileNotFoundError(f"{source} does not exist: expected a point store (.parquet, written by "
                                "`radarpc pointcloud`) or a prediction folder (written by `radarpc baseline`)")
    return export_store(source, out, fmt or "npy", DEFAULT_COLUMNS if columns is None else columns,
                        overwrite=overwrite, progress=progress)
