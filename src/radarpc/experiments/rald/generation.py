"""A RaLD run's generation for a ColoRadar split: the run's models, input and coordinates handed to
:func:`radarpc.pipelines.rald_generate.generate_predictions` (what ``radarpc generate`` calls), or,
for a stage-1 run, its autoencoder's reconstruction of the split's LiDAR handed to
:func:`radarpc.pipelines.rald_reconstruct.reconstruct_predictions`.

From the stage-2 run (:func:`radarpc.experiments.rald.runs.load_rald`: trained, or imported from the
official checkpoints) the generation takes

* the models: the diffusion model and the autoencoder stored with it (the one it was trained on);
* the model's input: the frame's RaLD cube as the run's training read it, intensity clipped to
  ``[0, radar.max_intensity_db]`` dB, divided by it and upsampled to the model's ``radar_shape``
  (:func:`radarpc.data.coloradar.rald_intensity`, as :class:`~radarpc.experiments.rald.task.DiffusionFrames`);
* the coordinates: the stage-1 config's grid (:meth:`LidarData.grid`) and frame (``mirror_azimuth``),
  so that the decoded queries map back to radar-frame metres by the inverse of the map the
  training applied to the LiDAR (:meth:`LidarData.to_radar` of :meth:`LidarData.to_model`);
* the identity in the folder's key: the SHA-256 of the run's ``best.safetensors`` (both networks),
  so that clouds of other weights are never mixed in, and the run folder (resolved), recorded but
  not compared (a locator: a moved run's rerun keeps the clouds and records the new place).

From a stage-1 run (:func:`radarpc.experiments.rald.runs.load_rald_ae`) the reconstruction takes the
autoencoder, its grid and frame as above, and the encoder's input of a frame: ``data.points`` of
the frame's LiDAR in the model's frame, drawn as the run's training draws them
(:func:`radarpc.experiments.rald.task.resample_points`, without replacement when the frame has
enough points), mapped to the model's coordinates (:func:`encoder_input`); the generator is the
frame's own (:func:`radarpc.rald.reconstruct.points_generator` of its seed), so a frame always
encodes the same points. The sampler's settings (``num_steps``, ``sigma_min``, ``sigma_max``,
``rho``) are refused for a stage-1 run, and the reconstruction's (``posterior``) for a stage-2 run.

:class:`GenerateConfig` is the YAML of ``radarpc generate --config``: the generation, its guide
points and (stage-1 runs) the reconstruction, each section optional (the official values by
default).
"""
from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Sequence

import torch

from radarpc.config import load_yaml
from radarpc.data.coloradar import rald_intensity
from radarpc.experiments.rald.runs import AutoencoderRun, RaldRun, load_rald, load_rald_ae, rald_stage
from radarpc.experiments.rald.task import resample_points
from radarpc.pipelines.rald_generate import GenerationJob, GenerationRun, file_digests, generate_predictions
from radarpc.pipelines.rald_reconstruct import SAMPLER_FIELDS, reconstruct_predictions
from radarpc.rald.generate import GenerationConfig
from radarpc.rald.guide import GuideConfig
from radarpc.rald.reconstruct import ReconstructionConfig
from radarpc.rald.voxels import model_coords
from radarpc.training.loop import BEST_WEIGHTS

__all__ = ["GenerateConfig", "load_generate_config", "with_generation", "run_root", "model_input", "encoder_input",
           "generate_run", "stage1_notice"]


@dataclass(frozen=True)
class GenerateConfig:
    """How a run generates: the generation (query counts, sampler, seed) and where the guided
    queries start. Sections left out of a YAML take the official values."""

    generation: GenerationConfig = field(default_factory=GenerationConfig)
    guide: GuideConfig = field(default_factory=GuideConfig)
    reconstruction: ReconstructionConfig = field(default_factory=ReconstructionConfig)   # stage-1 runs only


def load_generate_config(path: str | os.PathLike) -> GenerateConfig:
    """Read a :class:`GenerateConfig` YAML strictly (:func:`radarpc.config.load_yaml`: unknown keys,
    wrong types and bad values name the file and the field)."""
    return load_yaml(GenerateConfig, path)


