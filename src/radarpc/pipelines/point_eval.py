"""Scoring prediction folders against a ColoRadar split: each method's CD / EMD per scene, the
methods side by side, and a figure per scene (``radarpc evaluate-points``).

For each folder (:mod:`radarpc.eval.predictions`): its ``index.json`` must name the dataset root
and split (unless ``force``); every frame's cloud is scored against the reader's LiDAR cropped
to the frustum (:func:`radarpc.eval.pointsets.evaluate_clouds`) and the report written into the
folder (``metrics.json``, ``metrics.md``). With several folders the per-scene table of all
(:func:`radarpc.eval.comparison.comparison_markdown`) is written to ``out/comparison.md`` and
``comparison.json``; with ``figures``, one frame per scene is drawn with the radar cube, the
truth and every method's cloud (:func:`radarpc.viz.plot_cloud_comparison`) as
``out/figures/{scene}.png``. ``out`` defaults to the first folder.
"""
from __future__ import annotations

import json
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

from radarpc.data.coloradar import ColoRadar, scene_of_run
from radarpc.eval.comparison import comparison_dict, comparison_markdown
from radarpc.eval.pointsets import EMD_POINTS, EMD_SEED, PointSetReport, evaluate_clouds
from radarpc.eval.predictions import INDEX_FILE, check_index, prediction_pairs
from radarpc.io import DataFileError, atomic_write
from radarpc.pipelines.frames import comparison_views

__all__ = ["PointEvaluation", "method_names", "evaluate_folders"]


@dataclass(frozen=True)
class PointEvaluation:
    """What :func:`evaluate_folders` wrote."""

    reports: dict[str, PointSetReport]      # by method name, in the order of the folders
    folders: dict[str, Path]                # method name -> its prediction folder
    comparison: Path | None                 # comparison.md (several folders), else None
    figures: tuple[Path, ...]               # one per scene (with figures)


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


def evaluate_folders(folders: Sequence[str | os.PathLike], data: str | os.PathLike, split: str, *,
                     emd_points: int = EMD_POINTS, emd_seed: int = EMD_SEED, force: bool = False,
                     figures: bool = False, out: str | os.PathLike | None = None,
                     progress: bool = True) -> PointEvaluation:
    """Score each prediction folder, compare them, draw a frame per scene (module docstring).

    Raises
    ------
    radarpc.io.DataFileError
        A folder is missing, its index is missing or unreadable (without ``force``), or a cloud is
        missing, malformed or empty.
    ValueError
        An index names another root or split (without ``force``), the split has no frame, a bad
        ``emd_points``, or the same folder twice.
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
    reports: dict[str, PointSetReport] = {}
    for name, p in zip(names, paths):
        report = evaluate_clouds(prediction_pairs(ds, p), scene_of_run, emd_points=emd_points, emd_seed=emd_seed,
                                 progress=progress)
        report.extra = {"pred_dir": str(p), "method": name, "data": str(Path(data).resolve()), "split": split,
                        "index_checked": not force}
        report.write(p / "metrics.json", p / "metrics.md")
        reports[name] = report
    dest = Path(out) if out is not None else paths[0]
    folder_of = dict(zip(names, paths))
    comparison = None
    if len(paths) > 1:
        comparison = dest / "comparison.md"
        with atomic_write(comparison, "w") as f:
            f.write(comparison_markdown(reports))
        with atomic_write(dest / "comparison.json", "w") as f:
            json.dump({"data": str(Path(data).resolve()), "split": split,
                       **comparison_dict(reports, {n: str(p) for n, p in folder_of.items()})}, f, indent=1)
    drawn: list[Path] = []
    if figures:
        from radarpc.viz import plot_cloud_comparison

        notes = {n: {(f.run, f.frame): f"CD {f.chamfer:.3f} m" for f in r.frames} for n, r in reports.items()}
        for view in comparison_views(data, split, folder_of, notes=notes):
            drawn.append(plot_cloud_comparison(view, dest / "figures" / f"{_file_name(view.scene)}.png"))
    return PointEvaluation(reports, folder_of, comparison, tuple(drawn))
