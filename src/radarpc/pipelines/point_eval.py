"""Scoring prediction folders against a ColoRadar split: each method's CD / EMD / EMD_equal per
scene, the methods side by side, their per-frame CDFs and a figure per scene (``radarpc evaluate-points``).

For each folder (:mod:`radarpc.eval.predictions`): its ``index.json`` must name the dataset root
and split (unless ``force``), and the frames scored are exactly those it lists
(:func:`radarpc.eval.predictions.index_frames`: every paired frame of the split, or a subset such
as every K-th); each must be a paired frame of the split. With ``force`` a folder without an index
is scored on every paired frame of the split, and an index's frames outside the split are left out. Every listed frame's cloud is scored against the
reader's LiDAR cropped to the frustum (:func:`radarpc.eval.pointsets.evaluate_clouds`); an empty
cloud is counted, not scored (``empty``), a missing or malformed one is an error, and so is an
empty ground truth. The report is written into the folder (``metrics.json``, ``metrics.md``),
always over the folder's own frames.

Several folders are compared over the same frames: if their indexes list different frame sets the
evaluation is refused before any scoring, unless ``common_frames``, which compares them over the
frames every folder lists (each ``metrics.json`` still covers its folder's own frames). The
methods side by side (:func:`radarpc.eval.comparison.comparison_markdown`; when they scored
different frames because of empty predictions, also over the frames every method scored) go to
``out/comparison.md`` and ``comparison.json``. With ``figures``: the empirical CDFs of the
per-frame Chamfer distance, EMD and EMD_equal, one panel per scene and one of all frames, one
curve per method (:func:`radarpc.viz.plot_cdfs`, as the seed's Figs. 6-7), as
``out/figures/cdf_chamfer.png``, ``cdf_emd.png`` and ``cdf_emd_equal.png``; and one compared frame
per scene drawn with the radar cube, the truth and every method's cloud
(:func:`radarpc.viz.plot_cloud_comparison`) as ``out/figures/{scene}.png``. ``out`` defaults to
the first folder.

A folder's scores are computed once: when its ``metrics.json`` was written by the same scoring
(:data:`SCORING_VERSION`) for the same root, split, frames and EMD settings, and neither a
listed cloud (by SHA-256) nor the LiDAR and calibration files it is scored against (by size and
modification time) have changed since (:func:`score_identity`), the stored scores are used
(``reused``); ``rescore`` scores every folder again.
"""
from __future__ import annotations

import hashlib
import json
import os
import re
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Sequence

from radarpc.data.coloradar import ColoRadar, find_calib, scene_of_run
from radarpc.eval.comparison import CDF_METRICS, cdf_panels, comparison_dict, comparison_markdown
from radarpc.eval.pointsets import EMD_POINTS, EMD_SEED, PointSetReport, evaluate_clouds
from radarpc.eval.predictions import INDEX_FILE, check_index, index_frames, prediction_pairs, prediction_path
from radarpc.io import DataFileError, atomic_write
from radarpc.pipelines.frames import comparison_views

__all__ = ["PointEvaluation", "CDF_FIGURES", "SCORING_VERSION", "method_names", "folder_items", "score_identity",
           "evaluate_folders"]

SCORING_VERSION = 1
"""Stored scores are reused only when this version of the scoring made them: bump it with any change
that moves a frame's numbers (the metrics, the frustum crop, the pairing of radar and LiDAR frames)."""

CDF_FIGURES = {"chamfer": "cdf_chamfer.png", "emd": "cdf_emd.png", "emd_equal": "cdf_emd_equal.png"}
"""The CDF figures ``figures/`` receives, by per-frame score."""

_AXIS = {"chamfer": "Chamfer distance [m]", "emd": "EMD [m]", "emd_equal": "EMD_equal [m]"}


@dataclass(frozen=True)
class PointEvaluation:
    """What :func:`evaluate_folders` wrote."""

    reports: dict[str, PointSetReport]      # by method name, in the order of the folders; each over its own frames
    folders: dict[str, Path]                # method name -> its prediction folder
    comparison: Path | None                 # comparison.md (several folders), else None
    figures: tuple[Path, ...]               # the CDF figures, then one per scene (with figures)
    compared: tuple[tuple[str, int], ...] = ()   # (run, frame) the methods are compared over, split order
    common_frames: bool = False             # the folders listed different frames, compared over the common ones
    reused: tuple[str, ...] = ()            # methods whose stored metrics.json was used, not scored again

def _method(folder: Path) -> str:
    try:
        m = json.loads((folder / INDEX_FILE).read_text()).get("method")
    except (OSError, ValueError, AttributeError):
        m = None
    return str(m) if m else folder.name


def method_names(folders: Sequence[str | os.PathLike]) -> list[str]:
    """A distinct name per prediction folder: its ``index.json`` method (else the folder's name),
    with the folder's name added where two methods are the same, its path where that is not enough."""
    paths = [Path(f) for f in folders]
    base = [_method(p) for p in paths]
    names = [f"{m} ({p.name})" if base.count(m) > 1 else m for m, p in zip(base, paths)]
    if len(set(names)) < len(names):
        names = [f"{m} ({p})" for m, p in zip(base, paths)]
    return names


