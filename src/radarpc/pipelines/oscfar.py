"""OS-CFAR predictions for a ColoRadar split: tune (or reuse) the parameters, then one cloud per frame.

Fills a prediction folder (:mod:`radarpc.eval.predictions` for the layout):

* ``config.yaml`` -- the OS-CFAR parameters used: given (``config``), reused from the folder, or
  tuned on ``tune_split`` by :func:`radarpc.rald.oscfar_baseline.tune_oscfar`;
* ``tuning.json`` -- mean Chamfer distance of every candidate of the grid search (when tuned);
* ``{run}/{frame:06d}.npy`` and ``index.json``.

Ownership and resume: the folder is locked for the whole job (:func:`radarpc.runs.locked_output`;
a second writer is refused) and temp files of a killed job are removed. ``config.yaml`` is the
run's key: a rerun keeps it (unless a config is given or ``retune``) and keeps the frames already
written with it; a rerun with another config rewrites every frame. Every file is written
atomically, so an interrupted job resumes to the same files (the frame loop is
:func:`radarpc.pipelines.predictions.fill_predictions`, shared with RaLD's generation).
"""
from __future__ import annotations

import json
import os
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import yaml

from radarpc.data.coloradar import ColoRadar
from radarpc.eval.predictions import INDEX_FILE
from radarpc.io import atomic_write
from radarpc.pipelines.predictions import fill_predictions
from radarpc.rald.oscfar_baseline import (
    CubeAxes,
    OSCFARConfig,
    TuningGrid,
    detect_points,
    load_config,
    save_config,
    tune_oscfar,
)
from radarpc.runs import locked_output, read_json, remove_temp_files

__all__ = ["OSCFARJob", "OSCFARRun", "QUICK_GRID", "predict_oscfar"]

QUICK_GRID = TuningGrid(windows=((9, 3, 3),), guards=((3, 1, 1),), ranks=(0.75,), taus_db=(4.0, 8.0, 12.0),
                        angle_bins=(None,))
"""A 3-candidate grid (for smoke tests)."""


@dataclass(frozen=True)
class OSCFARJob:
    """What to predict and where."""

    root: str | os.PathLike                 # ColoRadar root (real or simulated)
    out: str | os.PathLike                  # prediction folder
    split: str = "test"                     # frames to predict
    tune_split: str = "val"                 # split whose frames tune the parameters
    max_tune_frames: int = 32               # evenly spaced frames of the tuning split in the search
    config: str | os.PathLike | None = None  # use this config.yaml instead of tuning
    retune: bool = False                    # tune again even if OUT/config.yaml exists
    quick_tune: bool = False                # search QUICK_GRID instead of the full TuningGrid()
    overwrite: bool = False                 # replace a folder of another root or split, or a foreign one
    every: int = 1                          # every k-th paired frame of each run

    def __post_init__(self) -> None:
        if self.max_tune_frames < 1:
            raise ValueError(f"--max-tune-frames must be >= 1, got {self.max_tune_frames}")


@dataclass(frozen=True)
class OSCFARRun:
    """What :func:`predict_oscfar` did."""

    config: OSCFARConfig
    how: str              # "given (...)", "reused (...)" or "tuned on ... frames (mean CD ... m)"
    n_frames: int         # frames of the split (files in the folder)
    n_new: int            # of which computed by this job (the rest were kept from an earlier one)


def _tuning_frames(ds: ColoRadar, max_frames: int):
    n = len(ds)
    picks = np.unique(np.linspace(0, n - 1, min(n, max_frames)).round().astype(int)) if n else []
    for i in picks:
        yield ds.cube(int(i)).intensity_db, ds.lidar_points(int(i))


def _axes(ds: ColoRadar) -> CubeAxes:
    cube = ds.cube(0)
    return CubeAxes.from_radians(cube.range_m, cube.azimuth_rad, cube.elevation_rad)


def _choose_config(job: OSCFARJob, axes: CubeAxes, cfg_path: Path, progress: bool) -> tuple[OSCFARConfig, str]:
    if job.config is not None:
        return load_config(job.config), f"given ({job.config})"
    if cfg_path.is_file() and not job.retune:
        return load_config(cfg_path), f"reused ({cfg_path})"
    val = ColoRadar(job.root, job.tune_split, cube_size=None)
    if len(val) == 0:
        raise ValueError(f"tuning split {job.tune_split!r} of {job.root} has no paired frame; "
                         "pass --tune-split with another split or --config FILE")
    grid = QUICK_GRID if job.quick_tune else TuningGrid()
    res = tune_oscfar(_tuning_frames(val, job.max_tune_frames), axes, grid, progress=progress)
    table = [{"config": c.to_dict(), "chamfer_m": cd, "points_per_frame": npts} for c, cd, npts in res.table]
    with atomic_write(Path(job.out) / "tuning.json", "w") as f:
        json.dump({"split": job.tune_split, "frames": res.n_frames, "best": res.best.to_dict(),
                   "best_chamfer_m": res.best_chamfer, "candidates": table}, f, indent=1)
    return res.best, f"tuned on {res.n_frames} {job.tune_split} frames (mean CD {res.best_chamfer:.3f} m)"


