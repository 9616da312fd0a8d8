"""Train a RaLD stage in a run folder: the autoencoder, or the diffusion model against a stage-1 run.

A run folder has the detection experiment's format: ``run.json`` (the key), ``config.yaml`` (the
resolved config, readable and reusable), ``checkpoints/last.safetensors``, ``best.safetensors`` and
``log.csv`` (:func:`radarpc.training.loop.fit`); the keys are :mod:`.runs`' (stage 2's records the
stage-1 run's path, key and weights hash).

Stage 2 loads the autoencoder from the stage-1 run's ``best.safetensors``
(:func:`radarpc.experiments.rald.runs.load_rald_ae`: its run key checked, non-finite weights
refused) and freezes it. Because the stage-1 key and the weights' hash are part of the stage-2
key, a rerun against another or a retrained stage-1 run is refused (the message names
``ae.run`` or ``ae.weights_sha256``) instead of resuming with other latents; ``overwrite``
starts over. A stage-2 ``best.safetensors`` holds both networks (:class:`~.task.RaldStage2`).

Fine-tuning (``init``, ``radarpc train --init RUN``; the seed's Tables 6 and 8): the run starts
from the best weights of another run of the same stage, model and inputs (stage 1's ``data``,
stage 2's ``radar``; a stage-2 ``init`` must have been trained against the same stage-1 weights as
``ae``) instead of fresh ones; the optimiser, schedule and steps are the config's. The key records
the initial run like the stage-1 run (``"init"``: path, key, weights' SHA-256), so a rerun from
other weights is refused. With the config's ``scenes`` this trains on the held-out scenes only.
"""
from __future__ import annotations

import functools
import os
from pathlib import Path
from typing import Callable, Sequence

from radarpc.config import save_yaml, to_dict
from radarpc.distributed import dist_env
from radarpc.experiments.rald.config import AutoencoderExperiment, DiffusionExperiment, RaldExperiment, canonical_key
from radarpc.experiments.rald.runs import (REFERENCE_LOCATORS, ae_reference, autoencoder_run_key, diffusion_run_key,
                                           file_sha256, init_reference, load_rald, load_rald_ae)
from radarpc.experiments.rald.task import AutoencoderTask, DiffusionTask
from radarpc.io import DataFileError
from radarpc.runs import RunMismatchError, read_json
from radarpc.training.loop import BEST_WEIGHTS, FitResult, fit

__all__ = ["CONFIG_YAML", "single_root", "train_autoencoder", "train_diffusion", "train_rald"]

CONFIG_YAML = "config.yaml"
"""The resolved config a run folder keeps beside its key (``run.json``)."""


def single_root(data: str | os.PathLike | Sequence[str | os.PathLike]) -> Path:
    """The one ColoRadar root of ``data`` (a path, or a sequence holding exactly one).

    Raises
    ------
    ValueError
        No root or several (RaLD experiments read one root; its runs give the splits).
    """
    roots = [data] if isinstance(data, (str, os.PathLike)) else list(data)
    if len(roots) != 1:
        raise ValueError(f"a RaLD experiment reads one ColoRadar root (its runs give the splits), got "
                         f"{len(roots)}: {', '.join(map(str, roots)) or 'none'}")
    return Path(roots[0])


def _fit(task, cfg: RaldExperiment, out: Path, key: dict, device, overwrite, progress, log, on_step) -> FitResult:
    stored = read_json(out / "run.json")
    if "init" not in key and not overwrite and isinstance(stored, dict) and isinstance(stored.get("init"), dict):
        # the key compares the entries this run has: a fine-tuning's "init" would pass unseen
        raise RunMismatchError(f"{out} holds a run fine-tuned from {stored['init'].get('path')} (differs in "
                               f"run.json:init); pass --init to resume it, --overwrite (overwrite=True) to replace "
                               f"it, or choose another output")
    res = fit(task, cfg.train, out, key, device=device, overwrite=overwrite, progress=progress, log=log,
              extra_outputs=(CONFIG_YAML,), on_step=on_step,
              canonical_key=functools.partial(canonical_key, num_workers=cfg.train.num_workers),
              locators=REFERENCE_LOCATORS)
    if dist_env().rank == 0 and not (out / CONFIG_YAML).is_file():      # under torchrun, rank 0 alone writes
        save_yaml(cfg, out / CONFIG_YAML)
    return res


def _load_init(init: str | os.PathLike, out: Path, cfg: RaldExperiment, log: Callable[[str], None]):
    """The run ``init`` a fine-tuning of ``cfg`` into ``out`` starts from, loaded and checked: not
    ``out`` itself, the same stage, model and coordinates (stage 1's ``data``) or radar input
    (stage 2's ``radar``)."""
    init = Path(init)
    if init.resolve() == out.resolve():
        raise ValueError(f"--init {init} is the run folder --out itself; fine-tune another run's weights into a "
                         f"new folder")
    try:
        start = load_rald_ae(init) if isinstance(cfg, AutoencoderExperiment) else load_rald(init)
    except (DataFileError, FileNotFoundError) as e:
        raise ValueError(f"--init {init}: not a run to fine-tune {cfg.name!r} from: {e}") from None
    if to_dict(start.config.model) != to_dict(cfg.model):
        raise ValueError(f"--init {init}: that run trains model {start.config.model.variant!r} with overrides "
                         f"{start.config.model.overrides or {}}, experiment {cfg.name!r} model {cfg.model.variant!r} "
                         f"with {cfg.model.overrides or {}}: a fine-tuning starts from the same network")
    section = "data" if isinstance(cfg, AutoencoderExperiment) else "radar"   # what the weights' inputs mean
    if to_dict(getattr(start.config, section)) != to_dict(getattr(cfg, section)):
        raise ValueError(f"--init {init}: that run's {section} section differs from experiment {cfg.name!r}'s "
                         f"({to_dict(getattr(start.config, section))} against {to_dict(getattr(cfg, section))}); its "
                         f"weights read other inputs")
    if start.status["finished"] is False:
        log(f"--init {init}: that run has not finished; its best weights so far (step "
            f"{start.status['weights_step']}) are the start, and the run key records their hash (a new best there "
            f"later makes this run's resume refuse)")
    log(f"fine-tuning from {init} (its best weights, step {start.status['weights_step']})")
    return start


