"""A radar-to-occupancy network's clouds for a ColoRadar split (the learned baseline of RaLD's
Table 2): one cloud per paired radar frame, resumably, in the layout RaLD's generation writes.

Fills a prediction folder (:mod:`radarpc.eval.predictions` for the layout) through the frame loop
every method shares (:func:`radarpc.pipelines.predictions.fill_predictions`):

* ``prediction.json`` -- the job's key: method, the dataset root (resolved) and split, the cloud
  settings (:class:`CloudConfig`), the occupancy grid and the caller's model identity (the run
  folder, ``model.run``, a locator that is recorded but not compared, and a digest of its weights);
* ``{run}/{frame:06d}.npy`` -- float32 ``(N, 3)`` Cartesian points in the single-chip radar frame,
  metres: one point per cell of the grid whose occupancy probability ``sigma(logit)`` exceeds
  ``threshold``, at the cell's centre, or with ``jitter`` uniform inside the cell in (range,
  azimuth, elevation), drawn from the frame's own seed (:func:`radarpc.rald.generate.frame_seed`
  of ``seed``, the run and the frame: the same points whatever frames are predicted, and in what
  order);
* ``prediction.csv`` -- one row per frame: run, scene, frame, file, points, ``empty``, the
  seconds of the network's forward pass;
* ``index.json`` -- the frames, the settings, the model and the list ``empty_frames``.

Ownership and resume as RaLD's generation (:class:`radarpc.runs.RunFolder`): the folder is locked
for the job, a rerun with the same key keeps every frame already written with its record, a
folder holding anything else is refused unless ``overwrite``. A frame with no cell above the
threshold is written as a ``(0, 3)`` cloud, flagged and reported, never silently.
"""
from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Mapping

import numpy as np
import torch

from radarpc.config import to_dict
from radarpc.data.coloradar import ColoRadar
from radarpc.dsp.tdm import RadarCube
from radarpc.pipelines.predictions import FilledFolder, FramePrediction, fill_predictions
from radarpc.pipelines.rald_generate import grid_key
from radarpc.rald.frustum import FrustumGrid, polar_to_cartesian
from radarpc.rald.generate import frame_seed
from radarpc.runs import RunFolder

__all__ = ["PREDICTION_FILE", "RECORDS_FILE", "CloudConfig", "OccupancyJob", "OccupancyPredictions",
           "occupancy_points", "predict_occupancy_clouds"]

PREDICTION_FILE = "prediction.json"
"""The folder's key (settings of the job)."""
RECORDS_FILE = "prediction.csv"
"""Per frame: points, empty flag, seconds of the forward pass."""


@dataclass(frozen=True)
class CloudConfig:
    """How occupancy probabilities become a cloud."""

    threshold: float = 0.5      # a cell is a point when sigma(logit) > threshold
    jitter: bool = False        # False: the cell's centre; True: uniform in the cell (range, azimuth, elevation)
    seed: int = 0               # base seed of the jitter (per frame: frame_seed(seed, run, frame))

    def __post_init__(self) -> None:
        if not (math.isfinite(self.threshold) and 0.0 <= self.threshold < 1.0):
            raise ValueError(f"threshold must be a probability in [0, 1), got {self.threshold}")
        if not isinstance(self.jitter, bool):
            raise ValueError(f"jitter must be true or false, got {self.jitter!r}")
        if isinstance(self.seed, bool) or int(self.seed) != self.seed or self.seed < 0:
            raise ValueError(f"seed must be an integer >= 0, got {self.seed!r}")


@dataclass(frozen=True)
class OccupancyJob:
    """What to predict and where."""

    root: str | os.PathLike                                  # ColoRadar root (real or simulated)
    out: str | os.PathLike                                   # prediction folder
    split: str = "test"                                      # frames to predict
    cloud: CloudConfig = field(default_factory=CloudConfig)
    overwrite: bool = False                                  # replace a folder holding anything else
    every: int = 1                                           # every k-th paired frame of each run


@dataclass(frozen=True)
class OccupancyPredictions:
    """What :func:`predict_occupancy_clouds` did."""

    out: Path
    n_frames: int                                  # clouds of the split (files in the folder)
    n_new: int                                     # of which predicted by this job
    empty: tuple[tuple[str, int], ...]             # (run, frame) of the clouds without a point
    warnings: tuple[str, ...]                      # this job's warnings, one line per empty frame
    seconds: float | None                          # mean seconds of a forward pass over this job's frames


