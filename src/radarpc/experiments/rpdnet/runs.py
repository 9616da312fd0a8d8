"""The learned baseline's run folders: their key, and a trained run's weights loaded and checked.

A run folder has the format of every radarpc training run (:func:`radarpc.training.loop.fit`):
``run.json`` (the key), ``config.yaml`` (the resolved config), ``checkpoints/last.safetensors``,
``best.safetensors`` (the network's state dict, with the run key in its ``info["run"]``) and
``log.csv``. The key, without the ``"software"`` record ``fit`` adds, is
``{"experiment": <OccupancyExperiment as a dict>, "data": <absolute root>}`` (:func:`run_key`).

:func:`load_occupancy_run` checks what RaLD's loaders check: the folder holds a run of this
baseline, the weights' run key is the folder's (weights copied in from another run are refused),
no weight is NaN or infinite, the weights fit the config's model; and it reports whether the run
had finished (:func:`~radarpc.training.loop.training_status`).
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import torch

from radarpc.config import to_dict
from radarpc.experiments.rpdnet.config import STAGE, OccupancyExperiment, canonical_key, experiment_from_dict, \
    is_occupancy_config
from radarpc.io import DataFileError
from radarpc.models.rpdnet import RPDNet
from radarpc.rald.frustum import FrustumGrid
from radarpc.runs import read_json
from radarpc.training.checkpoint import load_model_state, load_weights
from radarpc.training.loop import BEST_WEIGHTS, training_status

__all__ = ["OccupancyRun", "run_key", "is_occupancy_run", "load_occupancy_run"]


def run_key(cfg: OccupancyExperiment, data: str | os.PathLike) -> dict:
    """The run key: the whole config and the absolute path of its root."""
    return {"experiment": to_dict(cfg), "data": str(Path(data).resolve())}


def _comparable(key: object) -> object:
    if not isinstance(key, dict):
        return key
    return {k: v for k, v in canonical_key(key, num_workers=0).items() if k != "software"}


def is_occupancy_run(run_dir: str | os.PathLike) -> bool:
    """Whether ``run_dir`` holds a run of this baseline (its ``run.json`` names ``stage: occupancy``);
    False for anything else (another kind of run, no run, an unreadable key)."""
    key = read_json(Path(run_dir) / "run.json") if Path(run_dir).is_dir() else None
    return isinstance(key, dict) and is_occupancy_config(key.get("experiment"))


@dataclass(frozen=True)
class OccupancyRun:
    """A run loaded by :func:`load_occupancy_run`.

    Attributes
    ----------
    run_dir : Path
    config : OccupancyExperiment
    model : RPDNet
        The best weights, in eval mode, on the requested device.
    key : dict
        ``run.json`` as stored.
    status : dict
        :func:`~radarpc.training.loop.training_status` (``status["finished"]`` False: steps left).
    """

    run_dir: Path
    config: OccupancyExperiment
    model: RPDNet
    key: dict
    status: dict

    @property
    def finished(self) -> bool | None:
        return self.status["finished"]

    @property
    def grid(self) -> FrustumGrid:
        """The target grid the logits stand for (over AWR1843's field of view)."""
        return self.config.target.grid()


def load_occupancy_run(run_dir: str | os.PathLike, *, device: torch.device | str = "cpu") -> OccupancyRun:
    """The baseline run in ``run_dir`` with its best weights.

    Raises
    ------
    FileNotFoundError
        No ``run.json``, or no best weights yet.
    DataFileError
        ``run.json`` is not this baseline's key; ``best.safetensors`` is not a weights file, was
        written under another run key, holds non-finite values or does not fit the model.
    """
    folder = Path(run_dir)
    path = folder / "run.json"
    if folder.is_file():
        raise DataFileError(folder, "is a file; expected a run folder (run.json, best.safetensors, ...)")
    key = read_json(path)
    if key is None:
        raise FileNotFoundError(f"{folder}: no training run here (no run.json)")
    if not (isinstance(key, dict) and is_occupancy_config(key.get("experiment"))):
        raise DataFileError(path, f"not a run of the occupancy baseline (its experiment names no 'stage: {STAGE}')")
    cfg = experiment_from_dict(key["experiment"], where=str(path))
    best = folder / BEST_WEIGHTS
    if best.is_dir():
        raise DataFileError(best, "is a folder; expected the run's best weights (a safetensors file)")
    if not best.is_file():
        raise FileNotFoundError(f"{folder}: no {BEST_WEIGHTS} yet (the run has not validated once)")
    state, info = load_weights(best)
    if _comparable(info.get("run")) != _comparable(key):
        raise DataFileError(best, f"these weights were trained under another run key than {path} (another run's "
                                  f"weights copied in?); use them in their own run folder")
    model = cfg.build_model()
    load_model_state(model, state, best, f"model {cfg.model.variant!r} of {path}")
    return OccupancyRun(folder, cfg, model.to(device).eval(), key, training_status(folder))