def train_autoencoder(cfg: AutoencoderExperiment, data: str | os.PathLike, out: str | os.PathLike, *,
                      device: str | None = None, overwrite: bool = False, progress: bool = True,
                      log: Callable[[str], None] = print, on_step: Callable[[int], None] | None = None,
                      init: str | os.PathLike | None = None) -> FitResult:
    """Train RaLD's autoencoder (stage 1) on the root ``data`` into the run folder ``out``; resumable.

    ``on_step`` is called with the global step after each optimizer step (tests interrupt with it).
    ``init``: a stage-1 run folder whose best weights the run starts from (module docstring).

    Raises
    ------
    ValueError
        ``init`` is ``out``, not a stage-1 run, or holds another model or other ``data``.
    """
    out = Path(out)
    key, weights = autoencoder_run_key(cfg, data), None
    if init is not None:
        start = _load_init(init, out, cfg, log)
        key, weights = key | {"init": init_reference(init, out)}, start.ae
    return _fit(AutoencoderTask(cfg, data, init=weights), cfg, out, key, device, overwrite, progress, log, on_step)


def train_diffusion(cfg: DiffusionExperiment, data: str | os.PathLike, ae: str | os.PathLike,
                    out: str | os.PathLike, *, device: str | None = None, overwrite: bool = False,
                    progress: bool = True, log: Callable[[str], None] = print,
                    on_step: Callable[[int], None] | None = None,
                    init: str | os.PathLike | None = None) -> FitResult:
    """Train RaLD's diffusion model (stage 2) on the root ``data`` against the stage-1 run folder
    ``ae`` (frozen) into the run folder ``out``; resumable (see the module docstring). ``on_step``
    as in :func:`train_autoencoder`; ``init``: a stage-2 run folder, trained against the same
    stage-1 weights, whose best diffusion weights the run starts from.

    Raises
    ------
    DataFileError, FileNotFoundError
        ``ae`` is not a stage-1 run with usable best weights (or ``init`` not a stage-2 run).
    ValueError
        The diffusion model's latents are not the autoencoder's; ``init`` holds another model or
        was trained against other stage-1 weights.
    RunMismatchError
        ``out`` holds another run (another config, root or stage-1 run) and ``overwrite`` is False.
    """
    out, ae = Path(out), Path(ae)
    stage1 = load_rald_ae(ae)
    if stage1.status["finished"] is False:
        log(f"{ae}: the autoencoder run has not finished (step {stage1.status['steps_done']}); its best weights "
            f"so far (step {stage1.status['weights_step']}) are the frozen first stage")
    key, weights = diffusion_run_key(cfg, data, ae_reference(ae, out)), None
    if init is not None:
        start = _load_init(init, out, cfg, log)
        if start.key["ae"].get("weights_sha256") != file_sha256(ae / BEST_WEIGHTS):
            raise ValueError(f"--init {init} was trained against other autoencoder weights than --ae {ae} "
                             f"({start.ae_dir}); fine-tune against the autoencoder it was trained on")
        key, weights = key | {"init": init_reference(init, out)}, start.dit
    task = DiffusionTask(cfg, data, stage1.config, stage1.ae, init=weights)
    return _fit(task, cfg, out, key, device, overwrite, progress, log, on_step)


def train_rald(cfg: RaldExperiment, data: str | os.PathLike | Sequence[str | os.PathLike],
               out: str | os.PathLike, *, ae: str | os.PathLike | None = None, device: str | None = None,
               overwrite: bool = False, progress: bool = True, log: Callable[[str], None] = print,
               init: str | os.PathLike | None = None) -> FitResult:
    """Train the stage ``cfg`` names: :func:`train_autoencoder` or :func:`train_diffusion`
    (``init``: the run to fine-tune, of the same stage).

    Raises
    ------
    ValueError
        ``ae`` given to stage 1 (it trains the autoencoder itself), missing for stage 2, or not one
        root in ``data``.
    """
    root = single_root(data)
    if isinstance(cfg, AutoencoderExperiment):
        if ae is not None:
            raise ValueError(f"experiment {cfg.name!r} is stage 1 (stage: autoencoder): it trains the autoencoder "
                             f"and takes no --ae (that is stage 2's, the autoencoder run it builds on)")
        return train_autoencoder(cfg, root, out, device=device, overwrite=overwrite, progress=progress, log=log,
                                 init=init)
    if ae is None:
        raise ValueError(f"experiment {cfg.name!r} is stage 2 (stage: diffusion): give the stage-1 autoencoder "
                         f"run it trains against, --ae RUN (a folder written by `radarpc train` with a "
                         f"stage: autoencoder config)")
    return train_diffusion(cfg, root, ae, out, device=device, overwrite=overwrite, progress=progress, log=log,
                           init=init)