def with_generation(config: GenerateConfig, *, guide: str | None = None, posterior: str | None = None,
                    **changes) -> GenerateConfig:
    """``config`` with fields of its :class:`~radarpc.rald.generate.GenerationConfig` replaced
    (``changes``, checked by it) and, with ``guide``, another guide source, with ``posterior``
    another posterior to reconstruct from."""
    gen = dataclasses.replace(config.generation, **changes) if changes else config.generation
    src = dataclasses.replace(config.guide, source=guide) if guide is not None else config.guide
    rec = (dataclasses.replace(config.reconstruction, posterior=posterior) if posterior is not None
           else config.reconstruction)
    return GenerateConfig(generation=gen, guide=src, reconstruction=rec)


def run_root(run: RaldRun | AutoencoderRun) -> Path | None:
    """The ColoRadar root the run's key names (trained on, or given to the import), or None."""
    data = run.key.get("data")
    return Path(data) if isinstance(data, str) else None


def model_input(run: RaldRun) -> Callable:
    """``cube -> (R, A, E)`` tensor: the diffusion model's input of a frame's RaLD cube, as the run's
    stage-2 training reads it (module docstring)."""
    shape, max_db = run.dit.cfg.radar_shape, run.config.radar.max_intensity_db
    return lambda cube: rald_intensity(cube, shape, max_db=max_db)


def encoder_input(run: AutoencoderRun) -> Callable:
    """``(lidar, generator) -> (N, 3)`` float32 tensor: the autoencoder's input of a frame's LiDAR
    (radar frame, metres), drawn as the run's training draws it (module docstring)."""
    data, grid = run.config.data, run.grid

    def points(lidar, generator: torch.Generator) -> torch.Tensor:
        xyz = data.model_frame(torch.from_numpy(lidar))                                  # (M, 3) model frame
        return model_coords(grid, resample_points(xyz, data.points, generator)).to(torch.float32)   # (N, 3)

    return points


def generate_run(run_dir: str | os.PathLike, out: str | os.PathLike, *, data: str | os.PathLike | None = None,
                 split: str = "test", every: int = 1, config: GenerateConfig = GenerateConfig(),
                 device: str | None = None,
                 allow_unfinished: bool = False, overwrite: bool = False, progress: bool = True,
                 on_warning: Callable[[str], None] | None = None,
                 notice: Callable[[str], None] | None = None, given: Sequence[str] = ()) -> GenerationRun:
    """Generate one cloud per paired frame of ``split`` with the stage-2 run ``run_dir`` into the
    prediction folder ``out`` (resumable: :func:`~radarpc.pipelines.rald_generate.generate_predictions`),
    or, with a stage-1 run, reconstruct each frame's LiDAR through its autoencoder
    (:func:`~radarpc.pipelines.rald_reconstruct.reconstruct_predictions`).

    Parameters
    ----------
    run_dir : path-like
        A stage-2 run folder (``radarpc train`` with a diffusion config, or ``radarpc import-rald``),
        or a stage-1 one (``radarpc train`` with an autoencoder config, or ``OUT/ae`` of an import).
    out : path-like
        The prediction folder.
    data : path-like, optional
        The ColoRadar root; default the root the run's key names.
    split : str
    every : int
        Generate every ``every``-th paired frame of each run (1: all; see
        :class:`~radarpc.data.coloradar.ColoRadar`).
    config : GenerateConfig
        For a stage-1 run its sampler's fields must be the defaults; for a stage-2 run its
        reconstruction section.
    device : str, optional
        Default: a GPU if any, else the CPU.
    allow_unfinished : bool
        Generate with the best weights of a run that has not finished (refused otherwise).
    overwrite : bool
        Replace a folder that holds anything but this generation.
    progress : bool
    on_warning : callable, optional
        Each empty frame's warning line, as it happens.
    notice : callable, optional
        One-line notices: a stage-1 run reconstructs; the stage-1 folder a stage-2 run names has
        changed or is missing (the autoencoder stored with the run is used either way); an
        unfinished run generating.
    given : sequence of str
        Fields of ``config`` the caller set explicitly (``"num_steps"``, ``"posterior"``: the
        command's options): refused for a run of the other stage even at their default values.

    Raises
    ------
    FileNotFoundError, DataFileError
        ``run_dir`` is not a loadable RaLD run (:func:`~radarpc.experiments.rald.runs.load_rald`,
        :func:`~radarpc.experiments.rald.runs.load_rald_ae`).
    ValueError
        An unfinished run without ``allow_unfinished``; no ``data`` for a run that names no root;
        a split without paired frames; a setting of the other stage (above).
    RunMismatchError
        ``out`` holds anything else, without ``overwrite``.
    PermissionError
        ``out`` cannot be written (checked first).
    """
    from radarpc.machine import check_device
    from radarpc.runs import check_writable

    check_writable(out, "prediction folder")                 # before the models are read
    run_dir = Path(run_dir)
    stage = rald_stage(run_dir)
    _check_stage_settings(run_dir, stage, config, given)
    dev = check_device(device, "--device") if device else torch.device("cuda" if torch.cuda.is_available() else "cpu")
    run = load_rald(run_dir, device=dev) if stage == "diffusion" else load_rald_ae(run_dir, device=dev)
    say = notice or (lambda s: None)
    what = "diffusion" if stage == "diffusion" else "autoencoder"
    if run.finished is False:
        where = f"step {run.status['steps_done']}, best weights of step {run.status['weights_step']}"
        if not allow_unfinished:
            raise ValueError(f"{run_dir}: the {what} run has not finished ({where}); finish it with the same "
                             f"`radarpc train` command, or pass --allow-unfinished to generate with its best weights "
                             f"so far")
        say(f"{run_dir}: the {what} run has not finished ({where}); generating with its best weights so far")
    if stage == "diffusion" and run.ae_status != "same":
        say(stage1_notice(run_dir, run.ae_dir, run.ae_status))
    if data is None:
        data = run_root(run)
        if data is None:
            raise ValueError(f"{run_dir}: the run names no ColoRadar root (an import without --data); give --data ROOT")
    job = GenerationJob(data, out, split, every=every, generation=config.generation, guide=config.guide, overwrite=overwrite)
    identity = {"run": str(run_dir.resolve()), "weights": file_digests([run_dir / BEST_WEIGHTS])}
    if stage == "autoencoder":
        say(f"{run_dir}: a stage-1 run: each frame's LiDAR is encoded and decoded by the autoencoder (a "
            f"reconstruction, posterior {config.reconstruction.posterior}), not generated from the radar")
        return reconstruct_predictions(job, run.ae, encoder_input=encoder_input(run),
                                       reconstruction=config.reconstruction, grid=run.grid,
                                       mirror_azimuth=run.config.data.mirror_azimuth, model=identity,
                                       progress=progress, on_warning=on_warning)
    return generate_predictions(job, run.ae, run.dit, model_input=model_input(run), grid=run.grid,
                                mirror_azimuth=run.ae_config.data.mirror_azimuth, model=identity,
                                progress=progress, on_warning=on_warning)