def _made_from(out: Path) -> tuple[str | None, str | None, int | None]:
    """``(resolved root, split, every)`` the predictions in ``out`` were made from (index.json, else
    the provenance of config.yaml); ``(None, None, None)`` when neither says. A record without
    ``every`` predates the option: every frame (1)."""
    idx = read_json(out / INDEX_FILE)
    if isinstance(idx, dict) and "root" in idx:
        return str(idx["root"]), idx.get("split"), int(idx.get("every", 1))
    try:
        doc = yaml.safe_load((out / "config.yaml").read_text())
        prov = doc["provenance"]
        return str(Path(prov["root"]).resolve()), prov.get("split"), int(prov.get("every", 1))
    except (OSError, yaml.YAMLError, KeyError, TypeError, ValueError):
        return None, None, None


def _own_folder(out: Path, job: OSCFARJob) -> None:
    """Refuse (unless ``job.overwrite``) a non-empty folder that is not a prediction folder of this
    root, split and frame subset (``every``): its clouds would be mixed with this job's. With ``overwrite`` the earlier
    predictions (config, tuning, index and run folders of clouds) are removed first."""
    entries = [p for p in out.iterdir()] if out.is_dir() else []
    if not entries:
        return
    root, split, every = _made_from(out)
    want = str(Path(job.root).resolve())
    if root == want and split == job.split and every == job.every:
        return
    foreign = [p for p in entries if not (p.name in ("config.yaml", "tuning.json", INDEX_FILE) or (
        p.is_dir() and all(f.suffix == ".npy" for f in p.iterdir())))]
    if root is None and not foreign:
        return                              # a run killed before it recorded its root: resume it
    if not job.overwrite:
        what = ("is not empty and is not a prediction folder" if root is None else
                f"holds predictions of {root} (split {split}, every {every}), not of {want} (split {job.split}, "
                f"every {job.every})")
        raise FileExistsError(f"{out} {what}; pass --overwrite (overwrite=True) to replace them, or choose "
                              f"another --out")
    for p in entries:
        if p.name in ("config.yaml", "tuning.json", INDEX_FILE):
            p.unlink()
        elif p.is_dir() and not p.is_symlink() and all(f.suffix == ".npy" for f in p.iterdir()):
            shutil.rmtree(p)                # a run folder of clouds


def predict_oscfar(job: OSCFARJob, *, progress: bool = True,
                   on_config: Callable[[OSCFARConfig, str], None] | None = None) -> OSCFARRun:
    """Run ``job`` (see the module docstring).

    Parameters
    ----------
    job : OSCFARJob
    progress : bool
        tqdm bars for the tuning and the predictions.
    on_config : callable, optional
        Called with ``(config, how)`` once the parameters are chosen, before the predictions.

    Raises
    ------
    ValueError
        The split (or tuning split) has no paired radar/LiDAR frame.
    radarpc.runs.OutputBusyError
        Another process writes the same prediction folder.
    FileExistsError
        The folder holds predictions of another root or split, or other files, without
        ``job.overwrite``.
    PermissionError
        The prediction folder cannot be written.
    """
    out = Path(job.out)
    cfg_path = out / "config.yaml"
    ds = ColoRadar(job.root, job.split, cube_size=None, every=job.every)
    if len(ds) == 0:
        raise ValueError(f"split {job.split!r} of {job.root} has no paired radar/LiDAR frame")
    if out.exists() and not out.is_dir():
        raise NotADirectoryError(f"the prediction folder {out} exists and is not a folder")
    with locked_output(out, "prediction folder"):
        remove_temp_files(out)
        _own_folder(out, job)
        axes = _axes(ds)
        cfg, how = _choose_config(job, axes, cfg_path, progress)
        same = cfg_path.is_file() and load_config(cfg_path) == cfg
        if not same:
            save_config(cfg_path, cfg, method="os-cfar", root=str(job.root), split=job.split, every=ds.every,
                        tune_split=job.tune_split, how=how)
        if on_config is not None:
            on_config(cfg, how)
        res = fill_predictions(
            out, ds, lambda i: detect_points(ds.cube(i).intensity_db, axes, cfg).cpu().numpy(),
            keep=lambda i, path: same, method="os-cfar", root=job.root, split=job.split,
            index_extra={"every": ds.every},
            progress=progress, desc=f"OS-CFAR {job.split}")
    return OSCFARRun(cfg, how, res.n_frames, res.n_new)