def _file_name(scene: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", scene) or "scene"


def folder_items(folder: str | os.PathLike, ds: ColoRadar, *, force: bool = False) -> list[int]:
    """The items of ``ds`` (a ColoRadar split) that a prediction folder holds, in the split's order:
    the frames its ``index.json`` lists. With ``force``: every item when there is no index, and
    the listed frames that are frames of the split when the index was made on another split or root.

    Raises
    ------
    radarpc.io.DataFileError
        The index is missing (without ``force``) or malformed (:func:`radarpc.eval.predictions.index_frames`).
    ValueError
        The index lists no frame of the split, or (without ``force``) a frame that is not a paired
        frame of the split.
    """
    folder = Path(folder)
    if force and not (folder / INDEX_FILE).is_file():
        return list(range(len(ds)))
    keys = index_frames(folder)
    item_of = {(ds.runs[k].name, int(ri)): i for i, (k, ri, _) in enumerate(ds.index)}
    outside = [k for k in keys if k not in item_of]
    if outside and not force:
        run, frame = outside[0]
        raise ValueError(f"{folder / INDEX_FILE} lists run {run!r} frame {frame}, which is not a paired "
                         f"radar/LiDAR frame of split {ds.split!r} of {ds.root}")
    items = sorted(item_of[k] for k in keys if k in item_of)
    if not items:
        raise ValueError(f"{folder / INDEX_FILE} lists no frame of split {ds.split!r} of {ds.root}")
    return items


def _key(ds: ColoRadar, i: int) -> tuple[str, int]:
    k, ri, _ = ds.index[i]
    return ds.runs[k].name, int(ri)


def _differ_message(ds: ColoRadar, names: list[str], items: dict[str, list[int]], common: set[int]) -> str:
    counts = ", ".join(f"{n} lists {len(items[n])}" for n in names)
    odd = next(i for n in names for i in items[n] if i not in common)
    owners = [n for n in names if odd in set(items[n])]
    run, frame = _key(ds, odd)
    return (f"the prediction folders list different frames ({counts}, {len(common)} in common; e.g. run "
            f"{run!r} frame {frame} only by {', '.join(owners)}): pass --common-frames to compare them over the "
            f"frames every folder lists, or evaluate the folders one at a time")


def score_identity(ds: ColoRadar, folder: str | os.PathLike, items: Sequence[int], *, emd_points: int,
                   emd_seed: int) -> dict:
    """What a prediction folder's stored scores must match to be reused (module docstring): the
    scoring version, the EMD settings, the SHA-256 of the listed clouds with their runs and frames,
    and the size and modification time of the LiDAR scans and calibration files they are scored
    against. Raises ``OSError`` when one of those files is missing."""
    clouds, truth = hashlib.sha256(), hashlib.sha256()
    for i in items:
        k, ri, li = ds.index[i]
        run = ds.runs[k]
        digest = hashlib.sha256(prediction_path(folder, run.name, ri).read_bytes()).hexdigest()
        clouds.update(f"{run.name}/{ri}:{digest};".encode())
        st = run.lidar_path(li).stat()
        truth.update(f"{run.name}/{ri}/{li}:{st.st_size}:{st.st_mtime_ns};".encode())
    calib = find_calib(ds.root)
    for f in sorted(p for p in calib.rglob("*") if p.is_file()):
        st = f.stat()
        truth.update(f"{f.relative_to(calib)}:{st.st_size}:{st.st_mtime_ns};".encode())
    return {"version": SCORING_VERSION, "emd_points": int(emd_points), "emd_seed": int(emd_seed),
            "fov": asdict(ds.fov), "clouds_sha256": clouds.hexdigest(), "truth_files_sha256": truth.hexdigest()}


_LOCATORS = ("pred_dir", "method")
"""Provenance in ``metrics.json`` that names, not identifies: a moved folder or another method name
(which depends on the folders given together) keeps its scores."""


def _stored_report(folder: Path, extra: dict) -> PointSetReport | None:
    """The folder's ``metrics.json`` when its provenance equals ``extra`` but for the locators, else None."""
    try:
        d = json.loads((folder / "metrics.json").read_text())
        stored = {k: v for k, v in d["extra"].items() if k not in _LOCATORS}
        if stored != {k: v for k, v in json.loads(json.dumps(extra)).items() if k not in _LOCATORS}:
            return None
        return PointSetReport.from_dict(d)
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return None


def evaluate_folders(folders: Sequence[str | os.PathLike], data: str | os.PathLike, split: str, *,
                     emd_points: int = EMD_POINTS, emd_seed: int = EMD_SEED, force: bool = False,
                     figures: bool = False, out: str | os.PathLike | None = None,
                     common_frames: bool = False, rescore: bool = False, progress: bool = True) -> PointEvaluation:
    """Score each prediction folder, compare them, draw the CDFs and a frame per scene (module docstring).

    Raises
    ------
    radarpc.io.DataFileError
        A folder is missing, its index is missing or unreadable (without ``force``), or a cloud is
        missing or malformed.
    ValueError
        An index names another root or split (without ``force``) or a frame the split lacks, the
        split has no frame, the folders list different frames (without ``common_frames``) or none
        in common, a ground-truth cloud is empty (naming run and frame), a bad ``emd_points``, or
        the same folder twice.
    """
    paths = [Path(f) for f in folders]
    if not paths:
        raise ValueError("give at least one prediction folder")
    if len({p.resolve() for p in paths}) < len(paths):
        raise ValueError("the same prediction folder is given twice")
    if int(emd_points) < 1:
        raise ValueError(f"--emd-points must be >= 1, got {emd_points}")
    for p in paths:
        if not p.is_dir():
            raise DataFileError(p, "prediction folder is missing")
        if not force:
            check_index(p, data, split)
    ds = ColoRadar(data, split, cube_size=None)
    if len(ds) == 0:
        raise ValueError(f"split {split!r} of {data} has no paired radar/LiDAR frame")
    names = method_names(paths)
    items = {n: folder_items(p, ds, force=force) for n, p in zip(names, paths)}
    common = set.intersection(*(set(v) for v in items.values()))
    differ = any(set(v) != common for v in items.values())
    if differ and not common_frames:
        raise ValueError(_differ_message(ds, names, items, common))
    if not common:
        raise ValueError("the prediction folders have no frame in common: " + ", ".join(
            f"{n} lists {len(items[n])}" for n in names))
    compared = tuple(_key(ds, i) for i in sorted(common))

    reports: dict[str, PointSetReport] = {}
    reused: list[str] = []
    for name, p in zip(names, paths):
        extra = {"pred_dir": str(p), "method": name, "data": str(Path(data).resolve()), "split": split,
                 "index_checked": not force,
                 "frames_from": "index.json" if (p / INDEX_FILE).is_file() else "split (no index, --force)"}
        try:
            extra["scores"] = score_identity(ds, p, items[name], emd_points=emd_points, emd_seed=emd_seed)
        except OSError:
            extra["scores"] = None            # a cloud is missing: scoring below names it
        stored = None if rescore or extra["scores"] is None else _stored_report(p, extra)
        if stored is not None:
            stored.extra.update(pred_dir=str(p), method=name)
            reports[name] = stored
            reused.append(name)
            continue
        report = evaluate_clouds(prediction_pairs(ds, p, items[name], allow_empty=True), scene_of_run,
                                 emd_points=emd_points, emd_seed=emd_seed, progress=progress)
        report.extra = extra
        report.write(p / "metrics.json", p / "metrics.md")
        reports[name] = report
    shown = {n: r.subset(compared) for n, r in reports.items()} if differ else reports
    dest = Path(out) if out is not None else paths[0]
    folder_of = dict(zip(names, paths))
    comparison = None
    if len(paths) > 1:
        comparison = dest / "comparison.md"
        scope = (f"Compared over the {len(compared)} frame{'' if len(compared) == 1 else 's'} every folder lists "
                 "(--common-frames).\n\n"
                 if differ else "")
        with atomic_write(comparison, "w") as f:
            f.write(scope + comparison_markdown(shown))
        with atomic_write(dest / "comparison.json", "w") as f:
            json.dump({"data": str(Path(data).resolve()), "split": split, "n_frames": len(compared),
                       "frames": "common to every folder (--common-frames)" if differ else "every folder's",
                       **comparison_dict(shown, {n: str(p) for n, p in folder_of.items()})}, f, indent=1)
    drawn: list[Path] = []
    if figures:
        from radarpc.viz import plot_cdfs, plot_cloud_comparison

        footer = (f"radarpc evaluate-points: {len(names)} method(s) on {len(compared)} frames of split {split!r} "
                  f"of {Path(data).name}; EMD subsets / EMD_equal resampling n = {int(emd_points)}, seed {emd_seed}")
        for metric, file in CDF_FIGURES.items():
            drawn.append(plot_cdfs(cdf_panels(shown, metric), dest / "figures" / file,
                                   title=f"CDF of the per-frame {CDF_METRICS[metric]} ({split} split)",
                                   xlabel=_AXIS[metric], footer=footer))
        notes = {n: {f.key: "empty prediction" if f.empty else f"CD {f.chamfer:.3f} m" for f in r.frames}
                 for n, r in shown.items()}
        for view in comparison_views(data, split, folder_of, notes=notes, items=sorted(common)):
            drawn.append(plot_cloud_comparison(view, dest / "figures" / f"{_file_name(view.scene)}.png"))
    return PointEvaluation(reports, folder_of, comparison, tuple(drawn), compared, differ, tuple(reused))