def stage1_notice(run_dir: str | os.PathLike, ae_dir: str | os.PathLike, ae_status: str) -> str:
    """What generation says when a stage-2 run's stage-1 folder is not the run it trained on
    (``ae_status`` "changed" or "missing", :data:`~radarpc.experiments.rald.runs.AE_STATUSES`)."""
    if ae_status == "changed":
        state = "holds another run or other weights now"
    elif ae_status == "missing":
        # most often the stage-2 folder was moved or copied without its stage-1 folder
        state = "is not there or holds no finished stage-1 run (moved apart from this run?)"
    else:
        raise ValueError(f"stage1_notice: ae_status must be 'changed' or 'missing', got {ae_status!r}")
    return (f"{run_dir}: its stage-1 folder {ae_dir} {state}; the autoencoder stored with the run (the one the "
            f"diffusion model was trained on) is used")


_OPTIONS = {"num_steps": "--steps", "posterior": "--posterior"}


def _check_stage_settings(run_dir: Path, stage: str, config: GenerateConfig, given: Sequence[str]) -> None:
    """Refuse a setting that the run's stage does not read (module docstring)."""
    if stage == "autoencoder":
        default = GenerationConfig()
        fields = [f for f in SAMPLER_FIELDS if f in given or getattr(config.generation, f) != getattr(default, f)]
        if fields:
            names = ", ".join(f"generation.{f}" + (f" ({_OPTIONS[f]})" if f in _OPTIONS else "") for f in fields)
            verb = "applies" if len(fields) == 1 else "apply"
            raise ValueError(f"{run_dir}: a stage-1 (autoencoder) run reconstructs the LiDAR without the diffusion "
                             f"sampler; {names} {verb} to a stage-2 run only")
    elif "posterior" in given or config.reconstruction != ReconstructionConfig():
        raise ValueError(f"{run_dir}: a stage-2 (diffusion) run generates from the radar; reconstruction.posterior "
                         f"(--posterior) applies to a stage-1 (autoencoder) run only")