def occupancy_points(grid: FrustumGrid, prob: torch.Tensor, threshold: float = 0.5, *, jitter: bool = False,
                     generator: torch.Generator | None = None) -> torch.Tensor:
    """The cloud of an occupancy probability grid: one point per cell with ``prob > threshold``.

    A cell ``(i, j, k)`` spans ``[lo + (i, j, k) cell, lo + (i + 1, j + 1, k + 1) cell)`` in (range,
    azimuth, elevation); its point is ``lo + (ijk + u) cell`` with ``u = 1/2`` (the centre) or,
    with ``jitter``, ``u`` uniform in ``[0, 1)^3`` from ``generator``, then taken to Cartesian
    coordinates (:func:`radarpc.rald.frustum.polar_to_cartesian`).

    Parameters
    ----------
    grid : FrustumGrid
    prob : torch.Tensor, ``grid.shape``
    threshold : float
    jitter : bool
    generator : torch.Generator, optional
        CPU generator of the jitter.

    Returns
    -------
    torch.Tensor, float32 ``(N, 3)``
        Radar frame, metres; cells in the order of their linear index ``(i n_az + j) n_el + k``.

    Raises
    ------
    ValueError
        ``prob`` is not of the grid's shape.
    """
    if tuple(prob.shape) != grid.shape:
        raise ValueError(f"occupancy_points: probabilities of shape {tuple(prob.shape)} for a grid of {grid.shape}")
    ijk = torch.nonzero(prob.detach().cpu() > threshold).to(torch.float64)           # (N, 3), row-major order
    lo, _, cell = grid._tensors("cpu", torch.float64)
    u = torch.rand(ijk.shape, generator=generator, dtype=torch.float64) if jitter else torch.full_like(ijk, 0.5)
    return polar_to_cartesian(lo + (ijk + u) * cell).to(torch.float32)               # (N, 3)


def predict_occupancy_clouds(job: OccupancyJob, model: torch.nn.Module, *,
                             model_input: Callable[[RadarCube], torch.Tensor], grid: FrustumGrid,
                             method: str = "rpdnet", model_id: Mapping[str, object] | None = None,
                             progress: bool = True,
                             on_warning: Callable[[str], None] | None = None) -> OccupancyPredictions:
    """Run ``job`` (see the module docstring).

    Parameters
    ----------
    job : OccupancyJob
    model : torch.nn.Module
        ``model(x (1, R, A, E)) -> logits (1, *grid.shape)``, on the device to run on; put in
        evaluation mode here.
    model_input : callable
        ``model_input(cube)``: the network's input ``(R, A, E)`` of a frame's RaLD cube.
    grid : FrustumGrid
        The grid the logits stand for.
    method : str
        The method's name in ``index.json``.
    model_id : mapping, optional
        JSON-able identity of the weights, part of the key.
    progress : bool
    on_warning : callable, optional
        Called with each empty frame's warning line as it happens.

    Raises
    ------
    ValueError
        The split has no paired radar/LiDAR frame.
    radarpc.runs.RunMismatchError
        The folder holds anything but these predictions, without ``overwrite``.
    radarpc.runs.OutputBusyError
        Another process writes the folder.
    """
    ds = ColoRadar(job.root, job.split, cube_size=None, every=job.every)
    if len(ds) == 0:
        raise ValueError(f"split {job.split!r} of {job.root} has no paired radar/LiDAR frame")
    key = {"method": method, "root": str(Path(job.root).resolve()), "split": job.split, "every": ds.every,
           "cloud": to_dict(job.cloud),
           "grid": grid_key(grid), "model": dict(model_id or {})}
    model.eval()
    device = next(model.parameters()).device
    seconds: list[float] = []

    @torch.no_grad()
    def predict(i: int) -> FramePrediction:
        k, ri, _ = ds.index[i]
        run = ds.runs[k]
        x = model_input(ds.cube(i))[None].to(device)                                 # (1, R, A, E)
        t = time.perf_counter()
        prob = torch.sigmoid(model(x)[0].float())                                    # (n_r, n_az, n_el)
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        seconds.append(time.perf_counter() - t)
        g = torch.Generator().manual_seed(frame_seed(job.cloud.seed, run.name, ri))
        pts = occupancy_points(grid, prob, job.cloud.threshold, jitter=job.cloud.jitter, generator=g).numpy()
        warning = None if len(pts) else f"no cell above the threshold {job.cloud.threshold}: an empty cloud"
        return FramePrediction(pts, {"seconds_forward": seconds[-1]}, warning)

    def extra(res: FilledFolder) -> dict:
        return {**{k: key[k] for k in ("every", "cloud", "grid", "model")},
                "empty_frames": [{"run": r, "frame": f} for r, f in res.empty]}

    folder = RunFolder(job.out, {PREDICTION_FILE: key}, what="prediction folder", locators=("model.run",))
    with folder.start(overwrite=job.overwrite) as folder:
        res = fill_predictions(folder.path, ds, predict, keep=lambda i, path: folder.done(path), method=method,
                               root=job.root, split=job.split, index_extra=extra, records=RECORDS_FILE,
                               progress=progress, desc=f"{method} {job.split}", on_warning=on_warning)
    return OccupancyPredictions(Path(job.out), res.n_frames, res.n_new, res.empty, res.warnings,
                                float(np.mean(seconds)) if seconds else None)
