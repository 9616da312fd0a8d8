"""RaLD's run folders: their keys, and a trained run's weights loaded and checked.

A RaLD run folder has the detection experiment's format (:func:`radarpc.training.loop.fit`):
``run.json`` (the key), ``config.yaml`` (the resolved config), ``checkpoints/last.safetensors``,
``best.safetensors`` and ``log.csv``. The keys (without the ``"software"`` record ``fit`` adds):

* stage 1 (:func:`autoencoder_run_key`): ``{"experiment": <AutoencoderExperiment as a dict>,
  "data": <absolute root>}``;
* stage 2 (:func:`diffusion_run_key`): ``{"experiment": <DiffusionExperiment>, "data": <absolute
  root>, "ae": {"path": <stage-1 folder>, "run": <its key without "software" and without the paths of
  the runs it builds on>, "weights_sha256":
  <sha256 of its best.safetensors>}}`` (:func:`ae_reference`). ``ae.path`` is relative to the
  stage-2 folder when the stage-1 folder lies inside it (an imported official run is written as
  ``OUT/ae`` and ``OUT`` with ``"path": "ae"``), else absolute; a relative path is read against the
  stage-2 folder (:func:`resolve_ae_dir`). The path is where the stage-1 run is, not what it is
  (its key and weights' digest say that): it is not compared, and a resumed stage-2 run records
  the stage-1 folder's current place (:data:`REFERENCE_LOCATORS`), so study folders can move and
  stage runs be shared between studies.
* a fine-tuned run of either stage (``radarpc train --init RUN``) adds ``"init"``: the run its
  weights started from, in the same form as ``"ae"`` (:func:`init_reference`).

An imported run (:func:`radarpc.experiments.rald.official.import_official_rald`) has the same keys
plus ``"imported"`` (the official files, their SHA-256 and which weights were taken); its
``"data"`` is the root given to the import, or None (the weights were trained elsewhere).

Weights: a stage-1 ``best.safetensors`` holds the :class:`~radarpc.models.vecset.VecSetAutoencoder`'s
state dict; a stage-2 one holds :class:`~radarpc.experiments.rald.task.RaldStage2`'s, i.e.
``autoencoder.<key>`` and ``dit.<key>`` (:class:`~radarpc.models.latent_dit.LatentDiT`): the
frozen autoencoder the diffusion model was trained against travels with it. Both carry the run
key in their ``info["run"]`` (:func:`radarpc.training.checkpoint.save_weights`).

Coordinates: an autoencoder reads and decodes points in the coordinates its config's ``data``
describes (:class:`~radarpc.experiments.rald.config.LidarData`): radar-frame metres go in with
``data.to_model(xyz, run.grid)`` and decoded query coordinates come back with
``data.to_radar(u, run.grid)`` (the official checkpoints' frame is mirrored left-right and their
range ends at 15.8 m: ``max_range_m: 15.8``, ``mirror_azimuth: true``).

:func:`load_rald_ae` and :func:`load_rald` check what the detection experiment's ``load_trained``
does: the folder holds a run of that stage, the weights' run key is the folder's (weights copied in
from another run are refused), no weight is NaN or infinite, the weights fit the config's model;
and they report whether the run had finished (:func:`training_status`).
"""
from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass
from pathlib import Path

import torch

from radarpc.config import to_dict
from radarpc.experiments.rald.config import (RUN_REFERENCES, AutoencoderExperiment, DiffusionExperiment,
                                             canonical_key, experiment_from_dict, without_locators)
from radarpc.experiments.rald.task import RaldStage2
from radarpc.io import DataFileError
from radarpc.models.latent_dit import LatentDiT
from radarpc.models.vecset import VecSetAutoencoder
from radarpc.rald.frustum import FrustumGrid
from radarpc.rald.voxels import CartesianGrid
from radarpc.runs import read_json
from radarpc.training.checkpoint import load_model_state, load_weights
from radarpc.training.loop import BEST_WEIGHTS, training_status

