"""A trained baseline run's clouds of a ColoRadar split: the run's network, input and grid handed to
:func:`radarpc.pipelines.occupancy_clouds.predict_occupancy_clouds` (what ``radarpc generate RUN``
calls for a run of this baseline).

From the run (:func:`radarpc.experiments.rpdnet.runs.load_occupancy_run`) the prediction takes the
network's best weights; its input, the frame's RaLD cube as the run's training read it
(:func:`radarpc.data.coloradar.rald_intensity` with the run's ``radar.max_intensity_db`` and the
model's ``radar_shape``, as :class:`~radarpc.experiments.rpdnet.task.OccupancyFrames`); the target
grid its logits stand for; and the identity in the folder's key: the SHA-256 of its
``best.safetensors``, and the run folder (resolved) recorded but not compared.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Callable

import torch

from radarpc.data.coloradar import rald_intensity
from radarpc.experiments.rpdnet.runs import OccupancyRun, load_occupancy_run
from radarpc.pipelines.occupancy_clouds import CloudConfig, OccupancyJob, OccupancyPredictions, \
    predict_occupancy_clouds
from radarpc.pipelines.rald_generate import file_digests
from radarpc.training.loop import BEST_WEIGHTS

__all__ = ["model_input", "predict_run"]


def model_input(run: OccupancyRun) -> Callable:
    """``cube -> (R, A, E)`` tensor: the network's input of a frame's RaLD cube, as its training read it."""
    shape, max_db = run.model.cfg.radar_shape, run.config.radar.max_intensity_db
    return lambda cube: rald_intensity(cube, shape, max_db=max_db)


def predict_run(run_dir: str | os.PathLike, out: str | os.PathLike, *, data: str | os.PathLike | None = None,
                split: str = "test", every: int = 1, cloud: CloudConfig = CloudConfig(), device: str | None = None,
                allow_unfinished: bool = False, overwrite: bool = False, progress: bool = True,
                on_warning: Callable[[str], None] | None = None,
                notice: Callable[[str], None] | None = None) -> OccupancyPredictions:
    """One cloud per paired frame of ``split`` from the baseline run ``run_dir`` into the prediction
    folder ``out`` (resumable).

    Parameters
    ----------
    run_dir : path-like
        A run folder of ``radarpc train`` with a ``stage: occupancy`` config.
    out : path-like
    data : path-like, optional
        The ColoRadar root; default the root the run was trained on.
    split : str
    every : int
        Predict every ``every``-th paired frame of each run (1: all).
    cloud : CloudConfig
        Threshold, jitter and its seed.
    device : str, optional
        Default: a GPU if any, else the CPU.
    allow_unfinished : bool
        Predict with the best weights of a run that has not finished (refused otherwise).
    overwrite : bool
    progress : bool
    on_warning, notice : callable, optional
        Each empty frame's warning line; one-line notices (an unfinished run predicting).

    Raises
    ------
    FileNotFoundError, DataFileError
        ``run_dir`` is not a loadable baseline run.
    ValueError
        An unfinished run without ``allow_unfinished``; a split without paired frames.
    RunMismatchError
        ``out`` holds anything else, without ``overwrite``.
    PermissionError
        ``out`` cannot be written (checked first).
    """
    from radarpc.machine import check_device
    from radarpc.runs import check_writable

    check_writable(out, "prediction folder")
    dev = check_device(device, "--device") if device else torch.device("cuda" if torch.cuda.is_available() else "cpu")
    run_dir = Path(run_dir)
    run = load_occupancy_run(run_dir, device=dev)
    if run.finished is False:
        where = f"step {run.status['steps_done']}, best weights of step {run.status['weights_step']}"
        if not allow_unfinished:
            raise ValueError(f"{run_dir}: the run has not finished ({where}); finish it with the same `radarpc train` "
                             f"command, or pass --allow-unfinished to predict with its best weights so far")
        if notice is not None:
            notice(f"{run_dir}: the run has not finished ({where}); predicting with its best weights so far")
    job = OccupancyJob(data if data is not None else run.key["data"], out, split, cloud=cloud,
                       overwrite=overwrite, every=every)
    identity = {"run": str(run_dir.resolve()), "weights": file_digests([run_dir / BEST_WEIGHTS])}
    return predict_occupancy_clouds(job, run.model, model_input=model_input(run), grid=run.grid, method="rpdnet",
                                    model_id=identity, progress=progress, on_warning=on_warning)