__all__ = ["AutoencoderRun", "RaldRun", "rald_stage", "load_rald_ae", "load_rald", "autoencoder_run_key",
           "diffusion_run_key", "ae_reference", "init_reference", "resolve_ae_dir", "file_sha256", "AE_STATUSES",
           "REFERENCE_LOCATORS"]

REFERENCE_LOCATORS = tuple(f"{ref}.path" for ref in RUN_REFERENCES)
"""The keys of a run key that locate the runs it builds on (compared through their key and digest)."""

AE_STATUSES = ("same", "changed", "missing")
"""What :attr:`RaldRun.ae_status` says of the stage-1 folder a stage-2 run names."""


# ---- keys ---------------------------------------------------------------------------------------------

def _root(data: str | os.PathLike | None) -> str | None:
    return None if data is None else str(Path(data).resolve())


def autoencoder_run_key(cfg: AutoencoderExperiment, data: str | os.PathLike | None) -> dict:
    """Stage 1's run key: the whole config and the absolute path of its root (None: an imported
    run that names no root)."""
    return {"experiment": to_dict(cfg), "data": _root(data)}


def file_sha256(path: str | os.PathLike) -> str:
    """Hex SHA-256 of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def ae_reference(ae_dir: str | os.PathLike, out: str | os.PathLike, *, what: str = "stage-1") -> dict:
    """The ``"ae"`` entry of a stage-2 run key for the stage-1 run folder ``ae_dir``, as the
    stage-2 run folder ``out`` records it: ``{"path", "run", "weights_sha256"}`` (module docstring).
    The ``"init"`` entry of a fine-tuned run (:func:`init_reference`) has the same form.

    Raises
    ------
    FileNotFoundError
        ``ae_dir`` holds no run key or no best weights.
    """
    ae_dir, out = Path(ae_dir), Path(out)
    key = read_json(ae_dir / "run.json")
    if not isinstance(key, dict):
        raise FileNotFoundError(f"{ae_dir}: no {what} run here (no readable run.json)")
    best = ae_dir / BEST_WEIGHTS
    if not best.is_file():
        raise FileNotFoundError(f"{ae_dir}: no {BEST_WEIGHTS} yet (the {what} run has not validated once)")
    a, o = ae_dir.resolve(), out.resolve()
    path = a.relative_to(o).as_posix() if a.is_relative_to(o) and a != o else str(a)
    # the run as its key says, not where it and the runs under it lie (they may move)
    return {"path": path, "run": without_locators({k: v for k, v in key.items() if k != "software"}),
            "weights_sha256": file_sha256(best)}


def init_reference(init_dir: str | os.PathLike, out: str | os.PathLike) -> dict:
    """The ``"init"`` entry of a fine-tuned run's key: the run folder ``init_dir`` whose best weights
    it started from, as :func:`ae_reference` records a stage-1 run (path, key, weights' SHA-256)."""
    return ae_reference(init_dir, out, what="initial")


def resolve_ae_dir(run_dir: str | os.PathLike, path: str) -> Path:
    """The stage-1 run folder a stage-2 run's key names: ``path`` itself when absolute, else
    ``path`` relative to the stage-2 ``run_dir``."""
    p = Path(path)
    return p if p.is_absolute() else Path(run_dir) / p


def diffusion_run_key(cfg: DiffusionExperiment, data: str | os.PathLike | None, ae: dict) -> dict:
    """Stage 2's run key: the config, the absolute root (None: an imported run that names no root)
    and the stage-1 reference (:func:`ae_reference`)."""
    return {"experiment": to_dict(cfg), "data": _root(data), "ae": ae}


# ---- loading ------------------------------------------------------------------------------------------

def _comparable(key: object) -> object:
    """A run key as two copies of one run compare it: through the config types, without the
    software record, the loader processes and where the runs it builds on lie."""
    if not isinstance(key, dict):
        return key
    return without_locators({k: v for k, v in canonical_key(key, num_workers=0).items() if k != "software"})


def _read_rald_key(folder: Path):
    path = folder / "run.json"
    if folder.is_file():
        raise DataFileError(folder, "is a file; expected a RaLD run folder (run.json, best.safetensors, ...)")
    key = read_json(path)
    if key is None:
        raise FileNotFoundError(f"{folder}: no RaLD training run here (no run.json)")
    if not isinstance(key, dict) or not isinstance(key.get("experiment"), dict):
        raise DataFileError(path, "not a radarpc training run key (no 'experiment')")
    if "stage" not in key["experiment"]:
        raise DataFileError(path, "a detection training run, not a RaLD one (its experiment names no 'stage')")
    return experiment_from_dict(key["experiment"], where=str(path)), key


def rald_stage(run_dir: str | os.PathLike) -> str:
    """The stage of the RaLD run in ``run_dir``, ``"autoencoder"`` or ``"diffusion"``, from its
    ``run.json`` alone (no weights read).

    Raises
    ------
    FileNotFoundError
        No ``run.json``.
    DataFileError
        ``run_dir`` is a file, or ``run.json`` is not a RaLD run key.
    """
    return _read_rald_key(Path(run_dir))[0].stage


def _read_key(folder: Path, stage: str):
    path = folder / "run.json"
    cfg, key = _read_rald_key(folder)
    if cfg.stage != stage:
        hint = ("its diffusion model and frozen autoencoder load with load_rald" if stage == "autoencoder"
                else "it is a stage-1 run; give the stage-2 run trained against it")
        raise DataFileError(path, f"a RaLD {cfg.stage} run, not {_a(stage)} run ({hint})")
    if stage == "diffusion":
        ae = key.get("ae")
        if not (isinstance(ae, dict) and isinstance(ae.get("path"), str) and isinstance(ae.get("run"), dict)):
            raise DataFileError(path, "a stage-2 key without its stage-1 reference ('ae' with 'path' and 'run')")
    return cfg, key


def _a(word: str) -> str:
    return f"{'an' if word[0] in 'aeiou' else 'a'} {word}"


def _load_best(folder: Path, key: dict, model: torch.nn.Module, what: str) -> None:
    best = folder / BEST_WEIGHTS
    if best.is_dir():
        raise DataFileError(best, "is a folder; expected the run's best weights (a safetensors file)")
    if not best.is_file():
        raise FileNotFoundError(f"{folder}: no {BEST_WEIGHTS} yet (the run has not validated once)")
    state, info = load_weights(best)
    if _comparable(info.get("run")) != _comparable(key):
        raise DataFileError(best, f"these weights were trained under another run key than {folder / 'run.json'} "
                                  f"(another run's weights copied in?); use them in their own run folder")
    load_model_state(model, state, best, what)


@dataclass(frozen=True)
class AutoencoderRun:
    """A stage-1 run loaded by :func:`load_rald_ae`.

    Attributes
    ----------
    run_dir : Path
    config : AutoencoderExperiment
    ae : VecSetAutoencoder
        The best weights, in eval mode, on the requested device.
    key : dict
        ``run.json`` as stored.
    status : dict
        :func:`training_status` (``status["finished"]`` False: the run had not finished).
    """

    run_dir: Path
    config: AutoencoderExperiment
    ae: VecSetAutoencoder
    key: dict
    status: dict

    @property
    def finished(self) -> bool | None:
        """True when the run finished, False when it had steps left, None for imported weights."""
        return self.status["finished"]

    @property
    def grid(self) -> FrustumGrid | CartesianGrid:
        """The occupancy grid the autoencoder's coordinates are normalised over."""
        return self.config.data.grid()


@dataclass(frozen=True)
class RaldRun:
    """A stage-2 run loaded by :func:`load_rald`: the diffusion model and the frozen autoencoder it
    was trained against.

    Attributes
    ----------
    run_dir : Path
    ae_dir : Path
        The stage-1 folder its key names (resolved against ``run_dir`` when relative).
    config : DiffusionExperiment
    ae_config : AutoencoderExperiment
        The stage-1 run's config (its ``data``: points per frame, partition, cell).
    ae : VecSetAutoencoder
        The autoencoder weights stored with the run (those the diffusion model was trained on),
        eval mode.
    dit : LatentDiT
        The diffusion model's best weights, eval mode.
    key : dict
        ``run.json`` as stored.
    status : dict
        :func:`training_status` of the stage-2 run.
    ae_status : str
        ``"same"``: ``ae_dir`` holds the recorded stage-1 run with the same weights; ``"changed"``:
        it holds another run or other weights now; ``"missing"``: no run there (the stored
        autoencoder is used either way).
    """

    run_dir: Path
    ae_dir: Path
    config: DiffusionExperiment
    ae_config: AutoencoderExperiment
    ae: VecSetAutoencoder
    dit: LatentDiT
    key: dict
    status: dict
    ae_status: str

    @property
    def finished(self) -> bool | None:
        """True when the stage-2 run finished, False when it had steps left, None for imported weights."""
        return self.status["finished"]

    @property
    def grid(self) -> FrustumGrid | CartesianGrid:
        """The occupancy grid of the autoencoder's coordinates (decoded queries live in it)."""
        return self.ae_config.data.grid()


def load_rald_ae(run_dir: str | os.PathLike, *, device: torch.device | str = "cpu") -> AutoencoderRun:
    """The stage-1 run in ``run_dir`` with its best weights.

    Raises
    ------
    FileNotFoundError
        No ``run.json``, or no best weights yet.
    DataFileError
        ``run.json`` is not a RaLD stage-1 key; ``best.safetensors`` is not a weights file, was
        written under another run key, holds non-finite values or does not fit the model.
    """
    folder = Path(run_dir)
    cfg, key = _read_key(folder, "autoencoder")
    model = cfg.build_model()
    _load_best(folder, key, model, f"autoencoder {cfg.model.variant!r} of {folder / 'run.json'}")
    return AutoencoderRun(folder, cfg, model.to(device).eval(), key, training_status(folder))


def load_rald(run_dir: str | os.PathLike, *, device: torch.device | str = "cpu") -> RaldRun:
    """The stage-2 run in ``run_dir`` with its best weights (diffusion model and autoencoder).

    Raises
    ------
    FileNotFoundError
        No ``run.json``, or no best weights yet.
    DataFileError
        ``run.json`` is not a RaLD stage-2 key or its stage-1 reference is unreadable;
        ``best.safetensors`` is not a weights file, was written under another run key, holds
        non-finite values or does not fit the two models.
    """
    folder = Path(run_dir)
    cfg, key = _read_key(folder, "diffusion")
    ae_ref = key["ae"]
    where = f"{folder / 'run.json'}: ae.run"
    try:
        ae_cfg = experiment_from_dict(ae_ref["run"].get("experiment"), where=where)
    except ValueError as e:
        raise DataFileError(folder / "run.json", f"its stage-1 reference is not readable ({e})") from None
    if not isinstance(ae_cfg, AutoencoderExperiment):
        raise DataFileError(folder / "run.json", f"ae.run names a {ae_cfg.stage} run, not an autoencoder run")
    pair = RaldStage2(ae_cfg.build_model(), cfg.build_model(), p_mean=cfg.loss.p_mean, p_std=cfg.loss.p_std)
    _load_best(folder, key, pair, f"diffusion model {cfg.model.variant!r} with autoencoder "
                                  f"{ae_cfg.model.variant!r} of {folder / 'run.json'}")
    ae_dir = resolve_ae_dir(folder, ae_ref["path"])
    return RaldRun(folder, ae_dir, cfg, ae_cfg, pair.autoencoder.to(device).eval(), pair.dit.to(device).eval(), key,
                   training_status(folder), _ae_status(ae_dir, ae_ref))


def _ae_status(ae_dir: Path, ref: dict) -> str:
    key = read_json(ae_dir / "run.json") if ae_dir.is_dir() else None
    if not isinstance(key, dict) or not (ae_dir / BEST_WEIGHTS).is_file():
        return "missing"
    same = (_comparable(key) == _comparable(ref["run"])
            and ref.get("weights_sha256") == file_sha256(ae_dir / BEST_WEIGHTS))
    return "same" if same else "changed"
